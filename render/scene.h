// ============================================================================
//  flarelab render: Light, SceneOptions, renderScene
// ============================================================================
//
// A whole flare image of one lens under point lights at infinity: every ghost (ghost_quads.h)
// plus each light's own image as the Fraunhofer
// starburst of the aperture (starburst.h), with the tiled renderer (tiles.h) or the reference
// rasterizer. Per light, ghost and colour channel a ray grid is
// traced at that channel's wavelength, its size chosen by eq. 13 of Bodonyi & Kunkli 2023 from a
// coarse first trace.
//
// The tiled pipeline traces the grids of many ghosts at once on every core (oneTBB) and collects
// their primitives in a fixed order, so its image does not depend on the number of threads. The
// reference pipeline is the previous method as it runs: one ghost after another, traced and
// drawn into the frame buffer on one thread.
//
// Units. A light's rgb is its irradiance at the lens (power per mm^2 perpendicular to the axis,
// any unit). A pixel holds the power that lands on it, in that unit times mm^2: the starburst
// carries the light that passes the entrance pupil on the imaging path, each ghost what its path
// delivers. Summed over an image that holds them, the values are power, so ghost and light
// compare directly.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "optics/ghosts.h"
#include "optics/lens.h"
#include "render/ghost_quads.h"
#include "render/starburst.h"
#include "render/tiles.h"

namespace flarelab::render {

struct Light {
    double theta_deg = 0.0;  // from the optical axis; 90 and beyond: behind the camera, not drawn
    double phi_deg = 0.0;    // roll around the axis
    std::array<float, 3> rgb = {1.0f, 1.0f, 1.0f};  // irradiance at the lens, >= 0
};

struct SceneOptions {
    int64_t width = 1920;
    int64_t height = 1080;
    int base_grid = 256;  // eq. 13's base size, 2..2048
    // Grids of smooth ghosts are traced at no more than max_grid rays a side (0: always eq. 13's
    // size; else 2..2048). Eq. 13 gives a ghost as large as the sensor base_grid rays a side, and
    // where its map to the sensor hardly bends the light merge then draws it as blocks of up to
    // 16 x 16 cells anyway. "Smooth" is measured on the probe: a grid stays larger, up to its
    // eq. 13 size, where its sensor positions or its stop's outline, interpolated across one
    // cell, would be off by more than grid_bend_px pixels (from the probe's largest second
    // differences; gridForBend in scene.cpp). On the Canon 200 at 5 deg this takes 40 % off the
    // frame with the image unchanged (77.8 dB against the whole grids without merge either way);
    // a fixed cap without the bend test cost the double Gauss, the toy lens and the Nikon 28-75
    // 11 to 26 dB. Chosen on the Heliar and the Canon 200, scored on the others:
    // docs/renderer-issue19.md, "Seventh round".
    int max_grid = 64;
    double grid_bend_px = 0.03;  // > 0
    double grid_sigma = 1.0;     // eq. 13's sigma and phi
    double grid_phi = 0.5;
    int probe_grid = 16;  // the coarse trace that measures a ghost for eq. 13
    optics::EnumerationOptions ghosts;
    bool starburst = true;
    StarburstOptions starburst_options;
    RasterOptions raster;
    // true: collect every ghost's primitives and draw them with the tiled renderer (tiles.h);
    // false: draw ghost after ghost with the reference rasterizer. Both give the same image.
    bool tiled = true;
    // Dense tiles of 16 px (TileOptions' own default, 8, is the model renderer's): tile building
    // and traversal 1.01x to 1.37x as fast on all nine shipped lenses at 1920x1080 and on the
    // Heliar, Canon 200 and Itoh at 640x427, with the same bits (`flarelab bench render`'s
    // Table 4; chosen on the Heliar and the Canon 200, scored on the others, 2026-12-06).
    TileOptions tiles{128, 16, true};
    MergeOptions merge;  // primitive merge (ghost_quads.h); the reference draws merged quads too
    // The tiled renderer draws whenever this many primitives are waiting (sizeof(Primitive),
    // 528 bytes each), so memory stays bounded for any lens, grid and number of lights.
    int64_t max_pending_primitives = 1'000'000;
    // Culling, from each ghost's probe grid (per light and channel): its power on the image P and
    // the area A it spreads over there (pixels) give its mean value P / A and its share of the
    // image's L2 norm, P^2 / A. Ghosts whose probe footprint, grown by one probe cell, misses the
    // image are always skipped. Then the faintest ghosts are dropped as long as their shares
    // together stay within cull_relative_l2^2 of all ghosts' (0: keep every ghost), and any ghost
    // whose mean value is below cull_mean_below (image units; a simulated sensor's noise floor).
    double cull_relative_l2 = 1e-3;
    double cull_mean_below = 0.0;
    // How the ray grids are traced (ray_grid.h): Auto (float lanes where a probe allows) for
    // speed, Exact for a reference image.
    optics::GridTracer grid_tracer = optics::GridTracer::Auto;
    // Adaptive grids (ghost_quads.h adaptiveQuads): with a merge, trace coarse blocks first and
    // refine only those the merge's test fails, instead of the whole grid. Not with the Exact
    // tracer (which always traces the whole grid).
    bool adaptive_grid = false;
    // Where only part of a ghost's beam can reach the image (a ghost larger than the image, or
    // one partly off it), trace only that part of its entry square, found from the probe, at the
    // eq. 13 grid's ray spacing: the rays whose quads would all fall off the image are not
    // traced. false traces the whole eq. 13 grid (the benchmark's truth).
    bool image_window = true;
    // When not empty, only these of the enumerated ghost paths are drawn (one ghost alone: the
    // fit's oracle harness, bench/oracle_bench.h); a path the enumeration does not hold is
    // refused. Culling still applies, relative to the paths drawn.
    std::vector<optics::GhostPath> only_paths;
};

struct SceneStats {
    int64_t ghosts_drawn = 0;          // ghost x light x channel grids that put light in the image
    int64_t ghosts_off_image = 0;      // skipped: the probe's footprint misses the image
    int64_t ghosts_culled = 0;         // dropped by cull_relative_l2 or cull_mean_below
    double culled_relative_l2 = 0.0;   // the dropped ghosts' estimated share of the L2 norm
    int64_t channels_aimed_again = 0;  // red or blue beams that did not fit green's square
    int64_t grids_windowed = 0;        // grids shrunk to the image's window (image_window)
    int64_t quads = 0;
    int64_t rays = 0;
    int lights_behind = 0;  // lights at 90 degrees or more, skipped
    double trace_ms = 0.0;  // ray grids, quads and primitives (tiled: on every core)
    double draw_ms = 0.0;   // rasterization (tiles: building and traversal)
    double light_ms = 0.0;  // the lights' own images (starbursts)
    TileStats tiles;        // when tiled
};

// InvalidArgument (naming the field) for options out of range or a light with a non-finite or
// negative value; a light behind the camera is counted in stats and skipped, not an error.
Result<ImageRGB> renderScene(const optics::Lens& lens,
                             std::span<const Light> lights,
                             const SceneOptions& options,
                             SceneStats* stats = nullptr);

}  // namespace flarelab::render
