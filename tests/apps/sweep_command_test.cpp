#include "apps/sweep_command.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <future>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "hdr/sweep.h"
#include "tests/apps/command_runner.h"
#include "tests/test_files.h"

namespace flarelab::apps {
namespace {

using flarelab::testing::contains;

namespace fs = std::filesystem;
using testing::CommandRun;

CommandRun sweep(std::vector<std::string> args) {
    args.insert(args.begin(), "sweep");
    return testing::runCommand(addSweepCommands, args);
}

// A three-frame sweep of 8x6 images in a fresh directory, removed afterwards.
class SmallSweep {
public:
    SmallSweep() {
        static int counter = 0;
        dir_ = fs::temp_directory_path() /
               ("flarelab-sweep-command-test-" + std::to_string(::getpid()) + "-" +
                std::to_string(counter++));
        fs::remove_all(dir_);
        hdr::SweepHeader header;
        header.software_version = "flarelab test";
        header.lens.description = "heliar 50mm";
        header.lens.focal_length_mm = 50.0;
        header.camera.description = "mono test camera";
        header.camera.bit_depth = 12;
        header.camera.raw_format = hdr::RawFormat::Mono;
        header.capture.from_deg = 0.0;
        header.capture.to_deg = 1.0;
        header.capture.step_deg = 0.2;
        header.capture.exposure_times_s = {0.001, 0.1};
        header.capture.gain = 1.5;
        header.capture.width_px = 8;
        header.capture.height_px = 6;
        auto writer = hdr::SweepWriter::create(dir_.string(), header);
        EXPECT_TRUE(writer) << writer.error().message;
        for (int i = 0; i < 3; ++i) {
            ImageRGB image(8, 6);
            for (size_t k = 0; k < image.pixels.size(); ++k) image.pixels[k] = 0.5f * (k + i);
            hdr::SweepFrame frame;
            frame.angle_deg = 0.2 * i;
            frame.exposure_times_s = header.capture.exposure_times_s;
            frame.merge_method = "weighted";
            auto added = writer->addFrame(image, frame);
            EXPECT_TRUE(added) << added.error().message;
            files_.push_back(added->exr_file);
        }
    }
    ~SmallSweep() {
        std::error_code ec;
        fs::remove_all(dir_, ec);
    }
    std::string path() const { return dir_.string(); }
    std::string file(size_t index) const { return (dir_ / files_[index]).string(); }

private:
    fs::path dir_;
    std::vector<std::string> files_;
};

TEST(SweepInfo, PrintsLensCameraBracketsAndFrames) {
    SmallSweep s;
    const CommandRun run = sweep({"info", s.path()});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "lens: heliar 50mm, 50 mm")) << run.out;
    EXPECT_TRUE(contains(run.out, "camera: mono test camera, 12 bit, raw format mono")) << run.out;
    EXPECT_TRUE(contains(run.out, "brackets: 2 exposures of 0.001 0.1 s, gain 1.5")) << run.out;
    EXPECT_TRUE(contains(run.out, "frames: 3, 0 to 0.4 deg")) << run.out;
    EXPECT_TRUE(contains(run.out, "8x6 pixels")) << run.out;
    EXPECT_TRUE(contains(run.out, "manifest only")) << run.out;
}

TEST(SweepInfo, JsonHasFramesAnglesLensCameraAndBrackets) {
    SmallSweep s;
    const CommandRun run = sweep({"info", s.path(), "--json", "--check"});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto json = nlohmann::json::parse(run.out);
    EXPECT_EQ(json["frames"], 3);
    EXPECT_EQ(json["angles_deg"], (std::vector<double>{0.0, 0.2, 0.4}));
    EXPECT_EQ(json["lens"]["description"], "heliar 50mm");
    EXPECT_EQ(json["lens"]["focal_length_mm"], 50.0);
    EXPECT_TRUE(json["lens"]["f_number"].is_null());
    EXPECT_EQ(json["camera"]["bit_depth"], 12);
    EXPECT_EQ(json["camera"]["raw_format"], "mono");
    EXPECT_EQ(json["brackets"]["exposure_times_s"], (std::vector<double>{0.001, 0.1}));
    EXPECT_EQ(json["brackets"]["gain"], 1.5);
    EXPECT_EQ(json["capture"]["width_px"], 8);
    EXPECT_EQ(json["format_version"], hdr::kSweepFormatVersion);
    EXPECT_EQ(json["checked"], true);
    EXPECT_TRUE(json["warnings"].empty());
}

TEST(SweepInfo, CheckFindsBrokenFramesThatTheManifestAloneDoesNot) {
    SmallSweep s;
    fs::remove(s.file(1));
    EXPECT_EQ(sweep({"info", s.path()}).code, 0);
    const CommandRun run = sweep({"info", s.path(), "--check"});
    EXPECT_EQ(run.code, 1);
    EXPECT_TRUE(contains(run.err, "frames[1].exr_file")) << run.err;
    EXPECT_TRUE(run.out.empty());
}

TEST(SweepInfo, ExtraFilesAreWarningsUnlessStrict) {
    SmallSweep s;
    fs::copy_file(s.file(0), fs::path(s.path()) / "stray.exr");
    CommandRun run = sweep({"info", s.path(), "--check", "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto json = nlohmann::json::parse(run.out);
    ASSERT_EQ(json["warnings"].size(), 1u);
    EXPECT_TRUE(contains(json["warnings"][0].get<std::string>(), "stray.exr"));
    run = sweep({"info", s.path(), "--check"});
    EXPECT_TRUE(contains(run.out, "warning: ")) << run.out;
    run = sweep({"info", s.path(), "--strict"});
    EXPECT_EQ(run.code, 1);
    EXPECT_TRUE(contains(run.err, "stray.exr")) << run.err;
}

TEST(SweepInfo, ReadsVersionOneSweepsAndVersionTwoOnesWithTheirLog) {
    const CommandRun old =
        sweep({"info", std::string(FLARELAB_SOURCE_DIR) + "/tests/data/sweeps/nikon-hdr", "--check",
               "--json"});
    ASSERT_EQ(old.code, 0) << old.err;
    EXPECT_EQ(nlohmann::json::parse(old.out)["format_version"], 1);
    SmallSweep s;  // its writer was not finished: the frames are in frames.log
    ASSERT_TRUE(fs::exists(fs::path(s.path()) / hdr::kSweepFrameLogFile));
    const CommandRun run = sweep({"info", s.path(), "--check", "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(nlohmann::json::parse(run.out)["frames"], 3);
}

TEST(SweepInfo, AFifoALinkOrADeviceInPlaceOfAFileIsRefusedWithoutBlocking) {
    SmallSweep s;
    const fs::path dir = s.path();
    const std::vector<std::pair<std::string, std::string>> files = {
        {hdr::kSweepManifestFile, "info"},
        {hdr::kSweepFrameLogFile, "info"},
        {fs::path(s.file(1)).filename().string(), "--check"}};
    for (const auto& [name, mode] : files) {
        const std::string path = (dir / name).string();
        const std::string kept = path + ".kept";
        std::vector<std::function<void()>> hostile = {
            [&] { ASSERT_EQ(::mkfifo(path.c_str(), 0644), 0); },
            [&] { fs::create_symlink(kept, path); }};
        if (mode == "info")  // a manifest or log larger than any sweep's (sparse)
            hostile.push_back([&] {
                fs::copy_file(kept, path);
                ASSERT_EQ(::truncate(path.c_str(), hdr::kSweepMaxManifestBytes + 1), 0);
            });
        if (::geteuid() == 0)
            hostile.push_back(
                [&] { ASSERT_EQ(::mknod(path.c_str(), S_IFCHR | 0644, makedev(1, 5)), 0); });
        for (size_t h = 0; h < hostile.size(); ++h) {
            SCOPED_TRACE(name + ", case " + std::to_string(h));
            fs::rename(path, kept);
            hostile[h]();
            std::vector<std::string> args = {"info", s.path()};
            if (mode == "--check") args.push_back("--check");
            auto running = std::async(std::launch::async, [&] { return sweep(args); });
            if (running.wait_for(std::chrono::seconds(20)) != std::future_status::ready) {
                ADD_FAILURE() << "sweep info blocked";
                ::close(::open(path.c_str(), O_WRONLY | O_NONBLOCK));
            }
            const CommandRun run = running.get();
            EXPECT_EQ(run.code, 1);
            EXPECT_TRUE(contains(run.err, name)) << run.err;
            fs::remove(path);
            fs::rename(kept, path);
        }
    }
    EXPECT_EQ(sweep({"info", s.path(), "--check"}).code, 0);
}

TEST(SweepInfo, NoSweepIsAClearError) {
    const CommandRun run = sweep({"info", "/nonexistent/flarelab-sweep"});
    EXPECT_EQ(run.code, 1);
    EXPECT_TRUE(contains(run.err, "/nonexistent/flarelab-sweep/manifest.json")) << run.err;
    EXPECT_NE(sweep({"info"}).code, 0);  // DIR is required
}

}  // namespace
}  // namespace flarelab::apps
