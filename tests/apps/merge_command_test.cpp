#include "apps/merge_command.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>

#include "hdr/exr.h"
#include "hdr/raw_io.h"
#include "tests/apps/command_runner.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun merge(std::vector<std::string> args) {
    args.insert(args.begin(), "merge");
    return testing::runCommand(addMergeCommand, args);
}

// A 4x2 mono scene of radiance r(x) = 10^x DN/s (x = 0..3), noiseless, 12-bit with black 64,
// taken at `exposure_s`: clipped where it saturates.
hdr::RawFrame bracket(double exposure_s) {
    hdr::RawFrame f;
    f.width = 4;
    f.height = 2;
    f.bit_depth = 12;
    f.black_level_dn = 64;
    f.white_level_dn = 4095;
    f.exposure_s = exposure_s;
    f.angle_deg = 2.4;
    f.camera = "test camera";
    for (int y = 0; y < 2; ++y)
        for (int x = 0; x < 4; ++x)
            f.samples.push_back(static_cast<uint16_t>(
                std::min(4095.0, std::round(64.0 + std::pow(10.0, x) * exposure_s))));
    return f;
}

TEST(MergeCommand, MergesRawBracketsOnDiskIntoAnExrWithItsMetadata) {
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_merge_command_test";
    std::filesystem::create_directories(dir);
    std::vector<std::string> args;
    for (const double t : {4.0, 0.25, 1.0}) {  // out of order on purpose
        const std::string path = (dir / ("b" + std::to_string(t) + ".pgm")).string();
        ASSERT_TRUE(hdr::writeRaw(path, bracket(t)));
        args.push_back(path);
    }
    const std::string exr = (dir / "frame.exr").string();
    args.insert(args.end(), {"-o", exr, "--lens", "test lens"});
    const CommandRun run = merge(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("3 bracket(s)"), std::string::npos) << run.out;
    const auto image = hdr::readExr(exr);
    ASSERT_TRUE(image) << image.error().message;
    for (int x = 0; x < 4; ++x)
        EXPECT_NEAR(image->image.at(x, 1)[1], std::pow(10.0, x), 0.3 + 0.002 * std::pow(10.0, x))
            << x;
    EXPECT_EQ(image->meta.angle_deg, 2.4);
    EXPECT_EQ(image->meta.exposure_times_s, (std::vector<double>{0.25, 1.0, 4.0}));
    EXPECT_EQ(image->meta.lens, "test lens");
    EXPECT_EQ(image->meta.camera, "test camera");
    EXPECT_FALSE(image->meta.merge_method.empty());
}

TEST(MergeCommand, NamesTheBracketThatCannotBeReadOrMerged) {
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_merge_command_test";
    std::filesystem::create_directories(dir);
    const std::string a = (dir / "a.pgm").string(), b = (dir / "b.pgm").string();
    ASSERT_TRUE(hdr::writeRaw(a, bracket(1.0)));
    hdr::RawFrame other = bracket(4.0);
    other.width = 2;
    other.height = 4;
    ASSERT_TRUE(hdr::writeRaw(b, other));
    const std::string exr = (dir / "bad.exr").string();
    CommandRun run = merge({a, b, "-o", exr});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("bracket 1"), std::string::npos) << run.err;
    EXPECT_FALSE(std::filesystem::exists(exr));
    run = merge({a, (dir / "missing.pgm").string(), "-o", exr});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("missing.pgm"), std::string::npos) << run.err;
}

}  // namespace
}  // namespace flarelab::apps
