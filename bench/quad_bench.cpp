// quad_bench: the kernels between a traced ray grid and the simulator's pixels
// (render/ghost_quads.h, render/tiles.h), so that a change to one of them is measured where it
// happens. The first two run on one core; the tile fill on every core, as the renderer runs it.
//
//   BM_QuadsFromGrid/<merge>     quads of a traced grid and their primitives (quadsFromGrid, then
//                                preparePrimitive for each). Items are grid rays.
//   BM_QuadPixel/<merge>         primitiveValueAt over every pixel of every primitive's range:
//                                the pixel-area integration itself. Items are primitive-pixels.
//   BM_QuadTileFill/<merge>      renderTiled of all the primitives into the image: tile lists,
//                                traversal and the pixel sums. Items are image pixels.
//
// The ghost is the Heliar's brightest at 5 degrees, green, on a grid of 128 x 128, drawn into a
// 960 x 540 image; <merge> is none or light (the paper's light merge).
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cstdint>
#include <iostream>
#include <string>
#include <vector>

#include "common/units.h"
#include "optics/ghosts.h"
#include "optics/lens.h"
#include "optics/prescription.h"
#include "optics/ray_grid.h"
#include "render/ghost_quads.h"
#include "render/tiles.h"

namespace flarelab::bench {
namespace {

using namespace flarelab::render;

constexpr int64_t kWidth = 960, kHeight = 540;
constexpr int kGrid = 128;

struct Case {
    optics::Lens lens;
    optics::RayGrid grid;
    SensorToImage mapping;
};

// nullptr (and a message) when the lens or its ghosts cannot be had.
const Case* heliarCase() {
    static const Case* c = []() -> const Case* {
        auto prescription = optics::loadPrescription(std::string(FLARELAB_SOURCE_DIR) +
                                                     "/data/lenses/heliar-tronnier.csv");
        if (!prescription) return nullptr;
        auto lens = optics::Lens::make(*prescription, optics::CameraDescription{});
        if (!lens) return nullptr;
        const auto ghosts = optics::enumerateGhosts(*lens);
        const auto reference = optics::imagingPower(*lens, {5.0, 0.0}, 16);
        if (!ghosts || ghosts->ghosts.empty() || !reference) return nullptr;
        optics::GhostPath brightest = ghosts->ghosts.front();
        double power = -1.0;
        for (const optics::GhostPath& path : ghosts->ghosts) {
            const auto p = optics::ghostIntensity(*lens, path, {5.0, 0.0}, *reference);
            if (p && p->relative_power > power) {
                power = p->relative_power;
                brightest = path;
            }
        }
        auto grid =
            optics::traceRayGrid(*lens, brightest, degToRad(5.0), 0.0, kLambdaGreen_nm, kGrid);
        if (!grid) return nullptr;
        return new Case{*lens, std::move(*grid), sensorToImage(lens->camera(), kWidth, kHeight)};
    }();
    if (!c) std::cerr << "quad_bench: the Heliar's ghost grid could not be traced\n";
    return c;
}

std::vector<Primitive> primitivesOf(const Case& c, const MergeOptions& merge) {
    const GhostQuads quads = quadsFromGrid(c.grid, c.mapping, merge);
    std::vector<Primitive> out;
    for (size_t q = 0; q < quads.quads.size(); ++q)
        if (auto p = preparePrimitive(quads.quads[q], quads.cellArea(q), 1, 1.0f, kWidth, kHeight))
            out.push_back(*p);
    return out;
}

void BM_QuadsFromGrid(benchmark::State& state, MergeOptions merge) {
    const Case* c = heliarCase();
    if (!c) return state.SkipWithError("no grid, see stderr");
    for (auto _ : state) {
        std::vector<Primitive> p = primitivesOf(*c, merge);
        benchmark::DoNotOptimize(p.data());
    }
    state.SetItemsProcessed(state.iterations() * kGrid * kGrid);
}

void BM_QuadPixel(benchmark::State& state, MergeOptions merge) {
    const Case* c = heliarCase();
    if (!c) return state.SkipWithError("no grid, see stderr");
    const std::vector<Primitive> primitives = primitivesOf(*c, merge);
    const StopMask stop(c->lens.aperture());
    int64_t pixels = 0;
    for (const Primitive& p : primitives) pixels += (p.x1 - p.x0 + 1) * (p.y1 - p.y0 + 1);
    for (auto _ : state) {
        double sum = 0.0;
        for (const Primitive& p : primitives)
            for (int64_t y = p.y0; y <= p.y1; ++y)
                for (int64_t x = p.x0; x <= p.x1; ++x) sum += primitiveValueAt(p, x, y, stop);
        benchmark::DoNotOptimize(sum);
    }
    state.SetItemsProcessed(state.iterations() * pixels);
    state.counters["primitives"] = static_cast<double>(primitives.size());
}

void BM_QuadTileFill(benchmark::State& state, MergeOptions merge) {
    const Case* c = heliarCase();
    if (!c) return state.SkipWithError("no grid, see stderr");
    const std::vector<Primitive> primitives = primitivesOf(*c, merge);
    ImageRGB image(kWidth, kHeight);
    for (auto _ : state) {
        std::fill(image.pixels.begin(), image.pixels.end(), 0.0f);
        const Status drawn = renderTiled(image, primitives, c->lens.aperture());
        if (!drawn) return state.SkipWithError(drawn.error().message.c_str());
        benchmark::DoNotOptimize(image.pixels.data());
    }
    state.SetItemsProcessed(state.iterations() * kWidth * kHeight);
}

BENCHMARK_CAPTURE(BM_QuadsFromGrid, none, kNoMerge);
BENCHMARK_CAPTURE(BM_QuadsFromGrid, light, kLightMerge);
BENCHMARK_CAPTURE(BM_QuadPixel, none, kNoMerge);
BENCHMARK_CAPTURE(BM_QuadPixel, light, kLightMerge);
BENCHMARK_CAPTURE(BM_QuadTileFill, none, kNoMerge);
BENCHMARK_CAPTURE(BM_QuadTileFill, light, kLightMerge);

}  // namespace
}  // namespace flarelab::bench

BENCHMARK_MAIN();
