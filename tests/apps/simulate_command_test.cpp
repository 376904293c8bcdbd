#include "apps/simulate_command.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <sstream>

#include "hdr/exr.h"
#include "render/preview.h"
#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun simulate(std::vector<std::string> args) {
    args.insert(args.begin(), "simulate");
    return testing::runCommand(addSimulateCommand, args);
}

TEST(Simulate, WritesAnExrWithTheLightsAngleAndAPngPreview) {
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_simulate_test";
    std::filesystem::create_directories(dir);
    const std::string exr = (dir / "flare.exr").string(), png = (dir / "flare.png").string();
    const CommandRun run = simulate({"--lens", flarelab::testing::lensPath("heliar-tronnier.csv"),
                                     "--angle", "4", "--roll", "10", "--width", "64", "--height",
                                     "48", "--grid", "16", "-o", exr, "--png", png});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto image = hdr::readExr(exr);
    ASSERT_TRUE(image) << image.error().message;
    EXPECT_EQ(image->image.width, 64);
    EXPECT_EQ(image->meta.angle_deg, 4.0);
    // Without --exposure-stops the preview's exposure is chosen from the image and said: the
    // ghosts show (at 0 stops this frame's preview is black).
    EXPECT_NE(run.out.find("PNG exposure"), std::string::npos) << run.out;
    const auto preview = render::readPng(png);
    ASSERT_TRUE(preview) << preview.error().message;
    EXPECT_GT(*std::max_element(preview->pixels.begin(), preview->pixels.end()), 100);
    const CommandRun fixed = simulate({"--lens", flarelab::testing::lensPath("heliar-tronnier.csv"),
                                       "--angle", "4", "--roll", "10", "--width", "64", "--height",
                                       "48", "--grid", "16", "-o", exr, "--png", png,
                                       "--exposure-stops", "0"});
    ASSERT_EQ(fixed.code, 0) << fixed.err;
    EXPECT_EQ(fixed.out.find("PNG exposure"), std::string::npos) << fixed.out;
    std::filesystem::remove_all(dir);
}

TEST(Simulate, BadLightAndMissingLightAreClearErrors) {
    const std::string lens = flarelab::testing::lensPath("heliar-tronnier.csv");
    CommandRun run = simulate({"--lens", lens, "--light", "5,x", "-o", "/tmp/unused.exr"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--light '5,x'"), std::string::npos);
    run = simulate({"--lens", lens, "-o", "/tmp/unused.exr"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("needs --angle"), std::string::npos);
}

TEST(Simulate, AdaptiveGridNeedsAMergeAndDrawsWithOne) {
    const std::string lens = flarelab::testing::lensPath("heliar-tronnier.csv");
    CommandRun run = simulate({"--lens", lens, "--angle", "4", "--adaptive-grid", "-o",
                               "/tmp/unused.exr", "--width", "32", "--height", "24"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--adaptive-grid refines by the merge's test"), std::string::npos)
        << run.err;
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_simulate_adaptive_test";
    std::filesystem::create_directories(dir);
    const std::string exr = (dir / "flare.exr").string();
    run =
        simulate({"--lens", lens, "--angle", "4", "--adaptive-grid", "--merge", "light",
                  "--no-starburst", "--width", "64", "--height", "48", "--grid", "64", "-o", exr});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto image = hdr::readExr(exr);
    ASSERT_TRUE(image) << image.error().message;
    EXPECT_EQ(image->image.width, 64);
    std::filesystem::remove_all(dir);
}

TEST(Simulate, TracesOnlyTheImagesWindowUnlessToldNot) {
    const std::string lens = flarelab::testing::lensPath("heliar-tronnier.csv");
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_simulate_window_test";
    std::filesystem::create_directories(dir);
    const std::string exr = (dir / "flare.exr").string();
    const std::vector<std::string> args = {"--lens",  lens, "--angle",  "5",  "--no-starburst",
                                           "--width", "48", "--height", "32", "--grid",
                                           "48",      "-o", exr};
    CommandRun run = simulate(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(run.out.find(" 0 windowed to it"), std::string::npos) << run.out;
    EXPECT_NE(run.out.find(" windowed to it"), std::string::npos) << run.out;
    std::vector<std::string> whole = args;
    whole.push_back("--no-image-window");
    run = simulate(whole);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find(" 0 windowed to it"), std::string::npos) << run.out;
    std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace flarelab::apps
