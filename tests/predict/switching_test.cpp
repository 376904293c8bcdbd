#include "predict/switching.h"

#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <random>
#include <tuple>

namespace flarelab::predict {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

SwitchingPlan plan(const std::vector<std::vector<double>>& f, double threshold, int64_t dwell) {
    auto p = planSwitching(f, SwitchingOptions{threshold, dwell});
    EXPECT_TRUE(p) << p.error().message;
    return p ? *p : SwitchingPlan{};
}

TEST(PlanSwitching, CutsAwayFromAFlareAndBack) {
    // Camera 0 flares at steps 4..7, camera 1 at the start and the end.
    const std::vector<std::vector<double>> f = {
        {0, 0, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0},
        {1, 1, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 1, 1}};
    const SwitchingPlan p = plan(f, 0.1, 2);
    EXPECT_EQ(p.steps_over, 0);
    EXPECT_EQ(p.cuts, 2);
    ASSERT_EQ(p.segments.size(), 3u);
    EXPECT_EQ(p.segments[0].camera, 0);
    EXPECT_EQ(p.segments[1].camera, 1);
    EXPECT_EQ(p.segments[1].first_step, 4);
    EXPECT_EQ(p.segments[1].end_step, 8);
    EXPECT_EQ(p.segments[2].camera, 0);
    EXPECT_TRUE(p.no_clean_camera.empty());
}

TEST(PlanSwitching, HoldsAShotForItsDwellEvenThroughAFlare) {
    // Camera 1 is clean for two steps only; with a dwell of 4 a cut there would put four steps
    // on camera 1 (two of them over) to save two: the plan stays and takes the two.
    const std::vector<std::vector<double>> f = {{0, 0, 0, 0, 1, 1, 0, 0, 0, 0},
                                                {1, 1, 1, 1, 0, 0, 1, 1, 1, 1}};
    const SwitchingPlan p = plan(f, 0.5, 4);
    EXPECT_EQ(p.steps_over, 2);
    EXPECT_EQ(p.cuts, 0);
    ASSERT_EQ(p.segments.size(), 1u);
    // With a dwell of 2 the cut pays.
    EXPECT_EQ(plan(f, 0.5, 2).steps_over, 0);
}

TEST(PlanSwitching, ReportsWhenNoCameraIsCleanAndCountsUnknownAsOver) {
    const std::vector<std::vector<double>> f = {{0, 1, 1, kNaN, 0, 0}, {0, 1, kNaN, 1, 1, 0}};
    const SwitchingPlan p = plan(f, 0.5, 1);
    ASSERT_EQ(p.no_clean_camera.size(), 1u);
    EXPECT_EQ(p.no_clean_camera[0].first_step, 1);
    EXPECT_EQ(p.no_clean_camera[0].end_step, 4);
    EXPECT_EQ(p.steps_over, 3);
    // A single camera: its plan is the camera, whatever happens.
    const SwitchingPlan one = plan({{kNaN, kNaN, 0}}, 0.1, 10);
    ASSERT_EQ(one.segments.size(), 1u);
    EXPECT_EQ(one.segments[0].end_step, 3);
    EXPECT_EQ(one.steps_over, 2);
}

// Every plan, by brute force: the lexicographic best of (steps over, cuts, sum) among camera
// sequences whose shots, all but the last, last at least `dwell` steps.
std::tuple<int64_t, int64_t, double> bruteForce(const std::vector<std::vector<double>>& f,
                                                double threshold,
                                                int64_t dwell) {
    const int cameras = static_cast<int>(f.size());
    const int steps = static_cast<int>(f[0].size());
    std::tuple<int64_t, int64_t, double> best{INT64_MAX, 0, 0.0};
    std::vector<int> seq(static_cast<size_t>(steps), 0);
    std::function<void(int)> walk = [&](int t) {
        if (t == steps) {
            int64_t over = 0, cuts = 0, run = 1;
            double sum = 0.0;
            for (int i = 0; i < steps; ++i) {
                const double v = f[static_cast<size_t>(seq[i])][static_cast<size_t>(i)];
                over += !(v <= threshold);
                sum += std::isfinite(v) ? v : 0.0;
                if (i > 0 && seq[i] != seq[i - 1]) {
                    if (run < dwell) return;
                    ++cuts;
                    run = 1;
                } else if (i > 0) {
                    ++run;
                }
            }
            const std::tuple<int64_t, int64_t, double> cost{over, cuts, sum};
            if (std::get<0>(cost) < std::get<0>(best) ||
                (std::get<0>(cost) == std::get<0>(best) &&
                 (std::get<1>(cost) < std::get<1>(best) ||
                  (std::get<1>(cost) == std::get<1>(best) &&
                   std::get<2>(cost) < std::get<2>(best)))))
                best = cost;
            return;
        }
        for (int c = 0; c < cameras; ++c) {
            seq[static_cast<size_t>(t)] = c;
            walk(t + 1);
        }
    };
    walk(0);
    return best;
}

TEST(PlanSwitching, MatchesABruteForceSearchOnRandomTimelines) {
    std::mt19937_64 rng(17);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    for (int trial = 0; trial < 40; ++trial) {
        const int cameras = 2 + trial % 2, steps = 9;
        const int64_t dwell = 1 + trial % 4;
        std::vector<std::vector<double>> f(static_cast<size_t>(cameras));
        for (auto& c : f)
            for (int t = 0; t < steps; ++t) c.push_back(u(rng) < 0.05 ? kNaN : u(rng));
        const SwitchingPlan p = plan(f, 0.6, dwell);
        const auto [over, cuts, sum] = bruteForce(f, 0.6, dwell);
        EXPECT_EQ(p.steps_over, over) << "trial " << trial;
        EXPECT_EQ(p.cuts, cuts) << "trial " << trial;
        EXPECT_NEAR(p.figure_sum, sum, 1e-9) << "trial " << trial;
        // The segments say the same as the totals, and respect the dwell.
        int64_t step = 0, counted_over = 0;
        for (size_t s = 0; s < p.segments.size(); ++s) {
            EXPECT_EQ(p.segments[s].first_step, step);
            if (s + 1 < p.segments.size()) {
                EXPECT_GE(p.segments[s].end_step - p.segments[s].first_step, dwell);
            }
            for (int64_t t = p.segments[s].first_step; t < p.segments[s].end_step; ++t)
                counted_over +=
                    !(f[static_cast<size_t>(p.segments[s].camera)][static_cast<size_t>(t)] <= 0.6);
            step = p.segments[s].end_step;
        }
        EXPECT_EQ(step, steps);
        EXPECT_EQ(counted_over, p.steps_over);
    }
}

TEST(PlanSwitching, RefusesMalformedInput) {
    const SwitchingOptions ok{0.1, 1};
    EXPECT_FALSE(planSwitching(std::vector<std::vector<double>>{}, ok));
    EXPECT_FALSE(planSwitching(std::vector<std::vector<double>>{{}}, ok));
    EXPECT_FALSE(planSwitching(std::vector<std::vector<double>>{{1, 2}, {1}}, ok));
    EXPECT_FALSE(planSwitching(std::vector<std::vector<double>>{{1}}, SwitchingOptions{0.1, 0}));
    EXPECT_FALSE(planSwitching(std::vector<std::vector<double>>{{1}}, SwitchingOptions{kNaN, 1}));
    // Too many states for memory: refused with the way out named.
    const std::vector<std::vector<double>> big(100, std::vector<double>(100000, 0.0));
    auto refused = planSwitching(big, SwitchingOptions{0.1, 10});
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("longer step"), std::string::npos);
    // A dwell longer than the whole timeline is one shot.
    const SwitchingPlan p = plan({{1, 1, 1}, {0, 0, 0}}, 0.5, 1000);
    ASSERT_EQ(p.segments.size(), 1u);
    EXPECT_EQ(p.segments[0].camera, 1);
}

}  // namespace
}  // namespace flarelab::predict
