// ============================================================================
//  flarelab fit: GhostParameterInfo, ghostParameters, ghostStateFromParameters, modelGhostsAt,
//                ModelRenderOptions, renderModel, renderGhostStates, renderRotatedGhostStates
// ============================================================================
//
// What a model ghost's parameters are, and a model evaluated and drawn at any constellation.
//
// A ghost has kGhostParameterCount parameters, stored under these names in model files, each a
// smooth function of the angle that its Chebyshev pieces follow well:
//   centre_x_mm, centre_y_mm, half_height_mm, left_mm, right_mm    the shape (render/ghost_shape.h)
//   left_handle_x_fraction ... right_handle_y_fraction              handles over their extents,
//                                                                   in [0, 1]: any value between
//                                                                   two valid ones is valid
//   ln_border_rgb[c], ln_inner_rgb[c]                               natural logs of the border and
//                                                                   inner intensity (the frame's
//                                                                   unit): intensities span
//                                                                   decades, and stay >= 0
//   inner_falloff_mm, outer_falloff_mm, inner_exponent, outer_exponent
// A ghost is drawn over its fitted range (its first to its last fitted angle) and, beyond each
// end, fades linearly to nothing over one capture step (capture.step_deg): it was seen at the
// end angle and not at the next captured one, so between the two it faded or left, and a ghost
// that the fit followed as two tracks meeting there (one ending, the next starting a step later)
// is drawn as their mix rather than as nothing. At the captured angles nothing changes. On one
// Heliar model this took the held-out median from 0.110 to 0.098, and a fitted angle that no
// track covered from 1.0 to 0.55 half a step away.
// Evaluated between fitted angles, a value may leave its bounds; ghostStateFromParameters clamps
// it back (extents and falloffs to at least kMinExtentMm, fractions to [0, 1], exponents to
// [0.25, 4]), so any evaluation gives a valid ghost. Between two captured angles inside its range
// a ghost's light (estimated from its shape and shading) is held to 1.25 times the brighter of
// the two by scaling its intensities: each parameter has its own series, and two that trade (a
// thin bright rim against a wide dim one) can meet between frames in a combination no frame had.
//
// Constellation (DESIGN.md): a model fitted to a sweep at roll r0 is drawn for a light at
// (theta, phi) by evaluating it at theta and rotating the ghosts about the optical axis by
// phi - r0. The sweep's angle is the head angle; a negative head angle is the light on the other
// side, which for a rotationally symmetric lens equals theta = |angle| rotated by 180 degrees.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <utility>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "fit/frame.h"
#include "fit/model_file.h"
#include "render/tiles.h"

namespace flarelab::fit {

inline constexpr int kGhostParameterCount = 19;
inline constexpr double kMinExtentMm = 1e-4;

struct GhostParameterInfo {
    const char* name;
    const char* unit;  // "mm", "1", "ln(frame unit)"
    std::optional<double> lower_bound;
    std::optional<double> upper_bound;
};
const GhostParameterInfo& ghostParameterInfo(int index);  // 0 <= index < kGhostParameterCount

using GhostParameters = std::array<double, kGhostParameterCount>;

// A state's parameters in the order and form above. ln intensities are floored at ln_floor (at
// least kMinLnIntensity, which reads back as 0): a series through a ghost's frames should floor
// them near its own noise, not at -80, or one black frame swings the polynomial.
inline constexpr double kMinLnIntensity = -80.0;
GhostParameters ghostParameters(const GhostState& state, double ln_floor = kMinLnIntensity);
// The state the parameters describe, clamped into bounds. InvalidArgument for a non-finite value.
Result<GhostState> ghostStateFromParameters(std::span<const double> values);

struct ModelGhostAt {
    int64_t id = 0;
    GhostState state;  // rotated to the requested roll
};

// The ghosts of `model` defined at head angle `angle_deg`, rotated by roll_deg - capture roll.
// InvalidArgument for an angle outside the model's valid range or non-finite input.
Result<std::vector<ModelGhostAt>> modelGhostsAt(const FlareModel& model,
                                                double angle_deg,
                                                double roll_deg);

// Whether the model was fitted to colour frames: from capture.raw_format where the model records
// it (a Bayer mosaic: colour), else from its ghosts (a fit of monochrome frames gives every ghost
// the same series in R, G and B). `recorded` (when not null) says which.
bool fittedInColour(const FlareModel& model, bool* recorded = nullptr);

// A ghost's light in the frame, roughly, summed over the channels (>= 0): its inner intensity over
// the area of the ellipse through its extents, and eq. 6.4's border profile across the edge along
// that ellipse's perimeter. Cheap; for comparing a ghost with itself at neighbouring angles.
double roughGhostEnergy(const GhostState& ghost);

struct ModelRenderOptions {
    render::FastDistanceOptions distance{4, 4};  // the exact evaluation's
    // Fast: flattened loop, blocks skipped, filled or interpolated, per pixel only at the edges;
    // Exact: every pixel of every ghost's range by shadeGhostBlock (render/model_ghost.h).
    render::GhostEvaluation evaluation = render::GhostEvaluation::Fast;
    double smooth_tolerance = 1e-4;  // render::GhostDrawOptions::smooth_tolerance
    // The smooth tolerance a fraction of the frame's brightest ghost's peak (its largest border or
    // inner value) for every ghost, instead of each ghost's own: a frame drawn for people, whose
    // error budget is the frame's. Off for the fit's frames and the score, whose ruler stays per
    // ghost.
    bool frame_tolerance = false;
    render::TileOptions tiles;
    double intensity_scale = 1.0;        // multiplies every intensity (another light's power), >= 0
    render::TileStats* stats = nullptr;  // when set, the tile engine's counts and clocks
};

// The model's ghosts at (angle_deg, roll_deg) drawn by the tile engine into a width x height image
// of the model's sensor (ModelLens sensor size), in the frame unit of the sweep it was fitted to.
Result<ImageRGB> renderModel(const FlareModel& model,
                             double angle_deg,
                             double roll_deg,
                             int64_t width,
                             int64_t height,
                             const ModelRenderOptions& options = {});

// The same for states already evaluated: each ghost prepared as a tile-engine primitive.
ImageRGB renderGhostStates(std::span<const GhostState> ghosts,
                           const render::SensorToImage& mapping,
                           int64_t width,
                           int64_t height,
                           const ModelRenderOptions& options = {});
// ... with every ghost's loop rotated by rotation_deg about the optical axis.
ImageRGB renderRotatedGhostStates(std::span<const GhostState> ghosts,
                                  double rotation_deg,
                                  const render::SensorToImage& mapping,
                                  int64_t width,
                                  int64_t height,
                                  const ModelRenderOptions& options = {});

}  // namespace flarelab::fit
