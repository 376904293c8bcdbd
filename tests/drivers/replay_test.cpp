// Recorded sweeps (tests/data/sweeps/, made by scripts/make_test_sweeps.sh with the simulated rig)
// replayed through the camera and head interfaces, the bracket merge and sweep reading.
#include "drivers/replay.h"

#include <gtest/gtest.h>

#include <cmath>

#include "hdr/merge.h"
#include "hdr/raw_io.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

std::string sweepDir(const char* name) {
    return flarelab::testing::sourcePath(std::string("tests/data/sweeps/") + name);
}

TEST(Replay, RawBracketsComeBackAsRecordedAndMergeToTheRecordedFrames) {
    auto rig = openReplay(sweepDir("heliar-raw"));
    ASSERT_TRUE(rig) << rig.error().message;
    const hdr::Sweep& sweep = *rig->sweep;
    ASSERT_EQ(sweep.frames.size(), 5u);
    ASSERT_TRUE(rig->head->home(1.0));
    for (size_t i = 0; i < sweep.frames.size(); ++i) {
        const hdr::SweepFrame& f = sweep.frames[i];
        ASSERT_TRUE(rig->head->moveTo(f.angle_deg, 1.0));
        std::vector<hdr::RawFrame> bracket;
        for (size_t k = 0; k < f.exposure_times_s.size(); ++k) {
            ASSERT_TRUE(rig->camera->setExposure(f.exposure_times_s[k]));
            auto raw = rig->camera->capture(1.0);
            ASSERT_TRUE(raw) << raw.error().message;
            const auto recorded = hdr::readRaw(sweep.directory + "/" + f.raw_files[k]);
            ASSERT_TRUE(recorded);
            EXPECT_EQ(raw->samples, recorded->samples);
            EXPECT_EQ(raw->exposure_s, f.exposure_times_s[k]);
            bracket.push_back(std::move(*raw));
        }
        const auto merged = hdr::mergeBrackets(bracket);
        ASSERT_TRUE(merged) << merged.error().message;
        const auto image = hdr::toImage(*merged);
        const auto frame = hdr::loadFrame(sweep, i);
        ASSERT_TRUE(image && frame);
        ASSERT_EQ(image->pixels.size(), frame->image.pixels.size());
        for (size_t p = 0; p < image->pixels.size(); ++p)
            ASSERT_NEAR(image->pixels[p], frame->image.pixels[p],
                        1e-5f * std::abs(frame->image.pixels[p]) + 1e-6f)
                << "frame " << i << " value " << p;
    }
}

TEST(Replay, AnHdrOnlySweepIsExposedAgainAndMergesBackToItself) {
    auto rig = openReplay(sweepDir("nikon-hdr"));
    ASSERT_TRUE(rig) << rig.error().message;
    const hdr::Sweep& sweep = *rig->sweep;
    ASSERT_EQ(sweep.frames.size(), 3u);
    ASSERT_TRUE(rig->head->home(1.0));
    ASSERT_TRUE(rig->head->moveTo(sweep.frames[1].angle_deg, 1.0));
    std::vector<hdr::RawFrame> bracket;
    for (const double t : {0.25, 1.0, 4.0}) {
        ASSERT_TRUE(rig->camera->setExposure(t));
        auto raw = rig->camera->capture(1.0);
        ASSERT_TRUE(raw) << raw.error().message;
        EXPECT_EQ(raw->angle_deg, sweep.frames[1].angle_deg);
        bracket.push_back(std::move(*raw));
    }
    EXPECT_LT(bracket[0].sequence, bracket[2].sequence);
    const auto merged = hdr::mergeBrackets(bracket);
    ASSERT_TRUE(merged) << merged.error().message;
    const auto frame = hdr::loadFrame(sweep, 1);
    ASSERT_TRUE(frame);
    // Re-exposure rounds to whole DN and clips: where some bracket holds the pixel unclipped,
    // the merge gives the green channel back to within rounding.
    int64_t checked = 0;
    for (int64_t y = 0; y < frame->image.height; ++y)
        for (int64_t x = 0; x < frame->image.width; ++x) {
            const size_t i = static_cast<size_t>(y * frame->image.width + x);
            if (merged->count[i] == 0) continue;
            const double truth = frame->image.at(x, y)[1];
            ASSERT_NEAR(merged->radiance[i], truth, 0.5 / 0.25 + 1e-4 * truth) << x << "," << y;
            ++checked;
        }
    EXPECT_GT(checked, frame->image.width * frame->image.height / 2);
}

TEST(Replay, RefusesAnglesWithoutAFrameAndSweepsThatAreNotThere) {
    auto rig = openReplay(sweepDir("heliar-raw"));
    ASSERT_TRUE(rig);
    EXPECT_FALSE(rig->head->moveTo(1.0, 1.0));  // not homed
    ASSERT_TRUE(rig->head->home(1.0));
    const auto outside = rig->head->moveTo(5.0, 1.0);
    ASSERT_FALSE(outside);
    EXPECT_NE(outside.error().message.find("outside"), std::string::npos);
    ASSERT_TRUE(rig->head->moveTo(0.7, 1.0));  // between frames 0.5 and 1.0
    const auto nothing = rig->camera->capture(1.0);
    ASSERT_FALSE(nothing);
    EXPECT_NE(nothing.error().message.find("nothing was recorded"), std::string::npos);
    EXPECT_FALSE(openReplay(sweepDir("no-such-sweep")));
    ReplayOptions bad;
    bad.bit_depth = 20;
    EXPECT_FALSE(openReplay(sweepDir("heliar-raw"), bad));
}

}  // namespace
}  // namespace flarelab::drivers
