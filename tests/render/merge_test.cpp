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

int markedEdges(const GhostQuads& q) {
    int bits = 0;
    for (const Quad& quad : q.quads) bits += __builtin_popcount(quad.centre_edges);
    return bits;
}

MergeOptions centreEdges(int steps, double jump) {
    MergeOptions m;
    m.steps = steps;
    m.centre_edge_jump = jump;
    return m;
}

TEST(InteriorEdges, AreTheWholeEdgesBetweenQuadsOfTheSameDensityOnEitherSide) {
    // 17 x 17 rays, 16 x 16 cells, affine: each of the 2 x 16 x 15 interior edges is marked from
    // both sides, no border edge is, and nothing is marked without the option.
    const auto affine = syntheticGrid(17, [](int ix, int iy) {
        return Eigen::Vector2d(10.3 + 3.0 * ix + 0.5 * iy, 7.1 + 2.5 * iy + 0.2 * ix);
    });
    EXPECT_EQ(markedEdges(quadsFromGrid(affine, kIdentity)), 0);
    EXPECT_EQ(markedEdges(quadsFromGrid(affine, kIdentity, centreEdges(0, 0.01))), 2 * 2 * 16 * 15);
    // Merged into four 8 x 8 blocks: the four edges between them, from both sides.
    const GhostQuads blocks = quadsFromGrid(affine, kIdentity, centreEdges(3, 0.01));
    ASSERT_EQ(blocks.quads.size(), 4u);
    EXPECT_EQ(markedEdges(blocks), 8);

    // Columns 3 px wide up to x = 8, 3.3 px after: the density jumps by 9 % across that line.
    const auto stepped = syntheticGrid(17, [](int ix, int iy) {
        const double x = ix <= 8 ? 3.0 * ix : 24.0 + 3.3 * (ix - 8);
        return Eigen::Vector2d(5.2 + x, 5.1 + 3.0 * iy);
    });
    const int all = 2 * 2 * 16 * 15, across = 2 * 16;
    EXPECT_EQ(markedEdges(quadsFromGrid(stepped, kIdentity, centreEdges(0, 0.01))), all - across);
    EXPECT_EQ(markedEdges(quadsFromGrid(stepped, kIdentity, centreEdges(0, 0.1))), all);

    // A fold: rows run down to iy = 8 and back up after, so the quads on either side of row 8
    // turn opposite ways and overlap; the edges along the fold stay cut by area.
    const auto folded = syntheticGrid(17, [](int ix, int iy) {
        const double y = iy <= 8 ? 3.0 * iy : 48.0 - 3.0 * iy;
        return Eigen::Vector2d(5.2 + 3.0 * ix, 5.1 + y + 0.01 * ix * iy);
    });
    EXPECT_EQ(markedEdges(quadsFromGrid(folded, kIdentity, centreEdges(0, 0.01))), all - across);

    // A merged block beside single cells (a cut ray keeps the cells around it single): the
    // block's edge runs along two cells, a T-junction, and is not marked.
    auto cut = affine;
    cut.samples[static_cast<size_t>(3) * 17 + 3].valid = false;
    const GhostQuads mixed = quadsFromGrid(cut, kIdentity, centreEdges(1, 0.01));
    for (size_t i = 0; i < mixed.quads.size(); ++i) {
        if (mixed.cells[i] == 1) continue;
        const Quad& q = mixed.quads[i];
        const Eigen::Vector2d a = q.corners[0].position_px;
        // The 2 x 2 block at cells (4, 2): its left edge (corner 3 to 0) faces single cells.
        if (std::abs(a.x() - (10.3 + 3.0 * 4 + 0.5 * 2)) < 1e-9 &&
            std::abs(a.y() - (7.1 + 2.5 * 2 + 0.2 * 4)) < 1e-9) {
            EXPECT_EQ(q.centre_edges & 8u, 0u);
        }
    }
}

TEST(InteriorEdges, DrawASmoothGhostAsTheAreaCutDoesAndKeepItsPower) {
    // A barrel-distorted grid: the density changes smoothly from cell to cell (under 1 %
    // between neighbours at the rim), and the throughput varies. Drawn with the interior edges
    // by pixel centre, it must stay within a small relative error of the exact area cut.
    auto grid = syntheticGrid(65, [](int ix, int iy) {
        const double u = (ix - 32) / 32.0, v = (iy - 32) / 32.0, r2 = u * u + v * v;
        const double k = 1.0 - 0.04 * r2;
        return Eigen::Vector2d(100.37 + 90.0 * u * k, 80.21 + 70.0 * v * k);
    });
    for (int iy = 0; iy < 65; ++iy)
        for (int ix = 0; ix < 65; ++ix)
            grid.samples[static_cast<size_t>(iy) * 65 + ix].throughput =
                0.5f + 0.5f * std::cos(0.05f * static_cast<float>(ix + 2 * iy));
    ImageRGB exact(200, 160), centre(200, 160);
    rasterizeReference(exact, quadsFromGrid(grid, kIdentity), 1, 1.0f, optics::ApertureShape{});
    const GhostQuads marked = quadsFromGrid(grid, kIdentity, centreEdges(0, 0.01));
    EXPECT_GT(markedEdges(marked), 2 * 2 * 64 * 63 * 9 / 10);
    rasterizeReference(centre, marked, 1, 1.0f, optics::ApertureShape{});
    double diff = 0.0, norm = 0.0;
    for (size_t i = 0; i < exact.pixels.size(); ++i) {
        diff += std::pow(centre.pixels[i] - exact.pixels[i], 2);
        norm += std::pow(exact.pixels[i], 2);
    }
    EXPECT_LT(std::sqrt(diff / norm), 2e-3);
    EXPECT_NEAR(imageSum(centre), imageSum(exact), 1e-3 * imageSum(exact));
    const auto quality = psnr(centre, exact);
    ASSERT_TRUE(quality);
    EXPECT_GT(*quality, 55.0);
}

TEST(PrimitiveMerge, AMergedQuadIsNeverCutByTheStopOrAClearAperture) {
    // Stop coordinates from -1.5 to 1.5 across the grid (the stop's outline crosses it) and a
    // clear aperture cutting the right quarter: only blocks inside the stop and the aperture, or
    // dropped whole, merge; the outline's band stays single cells.
    auto grid = syntheticGrid(
        33, [](int ix, int iy) { return Eigen::Vector2d(5.3 + 2.0 * ix, 5.2 + 2.0 * iy); });
    for (int iy = 0; iy < 33; ++iy)
        for (int ix = 0; ix < 33; ++ix) {
            optics::GridSample& s = grid.samples[static_cast<size_t>(iy) * 33 + ix];
            s.stop_u = static_cast<float>(3.0 * ix / 32.0 - 1.5);
            s.stop_v = static_cast<float>(3.0 * iy / 32.0 - 1.5);
            s.aperture_ratio = static_cast<float>(0.5 + ix / 32.0);
            s.valid = s.aperture_ratio <= 1.0f;
            s.open_throughput = s.throughput;
        }
    const GhostQuads merged = quadsFromGrid(grid, kIdentity, kLightMerge);
    int blocks = 0;
    for (size_t i = 0; i < merged.quads.size(); ++i) {
        if (merged.cells[i] == 1) continue;
        ++blocks;
        bool clear = true, dark = true;
        for (const QuadCorner& c : merged.quads[i].corners) {
            clear = clear && c.aperture_ratio <= 1.0f && std::hypot(c.stop_u, c.stop_v) <= 1.0;
            dark = dark && std::hypot(c.stop_u, c.stop_v) > 1.0;
        }
        EXPECT_TRUE(clear || dark) << "merged quad " << i;
    }
    EXPECT_GT(blocks, 0);
    // With a smaller radius (a bladed stop's inscribed circle) fewer blocks merge.
    MergeOptions bladed = kLightMerge;
    bladed.clear_stop_radius = 0.8;
    EXPECT_GT(quadsFromGrid(grid, kIdentity, bladed).quads.size(), merged.quads.size());
    // The same light either way, against the single cells.
    ImageRGB a(80, 80), b(80, 80);
    rasterizeReference(a, quadsFromGrid(grid, kIdentity), 1, 1.0f, optics::ApertureShape{});
    rasterizeReference(b, merged, 1, 1.0f, optics::ApertureShape{});
    EXPECT_NEAR(imageSum(b), imageSum(a), 1e-3 * imageSum(a));
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
