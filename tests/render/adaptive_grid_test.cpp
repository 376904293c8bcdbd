// Adaptive grids (ghost_quads.h adaptiveQuads) and the point-by-point grid tracer under them
// (ray_grid.h GridFiller), against tracing the whole grid and merging.
#include <gtest/gtest.h>

#include <cmath>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "common/units.h"
#include "optics/ghosts.h"
#include "render/ghost_quads.h"
#include "render/metrics.h"
#include "render/scene.h"
#include "tests/test_paths.h"

namespace flarelab::render {
namespace {

optics::Lens lensNamed(const std::string& file) {
    return *optics::Lens::make(*optics::loadPrescription(flarelab::testing::lensPath(file)),
                               optics::CameraDescription{});
}

double fieldDeg(const optics::Lens& lens) {
    const auto& c = lens.camera();
    return radToDeg(
        std::atan(0.5 * std::hypot(c.sensor_width_mm, c.sensor_height_mm) / c.focal_length_mm));
}

// Quads of square blocks of 2^k cells, together no more cells than the grid has.
void expectATiling(const GhostQuads& quads, int n) {
    ASSERT_EQ(quads.cells.size(), quads.quads.size());
    int64_t total = 0;
    for (size_t i = 0; i < quads.quads.size(); ++i) {
        const int side = static_cast<int>(std::lround(std::sqrt(quads.cells[i])));
        ASSERT_EQ(side * side, quads.cells[i]);
        ASSERT_EQ(side & (side - 1), 0) << "blocks are powers of two";
        total += quads.cells[i];
    }
    EXPECT_LE(total, int64_t{n - 1} * (n - 1));
}

TEST(GridFiller, TracesThePointsItIsGivenOnceAndAsTheWholeGridDoes) {
    const optics::Lens lens = lensNamed("heliar-tronnier.csv");
    const optics::GhostPath path{2, 3};
    for (const optics::GridTracer tracer :
         {optics::GridTracer::Auto, optics::GridTracer::RowDouble}) {
        optics::RayGridOptions options;
        options.tracer = tracer;
        const int n = 97;
        const auto whole = optics::traceRayGrid(lens, path, degToRad(7.0), 0.3, 550.0, n, options);
        ASSERT_TRUE(whole);
        auto filler = optics::GridFiller::open(lens, path, degToRad(7.0), 0.3, 550.0, n, options);
        ASSERT_TRUE(filler);
        EXPECT_EQ(filler->tracedCount(), 0);
        std::vector<std::pair<int, int>> points;
        for (int k = 0; k < 700; ++k) points.emplace_back((k * 37) % n, (k * 53 + k / 5) % n);
        std::set<std::pair<int, int>> distinct(points.begin(), points.end());
        filler->trace(points);
        filler->trace(points);  // again: nothing new
        EXPECT_EQ(filler->tracedCount(), static_cast<int64_t>(distinct.size()));
        int valid = 0;
        for (int iy = 0; iy < n; ++iy)
            for (int ix = 0; ix < n; ++ix) {
                const optics::GridSample& a = filler->grid().at(ix, iy);
                if (!distinct.count({ix, iy})) {
                    EXPECT_FALSE(filler->traced(ix, iy));
                    EXPECT_FALSE(a.valid || a.has_position);
                    continue;
                }
                EXPECT_TRUE(filler->traced(ix, iy));
                const optics::GridSample& b = whole->at(ix, iy);
                valid += a.valid;
                // The same tracer and precision: the same bits, whatever the batch.
                EXPECT_EQ(a.valid, b.valid);
                EXPECT_EQ(a.has_position, b.has_position);
                EXPECT_EQ(a.sensor_x_mm, b.sensor_x_mm);
                EXPECT_EQ(a.sensor_y_mm, b.sensor_y_mm);
                EXPECT_EQ(a.throughput, b.throughput);
                EXPECT_EQ(a.stop_u, b.stop_u);
                EXPECT_EQ(a.aperture_ratio, b.aperture_ratio);
            }
        EXPECT_GT(valid, 300);
    }
    optics::RayGridOptions exact;
    exact.tracer = optics::GridTracer::Exact;
    const auto refused = optics::GridFiller::open(lens, path, 0.0, 0.0, 550.0, 9, exact);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("Exact"), std::string::npos);
    EXPECT_FALSE(optics::GridFiller::open(lens, path, degToRad(95.0), 0.0, 550.0, 9));
}

// A third of the ghosts of three lenses at two angles: the adaptive quads tile part of the grid and
// draw the image that tracing the whole grid and merging draws, to 45 dB per ghost with the light
// merge; with the heavy merge (gamma 0.1) most blocks pass at the first level and many rays are
// never traced. With the light merge's gamma (0.001) they save rays only where the whole grid
// merges too (the toy lens's ghosts hardly merge at all): not asserted.
TEST(AdaptiveQuads, DrawWhatTheWholeMergedGridDrawsWithFewerRays) {
    for (const char* file : {"heliar-tronnier.csv", "lensbaby-toy.csv", "nikon-28-75mm.csv"}) {
        const optics::Lens lens = lensNamed(file);
        const auto ghosts = optics::enumerateGhosts(lens);
        ASSERT_TRUE(ghosts);
        const SensorToImage mapping = sensorToImage(lens.camera(), 240, 160);
        for (const MergeOptions merge : {kLightMerge, kHeavyMerge}) {
            int64_t rays = 0, rays_whole = 0;
            for (const double fraction : {0.0, 0.9}) {
                const double theta = degToRad(fraction * fieldDeg(lens));
                for (size_t g = 0; g < ghosts->ghosts.size(); g += 3) {
                    const optics::GhostPath& path = ghosts->ghosts[g];
                    const int n = 65;
                    auto adaptive =
                        adaptiveQuads(lens, path, theta, 0.5, 550.0, n, {}, mapping, merge);
                    ASSERT_TRUE(adaptive) << file << " " << g;
                    expectATiling(adaptive->quads, n);
                    EXPECT_LE(adaptive->rays, int64_t{n} * n);
                    rays += adaptive->rays;
                    rays_whole += int64_t{n} * n;
                    if (merge.gamma > kLightMerge.gamma) continue;
                    const auto grid = optics::traceRayGrid(lens, path, theta, 0.5, 550.0, n);
                    ASSERT_TRUE(grid);
                    // Every edge cut by area, as the adaptive quads are drawn.
                    MergeOptions cut = merge;
                    cut.centre_edge_jump = 0.0;
                    const GhostQuads whole = quadsFromGrid(*grid, mapping, cut);
                    ImageRGB a(240, 160), b(240, 160);
                    rasterizeReference(a, adaptive->quads, 1, 1.0f, lens.aperture());
                    rasterizeReference(b, whole, 1, 1.0f, lens.aperture());
                    const double sum = imageSum(b);
                    EXPECT_NEAR(imageSum(a), sum, 2e-3 * sum + 1e-12) << file << " ghost " << g;
                    if (sum <= 0.0) continue;
                    const auto db = psnr(a, b);
                    ASSERT_TRUE(db);
                    EXPECT_GE(*db, 45.0) << file << " ghost " << g << " at " << fraction;
                }
            }
            // Blocks the stop's outline or a clear aperture crosses are refined down to single
            // cells (MergeOptions::clear_stop_radius), which costs rays on small grids like these.
            if (merge.gamma > kLightMerge.gamma) {
                EXPECT_LT(rays, rays_whole * 6 / 10) << file << ": the heavy merge's blocks";
            }
        }
    }
}

TEST(AdaptiveQuads, ExtremeGridsAndLights) {
    const optics::Lens lens = lensNamed("heliar-tronnier.csv");
    const SensorToImage mapping = sensorToImage(lens.camera(), 64, 48);
    const optics::GhostPath path{2, 3};
    // Without a merge, and on grids too small to have a block: the whole grid, as quadsFromGrid.
    for (const auto& [n, merge] : {std::pair{33, kNoMerge}, std::pair{2, kLightMerge},
                                   std::pair{3, kLightMerge}, std::pair{1, kLightMerge}}) {
        auto adaptive = adaptiveQuads(lens, path, 0.0, 0.0, 550.0, n, {}, mapping, merge);
        ASSERT_TRUE(adaptive) << n;
        EXPECT_EQ(adaptive->rays, int64_t{n} * n);
        const auto grid = optics::traceRayGrid(lens, path, 0.0, 0.0, 550.0, n);
        EXPECT_EQ(adaptive->quads.quads.size(), quadsFromGrid(*grid, mapping, merge).quads.size());
    }
    // Grids whose cell count is not a multiple of the block: the rim's blocks are split, and
    // every cell of the whole grid's quads is covered the same.
    for (const int n : {18, 100, 131}) {
        auto adaptive =
            adaptiveQuads(lens, path, degToRad(3.0), 0.0, 550.0, n, {}, mapping, kHeavyMerge);
        ASSERT_TRUE(adaptive) << n;
        expectATiling(adaptive->quads, n);
        const auto grid = optics::traceRayGrid(lens, path, degToRad(3.0), 0.0, 550.0, n);
        ImageRGB a(64, 48), b(64, 48);
        rasterizeReference(a, adaptive->quads, 0, 1.0f, lens.aperture());
        rasterizeReference(b, quadsFromGrid(*grid, mapping, kHeavyMerge), 0, 1.0f, lens.aperture());
        EXPECT_NEAR(imageSum(a), imageSum(b), 2e-3 * imageSum(b)) << n;
    }
    // A light so far off axis that nothing gets through: no quads, the grid traced whole to
    // find that out, no error.
    auto dark = adaptiveQuads(lens, path, degToRad(80.0), 0.0, 550.0, 65, {}, mapping, kLightMerge);
    ASSERT_TRUE(dark);
    EXPECT_TRUE(dark->quads.quads.empty());
    // A 1 x 1 image: the scene with adaptive grids draws it, finite.
    SceneOptions tiny;
    tiny.width = tiny.height = 1;
    tiny.base_grid = 64;
    tiny.starburst = false;
    tiny.merge = kLightMerge;
    tiny.adaptive_grid = true;
    const Light light{2.0, 0.0, {1.0f, 1.0f, 1.0f}};
    const auto one = renderScene(lens, std::span(&light, 1), tiny);
    ASSERT_TRUE(one);
    for (const float v : one->pixels) EXPECT_TRUE(std::isfinite(v));
    // Bad arguments are the grid's errors.
    EXPECT_FALSE(adaptiveQuads(lens, path, std::nan(""), 0.0, 550.0, 65, {}, mapping, kLightMerge));
    EXPECT_FALSE(adaptiveQuads(lens, optics::GhostPath{2, 99}, 0.0, 0.0, 550.0, 65, {}, mapping,
                               kLightMerge));
}

// The scene with adaptive grids: the same image as the whole grids to 45 dB, fewer rays.
TEST(AdaptiveQuads, SceneOptionDrawsTheSameImageWithFewerRays) {
    for (const char* file : {"heliar-tronnier.csv", "double-gauss-tronnier-50mm.csv"}) {
        const optics::Lens lens = lensNamed(file);
        SceneOptions options;
        options.width = 192;
        options.height = 108;
        options.base_grid = 96;
        options.starburst = false;
        options.merge = kLightMerge;
        const Light light{0.5 * fieldDeg(lens), 30.0, {1.0f, 1.0f, 1.0f}};
        SceneStats whole_stats, adaptive_stats;
        const auto whole = renderScene(lens, std::span(&light, 1), options, &whole_stats);
        options.adaptive_grid = true;
        const auto adaptive = renderScene(lens, std::span(&light, 1), options, &adaptive_stats);
        ASSERT_TRUE(whole && adaptive);
        EXPECT_LT(adaptive_stats.rays, whole_stats.rays) << file;
        EXPECT_EQ(adaptive_stats.ghosts_drawn, whole_stats.ghosts_drawn);
        const auto db = psnr(*adaptive, *whole);
        ASSERT_TRUE(db);
        EXPECT_GE(*db, 45.0) << file;
        // The Exact tracer ignores the option: it always traces the whole grid.
        if (file != std::string("heliar-tronnier.csv")) continue;
        options.grid_tracer = optics::GridTracer::Exact;
        options.base_grid = 24;
        SceneStats exact_stats, exact_whole_stats;
        ASSERT_TRUE(renderScene(lens, std::span(&light, 1), options, &exact_stats));
        options.adaptive_grid = false;
        ASSERT_TRUE(renderScene(lens, std::span(&light, 1), options, &exact_whole_stats));
        EXPECT_EQ(exact_stats.rays, exact_whole_stats.rays);
    }
}

}  // namespace
}  // namespace flarelab::render
