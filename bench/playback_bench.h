// ============================================================================
//  flarelab bench: PlaybackBenchOptions, PlaybackBenchResult, runPlaybackBench,
//                  playbackBenchJson (flarelab bench playback)
// ============================================================================
//
// Model playback as a lighting planner runs it: one model file drawn by fit::renderModel, frame
// after frame, at one constellation, on every core. The time of a frame is the whole call
// (ghosts evaluated from the model's series, prepared, tiled and drawn into a new image); the
// first frame is left out (it faults the image's pages in and warms the caches), the best of the
// others is `frame_ms`. The same frame drawn by the exact evaluation (every pixel of every ghost
// through shadeGhostBlock, render/model_ghost.h) is the reference of the error:
//   max_rel_err = max over pixels and channels of |fast - exact| / (the exact frame's peak),
// a fraction of the frame's brightest value (a pixel's own relative error is unbounded where the
// ghost fades to zero); rel_l2 = ||fast - exact|| / ||exact|| over the frame.
#pragma once

#include <cstdint>
#include <iosfwd>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>

#include "common/result.h"
#include "render/ghost_shape.h"
#include "render/tiles.h"

namespace flarelab::bench {

struct PlaybackBenchOptions {
    std::string model_path;
    int64_t width = 1920;
    int64_t height = 1080;
    double angle_deg = std::numeric_limits<double>::quiet_NaN();  // NaN: most ghosts (see .cpp)
    double roll_deg = std::numeric_limits<double>::quiet_NaN();   // NaN: the capture's roll
    int frames = 10;                 // timed frames after the first, >= 1
    double smooth_tolerance = 1e-4;  // fit::ModelRenderOptions::smooth_tolerance
    bool frame_tolerance = true;     // fit::ModelRenderOptions::frame_tolerance, as model render
    bool exact = true;               // false: no exact frame, no error figures
    double log_scale = 1e-3;         // log_rel_l2's tone mapping, as score's --log-scale
    int dense_tile_px = render::TileOptions{}.dense_tile_px;  // the fast frames' tiles
    int coarse_tile_px = render::TileOptions{}.coarse_tile_px;
    // The exact frame's Newton distance (the renderer's default is 4 seeds, 4 steps); more of
    // both bring it nearer the curve's true distance where sharp edges make 0.01 px matter.
    int exact_seeds = 4;
    int exact_iterations = 4;
};

struct PlaybackBenchResult {
    double angle_deg = 0.0;
    double roll_deg = 0.0;
    int64_t width = 0, height = 0;
    int64_t ghosts = 0;
    int frames = 0;
    double frame_ms = 0.0;         // best of the frames after the first
    double frame_median_ms = 0.0;  // their median
    double first_frame_ms = 0.0;
    double exact_ms = -1.0;     // one exact frame; -1 when not run
    double max_rel_err = -1.0;  // -1 when not run
    double max_abs_err = -1.0;
    double rel_l2 = -1.0;
    double log_rel_l2 = -1.0;  // relative L2 of the tone-mapped frames (fit::toneMapScore)
    double peak = 0.0;         // the exact frame's brightest value (the fast one's without it)
    int threads = 0;
    // The best frame's tile engine: dense tiles x ghosts interpolated and drawn per pixel, and its
    // clocks (classification while the tiles are built; drawing).
    int64_t tiles_smooth = 0, tiles_edge = 0;
    double build_ms = 0.0, traverse_ms = 0.0;
};

// InvalidArgument for options out of range; the model reader's and renderer's errors as they are.
Result<PlaybackBenchResult> runPlaybackBench(const PlaybackBenchOptions& options,
                                             std::ostream& log);
void printPlaybackBench(const PlaybackBenchResult& result, std::ostream& out);
nlohmann::json playbackBenchJson(const PlaybackBenchResult& result);

}  // namespace flarelab::bench
