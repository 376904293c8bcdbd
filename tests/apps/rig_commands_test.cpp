#include "apps/rig_commands.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "hdr/raw_io.h"
#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun rig(std::vector<std::string> args) {
    args.insert(args.begin(), "rig");
    return testing::runCommand(
        [](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
            CLI::App* r = app.add_subcommand("rig");
            r->require_subcommand(1);
            addRigDeviceCommands(r, out, err, code);
        },
        args);
}

TEST(RigDevices, ListsEveryBackendAndTheSimulatedDevicesAsJson) {
    const CommandRun run = rig({"devices", "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto doc = nlohmann::json::parse(run.out);
    std::set<std::string> schemes;
    for (const auto& b : doc["backends"])
        schemes.insert(b["kind"].get<std::string>() + ":" + b["scheme"].get<std::string>());
    EXPECT_TRUE(schemes.count("camera:aravis") && schemes.count("head:zaber") &&
                schemes.count("head:apt") && schemes.count("camera:v4l2"));
    bool sim_camera = false, sim_head = false;
    for (const auto& d : doc["devices"]) {
        sim_camera = sim_camera || (d["uri"] == "sim:" && d["kind"] == "camera");
        sim_head = sim_head || (d["uri"] == "sim:" && d["kind"] == "head");
    }
    EXPECT_TRUE(sim_camera && sim_head) << run.out;
}

TEST(RigCamera, TakesOneFrameAndSaysWhatTheCameraApplied) {
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_rig_camera_test";
    std::filesystem::create_directories(dir);
    const std::string pgm = (dir / "f.pgm").string(), png = (dir / "f.png").string();
    const CommandRun run =
        rig({"camera",
             "sim:?lens=" + flarelab::testing::lensPath("lensbaby-toy.csv") +
                 "&width=40&height=30&angle_deg=3",
             "--exposure", "0.02", "--gain", "2", "-o", pgm, "--png", png, "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto doc = nlohmann::json::parse(run.out);
    EXPECT_EQ(doc["exposure_s"], 0.02);
    EXPECT_EQ(doc["gain"], 2.0);
    EXPECT_EQ(doc["timestamp_marks"], "exposure-start");
    EXPECT_EQ(doc["response"], "linear");
    const auto frame = hdr::readRaw(pgm);
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_EQ(frame->width, 40);
    EXPECT_EQ(frame->angle_deg, 3.0);
    EXPECT_TRUE(std::filesystem::exists(png));
}

TEST(RigCommands, NameWhatIsWrong) {
    CommandRun run =
        rig({"camera", "sim:?lens=/nonexistent.csv", "--exposure", "1", "-o", "/tmp/x.pgm"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("/nonexistent.csv"), std::string::npos) << run.err;
    run = rig({"camera", "nosuch:thing", "--exposure", "1", "-o", "/tmp/x.pgm"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("known schemes"), std::string::npos) << run.err;
    run = rig({"camera", "sim:?lens=" + flarelab::testing::lensPath("lensbaby-toy.csv"),
               "--exposure", "-1", "-o", "/tmp/x.pgm"});
    EXPECT_EQ(run.code, 2);
    run = rig({"head", "sim:?time=fast", "spin"});
    EXPECT_EQ(run.code, 2);
    EXPECT_NE(run.err.find("home, move, position or stop"), std::string::npos) << run.err;
    run = rig({"head", "sim:?time=fast", "move"});
    EXPECT_EQ(run.code, 2);
    // A head that has not been homed does not know where it is.
    run = rig({"head", "sim:?time=fast", "move", "4"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("[not-homed]"), std::string::npos) << run.err;
    run = rig({"head", "sim:?time=fast", "home", "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(nlohmann::json::parse(run.out)["position_deg"], 0.0);
}

}  // namespace
}  // namespace flarelab::apps
