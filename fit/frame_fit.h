// ============================================================================
//  flarelab fit: Optimizer, CostOptions, FrameFitOptions, GhostFitReport, FrameFitReport,
//                checkFrameFitOptions, transformScales, fitFrame, drawFrameModel
// ============================================================================
//
// Fitting the ghosts of one frame (chapter 7 of the thesis), each ghost on its own crop with the
// others held at their current values (block coordinate descent, `passes` times over). Within a
// pass the ghosts are fitted one after another, brightest first, each against the others' latest
// states (Gauss-Seidel): fitted at once from the same state, overlapping ghosts would each fill
// the same residual and overshoot together. The cores share each ghost's cost evaluation.
//
// Cost (§7.1). A ghost's crop is its pixel range (control box grown by the outer falloff and
// `margin` times its size on every side, clipped to the frame) sampled on a grid of at most
// max_samples per side: a sample holds the mean of the frame over its block, less the
// background, and the model (this ghost plus the others) is taken as its mean over the same block
// (render::boxTransferWeights: exact for an edge straight across the block). Taken at the block's
// centre instead, a sharp edge averaged over a block of 10 to 40 pixels reads as a wide falloff,
// which the fit then learned and the renderer drew as blur. Within
// a pass the ghost may move and grow by at most `margin` / 2 of its size (box bounds), so it
// stays inside its crop and every change it makes is seen by the cost; the next pass and frame
// re-crop around the new state. Data and model go through T(v) = asinh(v / s) with
//   s = max(transform_sigmas x noise sigma, transform_fraction x the frame's 99th percentile)
// per channel: linear up to s, logarithmic above, so that a ghost a few percent as bright as the
// brightest still weighs, while the noise of the sky, far below s, cannot dominate (the thesis
// worked in 8-bit LDR). Residuals:
//   r_i = T(model_i) - T(data_i)                      (the thesis's MSE term)
//   e_i = edge_weight * (LoG * r)_i                   (its Gaussian-Laplacian edge term; LoG is
//                                                      linear, so this is LoG(T(model)) -
//                                                      LoG(T(data)))
// Samples touching the light's disc or any excluded pixel (FrameDetection::excluded) are left
// out of both. Each residual goes through the Cauchy loss rho(x) = c^2 log(1 + x / c^2),
// c = robust_scale, by the exact transform r -> sign(r) sqrt(rho(r^2)), so that least squares on
// the transformed residuals minimizes sum rho(r^2): stars, hot pixels and the other ghosts' misfit
// cannot pull a ghost far.
//
// Parameters. Nine shape values with each handle as a fraction of its extent (so the shape's
// bounds are boxes: extents >= half a pixel, fractions in [0, 1]), per fitted channel the border
// and inner intensity (>= 0, relative to the initial border), the two falloffs (>= a quarter
// pixel; the inner <= twice the ghost's size, the outer <= its size) and the two exponents (in
// [0.25, 4]). Derivatives: the signed distance's gradient with respect to the control points is
// exact at the closest point (the envelope theorem: d dist / d P_k = -u B_k(t*), u the unit
// vector from the curve to the sample), chained through the control points' dependence on the
// parameters and the transfer function by Ceres' Jets.
//
// Restarts (Ceres). Two local minima are common enough to be tried around: a ghost with no prior
// starts from its detection, whose blob reaches over the outer falloff, so the fit is also run
// from the extents less the outer falloff; and a fit that ends with every border under a tenth
// of its inner intensity (a dark rim: the shape too large, its edge drawn by a steep inner rise)
// is run again from the edge that rise draws. The lower final cost is kept.
//
// Optimizers. Ceres: Levenberg-Marquardt, dense QR, box bounds. Gradient descent: the thesis's
// baseline (§7.2): central differences with a step per parameter, a learning rate per parameter
// that decays every epoch, each parameter updated as soon as its derivative is known (online);
// an epoch that raises the cost is undone and the rate halved (the thesis tuned its rates by hand).
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "common/result.h"
#include "fit/detect.h"
#include "fit/frame.h"

namespace flarelab::fit {

enum class Optimizer { Ceres, GradientDescent };
const char* optimizerName(Optimizer optimizer);  // "ceres", "gradient-descent"

struct CostOptions {
    int max_samples = 32;              // crop samples per side, >= 4 (the resolution knob)
    double margin = 0.6;               // crop grows by this fraction of the ghost's size, > 0
    double transform_sigmas = 3.0;     // s of T in noise sigmas, > 0
    double transform_fraction = 0.05;  // s of T relative to the frame's bright level, >= 0
    double edge_weight = 0.5;          // >= 0; 0 leaves the edge term out
    double edge_sigma = 1.0;           // of the LoG, in samples, > 0
    double robust_scale = 3.0;         // Cauchy c in units of T, > 0
    render::FastDistanceOptions distance{4, 2};  // Newton steps, seeds per segment
};

struct FrameFitOptions {
    Optimizer optimizer = Optimizer::Ceres;
    int max_iterations = 10;           // per ghost and pass: LM iterations or descent epochs, >= 1
    // Ceres only: the most steps of the projected line search that follows each trust-region
    // step (0..100; 0: none; Ceres' own default is 20). Each step evaluates the Jacobian; with
    // none the sweep fit is about 1.5 times faster and as accurate (docs/fit-scoring.md). The
    // first fits after a gap of missing frames, which landed in worse minima without it, now
    // also start from the track's nearest sample and the matched detection (fitFrame's restarts).
    int line_search_steps = 0;
    // Ceres only: the Levenberg-Marquardt trust region's initial radius, 1 / the first step's
    // damping on the Jacobi-scaled normal equations, in [1e-6, 1e16]. Ceres' default 1e4 makes
    // the first step nearly Gauss-Newton's; 10 or 1 save 29 or 38 % of the evaluations, but the
    // held-out error moves by -18 % to +57 % by lens (docs/fit-scoring.md).
    double trust_region_radius = 1e4;
    int passes = 2;                    // >= 1
    double function_tolerance = 1e-5;  // relative cost change that ends a ghost's fit
    CostOptions cost;
    // Gradient descent only.
    double learning_rate = 0.05;    // initial, per parameter in units of its scale^2 / cost
    double learning_decay = 0.95;   // per epoch, in (0, 1]
    double difference_step = 1e-3;  // central difference step, times the parameter's scale
    // Stop a ghost's descent once its cost is at or below this (the bench's "same final cost");
    // <= 0: never.
    double target_cost = 0.0;
    // With priors (fitFrame's last argument, one per ghost: the tracker's predictions), the
    // shape may leave its prior by about this fraction of the ghost's size before the prior
    // weighs as much as one sample's residual of 1; 0: priors are ignored. See fitFrame.
    double prior_tolerance = 0.05;
};

struct GhostFitReport {
    double initial_cost = 0.0;  // sum of rho over its residuals, at the start of the first pass
    double final_cost = 0.0;
    int64_t evaluations = 0;  // cost evaluations (Ceres: residual evaluations, with or without J)
    int iterations = 0;
    int64_t samples = 0;  // crop samples used (per channel)
    bool ok = true;       // false: its optimizer failed; its state was left as it was
};

struct FrameFitReport {
    std::vector<GhostFitReport> ghosts;  // one per input ghost
    double initial_cost = 0.0;           // sums over ghosts
    double final_cost = 0.0;
    int64_t evaluations = 0;
    double time_ms = 0.0;
};

Status checkFrameFitOptions(const FrameFitOptions& options);

// The scale s of the cost's transform T(v) = asinh(v / s) per channel (see Cost above): the
// larger of transform_sigmas noise sigmas and transform_fraction of the frame's 99th percentile
// above its background, outside the excluded pixels. Unused channels of a one-channel frame: 0.
std::array<double, 3> transformScales(const FitFrame& frame,
                                      const FrameDetection& detection,
                                      const CostOptions& cost);

// Fits `ghosts` (initial states in, fitted states out; every state valid on entry) to the frame.
// The detection supplies background, noise and the excluded pixels. InvalidArgument for options
// out of range, an invalid state or a detection that does not match the frame's size. A ghost whose
// crop holds no usable sample keeps its state (report: samples 0).
//
// Fixed ghosts (optional) are part of every ghost's model but are not fitted: the context of a
// frame whose other ghosts are already known.
// Priors (optional; the first priors.size() ghosts get one): nine more residuals per ghost,
// (shape value - prior) / tolerance, so that what the frame does not constrain (an edge outside
// the frame, a rim hidden under a brighter ghost) stays where the track predicts it instead of
// drifting; where the data speaks, its thousands of samples outweigh the nine.
// Restarts (optional; restarts[g] for the first restarts.size() ghosts, each list possibly
// empty): other starts for ghost g, for a start that may be far off (a track predicted across
// missing frames). After the first pass's fit from the given state, each restart, as given and
// with its extents less its outer falloff, is fitted within bounds around itself on a crop that
// holds every box involved, without the prior; the state that explains that crop best is kept,
// and where a restart's is, the ghost's prior is dropped for the later passes. More restarts
// than ghosts, or an invalid restart state, is InvalidArgument.
Result<FrameFitReport> fitFrame(const FitFrame& frame,
                                const FrameDetection& detection,
                                std::vector<GhostState>& ghosts,
                                const FrameFitOptions& options = {},
                                std::span<const GhostState> priors = {},
                                std::span<const GhostState> fixed = {},
                                std::span<const std::vector<GhostState>> restarts = {});

// The frame's model: the ghosts drawn as pixel means (through the tile engine) plus the
// background, in the frame's unit, with the frame's channel count.
ImageRGB drawFrameModel(const FitFrame& frame,
                        const FrameDetection& detection,
                        const std::vector<GhostState>& ghosts,
                        const render::FastDistanceOptions& distance = {});

}  // namespace flarelab::fit
