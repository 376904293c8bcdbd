#include "render/model_ghost.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <numbers>

#include "render/tiles.h"

namespace flarelab::render {
namespace {

SensorToImage mappingFor(int64_t width, int64_t height) {
    SensorToImage m;
    m.px_per_mm_x = static_cast<double>(width) / 36.0;
    m.px_per_mm_y = static_cast<double>(height) / 24.0;
    m.centre_x_px = 0.5 * static_cast<double>(width);
    m.centre_y_px = 0.5 * static_cast<double>(height);
    return m;
}

GhostShading shading(double border, double inner) {
    GhostShading s;
    s.border_rgb = {border, 0.5 * border, 0.25 * border};
    s.inner_rgb = {inner, 0.5 * inner, 0.25 * inner};
    s.inner_falloff_mm = 0.8;
    s.outer_falloff_mm = 0.5;
    return s;
}

// Every pixel of the tiled image equals the ghost's mean shading over the pixel, summed over the
// ghosts, and nothing lies outside the ghosts' ranges.
TEST(ModelGhostPrimitive, TilesDrawEachPixelOnceWithTheGhostsShading) {
    const int64_t w = 200, h = 133;
    const SensorToImage m = mappingFor(w, h);
    const BezierLoop a = toBezierLoop(circleGhostShape(-3.0, 1.0, 5.0));
    const BezierLoop b = toBezierLoop(circleGhostShape(4.0, -2.0, 2.5));
    const GhostShading sa = shading(100.0, 30.0), sb = shading(50.0, 80.0);
    std::vector<GhostPrimitive> ghosts;
    for (const auto& [loop, s] : {std::pair{a, sa}, std::pair{b, sb}}) {
        auto p = prepareGhostPrimitive(loop, s, m, w, h);
        ASSERT_TRUE(p.has_value());
        ghosts.push_back(*p);
    }
    for (const TileOptions tiles :
         {TileOptions{}, TileOptions{16, 4, true}, TileOptions{8, 8, false}}) {
        ImageRGB image(w, h);
        TileStats stats;
        ASSERT_TRUE(
            renderTiled(image, {}, ghosts, optics::ApertureShape{}, tiles, &stats).has_value());
        EXPECT_EQ(stats.primitives, 2);
        const Eigen::Vector2d half_pixel(0.5 / m.px_per_mm_x, 0.5 / m.px_per_mm_y);
        for (int64_t y = 0; y < h; ++y) {
            for (int64_t x = 0; x < w; ++x) {
                const Eigen::Vector2d q((x + 0.5 - m.centre_x_px) / m.px_per_mm_x,
                                        (y + 0.5 - m.centre_y_px) / m.px_per_mm_y);
                double expected[3] = {0.0, 0.0, 0.0};
                for (size_t g = 0; g < ghosts.size(); ++g) {
                    const bool in = x >= ghosts[g].x0 && x <= ghosts[g].x1 && y >= ghosts[g].y0 &&
                                    y <= ghosts[g].y1;
                    const auto v =
                        shadeGhostBlock(ghosts[g].loop_mm, ghosts[g].shading, q, half_pixel);
                    for (int c = 0; c < 3; ++c) {
                        if (!in) {
                            // Outside its range the ghost is zero: the range is exact.
                            ASSERT_EQ(v[c], 0.0) << x << "," << y;
                        }
                        expected[c] += static_cast<float>(v[c]);
                    }
                }
                for (int c = 0; c < 3; ++c)
                    ASSERT_NEAR(image.at(x, y)[c], expected[c], 1e-4 * (1.0 + expected[c]))
                        << x << "," << y << " channel " << c;
            }
        }
    }
}

// A disc sharper than a pixel is drawn as pixels record it: its light summed over the image is
// its area times its intensity (point samples at pixel centres would be off by the lattice's
// count of centres inside, here about 1 %), and the pixels its edge crosses are partly lit.
TEST(ModelGhostPrimitive, SharpEdgesAreAntiAliasedAndKeepTheDiscsEnergy) {
    const int64_t w = 120, h = 90;
    const SensorToImage m = mappingFor(w, h);
    GhostShading sharp = shading(2.0, 2.0);
    sharp.inner_falloff_mm = 1e-4;
    sharp.outer_falloff_mm = 1e-4;
    for (const double radius : {3.3, 7.77, 0.9}) {
        auto g = prepareGhostPrimitive(toBezierLoop(circleGhostShape(0.37, -0.21, radius)), sharp,
                                       m, w, h);
        ASSERT_TRUE(g.has_value());
        ImageRGB image(w, h);
        ASSERT_TRUE(renderTiled(image, {}, std::vector<GhostPrimitive>{*g}, optics::ApertureShape{})
                        .has_value());
        double sum = 0.0;
        int partial = 0;
        for (int64_t y = 0; y < h; ++y)
            for (int64_t x = 0; x < w; ++x) {
                const double v = image.at(x, y)[0];
                sum += v;
                if (v > 0.1 && v < 1.9) ++partial;
            }
        const double pixel_area = 1.0 / (m.px_per_mm_x * m.px_per_mm_y);
        // The Bezier circle is within 0.03 % of a true one in radius; the pixel mean takes the
        // edge as straight across a pixel, which a disc 3 pixels across bends by about 1 %.
        const double area = std::numbers::pi * radius * radius;
        const double tolerance = radius * m.px_per_mm_x > 10.0 ? 2e-3 : 1.5e-2;
        EXPECT_NEAR(sum * pixel_area / 2.0, area, tolerance * area) << "radius " << radius;
        EXPECT_GT(partial, 0) << "radius " << radius;
    }
}

TEST(ModelGhostPrimitive, QuadsAndGhostsShareTheTiles) {
    const int64_t w = 64, h = 48;
    const SensorToImage m = mappingFor(w, h);
    auto g = prepareGhostPrimitive(toBezierLoop(circleGhostShape(0.0, 0.0, 6.0)),
                                   shading(10.0, 5.0), m, w, h);
    ASSERT_TRUE(g.has_value());
    ImageRGB only_ghost(w, h), both(w, h);
    ASSERT_TRUE(
        renderTiled(only_ghost, {}, std::vector<GhostPrimitive>{*g}, optics::ApertureShape{})
            .has_value());
    // A bad quad range is still refused when ghosts come along.
    Primitive bad;
    bad.x0 = 0;
    bad.x1 = w;  // one past the image
    bad.y0 = 0;
    bad.y1 = 0;
    EXPECT_FALSE(renderTiled(both, std::vector<Primitive>{bad}, std::vector<GhostPrimitive>{*g},
                             optics::ApertureShape{})
                     .has_value());
    GhostPrimitive outside = *g;
    outside.y1 = h;
    EXPECT_FALSE(
        renderTiled(both, {}, std::vector<GhostPrimitive>{outside}, optics::ApertureShape{})
            .has_value());
}

TEST(ModelGhostPrimitive, RangesClipAndRefuseWhatCannotBeDrawn) {
    const int64_t w = 100, h = 80;
    const SensorToImage m = mappingFor(w, h);
    // Image-filling: the range is the whole image.
    auto big = prepareGhostPrimitive(toBezierLoop(circleGhostShape(0.0, 0.0, 100.0)),
                                     shading(1.0, 1.0), m, w, h);
    ASSERT_TRUE(big.has_value());
    EXPECT_EQ(big->x0, 0);
    EXPECT_EQ(big->y0, 0);
    EXPECT_EQ(big->x1, w - 1);
    EXPECT_EQ(big->y1, h - 1);
    // Tiny: a ghost smaller than a pixel gets a range no wider than its outer falloff and the
    // half diagonal of the pixels that average it on either side (or none).
    auto tiny = prepareGhostPrimitive(toBezierLoop(circleGhostShape(0.01, 0.01, 0.001)),
                                      shading(1.0, 1.0), m, w, h);
    if (tiny) {
        const double half_diagonal_mm = 0.5 * std::hypot(1.0 / m.px_per_mm_x, 1.0 / m.px_per_mm_y);
        const double reach_px = (0.001 + 0.5 + half_diagonal_mm) * m.px_per_mm_x;
        EXPECT_LE(tiny->x1 - tiny->x0, static_cast<int64_t>(std::ceil(2.0 * reach_px)));
        EXPECT_GE(tiny->x1 - tiny->x0, 1);
    }
    // Off the image, black, non-finite or invalid: nothing to draw.
    EXPECT_FALSE(prepareGhostPrimitive(toBezierLoop(circleGhostShape(100.0, 0.0, 2.0)),
                                       shading(1.0, 1.0), m, w, h));
    EXPECT_FALSE(prepareGhostPrimitive(toBezierLoop(circleGhostShape(0.0, 0.0, 2.0)),
                                       shading(0.0, 0.0), m, w, h));
    BezierLoop nan_loop = toBezierLoop(circleGhostShape(0.0, 0.0, 2.0));
    nan_loop.control_points_mm[3].x() = std::numeric_limits<double>::quiet_NaN();
    EXPECT_FALSE(prepareGhostPrimitive(nan_loop, shading(1.0, 1.0), m, w, h));
    GhostShading negative = shading(1.0, 1.0);
    negative.outer_falloff_mm = -1.0;
    EXPECT_FALSE(
        prepareGhostPrimitive(toBezierLoop(circleGhostShape(0.0, 0.0, 2.0)), negative, m, w, h));
    EXPECT_FALSE(prepareGhostPrimitive(BezierLoop{}, shading(1.0, 1.0), m, w, h));
}

}  // namespace
}  // namespace flarelab::render
