// ============================================================================
//  flarelab predict: SwitchFigure, SwitchingOptions, PlanSegment, SwitchingPlan, planSwitching
// ============================================================================
//
// Camera switching for a broadcast (item 5 of issue 21): several cameras cover the same action;
// at every time step each has a figure of how bad its flare is (higher is worse; NaN where the
// model cannot say). The plan picks one camera per step so that
//   1. as few steps as possible are over the threshold (an unknown figure counts as over),
//   2. then as few cuts as possible,
//   3. then the figure summed over the plan is as small as possible,
// with every shot except the last at least `min_dwell_steps` long (a director does not cut back
// after a second). Exact, by dynamic programming over (step, camera, steps on it so far, capped at
// the dwell): O(steps x cameras x dwell) time, O(steps x cameras x dwell) bytes for the way back.
// Steps where every camera is over the threshold are reported as intervals with no clean camera.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "common/result.h"

namespace flarelab::predict {

enum class SwitchFigure {
    ContrastLoss,  // 1 - eq. 9.3's K_real / K_ideal, from the flare's mean
    FlareMean,     // the flare's mean, in the camera's DN
    FlarePeak,     // the flare's brightest pixel (an upper bound when several lights add)
    GlareIndicator,  // the flare's mean over the scene's log-average (§9.2 of the thesis)
};
// "contrast-loss", "flare-mean", "flare-peak", "glare"
const char* switchFigureName(SwitchFigure figure);

inline constexpr int64_t kMaxSwitchingStates = 50'000'000;

struct SwitchingOptions {
    double threshold = 0.1;       // a step is clean when its figure is <= threshold
    int64_t min_dwell_steps = 1;  // >= 1
};

struct PlanSegment {
    int camera = 0;          // index into the cameras
    int64_t first_step = 0;  // inclusive
    int64_t end_step = 0;    // exclusive
};

struct StepInterval {
    int64_t first_step = 0;
    int64_t end_step = 0;  // exclusive
};

struct SwitchingPlan {
    std::vector<PlanSegment> segments;          // in order, covering every step
    int64_t steps_over = 0;                     // steps whose chosen camera is over the threshold
    int64_t cuts = 0;                           // segments.size() - 1
    double figure_sum = 0.0;                    // over the chosen cameras' known figures
    std::vector<StepInterval> no_clean_camera;  // every camera over (or unknown) there
};

// `figures[c][t]`: camera c's figure at step t; every camera the same number of steps (>= 1).
// InvalidArgument for no camera, cameras of different lengths, no step, a dwell < 1, a threshold
// that is not finite, or more than kMaxSwitchingStates states (steps x cameras x dwell, 4 bytes
// each for the way back).
Result<SwitchingPlan> planSwitching(std::span<const std::vector<double>> figures,
                                    const SwitchingOptions& options);

}  // namespace flarelab::predict
