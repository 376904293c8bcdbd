// model_ghost_bench: the kernels of model playback (render/model_ghost.h), fast against exact, on
// one core.
//
//   BM_ModelGhostPixel/<fast|exact>   one pixel's value (ghostPixelValue), over the pixels of a
//                                     ring around the ghost's edge, where both evaluations do
//                                     their full work (distance, side, eq. 6.4's box mean).
//   BM_TileFill/<fast|exact>          a 256 x 256 image of one ghost through the tile engine
//                                     (renderTiled): the fast one's blocks skipped, filled and
//                                     interpolated, its edge tiles per pixel; the exact one every
//                                     pixel of the range. Items are pixels of the image.
//   BM_TileFillEdge/<fast|exact>      addGhostBlock on the 8 x 8 tiles an edge crosses: the
//                                     per-pixel path alone. Items are pixels.
//
// The ghost is a fitted-looking default shape (about 70 px across here) with a sharp outer edge,
// an inner falloff of a third of its size and exponents below and above 1.
#include <benchmark/benchmark.h>

#include <cstdint>
#include <utility>
#include <vector>

#include "common/image.h"
#include "render/model_ghost.h"
#include "render/tiles.h"

namespace flarelab::bench {
namespace {

using namespace flarelab::render;

constexpr int64_t kSide = 256;

SensorToImage mapping() {
    SensorToImage m;
    m.px_per_mm_x = m.px_per_mm_y = static_cast<double>(kSide) / 24.0;
    m.centre_x_px = m.centre_y_px = 0.5 * static_cast<double>(kSide);
    return m;
}

GhostPrimitive ghost(bool exact) {
    GhostShapeParams shape = circleGhostShape(0.7, -0.4, 3.3);
    shape.left_mm = 2.9;
    shape.right_handle_x_mm = 2.1;
    GhostShading s;
    s.border_rgb = {40.0, 30.0, 20.0};
    s.inner_rgb = {8.0, 9.0, 10.0};
    s.inner_falloff_mm = 1.1;
    s.outer_falloff_mm = 0.05;
    s.inner_exponent = 0.6;
    s.outer_exponent = 2.0;
    GhostDrawOptions options;
    if (exact) options.evaluation = GhostEvaluation::Exact;
    return *prepareGhostPrimitive(toBezierLoop(shape), s, mapping(), kSide, kSide, options);
}

const char* label(int64_t exact) { return exact ? "exact" : "fast"; }

void BM_ModelGhostPixel(benchmark::State& state) {
    const GhostPrimitive g = ghost(state.range(0) != 0);
    std::vector<std::pair<int64_t, int64_t>> pixels;  // a band across the edge
    for (int64_t y = g.y0; y <= g.y1; ++y)
        for (int64_t x = g.x0; x <= g.x1; x += 3) pixels.push_back({x, y});
    size_t i = 0;
    for (auto _ : state) {
        const auto& [x, y] = pixels[i];
        benchmark::DoNotOptimize(ghostPixelValue(g, x, y));
        i = i + 1 == pixels.size() ? 0 : i + 1;
    }
    state.SetItemsProcessed(state.iterations());
    state.SetLabel(label(state.range(0)));
}
BENCHMARK(BM_ModelGhostPixel)->Arg(0)->Arg(1);

void BM_TileFill(benchmark::State& state) {
    const std::vector<GhostPrimitive> ghosts = {ghost(state.range(0) != 0)};
    ImageRGB image(kSide, kSide);
    for (auto _ : state) {
        const Status drawn = renderTiled(image, {}, ghosts, optics::ApertureShape{});
        benchmark::DoNotOptimize(drawn);
        benchmark::ClobberMemory();
    }
    state.SetItemsProcessed(state.iterations() * kSide * kSide);
    state.SetLabel(label(state.range(0)));
}
BENCHMARK(BM_TileFill)->Arg(0)->Arg(1)->Unit(benchmark::kMicrosecond);

void BM_TileFillEdge(benchmark::State& state) {
    const GhostPrimitive g = ghost(state.range(0) != 0);
    const GhostPrimitive fast = ghost(false);
    // The tiles the fast evaluation draws per pixel.
    std::vector<std::pair<int64_t, int64_t>> tiles;
    for (int64_t ty = 0; ty < kSide; ty += 8)
        for (int64_t tx = 0; tx < kSide; tx += 8)
            if (coverGhostBlock(fast, tx, ty, tx + 7, ty + 7, true).kind == GhostBlockKind::Edge &&
                tx >= fast.x0 && tx + 7 <= fast.x1 && ty >= fast.y0 && ty + 7 <= fast.y1)
                tiles.push_back({tx, ty});
    std::vector<float> tile(8 * 8 * 3);
    size_t i = 0;
    for (auto _ : state) {
        const auto& [tx, ty] = tiles[i];
        addGhostBlock(g, tx, ty, tx + 7, ty + 7, tile.data(), 8 * 3);
        benchmark::ClobberMemory();
        i = i + 1 == tiles.size() ? 0 : i + 1;
    }
    state.SetItemsProcessed(state.iterations() * 64);
    state.SetLabel(label(state.range(0)));
    state.counters["edge_tiles"] = static_cast<double>(tiles.size());
}
BENCHMARK(BM_TileFillEdge)->Arg(0)->Arg(1);

}  // namespace
}  // namespace flarelab::bench

BENCHMARK_MAIN();
