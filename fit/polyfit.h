// ============================================================================
//  flarelab fit: PolyFitOptions, PolyPiece, PolyFit, fitPolynomial, evaluatePolyFit
// ============================================================================
//
// Compression along a sweep: one fitted ghost parameter, sampled once per head angle, becomes a
// low-order polynomial of the angle (DESIGN.md, "fit/ ... compress"). The model file stores the
// coefficients, the angle range they are valid for and the fit residuals.
//
// Basis. Chebyshev polynomials T_k(x) of the angle mapped onto x in [-1, 1] over the range of the
// samples, x = 2 (angle - min) / (max - min) - 1. In that basis the least-squares design matrix is
// well conditioned whatever the units or offset of the angle (a degree-8 monomial basis on 0..30
// deg has a condition number near 1e13; bench/polyfit_bench.cpp prints both), and evaluation is
// Clenshaw's recurrence, which is backward stable. Least squares are solved by column-pivoting
// Householder QR of the (weighted) design matrix, never by normal equations, which would square
// the condition number.
//
// Degree. Chosen by cross-validation over 0..min(max_degree, what the folds can fit):
//   - K-fold with interleaved folds (sample i is held out in fold i mod K): for an ordered sweep
//     every fold predicts angles between kept neighbours, which is how the model is used;
//     leave-one-out when there are no more samples than folds;
//   - a gap (two neighbouring samples more than twice the median spacing apart, as missing
//     frames leave) adds two folds, the samples within one gap's width after it and those
//     within one width before it (the nearest to the gap first, no more than an interleaved fold
//     holds out): the interleaved folds never test a gap's inside, where a high degree can
//     swing freely, and these judge each degree by how it predicts across one.
//     Without gaps nothing changes; the held-out error reported (and compared with the noise
//     for splitting) is the interleaved folds' alone;
//   - the held-out error of a degree is the weighted mean square over all held-out samples, its
//     standard error the spread of the per-fold mean squares over sqrt(the number of folds);
//   - one-standard-error rule (Hastie, Tibshirani & Friedman, ESL 2nd ed., sec. 7.10): the lowest
//     degree whose held-out error is within one standard error of the best degree's.
// A degree is only tried when every training fold has more samples than coefficients, so the
// chosen degree is at most n - 2 for n >= 3 samples. With 2 samples nothing can be held out: the
// fit is the line through both (degree min(1, max_degree)); 1 sample is a constant valid only at
// its own angle.
//
// Pieces. One polynomial cannot follow a step or a kink. The noise of the data is estimated from
// the samples themselves (each interior sample against the line through its two neighbours, the
// pseudo-residuals of Gasser, Sroka & Jennen-Steinmetz 1986, with a median so that a step does not
// inflate it). A piece whose held-out RMS error exceeds split_factor times that noise (plus
// absolute_tolerance) is split in two, at the sample boundary where two straight lines fit the
// piece best. The split is kept only when the two halves, each fitted again with its own degree,
// have a pooled held-out mean square error below 0.8 times the whole's; each half is split again if
// it still fails, while both halves keep min_samples_per_piece samples and the total stays within
// max_pieces (depth first, left half first). The knot is the midpoint between the two samples
// either side of the cut. No continuity is imposed at knots: a polynomial per piece, fitted
// independently, so a real step stays a step.
//
// Angles must be strictly increasing (a sweep is ordered; a duplicate or reversed angle is a bug
// upstream and is reported, not silently sorted). Evaluation outside the valid range is an error,
// never an extrapolation.
#pragma once

#include <optional>
#include <span>
#include <vector>

#include "common/result.h"

namespace flarelab::fit {

struct PolyFitOptions {
    int max_degree = 8;  // ceiling of the degree search; silently capped by what the data supports
    // When >= 0: fit exactly this degree in one piece, no cross-validation and no splitting; a
    // degree above n_samples - 1 is refused (InvalidArgument), not capped.
    int fixed_degree = -1;
    int cv_folds = 10;  // K of K-fold cross-validation; leave-one-out when n_samples <= cv_folds
    bool allow_pieces = true;
    int min_samples_per_piece = 8;  // >= 3, so that every piece is cross-validated
    int max_pieces = 8;
    // Split when held-out RMS > split_factor * noise + absolute_tolerance. Pure noise gives a
    // held-out RMS near the noise (1.0 to 1.2 times it); the default leaves room for the error
    // of the noise estimate (about 1.2 / sqrt(n) relative, for the median of n pseudo-residuals).
    double split_factor = 1.5;
    double absolute_tolerance = 0.0;  // in the units of the values; >= 0
};

// One polynomial, valid on [angle_min_deg, angle_max_deg].
struct PolyPiece {
    double angle_min_deg = 0.0;
    double angle_max_deg = 0.0;
    // Chebyshev coefficients: value = sum_k c_k T_k(x), x = 2 (angle - min) / (max - min) - 1
    // (x = 0 when min == max). The degree is coefficients.size() - 1.
    std::vector<double> coefficients;
    int first_sample = 0;  // index of the piece's first sample in the input
    int sample_count = 0;
    double rms_residual = 0.0;  // unweighted, over the piece's samples (value - fit)
    double max_abs_residual = 0.0;
    std::optional<double> held_out_rms;  // cross-validated RMS at the chosen degree, if any ran

    int degree() const { return static_cast<int>(coefficients.size()) - 1; }
};

struct PolyFit {
    double angle_min_deg = 0.0;  // valid range: first and last sample angle
    double angle_max_deg = 0.0;
    std::vector<PolyPiece> pieces;  // ordered; piece i ends where piece i + 1 starts (its knot)
    int sample_count = 0;
    double rms_residual = 0.0;  // over all samples, unweighted
    double max_abs_residual = 0.0;
    double noise_estimate = 0.0;  // see the header comment; 0 with fewer than 3 samples
};

// InvalidArgument naming the field when an option is outside its range.
Status checkPolyFitOptions(const PolyFitOptions& options);

// Fits values[i] at angles_deg[i] (strictly increasing), with optional weights[i] (finite, > 0;
// empty means all 1; a weight scales the square of its residual, so use 1 / sigma_i^2). Errors
// (InvalidArgument, naming the field and index): no samples, sizes that differ, a non-finite
// angle, value or weight, a weight <= 0, angles not strictly increasing (duplicates included), an
// angle range that overflows, bad options, fixed_degree above n - 1.
Result<PolyFit> fitPolynomial(std::span<const double> angles_deg,
                              std::span<const double> values,
                              const PolyFitOptions& options = {},
                              std::span<const double> weights = {});

// sum_k c_k T_k(x) by Clenshaw's recurrence; 0 for no coefficients. Any finite x is accepted
// (outside [-1, 1] this is the polynomial's continuation).
double chebyshevValue(std::span<const double> coefficients, double x);

// Chebyshev coefficients of d/dx of sum_k c_k T_k(x) (one fewer; empty for a constant).
std::vector<double> chebyshevDerivative(std::span<const double> coefficients);

// The fitted value at angle_deg. A knot belongs to the piece on its left. InvalidArgument when
// angle_deg is not finite or outside [angle_min_deg, angle_max_deg] (no extrapolation).
Result<double> evaluatePolyFit(const PolyFit& fit, double angle_deg);

// d value / d angle, per degree, with the same range rule; 0 for a single-sample constant.
Result<double> evaluatePolyFitSlope(const PolyFit& fit, double angle_deg);

// The median of the gaps between neighbouring angles, given in ascending order (the gap rule of
// the degree's cross-validation, and the sweep fit's step); 0 for fewer than two angles.
double medianSpacing(std::span<const double> ascending_deg);

}  // namespace flarelab::fit
