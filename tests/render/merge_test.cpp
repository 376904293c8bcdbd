// Primitive merge (ghost_quads.h, Bodonyi & Kunkli 2023 §4.2) on synthetic grids whose shape on
// the sensor is known exactly.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>

#include "render/ghost_quads.h"
#include "render/metrics.h"

namespace flarelab::render {
namespace {

// An n x n grid whose ray (ix, iy) lands at place(ix, iy) (pixels, with a 1 px/mm mapping), all
// rays valid with throughput 1, stop coordinates spread over [-0.5, 0.5].
optics::RayGrid syntheticGrid(int n, const std::function<Eigen::Vector2d(int, int)>& place) {
    optics::RayGrid grid;
    grid.n = n;
    grid.entry_half_width_mm = 0.5 * (n - 1);  // cell 1 mm
    grid.samples.resize(static_cast<size_t>(n) * n);
    for (int iy = 0; iy < n; ++iy)
        for (int ix = 0; ix < n; ++ix) {
            optics::GridSample& s = grid.samples[static_cast<size_t>(iy) * n + ix];
            const Eigen::Vector2d p = place(ix, iy);
            s.sensor_x_mm = static_cast<float>(p.x());
            s.sensor_y_mm = static_cast<float>(p.y());
            s.throughput = 1.0f;
            s.stop_u = static_cast<float>(ix) / (n - 1) - 0.5f;
            s.stop_v = static_cast<float>(iy) / (n - 1) - 0.5f;
            s.valid = s.has_position = true;
        }
    return grid;
}

const SensorToImage kIdentity{1.0, 1.0, 0.0, 0.0};

int64_t totalCells(const GhostQuads& q) {
    int64_t cells = 0;
    for (size_t i = 0; i < q.quads.size(); ++i) cells += q.cells.empty() ? 1 : q.cells[i];
    return cells;
}

TEST(PrimitiveMerge, AnAffineGridMergesIntoBlocksAndKeepsEveryCell) {
    // 33 x 33 rays, 32 x 32 cells, sheared and scaled: every line stays straight. The offsets
    // keep pixel centres off the outer edges, where merged and single quads round differently.
    const auto grid = syntheticGrid(33, [](int ix, int iy) {
        return Eigen::Vector2d(10.0123 + 3.0 * ix + 0.5 * iy, 7.0371 + 2.5 * iy + 0.2 * ix);
    });
    const GhostQuads plain = quadsFromGrid(grid, kIdentity);
    EXPECT_EQ(plain.quads.size(), 32u * 32u);
    const GhostQuads merged = quadsFromGrid(grid, kIdentity, kLightMerge);
    EXPECT_EQ(merged.quads.size(), 4u);  // four blocks of 16 x 16 cells after 4 steps
    EXPECT_EQ(totalCells(merged), 32 * 32);
    const GhostQuads two = quadsFromGrid(grid, kIdentity, {2, 0.001});
    EXPECT_EQ(two.quads.size(), 8u * 8u);

    // The same light on the image either way.
    ImageRGB a(140, 110), b(140, 110);
    rasterizeReference(a, plain, 1, 1.0f, optics::ApertureShape{});
    rasterizeReference(b, merged, 1, 1.0f, optics::ApertureShape{});
    EXPECT_NEAR(imageSum(b), imageSum(a), 1e-4 * imageSum(a));
    const auto quality = psnr(b, a);
    ASSERT_TRUE(quality);
    EXPECT_GT(*quality, 80.0);  // affine attributes interpolate exactly, up to rounding
}

TEST(PrimitiveMerge, TheThresholdIsTheSineOfTheAngleBetweenEdges) {
    // Rows are arcs turning 3 degrees per cell, columns are radial lines: consecutive row edges
    // are 3 degrees apart, sin 3 deg = 0.052, between light (0.001) and heavy (0.1).
    const double step = 3.0 * 3.14159265358979 / 180.0;
    const auto grid = syntheticGrid(9, [&](int ix, int iy) {
        const double radius = 200.0 + 4.0 * iy, a = step * (ix - 4);
        return Eigen::Vector2d(300.0 + radius * std::sin(a), radius * std::cos(a));
    });
    EXPECT_EQ(quadsFromGrid(grid, kIdentity).quads.size(), 64u);
    EXPECT_EQ(quadsFromGrid(grid, kIdentity, {1, 0.001}).quads.size(), 64u)
        << "edges 3 deg apart must not merge under sine 0.001";
    EXPECT_EQ(quadsFromGrid(grid, kIdentity, {1, 0.1}).quads.size(), 16u)
        << "edges 3 deg apart merge under sine 0.1";
    // Two cells turn 6 degrees (sine 0.105), four 12 degrees (0.208).
    EXPECT_EQ(quadsFromGrid(grid, kIdentity, {3, 0.1}).quads.size(), 16u);
    EXPECT_EQ(quadsFromGrid(grid, kIdentity, {3, 0.3}).quads.size(), 1u);
}

TEST(PrimitiveMerge, CellsWithACutOrMissingRayAreNeverMerged) {
    auto grid = syntheticGrid(
        17, [](int ix, int iy) { return Eigen::Vector2d(5.0 + 2.0 * ix, 5.0 + 2.0 * iy); });
    grid.samples[static_cast<size_t>(5) * 17 + 6].valid = false;  // cut: position kept
    grid.samples[static_cast<size_t>(5) * 17 + 6].throughput = 0.0f;
    const GhostQuads merged = quadsFromGrid(grid, kIdentity, kHeavyMerge);
    EXPECT_EQ(totalCells(merged), 16 * 16);
    // The 8 x 8 block holding the cut ray cannot merge, nor can its 4 x 4 and 2 x 2 blocks; the
    // four cells around the ray stay single.
    int singles = 0;
    for (size_t i = 0; i < merged.quads.size(); ++i) singles += merged.cells[i] == 1;
    EXPECT_GE(singles, 4);
    EXPECT_LT(merged.quads.size(), 20u);
    // Zero steps leave the grid as it is.
    EXPECT_TRUE(quadsFromGrid(grid, kIdentity, {0, 0.1}).cells.empty());
}

TEST(FillRule, APixelCentreOnASharedEdgeIsCountedOnce) {
    // Two unit-throughput squares side by side sharing the line x = 4.5, which holds the centres
    // of pixel column 4; and four squares meeting at the pixel centre (4.5, 4.5).
    const auto grid = syntheticGrid(
        3, [](int ix, int iy) { return Eigen::Vector2d(0.5 + 4.0 * ix, 0.5 + 4.0 * iy); });
    GhostQuads quads = quadsFromGrid(grid, kIdentity);
    ASSERT_EQ(quads.quads.size(), 4u);
    for (Quad& q : quads.quads)
        for (QuadCorner& c : q.corners) c.stop_u = c.stop_v = 0.0f;
    ImageRGB image(10, 10);
    rasterizeReference(image, quads, 0, 1.0f, optics::ApertureShape{});
    // Every covered pixel holds the same value: cell area 1 / quad area 16.
    // Every pixel inside holds the same value, cell area 1 over quad area 16, the centres on the
    // shared lines x = 4.5 and y = 4.5 (column and row 4) included, once.
    for (int64_t y = 1; y <= 7; ++y)
        for (int64_t x = 1; x <= 7; ++x)
            EXPECT_FLOAT_EQ(image.at(x, y)[0], 1.0f / 16.0f) << x << "," << y;
}

TEST(Psnr, IdenticalImagesAreInfiniteAndBadInputsAreNamed) {
    ImageRGB a(4, 3), b(4, 3), c(3, 4);
    a.pixels[5] = b.pixels[5] = 2.0f;
    EXPECT_TRUE(std::isinf(*psnr(a, b)));
    b.pixels[0] = 0.02f;  // MSE 0.0004 / 36, peak 2
    EXPECT_NEAR(*psnr(b, a), 10.0 * std::log10(4.0 / (0.0004 / 36.0)), 1e-3);
    EXPECT_NE(psnr(a, c).error().message.find("size"), std::string::npos);
    b.pixels[1] = std::nanf("");
    EXPECT_NE(psnr(b, a).error().message.find("non-finite"), std::string::npos);
    EXPECT_FALSE(psnr(ImageRGB(2, 2), ImageRGB(2, 2)));  // no positive reference value
}

}  // namespace
}  // namespace flarelab::render
