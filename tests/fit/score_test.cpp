// The score's figures on images whose answers are known, and its choice of angles.
#include "fit/score.h"

#include <gtest/gtest.h>

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <string>
#include <vector>

namespace flarelab::fit {
namespace {

ImageRGB filled(int64_t w, int64_t h, float value) {
    ImageRGB image(w, h);
    for (float& v : image.pixels) v = value;
    return image;
}

// A bright ghost and one a thousand times dimmer: dropping the dim one costs almost nothing in
// plain relative L2 and in energy, but the log image sees it.
TEST(Score, TheLogImageCountsADimGhostThatPlainL2HardlySees) {
    ImageRGB truth(64, 32), model(64, 32);
    for (int64_t y = 0; y < 32; ++y)
        for (int64_t x = 0; x < 64; ++x)
            for (int c = 0; c < 3; ++c) {
                const float bright = x < 32 ? 1000.0f : 0.0f;
                const float dim = x >= 32 ? 1.0f : 0.0f;
                truth.at(x, y)[c] = bright + dim;
                model.at(x, y)[c] = bright;  // the dim ghost missed
            }
    auto s = compareImages(model, truth, std::nullopt, 0.0, 1e-3);
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_NEAR(s->rel_l2, 1e-3, 1e-5);
    EXPECT_NEAR(s->energy_error, -1.0 / 1001.0, 1e-9);
    EXPECT_NEAR(s->missed_light, 1.0 / 1001.0, 1e-9);
    // Tone-mapped, the bright half maps to 1 and the dim half to log(2) / log(1001) ~ 0.1.
    const double dim = std::log(2.0) / std::log(1001.0);
    EXPECT_NEAR(s->log_rel_l2, dim / std::sqrt(1.0 + dim * dim), 1e-6);
    EXPECT_GT(s->log_rel_l2, 50.0 * s->rel_l2);
    EXPECT_EQ(s->masked_energy_fraction, 0.0);
}

TEST(Score, EnergyInsideTheLightsDiscIsReportedNotScored) {
    const ImageRGB truth = filled(40, 40, 2.0f);
    ImageRGB model = filled(40, 40, 2.0f);
    // Inside the disc the model is wrong; it does not count, but the disc's share is reported.
    const Eigen::Vector2d light(20.0, 20.0);
    int64_t inside = 0;
    for (int64_t y = 0; y < 40; ++y)
        for (int64_t x = 0; x < 40; ++x)
            if (std::hypot(x + 0.5 - 20.0, y + 0.5 - 20.0) <= 5.0) {
                ++inside;
                for (int c = 0; c < 3; ++c) model.at(x, y)[c] = 50.0f;
            }
    auto s = compareImages(model, truth, light, 5.0);
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_EQ(s->rel_l2, 0.0);
    EXPECT_EQ(s->energy_error, 0.0);
    EXPECT_EQ(s->log_rel_l2, 0.0);
    EXPECT_NEAR(s->masked_energy_fraction, static_cast<double>(inside) / 1600.0, 1e-12);
}

TEST(Score, ABlackTruthScoresWhatIsDrawnAsAllError) {
    const ImageRGB black = filled(8, 8, 0.0f);
    auto both = compareImages(black, black, std::nullopt, 0.0);
    ASSERT_TRUE(both);
    EXPECT_EQ(both->rel_l2, 0.0);
    EXPECT_EQ(both->energy_error, 0.0);
    EXPECT_EQ(both->log_rel_l2, 0.0);
    auto drawn = compareImages(filled(8, 8, 1.0f), black, std::nullopt, 0.0);
    ASSERT_TRUE(drawn);
    EXPECT_EQ(drawn->rel_l2, 1.0);
    EXPECT_EQ(drawn->energy_error, 1.0);
    EXPECT_EQ(drawn->log_rel_l2, 1.0);
    EXPECT_EQ(drawn->missed_light, 0.0);
    // Light drawn in the wrong place: nothing of the truth drawn, all of it missed, although the
    // total energy is right.
    ImageRGB left(8, 8), right(8, 8);
    for (int64_t y = 0; y < 8; ++y)
        for (int c = 0; c < 3; ++c) {
            left.at(0, y)[c] = 1.0f;
            right.at(7, y)[c] = 1.0f;
        }
    auto moved = compareImages(right, left, std::nullopt, 0.0);
    ASSERT_TRUE(moved);
    EXPECT_EQ(moved->energy_error, 0.0);
    EXPECT_EQ(moved->missed_light, 1.0);
    EXPECT_FALSE(compareImages(black, black, std::nullopt, 0.0, 0.0));
    EXPECT_FALSE(compareImages(black, filled(8, 7, 0.0f), std::nullopt, 0.0));
}

TEST(Score, ToneMapRunsFromZeroToOneOverTheChosenRange) {
    EXPECT_EQ(toneMapScore(0.0, 100.0, 1e-3), 0.0);
    EXPECT_NEAR(toneMapScore(100.0, 100.0, 1e-3), 1.0, 1e-12);
    EXPECT_EQ(toneMapScore(-5.0, 100.0, 1e-3), 0.0);
    EXPECT_EQ(toneMapScore(5.0, 0.0, 1e-3), 0.0);
    EXPECT_LT(toneMapScore(0.1, 100.0, 1e-3), toneMapScore(0.2, 100.0, 1e-3));
}

FlareModel gridModel(double from, double to, double step) {
    FlareModel model;
    model.capture.from_deg = from;
    model.capture.to_deg = to;
    model.capture.step_deg = step;
    model.valid_from_deg = from;
    model.valid_to_deg = to;
    return model;
}

// A model fitted to every fifth frame of a 0.2 deg sweep (step 1 deg): the frames left out are
// held out as their own kind, never scored twice, and refused outside the valid range.
TEST(Score, LeftOutFramesAreHeldOutOnceAndChecked) {
    const FlareModel model = gridModel(0.0, 3.0, 1.0);
    ScoreOptions options;
    options.random_angles = 0;
    for (int i = 0; i <= 15; ++i)
        if (i % 5 != 0) options.left_out_deg.push_back(0.2 * i);
    auto angles = scoreAngles(model, options);
    ASSERT_TRUE(angles) << angles.error().message;
    int fitted = 0, left = 0, halfway = 0;
    for (const ScoredAngle& a : *angles) {
        if (a.kind == AngleKind::Fitted) ++fitted;
        if (a.kind == AngleKind::LeftOut) ++left;
        if (a.kind == AngleKind::Halfway) ++halfway;
    }
    EXPECT_EQ(fitted, 4);   // 0, 1, 2, 3
    EXPECT_EQ(left, 12);    // four between each pair of fitted frames
    EXPECT_EQ(halfway, 3);  // 0.5, 1.5, 2.5: none coincides with a left-out frame
    for (size_t i = 1; i < angles->size(); ++i) {
        if ((*angles)[i].kind != AngleKind::Fitted && (*angles)[i - 1].kind != AngleKind::Fitted) {
            EXPECT_LT((*angles)[i - 1].angle_deg, (*angles)[i].angle_deg);
        }
    }

    // k = 2: the half-way angles are the left-out frames, scored once, as left-out, even those
    // the cap on left-out frames leaves unscored.
    ScoreOptions two;
    two.random_angles = 0;
    two.left_out_deg = {0.5, 1.5, 2.5};
    two.left_out_angles = 2;
    auto pairs = scoreAngles(model, two);
    ASSERT_TRUE(pairs);
    int pair_left = 0;
    for (const ScoredAngle& a : *pairs) {
        EXPECT_NE(a.kind, AngleKind::Halfway) << a.angle_deg;
        pair_left += a.kind == AngleKind::LeftOut;
    }
    EXPECT_EQ(pair_left, 2);

    ScoreOptions outside;
    outside.left_out_deg = {3.4};
    auto refused = scoreAngles(model, outside);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("left-out angle"), std::string::npos);
}

// scoreModel reports each kind's summary and shows every angle's images once.
TEST(Score, EveryKindIsSummarizedAndEveryAngleShown) {
    FlareModel model = gridModel(0.0, 2.0, 1.0);
    model.capture.width_px = 16;
    model.capture.height_px = 8;
    model.lens.sensor_width_mm = 16.0;
    model.lens.sensor_height_mm = 8.0;
    const TruthSource truth = [](double) -> Result<TruthFrame> {
        TruthFrame t;
        t.image = filled(16, 8, 1.0f);
        return t;
    };
    ScoreOptions options;
    options.left_out_deg = {0.4, 1.6};
    options.random_angles = 1;
    int shown = 0;
    auto report = scoreModel(model, truth, options, {}, [&](const ScoreImages& v) -> Status {
        ++shown;
        EXPECT_EQ(v.truth.width, 16);
        EXPECT_EQ(v.model.width, 16);
        return Ok{};
    });
    ASSERT_TRUE(report) << report.error().message;
    EXPECT_EQ(shown, static_cast<int>(report->angles.size()));
    ASSERT_EQ(report->by_kind.size(), 4u);  // fitted, left-out, half-way, random
    EXPECT_EQ(report->by_kind[0].first, AngleKind::Fitted);
    EXPECT_EQ(report->by_kind[1].first, AngleKind::LeftOut);
    EXPECT_EQ(report->by_kind[1].second.count, 2);
    // A model with no ghosts misses all the light: every angle is all error, energy -100 %.
    EXPECT_EQ(report->heldout_rel_l2.median, 1.0);
    EXPECT_EQ(report->heldout_rel_l2.median_abs_energy_error, 1.0);
    // An error from the images' consumer ends the score with it.
    auto stopped = scoreModel(model, truth, options, {}, [](const ScoreImages&) -> Status {
        return makeError(ErrorCode::IoError, "disk full");
    });
    ASSERT_FALSE(stopped);
    EXPECT_NE(stopped.error().message.find("disk full"), std::string::npos);
}


TEST(Score, TheLightsDiscIsTheOneTheFitRecorded) {
    FlareModel model = gridModel(0.0, 2.0, 1.0);
    EXPECT_FALSE(lightDiscRadius(model, 1.0));  // not recorded
    model.capture.light_discs = {{0.0, 10.0}, {1.0, 20.0}, {1.5, 0.0}, {2.0, 6.0}};
    EXPECT_EQ(*lightDiscRadius(model, 0.0), 10.0);
    EXPECT_DOUBLE_EQ(*lightDiscRadius(model, 0.25), 12.5);  // between two lit frames: linear
    EXPECT_EQ(*lightDiscRadius(model, 1.0), 20.0);
    EXPECT_EQ(*lightDiscRadius(model, 1.2), 20.0);  // beside a frame with no light: the larger
    EXPECT_EQ(*lightDiscRadius(model, 1.5), 0.0);
    EXPECT_EQ(*lightDiscRadius(model, 1.7), 6.0);
    EXPECT_EQ(*lightDiscRadius(model, -1.0), 10.0);  // beyond the record: the nearest
    EXPECT_EQ(*lightDiscRadius(model, 2.5), 6.0);

    // scoreModel leaves out that disc, per angle, around the truth's light: a model wrong only
    // inside the recorded disc scores 0, and a model wrong just outside it does not.
    model.capture.width_px = 64;
    model.capture.height_px = 64;
    model.lens.sensor_width_mm = 64.0;
    model.lens.sensor_height_mm = 64.0;
    model.capture.light_discs = {{0.0, 20.0}, {1.0, 20.0}, {2.0, 20.0}};
    // The truth has light the (empty) model does not draw in a ring 10..18 px from the light:
    // inside the recorded disc, outside 3% of the diagonal (2.7 px).
    const TruthSource truth = [](double) -> Result<TruthFrame> {
        TruthFrame t;
        t.image = ImageRGB(64, 64);
        t.light_px = Eigen::Vector2d(32.0, 32.0);
        for (int64_t y = 0; y < 64; ++y)
            for (int64_t x = 0; x < 64; ++x) {
                const double r = std::hypot(x + 0.5 - 32.0, y + 0.5 - 32.0);
                for (int c = 0; c < 3; ++c) t.image.at(x, y)[c] = r >= 10.0 && r <= 18.0 ? 1.0f : 0.0f;
            }
        return t;
    };
    ScoreOptions options;
    options.random_angles = 0;
    auto recorded = scoreModel(model, truth, options);
    ASSERT_TRUE(recorded) << recorded.error().message;
    for (const AngleScore& a : recorded->angles) {
        EXPECT_EQ(a.light_mask_px, 20.0) << a.angle_deg;
        EXPECT_EQ(a.rel_l2, 0.0) << a.angle_deg;
        EXPECT_EQ(a.masked_energy_fraction, 1.0) << a.angle_deg;
    }
    // Asked for the old fixed disc, the ring is scored and missed.
    options.light_mask_px = 0.03 * std::hypot(64.0, 64.0);
    auto fixed = scoreModel(model, truth, options);
    ASSERT_TRUE(fixed) << fixed.error().message;
    for (const AngleScore& a : fixed->angles) EXPECT_EQ(a.rel_l2, 1.0) << a.angle_deg;
    // A model that records none falls back to the 3 %.
    model.capture.light_discs.clear();
    options.light_mask_px = -1.0;
    auto old = scoreModel(model, truth, options);
    ASSERT_TRUE(old) << old.error().message;
    EXPECT_NEAR(old->angles.front().light_mask_px, 0.03 * std::hypot(64.0, 64.0), 1e-12);
}

// The measured truth (`score --measured`): a sweep of three 64 x 48 frames on a sky of 5, each
// with a light (a disc of 4 px radius at 5000 on the left) and a ghost (a 10 x 10 px square of
// 40 on the right); the middle frame also holds a veil of 3 over the whole frame (a ghost larger
// than the frame). The truth is each frame less the sky, the veil kept; the light where it is.
TEST(MeasuredTruth, TheFramesLessTheSkyWithTheLightWhereItIs) {
    namespace fs = std::filesystem;
    const fs::path root =
        fs::temp_directory_path() / ("flarelab_measured_truth_" + std::to_string(::getpid()));
    fs::remove_all(root);
    constexpr int64_t kW = 64, kH = 48;
    constexpr float kSky = 5.0f, kVeil = 3.0f, kGhost = 40.0f, kLight = 5000.0f;
    const std::vector<double> angles = {0.0, 0.5, 1.0};
    hdr::SweepHeader header;
    header.software_version = "test";
    header.lens.description = "test lens";
    header.camera.description = "test camera";
    header.capture.from_deg = 0.0;
    header.capture.to_deg = 1.0;
    header.capture.step_deg = 0.5;
    header.capture.width_px = kW;
    header.capture.height_px = kH;
    auto writer = hdr::SweepWriter::create((root / "sweep").string(), header);
    ASSERT_TRUE(writer) << writer.error().message;
    std::vector<ImageRGB> frames;
    for (size_t i = 0; i < angles.size(); ++i) {
        ImageRGB image(kW, kH);
        for (int64_t y = 0; y < kH; ++y)
            for (int64_t x = 0; x < kW; ++x) {
                float v = kSky + (i == 1 ? kVeil : 0.0f);
                // A little texture, so that the sky is a level with noise around it.
                v += 0.01f * static_cast<float>((x * 7 + y * 13) % 5 - 2);
                if (x >= 40 && x < 50 && y >= 19 && y < 29) v += kGhost;
                if (std::hypot(x + 0.5 - 16.0, y + 0.5 - 24.0) < 4.0) v += kLight;
                for (int c = 0; c < 3; ++c) image.at(x, y)[c] = v;
            }
        hdr::SweepFrame frame;
        frame.angle_deg = angles[i];
        auto added = writer->addFrame(image, frame);
        ASSERT_TRUE(added) << added.error().message;
        frames.push_back(std::move(image));
    }
    ASSERT_TRUE(writer->finish());
    const hdr::Sweep sweep = writer->sweep();
    auto truth = measuredTruth(sweep, 6.4, 4.8);
    ASSERT_TRUE(truth) << truth.error().message;
    for (size_t i = 0; i < angles.size(); ++i) {
        auto t = (*truth)(angles[i]);
        ASSERT_TRUE(t) << t.error().message;
        ASSERT_EQ(t->image.width, kW);
        ASSERT_EQ(t->image.height, kH);
        // The same sky is taken from every frame: the lowest background of the frames (the
        // first's and the last's level), not the middle frame's own, which holds the veil.
        const double subtracted = frames[i].at(0, 0)[1] - t->image.at(0, 0)[1];
        EXPECT_NEAR(subtracted, kSky, 0.03) << angles[i];
        for (int64_t y = 0; y < kH; ++y)
            for (int64_t x = 0; x < kW; ++x)
                for (int c = 0; c < 3; ++c)
                    ASSERT_NEAR(t->image.at(x, y)[c], frames[i].at(x, y)[c] - subtracted, 1e-3)
                        << x << ", " << y;
        EXPECT_NEAR(t->image.at(60, 5)[1], i == 1 ? kVeil : 0.0, 0.03) << angles[i];
        EXPECT_NEAR(t->image.at(45, 24)[1], kGhost + (i == 1 ? kVeil : 0.0), 0.03) << angles[i];
        ASSERT_TRUE(t->light_px.has_value()) << angles[i];
        EXPECT_NEAR(t->light_px->x(), 16.0, 1.0);
        EXPECT_NEAR(t->light_px->y(), 24.0, 1.0);
    }
    // Angles no frame was captured at, and what cannot be a truth at all.
    for (const double between : {0.25, -1.0, std::nan("")}) {
        auto t = (*truth)(between);
        ASSERT_FALSE(t) << between;
        EXPECT_EQ(t.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(t.error().message.find("no frame captured at"), std::string::npos)
            << t.error().message;
    }
    EXPECT_FALSE(measuredTruth(sweep, 0.0, 4.8));
    EXPECT_FALSE(measuredTruth(sweep, 6.4, std::nan("")));
    DetectOptions bad;
    bad.threshold_sigmas = -1.0;
    EXPECT_FALSE(measuredTruth(sweep, 6.4, 4.8, bad));
    hdr::Sweep empty = sweep;
    empty.frames.clear();
    auto none = measuredTruth(empty, 6.4, 4.8);
    ASSERT_FALSE(none);
    EXPECT_NE(none.error().message.find("no frames"), std::string::npos) << none.error().message;
    fs::remove_all(root);
}

}  // namespace
}  // namespace flarelab::fit
