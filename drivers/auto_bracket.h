// ============================================================================
//  flarelab drivers: BracketPlanOptions, BracketPlan, planBrackets
// ============================================================================
//
// Auto-bracketing: the exposure times of a sweep's brackets, chosen from probe exposures of the
// scene in front of the camera (the head already at the sweep's first angle), for any Camera.
//
// Goals.
//   - The shortest exposure does not clip the light's core: the brightest pixel of the frame
//     stays at or below core_level of the range above black (white or the calibrated saturation
//     level). The headroom below 1 is for the sweep: the light's image and its ghosts change
//     from angle to angle, and the plan is made at the first one.
//   - The longest exposure reaches the ghosts' noise floor. The floor is the scene's dark level,
//     the floor_percentile-th percentile of the signal rate over the frame (the background the
//     ghosts' tails sink into: ambient light and the lens's veiling glare). It is reached when the
//     longest exposure records it with a signal-to-noise ratio of at least floor_snr, noise from
//     the sensor's model var = read^2 + signal / K (+ 1/12 DN^2 of rounding): anything dimmer is
//     below what the scene lets a fit tell from its background. The plan aims at a floor
//     floor_headroom times dimmer than the first angle's, since the glare that lifts the floor
//     there leaves the frame as the sweep turns away from the light.
//   - Between them, neighbouring exposures differ by at most a factor r, so that every radiance
//     in between is well exposed in at least one: r = min(max_ratio, high / low) with high =
//     well_level of the range (below clipping) and low the signal with a signal-to-noise ratio of
//     well_snr. The times are spaced evenly in log between the shortest and the longest.
//   - Within the camera's range of exposures and the time budget (the sum of a bracket's
//     exposures): when the budget cannot hold the longest, it is shortened and the plan says the
//     floor is not reached.
//
// Probes. Each is one frame (applyCalibration'd when a calibration is given). The core: from the
// camera's current exposure, down by 16 while the brightest pixel clips, up while it is too dim to
// measure (below 5 % of the range), then t_short = t * core_level / (peak fraction), checked by a
// frame at t_short (halved while it clips). The floor: up from t_short until the floor
// percentile's signal is measurable (above 10 read-noise sigmas or 1 % of the range), at most the
// budget and the camera's longest exposure. The noise model: the frame's read_noise_dn and
// electrons_per_dn where the camera (or calibration) gives them; else photon transfer on a pair
// of frames of the floor probe; else MergeOptions' fallback (K = 1, read noise 2 DN), said so.
//
// The plan records why each time was chosen (reasons: lines for the sweep manifest) and says so
// plainly when a goal cannot be met (core_unclipped, floor_reached false with a line saying why):
// the shortest exposure the camera has still clips the core; the floor lies below what the
// longest exposure or the budget can reach (a dark lab without veiling glare has no floor above
// black). Errors are the camera's (with the probe's exposure as context) and InvalidArgument for
// options out of range.
#pragma once

#include <string>
#include <vector>

#include "common/result.h"
#include "drivers/calibration.h"
#include "drivers/camera.h"

namespace flarelab::drivers {

struct BracketPlanOptions {
    double core_level = 0.5;  // the core's peak in the shortest exposure, of the range; (0, 1)
    double floor_percentile = 0.05;  // the scene's dark level; (0, 0.5]
    double floor_snr = 10.0;         // the floor's signal-to-noise ratio in the longest; > 0
    // The longest exposure records a floor this many times dimmer than the one measured at the
    // first angle, >= 1: along a sweep the light's veiling glare leaves the frame and the floor
    // sinks to the ambient background.
    double floor_headroom = 8.0;
    double well_level = 0.9;         // top of the well-exposed band, of the range; (0, 1)
    double well_snr = 10.0;          // bottom of the well-exposed band; > 0
    double max_ratio = 16.0;         // between neighbouring exposures; > 1
    int max_exposures = 12;          // in a bracket; 1..255
    double budget_s = 30.0;          // most exposure time one bracket may take; > 0
    int max_probes = 24;             // frames the probes may take; >= 4
    double timeout_margin_s = 10.0;  // added to each probe's exposure for its capture timeout
    // Applied to every probe frame when given (hot pixels repaired, curve linearized, noise).
    const CameraCalibration* calibration = nullptr;
};

struct BracketPlan {
    std::vector<double> exposure_times_s;  // ascending
    double gain = 1.0;                     // the camera's, as planned at
    bool core_unclipped = false;   // the shortest keeps the core at or below core_level (probed)
    bool floor_reached = false;    // the longest records the floor at floor_snr or more
    double core_peak = 0.0;        // the core's peak in the shortest exposure, of the range
    double floor_rate_dn_s = 0.0;  // the floor's signal rate (DN/s above black); 0: none
    // The predicted signal-to-noise ratio in the longest exposure of the floor measured at the
    // first angle (of one floor_headroom times dimmer: less).
    double floor_snr = 0.0;
    double ratio = 0.0;          // between neighbouring exposures
    double read_noise_dn = 0.0;  // the noise model used
    double electrons_per_dn = 0.0;
    int probes = 0;
    std::vector<std::string> reasons;  // why, one line each
};

Result<BracketPlan> planBrackets(Camera& camera, const BracketPlanOptions& options = {});

}  // namespace flarelab::drivers
