// ============================================================================
//  flarelab fit: ShadingRefitOptions, ShadingRefitReport, checkShadingRefitOptions, refitShading
// ============================================================================
//
// The shading series of a model fitted to the frames themselves, after compression.
//
// Why. A ghost's shape is well fixed by each frame, but its shading (eq. 6.4: border and inner
// intensity, two falloffs, two exponents) is not: a disc of even brightness is drawn as well by
// a bright thin rim fading fast to a dimmer inside as by an even disc, so per-frame fits wander
// between such equivalent settings from one frame to the next. Each parameter compressed on its
// own then mixes settings that were never seen together, and draws a ghost no frame showed
// (measured on the Heliar sweep: the per-frame fits' median relative L2 of 0.12 became 0.28 after
// compression, all of it from the shading; the compressed shapes with per-frame shading stay at
// 0.12).
//
// What. Shapes stay as compressed. The Chebyshev coefficients of each ghost's ten shading
// parameters (three ln border, three ln inner intensities, falloffs, exponents; pieces and
// degrees as compression chose them, raised to min_degree) are refitted, by Ceres, to the frames'
// pixels at up to frames_per_ghost frames spread over the ghost's range, in the frame fit's cost
// (asinh domain, Cauchy loss; fit/frame_fit.h), with the other ghosts drawn from their own series.
// Ghosts are refitted one after another, brightest first, `passes` times (Gauss-Seidel, as in a
// frame). Since the cost is on the images, settings that draw the same ghost are equally good and
// the series, being smooth by construction, cannot jump between them. Each parameter keeps its
// bounds (evaluation clamps to them); where a series strays out of them at a frame, the clamp
// leaves the image no say, so one more residual per frame and value (the excursion over the
// bounds' width) draws it back. Where two pieces of a series meet (half-way between two frames,
// so no frame holds the joint) one more residual holds them together: without it a piece's free
// end once swung a ghost 40 times too bright half a step before its first frame. Samples are
// block means compared with the model's block mean, as in the frame fit. The residual fields of
// the refitted pieces are left as they were; fitSweep then recomputes them against the per-frame
// values. One-channel frames fit one intensity series per kind and copy it to the three channels.
//
// Shapes too (shape_passes > 0; issue 20, item 4, per ghost). After the shading passes, every
// series of a ghost (its nine shape values as well as its ten shading values) is refitted to the
// same frames' samples, the other ghosts drawn from their own current series, brightest first,
// shape_passes times. The distance to the loop is sought per sample and evaluation (cached while
// the shape does not change), and its gradient with respect to the shape series is exact at the
// closest point (the frame fit's envelope theorem, fit/frame_fit.h), chained through the
// Chebyshev basis. The compression fitted each shape value to the per-frame fits; this fits them
// to the pixels, so a shape that the frames' noise, the tracker's priors or a neighbour's misfit
// pulled off in some frames is drawn where the sweep as a whole puts it. Shape series keep their
// compressed degrees; the shape values' bounds are opened to half the ghost's size (the
// compression's would hold a shape where every frame put it), the shading's are kept; joints as
// for the shading. A ghost whose outline lies mostly outside its frames (a veil larger than the
// frame) keeps its compressed shape: the pixels do not fix it, and refitted it spread to take a
// lost ghost's light. On by default: on the sparse protocol it lowers the held-out median on
// every shipped lens with ghosts (docs/shape-refit.md).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>

#include "common/result.h"
#include "fit/detect.h"
#include "fit/frame_fit.h"
#include "fit/model_file.h"

namespace flarelab::fit {

struct FrameSource;

struct ShadingRefitOptions {
    int frames_per_ghost = 60;  // frames a ghost's series are fitted to, >= 2; 0: no refit
    int max_samples = 16;       // samples per side of a ghost's crop in a frame, >= 4
    int max_iterations = 15;    // Levenberg-Marquardt iterations per ghost and pass, >= 1
    // Gauss-Seidel over overlapping ghosts converges slowly: on the Heliar sweep the fitted and
    // held-out errors fall up to about 6 passes (README, "Fitting: measured"). 1..100.
    int passes = 6;
    // Each shading series is raised to at least this degree (capped by the frames its piece
    // spans, less one) before the refit: cross-validated on wandering per-frame values, the
    // compression picks low degrees that no image would choose. Higher degrees follow the frames
    // more closely and wander between them: on the Heliar, 5 raised the held-out median on each
    // noise seed tried; 2 instead of 3 lowered it on two seeds and left it on the others. 0..12.
    int min_degree = 2;
    // Passes of the shape-and-shading refit after the shading passes, 0..100; 0: shapes stay as
    // compressed. Chosen on the Heliar (one frame in 5 fitted: one pass 0.1017 held out, two
    // 0.0978); scored on the other shipped lenses (docs/shape-refit.md).
    int shape_passes = 2;
    // Frames each ghost's shape refit sees: up to this many of its shading refit's frames, evenly
    // spread, >= 2. Fewer than the shading refit's leave the series free to swing between them:
    // on a two-ghost sweep of 13 frames, 7 of them drew the ghosts 0.38 off between the ends'
    // frames where all 13 kept every angle within 0.04.
    int shape_frames_per_ghost = 60;
    // A ghost's shape is refitted only where at least this share of its outline (as compressed)
    // lies in the frame, at the median of its frames, 0..1: a shape whose outline the frames do
    // not show is not fixed by their pixels. Chosen on the Heliar, one frame in 5 fitted (held
    // out: 0.1 0.0920, 0.25 0.0986, 0.5 0.0995, none required 0.0931; docs/shape-refit.md).
    double shape_min_outline_in_frame = 0.1;
};

struct ShadingRefitReport {
    int ghosts = 0;         // ghosts refitted
    int frames_loaded = 0;  // distinct frames read
    int64_t evaluations = 0;
    double initial_cost = 0.0;  // summed over ghosts, first pass
    double final_cost = 0.0;    // summed over ghosts, last pass
    // The shape refit (shape_passes > 0): ghosts refitted, their summed cost before its first
    // pass and after its last (each in its own frames' samples), and its time.
    int shape_ghosts = 0;
    int shape_unobserved = 0;  // ghosts left out for an outline mostly outside their frames
    double shape_initial_cost = 0.0;
    double shape_final_cost = 0.0;
    double shape_ms = 0.0;
    double time_ms = 0.0;
};

// One sample of a ghost's crop: the inclusive pixel rectangle [x0, x1] x [y0, y1] whose mean
// the refit compares with the model's mean over it, and its residual's weight.
struct SampleBlock {
    int64_t x0 = 0, x1 = -1, y0 = 0, y1 = -1;
    double weight = 1.0;
    bool operator==(const SampleBlock&) const = default;
};

// The samples of the crop [x0, x1] x [y0, y1] of a frame `width` pixels wide: blocks of `stride`
// pixels a side from (x0, y0) (smaller at the crop's far edges), each of weight 1. A block that
// holds pixels `excluded` marks (the light's disc, FrameDetection::excluded) is halved along its
// longer side until its parts hold none, parts wholly excluded dropped, so that the samples cover
// every pixel of the crop outside the excluded ones exactly once; a part weighs the square root
// of its share of the block's pixels, so that the parts of a block together weigh what it would.
// `excluded` must hold the frame's pixels; stride >= 1.
std::vector<SampleBlock> sampleBlocks(int64_t x0,
                                      int64_t x1,
                                      int64_t y0,
                                      int64_t y1,
                                      int64_t stride,
                                      const std::vector<uint8_t>& excluded,
                                      int64_t width);

namespace detail {

// Least-squares rows r + D x (D m x k) in at most k + 1 rows: D = Q R, the rows become
// `head` + `factor` x (the first min(m, k) rows of Q' r and R) and one constant row `rest` (the
// norm of the rest of Q' r), whose squares sum to those of the original rows for every x, so
// that a Gauss-Newton or Levenberg-Marquardt step on them is the same. The refit hands each
// frame's sample rows (D the residuals' derivatives with respect to the ghost's values) to Ceres
// this way: its dense QR then sees 10 or 19 rows and one per frame instead of one per sample,
// and its Householder products had been 40 % of a refit's time.
struct CompressedRows {
    Eigen::MatrixXd factor;  // min(m, k) x k, upper triangular
    Eigen::VectorXd head;    // min(m, k)
    double rest = 0.0;
};
CompressedRows compressRows(const Eigen::MatrixXd& d, Eigen::VectorXd r);
// The same on the caller's rows, which it overwrites (with the QR's factors, and Q' r).
CompressedRows compressRowsInPlace(Eigen::Ref<Eigen::MatrixXd> d, Eigen::Ref<Eigen::VectorXd> r);

}  // namespace detail

Status checkShadingRefitOptions(const ShadingRefitOptions& options);

// Refits the shading series of `model`'s ghosts to `frames` (the sweep the model was compressed
// from, angles in the model's head angles). `sky` is the background every frame's ghosts sit
// on (per channel; a non-finite value: each frame's own detected background). The detection
// options give the light's disc and excluded pixels; the cost options the transform, robust
// loss and distance. On error the model is left as it was.
Result<ShadingRefitReport> refitShading(FlareModel& model,
                                        const FrameSource& frames,
                                        const std::array<double, 3>& sky,
                                        const DetectOptions& detect,
                                        const CostOptions& cost,
                                        const ShadingRefitOptions& options);

}  // namespace flarelab::fit
