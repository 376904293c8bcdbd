#include "apps/calibrate_command.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <sstream>

#include "drivers/calibration.h"
#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun calibrate(std::vector<std::string> args, const std::string& operator_input = "") {
    args.insert(args.begin(), "calibrate");
    std::istringstream in(operator_input);
    return testing::runCommand([&in](CLI::App& app, std::ostream& out, std::ostream& err,
                                     int& code) { addCalibrateCommand(app, out, err, code, in); },
                               args);
}

std::string output(const std::string& name) {
    const auto dir = std::filesystem::temp_directory_path() /
                     ("flarelab_calibrate_test_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    return (dir / name).string();
}

// The simulated camera at 240 x 160 with the Heliar, the light 3 deg off axis.
std::string simCamera(const std::string& more = "") {
    return "sim:?lens=" + flarelab::testing::lensPath("heliar-tronnier.csv") +
           "&width=240&height=160&angle_deg=3" + more;
}

TEST(Calibrate, ReportsTheSimulatedCameraLinearWithItsFiguresWithinFivePercent) {
    const std::string file = output("linear.cal.json");
    const CommandRun run = calibrate({"--camera", simCamera(), "--yes", "-o", file});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("response: linear"), std::string::npos) << run.out;
    EXPECT_NE(run.out.find("the simulated camera's lens is capped"), std::string::npos);
    auto c = drivers::readCalibration(file);
    ASSERT_TRUE(c) << c.error().message;
    // The simulated sensor: black 64 DN, 4 e-/DN, read noise 3 e-, 12 bits (white 4095).
    EXPECT_NEAR(c->black_level_dn, 64.0, 0.05 * 64.0);
    EXPECT_NEAR(c->electrons_per_dn, 4.0, 0.05 * 4.0);
    EXPECT_NEAR(c->read_noise_e, 3.0, 0.05 * 3.0);
    EXPECT_NEAR(c->saturation_dn, 4095.0, 0.05 * 4095.0);
    EXPECT_TRUE(c->linear);
    EXPECT_EQ(c->camera_serial, "SIMCAM-0");
}

TEST(Calibrate, ReportsACurvedResponseNotLinearAndKeepsItsCurve) {
    const std::string file = output("gamma.cal.json");
    const CommandRun run =
        calibrate({"--camera", simCamera("&response=gamma"), "--yes", "-o", file});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("the camera says its response is not linear"), std::string::npos);
    EXPECT_NE(run.out.find("response: not linear"), std::string::npos) << run.out;
    auto c = drivers::readCalibration(file);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_FALSE(c->linear);
    EXPECT_TRUE(c->response_curve);
}

TEST(Calibrate, AsksTheOperatorOrTakesDarkFramesFromAnotherUri) {
    const std::string file = output("asked.cal.json");
    // Dark frames from the same camera capped; the operator answers the one prompt left.
    CommandRun run = calibrate({"--camera", simCamera(), "--dark-frames-from", simCamera("&cap=1"),
                                "--exposures", "0.125,0.25,0.5,1,2,4,8,16,32", "-o", file},
                               "\n");
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("uncap the lens"), std::string::npos) << run.out;
    EXPECT_NE(run.out.find("9 exposures"), std::string::npos) << run.out;
    EXPECT_TRUE(drivers::readCalibration(file));

    // Nobody answers: no calibration, and the message says how to go on.
    const std::string none = output("unanswered.cal.json");
    run = calibrate({"--camera", simCamera(), "-o", none});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--yes"), std::string::npos) << run.err;
    EXPECT_FALSE(std::filesystem::exists(none));
}

TEST(Calibrate, RefusesWhatIsNotTheCameraOrNotDark) {
    const std::string file = output("refused.cal.json");
    // Dark frames from another camera (another lens makes another simulated model).
    CommandRun run = calibrate({"--camera", simCamera(), "--dark-frames-from",
                                "sim:?lens=" + flarelab::testing::lensPath("lensbaby-toy.csv") +
                                    "&width=240&height=160&cap=1",
                                "--yes", "-o", file});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("not the camera being calibrated"), std::string::npos) << run.err;
    // "Dark" frames with the lens left open.
    run = calibrate(
        {"--camera", simCamera(), "--dark-frames-from", simCamera(), "--yes", "-o", file});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("not dark"), std::string::npos) << run.err;
    run = calibrate({"--camera", simCamera(), "--exposures", "1,2,x", "--yes", "-o", file});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--exposures: 'x'"), std::string::npos) << run.err;
    run = calibrate({"--camera", "nosuch:thing", "--yes", "-o", file});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("nosuch"), std::string::npos) << run.err;
    EXPECT_FALSE(std::filesystem::exists(file));
}

}  // namespace
}  // namespace flarelab::apps
