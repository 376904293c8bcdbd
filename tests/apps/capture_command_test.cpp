#include "apps/capture_command.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>

#include "hdr/sweep.h"
#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun capture(std::vector<std::string> args) {
    args.insert(args.begin(), "capture");
    return testing::runCommand(addCaptureCommand, args);
}

std::string freshDir(const std::string& name) {
    const auto dir = std::filesystem::temp_directory_path() / ("flarelab_capture_test_" + name);
    std::filesystem::remove_all(dir);
    return dir.string();
}

std::vector<std::string> small(const std::string& dir) {
    return {"--sim",    "--fast", "--lens",  flarelab::testing::lensPath("lensbaby-toy.csv"),
            "--from",   "0",      "--to",    "0.4",
            "--step",   "0.2",    "--width", "48",
            "--height", "32",     "-o",      dir};
}

TEST(Capture, WritesASweepThatReadsBackWithRawBracketsAndResumes) {
    const std::string dir = freshDir("sweep");
    auto args = small(dir);
    args.insert(args.end(), {"--keep-raw", "--brackets", "0.25,1,4"});
    CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("3 frames"), std::string::npos) << run.out;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    ASSERT_EQ(sweep->frames.size(), 3u);
    EXPECT_EQ(sweep->frames[2].angle_deg, 0.4);
    EXPECT_EQ(sweep->frames[0].raw_files.size(), 3u);
    EXPECT_EQ(sweep->header.capture.exposure_times_s, (std::vector<double>{0.25, 1.0, 4.0}));
    // Asked again for a longer range with --resume, only the new frames are taken.
    args = small(dir);
    args[7] = "0.8";
    args.insert(args.end(), {"--keep-raw", "--brackets", "0.25,1,4"});
    run = capture(args);
    EXPECT_EQ(run.code, 1) << "a new range is a different sweep";
    args = small(dir);
    args.insert(args.end(), {"--keep-raw", "--brackets", "0.25,1,4"});
    args.push_back("--resume");
    run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("3 already there"), std::string::npos) << run.out;
}

TEST(Capture, RecordsEachExposuresClippingAndWarnsOfASaturatedSweep) {
    // The double Gauss's ghosts are far brighter than the lensbaby's: with the brackets of the
    // lensbaby (0.25 / 1 / 4 s) its whole frame saturates every exposure; with 1/64 of them it
    // does not.
    const std::string dir = freshDir("clipped");
    auto args = small(dir);
    args[3] = flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv");
    args.insert(args.end(), {"--brackets", "0.25,1,4"});
    CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.err.find("warning: 3 of 3 frames have more than 1% of their samples saturated"),
              std::string::npos)
        << run.err;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    ASSERT_EQ(sweep->frames[0].brackets.size(), 3u);
    for (const hdr::SweepFrame& f : sweep->frames)
        for (size_t k = 0; k < 3; ++k) {
            EXPECT_EQ(f.brackets[k].exposure_s, f.exposure_times_s[k]);
            EXPECT_LE(f.brackets[k].samples_used + f.brackets[k].samples_clipped, 48u * 32u);
        }
    // Longer exposures clip at least as much.
    EXPECT_LE(sweep->frames[1].brackets[0].samples_clipped,
              sweep->frames[1].brackets[2].samples_clipped);

    const std::string short_dir = freshDir("short");
    args = small(short_dir);
    args[3] = flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv");
    args.insert(args.end(), {"--brackets", "0.004,0.016,0.064"});
    run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(run.err.find("warning"), std::string::npos) << run.err;
}

TEST(Capture, PlansTheBracketWhenNoneIsGivenAndKeepsItsOwnOnResume) {
    // The double Gauss saturates 0.25 / 1 / 4 s; the planned bracket keeps the light's core
    // unclipped in its shortest exposure and reaches the ghosts' floor in its longest.
    const std::string dir = freshDir("auto");
    auto args = small(dir);
    args[3] = flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv");
    args[7] = "0.2";
    CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.err.find("flarelab: bracket: "), std::string::npos) << run.err;
    EXPECT_EQ(run.err.find("warning"), std::string::npos) << run.err;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    const std::vector<double> planned = sweep->header.capture.exposure_times_s;
    ASSERT_GE(planned.size(), 2u);
    EXPECT_TRUE(std::is_sorted(planned.begin(), planned.end()));
    // The shortest exposure of the first frame clips nothing.
    EXPECT_EQ(sweep->frames[0].brackets[0].samples_clipped, 0u);
    // Resumed, the sweep keeps the bracket it was taken with instead of planning another.
    args[7] = "0.2";
    args.push_back("--resume");
    run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(run.err.find("flarelab: bracket: "), std::string::npos) << run.err;
    EXPECT_NE(run.out.find("2 already there"), std::string::npos) << run.out;
}

TEST(Capture, TakesItsDevicesByUri) {
    const std::string dir = freshDir("uri");
    CommandRun run = capture({"--camera",
                              "sim:?lens=" + flarelab::testing::lensPath("lensbaby-toy.csv") +
                                  "&width=40&height=30&format=rggb",
                              "--head", "sim:?time=fast&settle_s=0", "--from", "0", "--to", "0.2",
                              "--step", "0.2", "--brackets", "0.5,2", "-o", dir});
    ASSERT_EQ(run.code, 0) << run.err;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 2u);
    EXPECT_EQ(sweep->header.capture.width_px, 40);  // the camera's size, not --width's
    EXPECT_GT(sweep->header.camera.pixel_pitch_um, 0.0);
    EXPECT_NE(sweep->header.lens.description.find("ensbaby"), std::string::npos)
        << sweep->header.lens.description;

    run = capture({"--camera", "sim:", "--head", "sim:", "-o", freshDir("nolens")});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("needs a lens"), std::string::npos) << run.err;
    run = capture({"--camera", "aravis:", "--head", "warp:", "-o", freshDir("nohead")});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("head 'warp:'"), std::string::npos) << run.err;
}

TEST(Capture, RefusesBadRequestsNamingWhatIsWrong) {
    const std::string dir = freshDir("bad");
    auto args = small(dir);
    args.erase(args.begin());  // no --sim
    CommandRun run = capture(args);
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--sim"), std::string::npos);
    args = small(dir);
    args.insert(args.end(), {"--brackets", "0.25,abc"});
    run = capture(args);
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("abc"), std::string::npos) << run.err;
    args = small(dir);
    args[5] = "1";  // --from 1 > --to 0.4
    run = capture(args);
    EXPECT_EQ(run.code, 1);
    EXPECT_FALSE(std::filesystem::exists(dir + "/manifest.json"));
}

}  // namespace
}  // namespace flarelab::apps
