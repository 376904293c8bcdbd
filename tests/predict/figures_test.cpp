#include "predict/figures.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <random>
#include <thread>
#include <vector>

#include "fit/model_eval.h"
#include "tests/predict/moving_disc_model.h"

namespace flarelab::predict {
namespace {

TEST(FlareFigures, MinMaxMeanAndLogAverageOfTheLuminance) {
    ImageRGB image(2, 2);
    const float values[4][3] = {{0, 0, 0}, {1, 1, 1}, {4, 4, 4}, {10, 0, 0}};
    for (int i = 0; i < 4; ++i)
        for (int c = 0; c < 3; ++c) image.pixels[static_cast<size_t>(3 * i + c)] = values[i][c];
    const FlareFigures f = flareFigures(image);
    EXPECT_DOUBLE_EQ(f.min, 0.0);
    EXPECT_NEAR(f.max, 4.0, 1e-12);
    EXPECT_NEAR(f.mean, (0.0 + 1.0 + 4.0 + 2.126) / 4.0, 1e-6);
    EXPECT_NEAR(f.total, 7.126, 1e-5);
    // The black pixel counts at 1e-6 of the peak.
    EXPECT_NEAR(f.log_average,
                std::exp((std::log(4e-6) + 0.0 + std::log(4.0) + std::log(2.126)) / 4.0), 1e-6);
    // Every figure scales with the light.
    for (float& v : image.pixels) v *= 8.0f;
    const FlareFigures g = flareFigures(image);
    EXPECT_NEAR(g.log_average, 8.0 * f.log_average, 1e-9 * g.log_average);
    EXPECT_NEAR(g.mean, 8.0 * f.mean, 1e-6);
    EXPECT_EQ(flareFigures(ImageRGB(3, 3)).log_average, 0.0);  // black: all zero, no NaN
    EXPECT_EQ(flareFigures(ImageRGB()).mean, 0.0);
}

TEST(ContrastRatio, FollowsEquation93) {
    EXPECT_EQ(contrastRatio(10.0, 1000.0, 0.0), 1.0);
    EXPECT_NEAR(contrastRatio(10.0, 1000.0, 5.0), 1010.0 / 1020.0, 1e-15);
    EXPECT_NEAR(contrastRatio(0.0, 1.0, 1e9), 5e-10, 1e-15);  // drowned, never negative
    EXPECT_DEATH(contrastRatio(10.0, 5.0, 1.0), "");
}

TEST(FlareFigureTable, AgreesWithDrawingEachConstellation) {
    const fit::FlareModel model = testing::movingDiscModel();
    FigureTableOptions options;
    options.theta_step_deg = 0.5;
    options.phi_step_deg = 10.0;
    options.width = 144;
    auto table = FlareFigureTable::build(model, options);
    ASSERT_TRUE(table) << table.error().message;
    EXPECT_EQ(table->thetaCount(), 21);
    EXPECT_EQ(table->phiCount(), 36);
    EXPECT_EQ(table->thetaAt(20), 10.0);
    // At the nodes: the turned canvas against the frame drawn at that roll.
    for (int64_t i : {0, 7, 20})
        for (int64_t j : {0, 5, 35}) {
            auto image = fit::renderModel(model, table->thetaAt(i), table->phiAt(j), 144, 96);
            ASSERT_TRUE(image);
            const FlareFigures direct = flareFigures(*image);
            const auto f = table->at(table->thetaAt(i), table->phiAt(j));
            ASSERT_TRUE(f);
            EXPECT_NEAR(f->mean, direct.mean, 0.02 * direct.mean) << i << " " << j;
            EXPECT_NEAR(f->max, direct.max, 0.02 * direct.max) << i << " " << j;
        }
    // Between nodes, against drawing the constellation itself (seeded random constellations).
    // Where the disc crosses the frame's edge the mean changes fast with roll and a small mean
    // can be far off relatively, so the worst error is taken against the largest mean.
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<double> theta(0.0, 10.0), phi(-180.0, 180.0);
    std::vector<double> relative;
    double worst = 0.0, largest = 0.0;
    for (int k = 0; k < 60; ++k) {
        const double t = theta(rng), p = phi(rng);
        auto image = fit::renderModel(model, t, p, 144, 96);
        ASSERT_TRUE(image);
        const double direct = flareFigures(*image).mean, tabled = table->at(t, p)->mean;
        relative.push_back(std::abs(tabled / direct - 1.0));
        worst = std::max(worst, std::abs(tabled - direct));
        largest = std::max(largest, direct);
    }
    std::sort(relative.begin(), relative.end());
    EXPECT_LT(relative[relative.size() / 2], 0.01);
    EXPECT_LT(worst, 0.05 * largest);
    // Roll matters only where the ghost leaves the frame: at 10 deg the disc (15 mm out) is cut
    // by the frame's top (12 mm) when the light is below, not by its side (18 mm) when it is to
    // the right.
    EXPECT_LT(table->at(10.0, 90.0)->mean, 0.8 * table->at(10.0, 0.0)->mean);
    EXPECT_NEAR(table->at(1.0, 90.0)->mean, table->at(1.0, 0.0)->mean,
                0.02 * table->at(1.0, 0.0)->mean);
    // Periodic in roll; nothing outside the model's angles.
    EXPECT_NEAR(table->at(3.3, 350.0)->mean, table->at(3.3, -10.0)->mean, 1e-12);
    EXPECT_FALSE(table->at(10.5, 0.0));
    EXPECT_FALSE(table->at(-0.1, 0.0));
    EXPECT_FALSE(table->at(2.0, std::nan("")));
}

TEST(FlareFigureTable, CoversEveryAngleTheModelDrawsOnEitherSide) {
    // Head angles -20..10: a light at theta 15 is the head angle -15 turned half a turn.
    fit::FlareModel model = testing::movingDiscModel();
    model.capture.from_deg = model.valid_from_deg = -20.0;
    auto table = FlareFigureTable::build(model, tableOptions(1.0, 30.0, 48));
    ASSERT_TRUE(table) << table.error().message;
    EXPECT_EQ(table->thetaFromDeg(), 0.0);
    EXPECT_EQ(table->thetaToDeg(), 20.0);
    EXPECT_TRUE(table->at(15.0, 0.0));
    // At 5 deg the disc is drawn directly; the table agrees with drawing it.
    auto image = fit::renderModel(model, 5.0, 0.0, 48, 32);
    ASSERT_TRUE(image);
    EXPECT_NEAR(table->at(5.0, 0.0)->mean, flareFigures(*image).mean,
                0.03 * flareFigures(*image).mean);
}

TEST(FlareFigureTable, StopsBetweenAngles) {
    // Asked before each angle is drawn: told to stop at the fifth question, the build ends with
    // "stopped" having asked at most once more per worker thread, not once per angle (41).
    const fit::FlareModel model = testing::movingDiscModel();
    std::atomic<int> asked{0};
    FigureTableOptions options = tableOptions(0.25, 30.0, 48);
    options.stop_requested = [&] { return ++asked >= 5; };
    auto table = FlareFigureTable::build(model, options);
    ASSERT_FALSE(table);
    EXPECT_EQ(table.error().code, ErrorCode::Unsupported);
    EXPECT_EQ(table.error().message, "figure table: stopped");
    EXPECT_LE(asked.load(), 5 + static_cast<int>(std::thread::hardware_concurrency()));
    // Never told to stop: the whole table, one question per angle.
    asked = 0;
    options.stop_requested = [&] { return ++asked < 0; };
    table = FlareFigureTable::build(model, options);
    ASSERT_TRUE(table) << table.error().message;
    EXPECT_EQ(asked.load(), table->thetaCount());
}

TEST(FlareFigureTable, RefusesBadOptionsAndEmptyRanges) {
    const fit::FlareModel model = testing::movingDiscModel();
    FigureTableOptions o;
    o.phi_step_deg = 7.0;  // does not divide 360
    EXPECT_FALSE(FlareFigureTable::build(model, o));
    o = {};
    o.width = 2;
    EXPECT_FALSE(FlareFigureTable::build(model, o));
    o = {};
    o.theta_step_deg = -1.0;
    EXPECT_FALSE(FlareFigureTable::build(model, o));
    // A model of no ghost tables zeros, not an error.
    auto empty = FlareFigureTable::build(testing::movingDiscModel(0), FigureTableOptions{});
    ASSERT_TRUE(empty) << empty.error().message;
    EXPECT_EQ(empty->at(5.0, 0.0)->mean, 0.0);
}

}  // namespace
}  // namespace flarelab::predict
