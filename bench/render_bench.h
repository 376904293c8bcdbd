// ============================================================================
//  flarelab bench: RenderBenchOptions, runRenderBench (flarelab bench render)
// ============================================================================
//
// The tiled renderer against the reference rasterizer, measured side by side in one run, as the
// tables of Bodonyi & Kunkli 2023 (§5): per lens and number of lights the phases and total of the
// tiled pipeline, the reference's total, the speed-up and the PSNR of the tiled image against the
// reference (Tables 2 and 3); primitive counts, tile entries and memory with no, light and heavy
// merge (Tables 5-7); tile sizes with and without the coarse level (Table 4); and, beyond the
// paper, the speed/accuracy trade of grid size and merge against a dense-grid reference and the
// cost against the number of lights and the image size.
//
// Every time is the best of `repeat` runs. Images are the ghosts only (no starburst: it is the
// same in both renderers and its peak would dwarf the ghosts in the PSNR).
#pragma once

#include <iosfwd>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/result.h"
#include "render/scene.h"

namespace flarelab::bench {

struct RenderBenchOptions {
    std::vector<std::string> lens_files;  // empty: the paper's five from lens_dir
    std::string lens_dir = "data/lenses";
    std::vector<int> light_counts = {1, 2};
    bool quick = false;  // two small lenses, 640 x 360, grid 64, one run: a smoke test
    int repeat = 2;
    int64_t width = 1920;
    int64_t height = 1080;
    int base_grid = render::SceneOptions{}.base_grid;  // the default pipeline's
    int max_grid = render::SceneOptions{}.max_grid;    // the default pipeline's (0: no cap)
    // The eq. 13 base of the truth the lens, culling and interior-edge tables measure against
    // (every ghost traced exactly on its whole eq. 13 grid, no cap, no merge); 0: base_grid. The
    // truth never takes max_grid's cap, so the default pipeline is scored against whole grids.
    int truth_grid = 0;
    bool lenses = true;        // the per-lens tables (Tables 2-7)
    bool trade = true;         // grid size x merge against a dense-grid reference
    bool scaling = true;       // lights 1..8, image 480p..4K
    bool cull = true;          // ghost culling: cull_relative_l2 from 0 to 1e-2, per lens
    bool centre_edges = true;  // interior edges by pixel centre: centre_edge_jump 0 to 0.1
    // N > 0: also draw the main configuration with N x N point samples per pixel (the same
    // primitives; RasterOptions::supersample) and report the default image's PSNR against it
    // (`truth_psnr_db`, `truth_ms`): how far pixel-area integration is from the sampled truth.
    int truth_samples = 0;
};

// Runs the benchmark, prints Markdown tables to `out` as it goes (progress to `log`) and returns
// the JSON document: {"settings", "lenses": [{name, lights, tiled_ms, reference_ms, speedup,
// psnr_db, ...}], "merge", "tiles", "cull", "centre_edges", "trade", "lights_scaling",
// "size_scaling"}.
Result<nlohmann::json> runRenderBench(const RenderBenchOptions& options,
                                      std::ostream& out,
                                      std::ostream& log);

}  // namespace flarelab::bench
