// ============================================================================
//  flarelab fit: TruthFrame, TruthSource, ScoreOptions, AngleScore, ScoreSummary, ScoreReport,
//                scoreAngles, scoreModel, compareImages
// ============================================================================
//
// A model scored against ground truth: the model drawn at an angle (renderModel) against what
// the simulator shows there of the ghosts alone, noiselessly, in the same unit (TruthSource; the
// command line re-simulates the sweep's camera). Pixels within light_mask_px of the light's own
// image are left out of both, as the fit leaves them out.
//   relative L2 = ||model - truth|| / ||truth||     over the remaining pixels and channels
//   PSNR        = 10 log10(max(truth)^2 / mean((model - truth)^2))
// Two sets of angles: the captured angles (fit error: how well the compressed model reproduces
// what it was fitted to) and held-out angles, half-way between captured angles plus a few seeded
// random ones inside the valid range (prediction error: what a user gets between the angles).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <optional>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "fit/model_eval.h"
#include "fit/model_file.h"

namespace flarelab::fit {

struct TruthFrame {
    ImageRGB image;                           // ghosts only, the model's frame unit
    std::optional<Eigen::Vector2d> light_px;  // where the light's own image is, if in view
};
using TruthSource = std::function<Result<TruthFrame>(double angle_deg)>;

struct ScoreOptions {
    std::vector<double> angles_deg;  // held-out angles to score; empty: chosen as above
    int halfway_angles = 16;         // at most this many half-way angles, evenly spread, >= 0
    int random_angles = 4;           // >= 0
    int fit_angles = 16;             // captured angles scored, evenly spread, >= 0
    uint64_t seed = 1;
    double light_mask_px = -1.0;  // < 0: 3% of the image diagonal
    ModelRenderOptions render;
};

struct AngleScore {
    double angle_deg = 0.0;
    bool held_out = false;
    double rel_l2 = 0.0;
    double psnr_db = 0.0;
    double truth_energy = 0.0;  // sum of the truth over the scored pixels
};

struct ScoreSummary {
    int count = 0;
    double median = 0.0;
    double worst = 0.0;
    double worst_angle_deg = 0.0;
    double median_psnr_db = 0.0;
};

struct ScoreReport {
    std::vector<AngleScore> angles;
    ScoreSummary heldout_rel_l2;
    ScoreSummary fit_rel_l2;
};

// The angles scoreModel uses: {captured (fit) angles, held-out angles}, each ascending.
Result<std::pair<std::vector<double>, std::vector<double>>> scoreAngles(
    const FlareModel& model, const ScoreOptions& options);

// Relative L2 and PSNR of `model` against `truth` (same size) outside a disc; InvalidArgument for
// mismatched sizes. A truth that is zero everywhere scores rel_l2 = 0 when the model is zero too
// and 1 otherwise (nothing to predict, so anything drawn is all error).
Result<AngleScore> compareImages(const ImageRGB& model,
                                 const ImageRGB& truth,
                                 std::optional<Eigen::Vector2d> light_px,
                                 double light_mask_px);

Result<ScoreReport> scoreModel(const FlareModel& model,
                               const TruthSource& truth,
                               const ScoreOptions& options = {},
                               const std::function<void(int done, int total)>& progress = {});

}  // namespace flarelab::fit
