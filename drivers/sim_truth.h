// ============================================================================
//  flarelab drivers: simulatedGhostTruth
// ============================================================================
//
// Ground truth for scoring a model (fit/score.h): what the simulated camera of
// `flarelab capture --sim` (SimCamera with its default options at the model's frame size) shows
// of the ghosts alone at a head angle, noiseless, without the light's own image, the sky
// background or dark current, in DN per second at unity gain, the unit of the merged frames the
// model was fitted to; with where the light's own image lands. The camera renders with the same
// settings as the capture did (simRenderDefaults), so nothing but the noise differs.
//
// Colour: a monochrome capture's camera sees the green channel (550 nm; drivers/sim_camera.h),
// copied to R, G and B as the mono frames are; a colour (Bayer) capture's frames are demosaiced
// RGB, and its truth is red, green and blue (650, 550, 450 nm) at every pixel, what the
// demosaicing estimates.
#pragma once

#include <cstdint>
#include <vector>

#include "fit/score.h"
#include "optics/lens.h"

namespace flarelab::drivers {

// Errors: the frame size or lens the simulated camera refuses; with only_paths (not empty: those
// ghost paths alone, render::SceneOptions::only_paths) a path the lens does not have, when a
// frame is asked for.
Result<fit::TruthSource> simulatedGhostTruth(const optics::Lens& lens,
                                             int64_t width,
                                             int64_t height,
                                             const std::vector<optics::GhostPath>& only_paths = {},
                                             bool colour = false);

}  // namespace flarelab::drivers
