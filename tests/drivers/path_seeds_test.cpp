#include "drivers/path_seeds.h"

#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "drivers/sim_truth.h"
#include "optics/ghosts.h"
#include "optics/prescription.h"
#include "render/ghost_quads.h"
#include "tests/test_lenses.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

using flarelab::testing::heliar;

struct Box {
    double x0 = std::numeric_limits<double>::infinity(), y0 = x0;
    double x1 = -std::numeric_limits<double>::infinity(), y1 = x1;
};

// Every seed's outline spans what the simulator draws of its path alone: the box of the pixels
// the path lights (above a thousandth of its brightest) against the box of the seed's outline in
// the frame, to 2 px plus 3 % of the ghost's size (the simulator's three wavelengths and its grid
// spread the edges by a few pixels at this size). Vignetting included: a ghost cut by a clear
// aperture is seeded with the cut box, not the stop image's whole disc.
TEST(PathSeeds, OutlinesSpanWhatTheSimulatorDrawsOfEachPath) {
    constexpr float kLitFraction = 1e-3f;
    constexpr int64_t kW = 320, kH = 214;
    auto seeder = pathSeeder(heliar());
    ASSERT_TRUE(seeder) << seeder.error().message;
    auto paths = optics::enumerateGhosts(heliar());
    ASSERT_TRUE(paths);
    const auto mapping = render::sensorToImage(heliar().camera(), kW, kH);
    int compared = 0;
    for (const double angle : {4.0, 15.0, 25.0}) {
        auto seeds = (*seeder)(angle);
        ASSERT_TRUE(seeds) << seeds.error().message;
        ASSERT_FALSE(seeds->empty()) << angle;
        for (size_t a = 0; a < seeds->size(); ++a)
            for (size_t b = a + 1; b < seeds->size(); ++b)
                EXPECT_NE((*seeds)[a].path, (*seeds)[b].path);
        for (const fit::PathSeed& seed : *seeds) {
            ASSERT_GE(seed.path, 0);
            ASSERT_LT(seed.path, static_cast<int64_t>(paths->ghosts.size()));
            EXPECT_TRUE(render::validateGhostShape(seed.shape));
            auto truth = simulatedGhostTruth(heliar(), kW, kH,
                                             {paths->ghosts[static_cast<size_t>(seed.path)]});
            ASSERT_TRUE(truth) << truth.error().message;
            auto frame = (*truth)(angle);
            ASSERT_TRUE(frame) << frame.error().message;
            float peak = 0.0f;
            for (float v : frame->image.pixels) peak = std::max(peak, v);
            if (!(peak > 0.0f)) continue;  // lit only off the frame
            Box lit;
            for (int64_t y = 0; y < kH; ++y)
                for (int64_t x = 0; x < kW; ++x)
                    if (frame->image.at(x, y)[1] > kLitFraction * peak) {
                        lit.x0 = std::min(lit.x0, static_cast<double>(x));
                        lit.x1 = std::max(lit.x1, static_cast<double>(x + 1));
                        lit.y0 = std::min(lit.y0, static_cast<double>(y));
                        lit.y1 = std::max(lit.y1, static_cast<double>(y + 1));
                    }
            // The seed's outline (an ellipse through its box) as the frame shows it.
            const auto& s = seed.shape;
            Box drawn;
            for (int64_t y = 0; y < kH; ++y)
                for (int64_t x = 0; x < kW; ++x) {
                    const double dx =
                        (x + 0.5 - mapping.centre_x_px) / mapping.px_per_mm_x - s.centre_x_mm;
                    const double dy =
                        (y + 0.5 - mapping.centre_y_px) / mapping.px_per_mm_y - s.centre_y_mm;
                    const double ex = dx < 0.0 ? s.left_mm : s.right_mm;
                    if (std::hypot(dx / ex, dy / s.half_height_mm) > 1.0) continue;
                    drawn.x0 = std::min(drawn.x0, static_cast<double>(x));
                    drawn.x1 = std::max(drawn.x1, static_cast<double>(x + 1));
                    drawn.y0 = std::min(drawn.y0, static_cast<double>(y));
                    drawn.y1 = std::max(drawn.y1, static_cast<double>(y + 1));
                }
            // A sliver at the frame's edge (under 24 px across in view) is left out: there a
            // tenth of a pixel along the light's line moves its visible height by many.
            if (!(drawn.x1 - drawn.x0 >= 24.0 && drawn.y1 - drawn.y0 >= 24.0 &&
                  lit.x1 - lit.x0 >= 24.0 && lit.y1 - lit.y0 >= 24.0))
                continue;
            const double size_px =
                std::max(s.left_mm + s.right_mm, 2.0 * s.half_height_mm) * mapping.px_per_mm_x;
            const double tolerance = 2.0 + 0.03 * size_px;
            const std::string where =
                "path " + optics::pathLabel(paths->ghosts[static_cast<size_t>(seed.path)]) +
                " at " + std::to_string(angle) + " deg";
            EXPECT_NEAR(drawn.x0, lit.x0, tolerance) << where;
            EXPECT_NEAR(drawn.x1, lit.x1, tolerance) << where;
            EXPECT_NEAR(drawn.y0, lit.y0, tolerance) << where;
            EXPECT_NEAR(drawn.y1, lit.y1, tolerance) << where;
            ++compared;
        }
    }
    EXPECT_GE(compared, 12);
}

TEST(PathSeeds, RefusesWhatItCannotSeed) {
    EXPECT_FALSE(pathSeeder(heliar(), -0.1));
    EXPECT_FALSE(pathSeeder(heliar(), 1.0));
    auto seeder = pathSeeder(heliar());
    ASSERT_TRUE(seeder);
    for (const double bad : {90.0, -95.0, std::nan(""), std::numeric_limits<double>::infinity()}) {
        auto seeds = (*seeder)(bad);
        ASSERT_FALSE(seeds) << bad;
        EXPECT_EQ(seeds.error().code, ErrorCode::InvalidArgument);
    }
    // Far beyond the lens's field, nothing gets through: no seeds, no error.
    auto far = (*seeder)(80.0);
    ASSERT_TRUE(far) << far.error().message;
    EXPECT_TRUE(far->empty());
    // Fewer seeds the higher the share a path must carry.
    auto all = pathSeeder(heliar(), 0.0);
    auto few = pathSeeder(heliar(), 0.2);
    ASSERT_TRUE(all && few);
    EXPECT_GT((*all)(10.0)->size(), (*few)(10.0)->size());
}

// The paths are traced on every core; the seeds are the same on one thread, bit for bit.
TEST(PathSeeds, TheSeedsDoNotDependOnTheThreads) {
    auto seeder = pathSeeder(heliar(), 0.0);
    ASSERT_TRUE(seeder);
    for (const double angle : {0.0, 7.3, -15.0}) {
        auto many = (*seeder)(angle);
        ASSERT_TRUE(many) << many.error().message;
        tbb::task_arena one(1);
        Result<std::vector<fit::PathSeed>> single = std::vector<fit::PathSeed>{};
        one.execute([&] { single = (*seeder)(angle); });
        ASSERT_TRUE(single) << single.error().message;
        ASSERT_EQ(many->size(), single->size()) << angle;
        EXPECT_FALSE(many->empty()) << angle;
        for (size_t k = 0; k < many->size(); ++k) {
            EXPECT_EQ((*many)[k].path, (*single)[k].path) << angle;
            EXPECT_EQ((*many)[k].shape, (*single)[k].shape) << angle << " path " << (*many)[k].path;
        }
    }
}

}  // namespace
}  // namespace flarelab::drivers
