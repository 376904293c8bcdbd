// ============================================================================
//  flarelab fit: TruthFrame, TruthSource, AngleKind, angleKindName, ScoredAngle, ScoreOptions,
//                AngleScore, ScoreSummary, ScoreReport, ScoreImages, scoreAngles, scoreModel,
//                compareImages, toneMapScore, measuredTruth
// ============================================================================
//
// A model scored against ground truth: the model drawn at an angle (renderModel) against what
// the simulator shows there of the ghosts alone, noiselessly, in the same unit (TruthSource; the
// command line re-simulates the sweep's camera). Pixels within the light's disc are left out of
// both: by default the disc the fit left out of its frames (the model records it per fitted frame,
// ModelCapture::light_discs; lightDiscRadius), so that what is scored is what was fitted.
//   relative L2   = ||model - truth|| / ||truth||     over the remaining pixels and channels
//   PSNR          = 10 log10(max(truth)^2 / mean((model - truth)^2))
//   energy error  = (sum(model) - sum(truth)) / sum(truth)   (the total ghost light)
//   log rel. L2   = relative L2 of the images tone-mapped by v -> log(1 + v / s), s = log_scale
//                   times the truth's peak at that angle: a ghost a thousand times dimmer than
//                   the brightest still counts, where plain L2 hardly sees it
//   missed light  = sum(max(truth - model, 0)) / sum(truth): the light the model does not draw
//                   where the truth has it (a ghost left out counts whole; per pixel, not per
//                   ghost: a model ghost elsewhere does not make up for it)
//   masked energy = the truth's ghost light inside the light's disc over all of it: what the
//                   score (and the fit) cannot see
// The angles, by kind (AngleKind):
//   fitted    the model's captured angles (fit error: how well the compressed model reproduces
//             what it was fitted to);
//   left-out  captured frames the model was not fitted to (a sparse fit, `fit --every K`, scored
//             with the sweep, `score --sweep`): the held-out protocol no default was chosen on;
//   half-way  half-way between the model's captured angles;
//   random    seeded random angles inside the valid range;
//   given     angles the caller names.
// Every kind but fitted is held out (prediction error: what a user gets between the angles).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <optional>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "fit/detect.h"
#include "fit/model_eval.h"
#include "fit/model_file.h"
#include "hdr/sweep.h"

namespace flarelab::fit {

struct TruthFrame {
    ImageRGB image;                           // ghosts only, the model's frame unit
    std::optional<Eigen::Vector2d> light_px;  // where the light's own image is, if in view
};
using TruthSource = std::function<Result<TruthFrame>(double angle_deg)>;

enum class AngleKind { Fitted, LeftOut, Halfway, Random, Given };
inline constexpr AngleKind kAngleKinds[] = {
    AngleKind::Fitted, AngleKind::LeftOut, AngleKind::Halfway, AngleKind::Random, AngleKind::Given};
// "fitted", "left-out", "half-way", "random", "given".
const char* angleKindName(AngleKind kind);

struct ScoredAngle {
    double angle_deg = 0.0;
    AngleKind kind = AngleKind::Fitted;
};

struct ScoreOptions {
    std::vector<double> angles_deg;  // held-out angles to score (kind given); empty: chosen
    // Captured angles the model was not fitted to, each inside its valid range; at most
    // left_out_angles of them, evenly spread, are scored (besides the chosen kinds).
    std::vector<double> left_out_deg;
    int left_out_angles = 40;  // >= 0
    int halfway_angles = 16;   // at most this many half-way angles, evenly spread, >= 0
    int random_angles = 4;     // >= 0
    int fit_angles = 16;       // captured angles scored, evenly spread, >= 0
    uint64_t seed = 1;
    // The light's disc, pixels; < 0: the model's own (lightDiscRadius), or 3% of the image
    // diagonal for a model that does not record it (format version 4 and older).
    double light_mask_px = -1.0;
    double log_scale = 1e-3;      // of the log image, relative to the truth's peak; > 0
    ModelRenderOptions render;
};

struct AngleScore {
    double angle_deg = 0.0;
    AngleKind kind = AngleKind::Fitted;
    bool held_out = false;
    double rel_l2 = 0.0;
    double psnr_db = 0.0;
    double truth_energy = 0.0;  // sum of the truth over the scored pixels
    double model_energy = 0.0;  // sum of the model over the same pixels
    // (model_energy - truth_energy) / truth_energy; 0 when both are 0, 1 when only the truth is.
    double energy_error = 0.0;
    double log_rel_l2 = 0.0;
    double missed_light = 0.0;  // 0 for a black truth
    // The truth's light inside the light's disc over its light in the whole image; 0 for a black
    // truth.
    double masked_energy_fraction = 0.0;
    double light_mask_px = 0.0;  // the radius of the light's disc left out here
};

struct ScoreSummary {
    int count = 0;
    double median = 0.0;  // of rel_l2
    double worst = 0.0;
    double worst_angle_deg = 0.0;
    double median_psnr_db = 0.0;
    double median_abs_energy_error = 0.0;  // of |energy_error|
    double worst_abs_energy_error = 0.0;
    double median_log_rel_l2 = 0.0;
    double worst_log_rel_l2 = 0.0;
    double median_missed_light = 0.0;
    double median_masked_energy_fraction = 0.0;
};

struct ScoreReport {
    std::vector<AngleScore> angles;
    ScoreSummary heldout_rel_l2;  // every held-out kind together
    ScoreSummary fit_rel_l2;
    // One summary per kind that was scored, in the order of kAngleKinds.
    std::vector<std::pair<AngleKind, ScoreSummary>> by_kind;
};

// What scoreModel shows of one angle, for images a person looks at (score --images).
struct ScoreImages {
    const AngleScore& score;
    const ImageRGB& model;
    const ImageRGB& truth;
    std::optional<Eigen::Vector2d> light_px;
    double light_mask_px = 0.0;
};

// The radius of the disc around the light that the fit left out at `angle_deg`, from the model's
// record (ModelCapture::light_discs): a recorded angle's own; between two, the linear
// interpolation of their radii, or the larger where one frame had no light (the light coming
// into or leaving view); beyond them, the nearest one's. nullopt when nothing is recorded.
std::optional<double> lightDiscRadius(const FlareModel& model, double angle_deg);

// The angles scoreModel uses: the fitted ones ascending, then the held-out ones ascending (an
// angle of two held-out kinds is scored once, as the first of left-out, half-way, random; a
// half-way angle that is a left-out frame is left to the left-out kind, scored or not).
Result<std::vector<ScoredAngle>> scoreAngles(const FlareModel& model, const ScoreOptions& options);

// The scores of `model` against `truth` (same size) outside a disc; InvalidArgument for
// mismatched sizes or a log_scale not > 0. A truth that is zero everywhere scores rel_l2 = 0 when
// the model is zero too and 1 otherwise (nothing to predict, so anything drawn is all error).
Result<AngleScore> compareImages(const ImageRGB& model,
                                 const ImageRGB& truth,
                                 std::optional<Eigen::Vector2d> light_px,
                                 double light_mask_px,
                                 double log_scale = 1e-3);

// The score's tone mapping of one value: log(1 + v / s) / log(1 + peak / s) with s = log_scale *
// peak, in [0, 1] for v in [0, peak] (negative v counts as 0); 0 when peak is not > 0.
double toneMapScore(double v, double peak, double log_scale);

// `images`, when given, sees each angle's images once scored; an error from it ends the score.
Result<ScoreReport> scoreModel(const FlareModel& model,
                               const TruthSource& truth,
                               const ScoreOptions& options = {},
                               const std::function<void(int done, int total)>& progress = {},
                               const std::function<Status(const ScoreImages&)>& images = {});

// The sweep's own frames as the truth (`score --measured`), for a lens whose prescription the lab
// does not have: at each captured angle, the frame less the sky (the lowest background, per
// channel, that detectGhosts finds in 9 frames spread over the sweep, as the fit takes it: a
// frame's own background may hold a veil larger than the frame), not clamped (the noise's lower
// half stays; the log image counts values below 0 as 0), and the light where the detection finds
// it (its disc's radius is the model's, as always). Unlike the simulator's truth these hold the
// camera's noise, so a perfect model scores the noise's share of the ghost light rather than 0,
// the light's glare beyond the disc counts as ghost light, and the masked share is mostly the
// light itself; the ranking of models fitted to one sweep is what they are for. Frames are read
// when asked for (from several threads at once). An angle no frame of the sweep was captured at
// (within 1e-6 deg) is an InvalidArgument naming it and the sweep; a frame that cannot be read,
// its error with the file's name. InvalidArgument for sensor sizes not > 0, a sweep without
// frames or bad detection options.
Result<TruthSource> measuredTruth(const hdr::Sweep& sweep,
                                  double sensor_width_mm,
                                  double sensor_height_mm,
                                  const DetectOptions& detect = {});

}  // namespace flarelab::fit
