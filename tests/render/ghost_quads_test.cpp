#include "render/ghost_quads.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "common/units.h"
#include "tests/test_paths.h"

namespace flarelab::render {
namespace {

using optics::GhostPath;

optics::Lens heliar() {
    return *optics::Lens::make(
        *optics::loadPrescription(flarelab::testing::lensPath("heliar-tronnier.csv")),
        optics::CameraDescription{});
}

double channelSum(const ImageRGB& image, int channel) {
    double sum = 0.0;
    for (int64_t i = 0; i < image.width * image.height; ++i) {
        const float v = image.pixels[static_cast<size_t>(i) * 3 + channel];
        EXPECT_TRUE(std::isfinite(v));
        sum += v;
    }
    return sum;
}

TEST(AdaptiveGridSize, FollowsEquationThirteen) {
    EXPECT_EQ(adaptiveGridSize(256, 864.0, 864.0), 256);
    EXPECT_EQ(adaptiveGridSize(256, 2000.0, 864.0), 256);         // capped at 1
    EXPECT_EQ(adaptiveGridSize(256, 8.64, 864.0), 26);            // sqrt(0.01) = 0.1
    EXPECT_EQ(adaptiveGridSize(256, 1e-6, 864.0), 13);            // floored at 0.05
    EXPECT_EQ(adaptiveGridSize(256, 8.64, 864.0, 4.0, 0.5), 51);  // sigma scales the ratio
    EXPECT_EQ(adaptiveGridSize(16, 0.0, 864.0), 2);               // never below one quad
    EXPECT_EQ(adaptiveGridSize(64, std::nan(""), 864.0), 64);     // no ghost size: full grid
}

TEST(QuadsFromGrid, KeepsQuadsWithAValidCornerAndPlacesThemOnTheImage) {
    const optics::Lens lens = heliar();
    const auto grid = optics::traceRayGrid(lens, GhostPath{2, 3}, degToRad(5.0), 0.0, 550.0, 33);
    ASSERT_TRUE(grid);
    const SensorToImage mapping = sensorToImage(lens.camera(), 720, 480);
    EXPECT_DOUBLE_EQ(mapping.px_per_mm_x, 20.0);
    const GhostQuads ghost = quadsFromGrid(*grid, mapping);
    EXPECT_GT(ghost.quads.size(), 500u);
    EXPECT_LE(ghost.quads.size(), 32u * 32u);
    EXPECT_GT(ghost.cell_area_mm2, 0.0);
    for (const Quad& q : ghost.quads) {
        float best = 0.0f;
        for (const QuadCorner& c : q.corners) best = std::max(best, c.throughput);
        EXPECT_GT(best, 0.0f);
    }
    const auto one = optics::traceRayGrid(lens, GhostPath{2, 3}, 0.0, 0.0, 550.0, 1);
    EXPECT_TRUE(quadsFromGrid(*one, mapping).quads.empty());
}

// A ghost entirely inside the frame puts on it the power that entered through the cells of rays
// inside the stop, whatever the grid size: the reference rasterizer conserves energy.
TEST(RasterizeReference, ConservesTheGhostsPowerOnTheImage) {
    const optics::Lens lens = heliar();
    const SensorToImage mapping = sensorToImage(lens.camera(), 720, 480);
    for (int n : {33, 129, 257}) {  // 257: quads far below a pixel
        const auto grid =
            optics::traceRayGrid(lens, GhostPath{1, 3}, degToRad(1.0), 0.0, 550.0, n);  // 2-4: 3 mm
        ASSERT_TRUE(grid);
        const GhostQuads ghost = quadsFromGrid(*grid, mapping);
        double expected = 0.0;
        for (const optics::GridSample& s : grid->samples)
            if (s.valid && lens.aperture().contains(s.stop_u, s.stop_v))
                expected += s.throughput * ghost.cell_area_mm2;
        ImageRGB image(720, 480);
        rasterizeReference(image, ghost, 1, 1.0f, lens.aperture());
        EXPECT_NEAR(channelSum(image, 1), expected, 0.01 * expected) << n;
        EXPECT_EQ(channelSum(image, 0), 0.0);
    }
}

// A pixel wholly inside a convex quad, which no stop edge or clear aperture comes near, takes
// the throughput at its centre: primitiveValueAt evaluates it from the Wachspress sums expanded
// into polynomials of the pixel (Primitive::inside_total), and must agree with the weights
// evaluated directly (convexValueAt) to rounding. Masked quads (round stop, vignetting) as well:
// there a pixel counts as clear when the direct evaluation is lit at its centre and its corners
// and every clear aperture passes (a circle is convex, so the whole pixel is then inside it).
TEST(PrimitiveValueAt, InsidePixelsTakeTheThroughputAtTheirCentre) {
    const optics::Lens lens = heliar();
    const SensorToImage mapping = sensorToImage(lens.camera(), 480, 320);
    const StopMask stop(lens.aperture());
    int64_t unmasked_pixels = 0, masked_pixels = 0;
    for (const auto& [theta_deg, merge] : {std::pair{2.0, kLightMerge}, std::pair{9.0, kHeavyMerge},
                                           std::pair{16.0, kNoMerge}}) {
        for (const GhostPath path : {GhostPath{1, 3}, GhostPath{2, 6}, GhostPath{4, 7}}) {
            const auto grid =
                optics::traceRayGrid(lens, path, degToRad(theta_deg), 0.7, 550.0, 41);
            ASSERT_TRUE(grid);
            const GhostQuads ghost = quadsFromGrid(*grid, mapping, merge);
            for (size_t q = 0; q < ghost.quads.size(); ++q) {
                const auto p = preparePrimitive(ghost.quads[q], ghost.cellArea(q), 1, 1.0f, 480, 320);
                if (!p || !p->convex || p->splat) continue;
                const bool masked =
                    !(p->stop_radius <= stop.inscribedRadius()) || !p->vignette_clear;
                for (int64_t y = p->y0; y <= p->y1; ++y) {
                    for (int64_t x = p->x0; x <= p->x1; ++x) {
                        const double cx = static_cast<double>(x) + 0.5;
                        const double cy = static_cast<double>(y) + 0.5;
                        bool inside = true;
                        for (const EdgeFunction& e : p->edge)
                            inside = inside && (e.by_centre ? e.at(cx, cy) > 0.0
                                                            : e.at(cx, cy) >= 1.01 * e.reach);
                        if (!inside) continue;
                        const double centre = convexValueAt(*p, cx, cy, stop);
                        if (masked) {
                            if (!p->vignette_clear || !(centre > 0.0)) continue;
                            bool lit = true;
                            for (const double dx : {-0.5, 0.5})
                                for (const double dy : {-0.5, 0.5})
                                    lit = lit && convexValueAt(*p, cx + dx, cy + dy, stop) > 0.0;
                            if (!lit) continue;
                        }
                        const double value = primitiveValueAt(*p, x, y, stop);
                        ASSERT_NEAR(value, centre, 1e-9 * std::abs(centre) + 1e-300)
                            << "theta " << theta_deg << " quad " << q << " pixel " << x << ","
                            << y << (masked ? " masked" : "");
                        ++(masked ? masked_pixels : unmasked_pixels);
                    }
                }
            }
        }
    }
    EXPECT_GT(unmasked_pixels, 10000);
    EXPECT_GT(masked_pixels, 300);
}

TEST(RasterizeReference, DegenerateHugeAndOutsideQuadsNeverWriteNaN) {
    GhostQuads ghost;
    ghost.cell_area_mm2 = 1.0;
    const auto quad = [](Eigen::Vector2d a, Eigen::Vector2d b, Eigen::Vector2d c,
                         Eigen::Vector2d d) {
        Quad q;
        const Eigen::Vector2d p[4] = {a, b, c, d};
        for (int k = 0; k < 4; ++k) q.corners[k] = QuadCorner{p[k], 1.0f, 0.0f, 0.0f};
        return q;
    };
    const Eigen::Vector2d c(3.5, 3.5);
    ghost.quads.push_back(quad(c, c, c, c));                                          // a point
    ghost.quads.push_back(quad({1, 1}, {5, 5}, {3, 3}, {2, 2}));                      // zero area
    ghost.quads.push_back(quad({-1e9, -1e9}, {1e9, -1e9}, {1e9, 1e9}, {-1e9, 1e9}));  // huge
    ghost.quads.push_back(quad({1e12, 1e12}, {1e12 + 5, 1e12}, {1e12 + 5, 1e12 + 5},
                               {1e12, 1e12 + 5}));  // far outside
    const double inf = std::numeric_limits<double>::infinity();
    ghost.quads.push_back(quad({0, 0}, {inf, 0}, {inf, inf}, {0, inf}));  // not finite
    for (const auto& [w, h] : {std::pair<int64_t, int64_t>{8, 8}, {1, 1}, {0, 0}}) {
        ImageRGB image(w, h);
        rasterizeReference(image, ghost, 2, 1.0f, optics::ApertureShape{});
        for (float v : image.pixels) EXPECT_TRUE(std::isfinite(v));
    }
    ImageRGB image(8, 8);
    rasterizeReference(image, ghost, 0, std::nanf(""), optics::ApertureShape{});
    rasterizeReference(image, ghost, 0, 0.0f, optics::ApertureShape{});
    EXPECT_EQ(channelSum(image, 0), 0.0);
}

}  // namespace
}  // namespace flarelab::render
