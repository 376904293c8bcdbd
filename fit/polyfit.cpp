#include "fit/polyfit.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>
#include <string>
#include <utility>

namespace flarelab::fit {

namespace {

constexpr int kMaxDegreeLimit = 30;
// A split must cut the held-out mean square error by this factor: held-out errors are themselves
// noisy, and a split that only wins by chance costs samples per piece.
constexpr double kSplitGain = 0.8;

Error invalid(std::string message) {
    return makeError(ErrorCode::InvalidArgument, std::move(message));
}

// "name[i]", for messages.
std::string field(const char* name, size_t i) {
    std::ostringstream out;
    out << name << '[' << i << ']';
    return out.str();
}

// All the digits of a double: angles 1e-8 deg apart must read as different.
std::string number(double v) {
    std::ostringstream out;
    out << std::setprecision(17) << v;
    return out.str();
}

// The samples of one fit, the weights already as square roots (row scaling of the design
// matrix turns weighted least squares into ordinary least squares).
struct Samples {
    std::span<const double> angles_deg;
    std::span<const double> values;
    std::vector<double> sqrt_weights;
};

// Maps an angle onto [-1, 1] over [lo, hi]. Subtracting lo first keeps the digits of the angle's
// offset out of the result (angles near 1e6 deg spanning 1e-6 deg map as well as 0..30).
double normalize(double angle_deg, double lo, double hi) {
    if (hi == lo) return 0.0;
    return 2.0 * ((angle_deg - lo) / (hi - lo)) - 1.0;
}

// Weighted least squares in the Chebyshev basis over the samples rows[], normalized to [lo, hi].
Eigen::VectorXd solveChebyshev(
    const Samples& s, std::span<const int> rows, int degree, double lo, double hi) {
    const Eigen::Index m = static_cast<Eigen::Index>(rows.size());
    Eigen::MatrixXd a(m, degree + 1);
    Eigen::VectorXd b(m);
    for (Eigen::Index r = 0; r < m; ++r) {
        const int i = rows[r];
        const double x = normalize(s.angles_deg[i], lo, hi);
        const double w = s.sqrt_weights[i];
        double t_prev = 1.0;
        double t = x;
        a(r, 0) = w;
        if (degree >= 1) a(r, 1) = w * x;
        for (int k = 2; k <= degree; ++k) {
            const double t_next = 2.0 * x * t - t_prev;
            a(r, k) = w * t_next;
            t_prev = t;
            t = t_next;
        }
        b(r) = w * s.values[i];
    }
    const Eigen::VectorXd c = a.colPivHouseholderQr().solve(b);
    return c;
}

std::vector<double> toVector(const Eigen::VectorXd& c) {
    return std::vector<double>(c.data(), c.data() + c.size());
}

struct DegreeChoice {
    int degree = 0;
    std::optional<double> held_out_rms;
};

// Cross-validated degree for samples [begin, end) on [lo, hi] (see the header for the rule).
DegreeChoice chooseDegree(
    const Samples& s, int begin, int end, double lo, double hi, const PolyFitOptions& options) {
    const int n = end - begin;
    if (n == 1) return {0, std::nullopt};
    if (n == 2) return {std::min(1, options.max_degree), std::nullopt};
    const int interleaved = n <= options.cv_folds ? n : options.cv_folds;
    // The smallest training set has n - ceil(n / folds) samples; it must exceed the coefficients.
    const int min_train = n - (n + interleaved - 1) / interleaved;
    const int top = std::min(options.max_degree, min_train - 1);
    // The folds' held-out samples: the interleaved folds, then two more for each gap (neighbours
    // more than twice the median spacing apart, as missing frames leave), holding out the samples
    // within one gap's width after it and before it (the nearest first), so that a degree is
    // also judged by how it predicts across a gap, where the interleaved folds never test it.
    std::vector<std::vector<int>> held(static_cast<size_t>(interleaved));
    for (int i = begin; i < end; ++i)
        held[static_cast<size_t>((i - begin) % interleaved)].push_back(i);
    const double median =
        medianSpacing(s.angles_deg.subspan(static_cast<size_t>(begin), static_cast<size_t>(n)));
    for (int i = begin + 1; i < end; ++i) {
        const double from = s.angles_deg[i - 1], to = s.angles_deg[i];
        if (!(to - from > 2.0 * median)) continue;
        const double width = to - from;
        // Nearest the gap first, as many as an interleaved fold holds out or half the samples
        // on that side, whichever is more.
        const int most_after = std::max(n - min_train, (end - i) / 2);
        const int most_before = std::max(n - min_train, (i - begin) / 2);
        std::vector<int> after, before;
        for (int k = i; k < end && s.angles_deg[k] <= to + width; ++k)
            if (static_cast<int>(after.size()) < most_after) after.push_back(k);
        for (int k = i - 1; k >= begin && s.angles_deg[k] >= from - width; --k)
            if (static_cast<int>(before.size()) < most_before) before.push_back(k);
        held.push_back(std::move(after));
        held.push_back(std::move(before));
    }
    const int folds = static_cast<int>(held.size());

    std::vector<double> cv_mse(top + 1, 0.0);
    std::vector<double> cv_se(top + 1, 0.0);
    // The interleaved folds' mean square alone: the held-out error the pieces' split rule
    // compares with the noise (a gap fold's error is the gap's, which a split cannot mend).
    std::vector<double> interleaved_mse(top + 1, 0.0);
    std::vector<int> train;
    std::vector<char> out(static_cast<size_t>(n));  // held out in the fold at hand
    for (int d = 0; d <= top; ++d) {
        double sum_sq = 0.0;
        double sum_w = 0.0;
        std::vector<double> fold_mse;
        for (int f = 0; f < folds; ++f) {
            const std::vector<int>& test = held[static_cast<size_t>(f)];
            std::fill(out.begin(), out.end(), 0);
            for (const int i : test) out[static_cast<size_t>(i - begin)] = 1;
            train.clear();
            for (int i = begin; i < end; ++i)
                if (!out[static_cast<size_t>(i - begin)]) train.push_back(i);
            const std::vector<double> c = toVector(solveChebyshev(s, train, d, lo, hi));
            double fold_sq = 0.0;
            double fold_w = 0.0;
            for (const int i : test) {
                const double e =
                    s.values[i] - chebyshevValue(c, normalize(s.angles_deg[i], lo, hi));
                const double w = s.sqrt_weights[i] * s.sqrt_weights[i];
                fold_sq += w * e * e;
                fold_w += w;
            }
            sum_sq += fold_sq;
            sum_w += fold_w;
            fold_mse.push_back(fold_sq / fold_w);
            if (f + 1 == interleaved) interleaved_mse[static_cast<size_t>(d)] = sum_sq / sum_w;
        }
        cv_mse[d] = sum_sq / sum_w;
        double mean = 0.0;
        for (const double v : fold_mse) mean += v;
        mean /= folds;
        double var = 0.0;
        for (const double v : fold_mse) var += (v - mean) * (v - mean);
        var /= std::max(1, folds - 1);
        cv_se[d] = std::sqrt(var / folds);
    }
    const int best =
        static_cast<int>(std::min_element(cv_mse.begin(), cv_mse.end()) - cv_mse.begin());
    // Exact data leaves only round-off in the held-out errors; differences below it (relative
    // 1e-12 of the largest value) do not count, so that exact data gets its true degree.
    double scale = 0.0;
    for (int i = begin; i < end; ++i) scale = std::max(scale, std::abs(s.values[i]));
    const double round_off = 1e-12 * scale;
    int chosen = best;
    for (int d = 0; d < best; ++d) {
        if (cv_mse[d] <= cv_mse[best] + cv_se[best] + round_off * round_off) {
            chosen = d;
            break;
        }
    }
    return {chosen, std::sqrt(interleaved_mse[static_cast<size_t>(chosen)])};
}

// Residual statistics of a piece over its samples.
void fillResiduals(const Samples& s, PolyPiece& piece) {
    double sum_sq = 0.0;
    double max_abs = 0.0;
    const int end = piece.first_sample + piece.sample_count;
    for (int i = piece.first_sample; i < end; ++i) {
        const double x = normalize(s.angles_deg[i], piece.angle_min_deg, piece.angle_max_deg);
        const double e = s.values[i] - chebyshevValue(piece.coefficients, x);
        sum_sq += e * e;
        max_abs = std::max(max_abs, std::abs(e));
    }
    piece.rms_residual = std::sqrt(sum_sq / piece.sample_count);
    piece.max_abs_residual = max_abs;
}

PolyPiece fitPiece(
    const Samples& s, int begin, int end, double lo, double hi, const PolyFitOptions& options) {
    std::vector<int> rows;
    for (int i = begin; i < end; ++i) rows.push_back(i);
    PolyPiece piece;
    piece.angle_min_deg = lo;
    piece.angle_max_deg = hi;
    piece.first_sample = begin;
    piece.sample_count = end - begin;
    int degree = options.fixed_degree;
    if (degree < 0) {
        const DegreeChoice choice = chooseDegree(s, begin, end, lo, hi, options);
        degree = choice.degree;
        piece.held_out_rms = choice.held_out_rms;
    }
    piece.coefficients = toVector(solveChebyshev(s, rows, degree, lo, hi));
    fillResiduals(s, piece);
    return piece;
}

// Noise standard deviation from pseudo-residuals (Gasser, Sroka & Jennen-Steinmetz 1986): each
// interior sample minus the line through its neighbours, scaled to unit variance under white
// noise; the median absolute value (times 1.4826, the normal consistency factor) so that the few
// samples at a step or kink do not count.
double estimateNoise(const Samples& s) {
    const int n = static_cast<int>(s.values.size());
    if (n < 3) return 0.0;
    std::vector<double> scaled;
    for (int i = 1; i + 1 < n; ++i) {
        const double h = s.angles_deg[i + 1] - s.angles_deg[i - 1];
        const double a = (s.angles_deg[i + 1] - s.angles_deg[i]) / h;
        const double b = (s.angles_deg[i] - s.angles_deg[i - 1]) / h;
        const double r = s.values[i] - a * s.values[i - 1] - b * s.values[i + 1];
        scaled.push_back(std::abs(r) / std::sqrt(1.0 + a * a + b * b));
    }
    auto mid = scaled.begin() + static_cast<std::ptrdiff_t>(scaled.size() / 2);
    std::nth_element(scaled.begin(), mid, scaled.end());
    return 1.4826 * *mid;
}

// The first sample of the right half of [begin, end) where one line per side has the least total
// weighted square error; both halves keep min_samples samples.
int findSplit(const Samples& s, int begin, int end, int min_samples) {
    double best_sse = std::numeric_limits<double>::infinity();
    int best = begin + min_samples;
    std::vector<int> rows;
    for (int cut = begin + min_samples; cut <= end - min_samples; ++cut) {
        double sse = 0.0;
        for (const auto& [b, e] : {std::pair{begin, cut}, std::pair{cut, end}}) {
            rows.clear();
            for (int i = b; i < e; ++i) rows.push_back(i);
            const double lo = s.angles_deg[b];
            const double hi = s.angles_deg[e - 1];
            const std::vector<double> c = toVector(solveChebyshev(s, rows, 1, lo, hi));
            for (const int i : rows) {
                const double r =
                    s.sqrt_weights[i] *
                    (s.values[i] - chebyshevValue(c, normalize(s.angles_deg[i], lo, hi)));
                sse += r * r;
            }
        }
        if (sse < best_sse) {
            best_sse = sse;
            best = cut;
        }
    }
    return best;
}

// Fits [begin, end) on [lo, hi], splitting while the piece fails the tolerance and the budget of
// extra pieces (splits_left) lasts; depth first, left half first.
void fitRange(const Samples& s,
              int begin,
              int end,
              double lo,
              double hi,
              double tolerance,
              const PolyFitOptions& options,
              int& splits_left,
              std::vector<PolyPiece>& out) {
    PolyPiece piece = fitPiece(s, begin, end, lo, hi, options);
    const bool fails = piece.held_out_rms && *piece.held_out_rms > tolerance;
    if (!fails || !options.allow_pieces || options.fixed_degree >= 0 || splits_left <= 0 ||
        end - begin < 2 * options.min_samples_per_piece) {
        out.push_back(std::move(piece));
        return;
    }
    const int cut = findSplit(s, begin, end, options.min_samples_per_piece);
    const double knot = 0.5 * (s.angles_deg[cut - 1] + s.angles_deg[cut]);
    // Split only when the halves predict held-out samples clearly better than the whole did: a
    // piece that merely misjudged the noise gains nothing from having fewer samples.
    const PolyPiece left = fitPiece(s, begin, cut, lo, knot, options);
    const PolyPiece right = fitPiece(s, cut, end, knot, hi, options);
    const double pooled_mse = (*left.held_out_rms * *left.held_out_rms * left.sample_count +
                               *right.held_out_rms * *right.held_out_rms * right.sample_count) /
                              (end - begin);
    if (!(pooled_mse < kSplitGain * *piece.held_out_rms * *piece.held_out_rms)) {
        out.push_back(std::move(piece));
        return;
    }
    --splits_left;
    fitRange(s, begin, cut, lo, knot, tolerance, options, splits_left, out);
    fitRange(s, cut, end, knot, hi, tolerance, options, splits_left, out);
}

const PolyPiece* findPiece(const PolyFit& fit, double angle_deg) {
    for (const PolyPiece& piece : fit.pieces)
        if (angle_deg <= piece.angle_max_deg) return &piece;
    return nullptr;
}

Result<const PolyPiece*> pieceAt(const PolyFit& fit, double angle_deg) {
    if (!std::isfinite(angle_deg)) return invalid("angle_deg: not finite");
    if (fit.pieces.empty()) return invalid("fit: has no pieces");
    if (angle_deg < fit.angle_min_deg || angle_deg > fit.angle_max_deg)
        return invalid("angle_deg: " + number(angle_deg) + " is outside the valid range [" +
                       number(fit.angle_min_deg) + ", " + number(fit.angle_max_deg) + "]");
    const PolyPiece* piece = findPiece(fit, angle_deg);
    if (piece == nullptr) return invalid("fit: pieces do not cover angle_deg");
    return piece;
}

}  // namespace

Status checkPolyFitOptions(const PolyFitOptions& options) {
    if (options.max_degree < 0 || options.max_degree > kMaxDegreeLimit)
        return invalid("max_degree: " + std::to_string(options.max_degree) + " is not in [0, " +
                       std::to_string(kMaxDegreeLimit) + "]");
    if (options.fixed_degree < -1 || options.fixed_degree > kMaxDegreeLimit)
        return invalid("fixed_degree: " + std::to_string(options.fixed_degree) +
                       " is not -1 (choose) or in [0, " + std::to_string(kMaxDegreeLimit) + "]");
    if (options.cv_folds < 2)
        return invalid("cv_folds: " + std::to_string(options.cv_folds) + " is below 2");
    if (options.min_samples_per_piece < 3)  // so that every piece is cross-validated
        return invalid("min_samples_per_piece: " + std::to_string(options.min_samples_per_piece) +
                       " is below 3");
    if (options.max_pieces < 1)
        return invalid("max_pieces: " + std::to_string(options.max_pieces) + " is below 1");
    if (!std::isfinite(options.split_factor) || options.split_factor < 1.0)
        return invalid("split_factor: must be finite and >= 1");
    if (!std::isfinite(options.absolute_tolerance) || options.absolute_tolerance < 0.0)
        return invalid("absolute_tolerance: must be finite and >= 0");
    return Ok{};
}

Result<PolyFit> fitPolynomial(std::span<const double> angles_deg,
                              std::span<const double> values,
                              const PolyFitOptions& options,
                              std::span<const double> weights) {
    if (const Status ok = checkPolyFitOptions(options); !ok) return ok.error();
    const size_t n = angles_deg.size();
    if (n == 0) return invalid("angles_deg: no samples (at least 1 needed)");
    if (values.size() != n)
        return invalid("values: " + std::to_string(values.size()) + " values for " +
                       std::to_string(n) + " angles");
    if (!weights.empty() && weights.size() != n)
        return invalid("weights: " + std::to_string(weights.size()) + " weights for " +
                       std::to_string(n) + " angles");
    if (n > static_cast<size_t>(std::numeric_limits<int>::max()))
        return invalid("angles_deg: too many samples");
    for (size_t i = 0; i < n; ++i) {
        if (!std::isfinite(angles_deg[i])) return invalid(field("angles_deg", i) + ": not finite");
        if (!std::isfinite(values[i])) return invalid(field("values", i) + ": not finite");
        if (!weights.empty() && !(std::isfinite(weights[i]) && weights[i] > 0.0))
            return invalid(field("weights", i) + ": must be finite and > 0");
        if (i > 0 && !(angles_deg[i] > angles_deg[i - 1]))
            return invalid(field("angles_deg", i) + ": " + number(angles_deg[i]) +
                           " is not greater than " + field("angles_deg", i - 1) + ": " +
                           number(angles_deg[i - 1]) + " (angles must be strictly increasing)");
    }
    const double lo = angles_deg.front();
    const double hi = angles_deg.back();
    if (!std::isfinite(hi - lo)) return invalid("angles_deg: range overflows");
    if (options.fixed_degree > static_cast<int>(n) - 1)
        return invalid("fixed_degree: " + std::to_string(options.fixed_degree) + " needs " +
                       std::to_string(options.fixed_degree + 1) + " samples, got " +
                       std::to_string(n));

    Samples s{angles_deg, values, std::vector<double>(n, 1.0)};
    if (!weights.empty())
        for (size_t i = 0; i < n; ++i) s.sqrt_weights[i] = std::sqrt(weights[i]);

    PolyFit fit;
    fit.angle_min_deg = lo;
    fit.angle_max_deg = hi;
    fit.sample_count = static_cast<int>(n);
    fit.noise_estimate = estimateNoise(s);
    double scale = 0.0;
    for (const double v : values) scale = std::max(scale, std::abs(v));
    // The last term keeps round-off of exactly representable data from counting as misfit.
    const double tolerance =
        options.split_factor * fit.noise_estimate + options.absolute_tolerance + 1e-12 * scale;
    int splits_left = options.max_pieces - 1;
    fitRange(s, 0, static_cast<int>(n), lo, hi, tolerance, options, splits_left, fit.pieces);

    double sum_sq = 0.0;
    for (const PolyPiece& piece : fit.pieces) {
        sum_sq += piece.rms_residual * piece.rms_residual * piece.sample_count;
        fit.max_abs_residual = std::max(fit.max_abs_residual, piece.max_abs_residual);
        for (const double c : piece.coefficients)
            if (!std::isfinite(c))
                return makeError(ErrorCode::Internal, "coefficients: not finite after the fit");
    }
    fit.rms_residual = std::sqrt(sum_sq / static_cast<double>(n));
    return fit;
}

double medianSpacing(std::span<const double> ascending_deg) {
    if (ascending_deg.size() < 2) return 0.0;
    std::vector<double> gaps;
    for (size_t i = 1; i < ascending_deg.size(); ++i)
        gaps.push_back(ascending_deg[i] - ascending_deg[i - 1]);
    std::nth_element(gaps.begin(), gaps.begin() + static_cast<std::ptrdiff_t>(gaps.size() / 2),
                     gaps.end());
    return gaps[gaps.size() / 2];
}

double chebyshevValue(std::span<const double> coefficients, double x) {
    // Clenshaw: b_k = c_k + 2 x b_{k+1} - b_{k+2}; value = c_0 + x b_1 - b_2.
    double b1 = 0.0;
    double b2 = 0.0;
    const size_t n = coefficients.size();
    if (n == 0) return 0.0;
    for (size_t k = n - 1; k >= 1; --k) {
        const double b0 = coefficients[k] + 2.0 * x * b1 - b2;
        b2 = b1;
        b1 = b0;
    }
    return coefficients[0] + x * b1 - b2;
}

std::vector<double> chebyshevDerivative(std::span<const double> coefficients) {
    const int n = static_cast<int>(coefficients.size());
    if (n <= 1) return {};
    // d_{k-1} = d_{k+1} + 2 k c_k, from the top down; d_0 is halved (T_0's weight convention).
    std::vector<double> d(n + 1, 0.0);
    for (int k = n - 1; k >= 1; --k) d[k - 1] = d[k + 1] + 2.0 * k * coefficients[k];
    d[0] *= 0.5;
    d.resize(n - 1);
    return d;
}

Result<double> evaluatePolyFit(const PolyFit& fit, double angle_deg) {
    const Result<const PolyPiece*> piece = pieceAt(fit, angle_deg);
    if (!piece) return piece.error();
    const PolyPiece& p = **piece;
    return chebyshevValue(p.coefficients, normalize(angle_deg, p.angle_min_deg, p.angle_max_deg));
}

Result<double> evaluatePolyFitSlope(const PolyFit& fit, double angle_deg) {
    const Result<const PolyPiece*> piece = pieceAt(fit, angle_deg);
    if (!piece) return piece.error();
    const PolyPiece& p = **piece;
    if (p.angle_max_deg == p.angle_min_deg) return 0.0;
    const std::vector<double> d = chebyshevDerivative(p.coefficients);
    const double x = normalize(angle_deg, p.angle_min_deg, p.angle_max_deg);
    // dx / d angle = 2 / (max - min).
    return chebyshevValue(d, x) * (2.0 / (p.angle_max_deg - p.angle_min_deg));
}

}  // namespace flarelab::fit
