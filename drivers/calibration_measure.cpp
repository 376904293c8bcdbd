#include "drivers/calibration_measure.h"

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <ctime>
#include <functional>
#include <iomanip>
#include <limits>
#include <numeric>
#include <sstream>

namespace flarelab::drivers {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// Pixels the maximum-likelihood refinement of a response curve works on.
constexpr size_t kRefinedPixels = 8000;
// The converter rounds to integers: uniform rounding error of variance 1/12 DN^2.
constexpr double kQuantizationVariance = 1.0 / 12.0;

std::string num(double x, int digits = 4) {
    std::ostringstream out;
    out << std::setprecision(digits) << x;
    return out.str();
}

std::string percent(double fraction) { return num(100.0 * fraction, 3) + " %"; }

Error invalid(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "calibration: " + what);
}

// The value at fraction q (0..1) of the sorted values (nearest rank); NaN when empty. Reorders.
double quantile(std::vector<double>& values, double q) {
    if (values.empty()) return kNaN;
    const auto k =
        static_cast<size_t>(std::clamp(std::floor(q * static_cast<double>(values.size())), 0.0,
                                       static_cast<double>(values.size() - 1)));
    std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k), values.end());
    return values[k];
}

double median(std::vector<double> values) { return quantile(values, 0.5); }

// Median and the standard deviation a normal distribution with the same median absolute
// deviation has (1.4826 MAD), the latter at least `floor`.
std::pair<double, double> robustCentre(std::vector<double> values, double floor) {
    const double m = median(values);
    for (double& v : values) v = std::abs(v - m);
    return {m, std::max(floor, 1.4826 * median(std::move(values)))};
}

Status sameShape(const hdr::RawFrame& a, const hdr::RawFrame& b, const std::string& what) {
    if (a.width != b.width || a.height != b.height || a.format != b.format ||
        a.bit_depth != b.bit_depth)
        return invalid(what + " differs in size, format or bit depth from the first frame");
    if (b.samples.size() != static_cast<size_t>(b.width * b.height))
        return invalid(what + " holds " + std::to_string(b.samples.size()) +
                       " samples, not width * height");
    if (b.width < 1 || b.height < 1) return invalid(what + " is empty");
    return Ok{};
}

std::vector<bool> hotMask(const std::vector<int64_t>& hot_pixels, size_t n) {
    std::vector<bool> mask(n, false);
    for (const int64_t p : hot_pixels)
        if (p >= 0 && static_cast<size_t>(p) < n) mask[static_cast<size_t>(p)] = true;
    return mask;
}

// Variance of a - shift(b, dx, dy) over the overlap, every `step`-th row.
double shiftedDifferenceVariance(
    const hdr::RawFrame& a, const hdr::RawFrame& b, int dx, int dy, int64_t border) {
    double sum = 0.0, sum2 = 0.0;
    int64_t n = 0;
    for (int64_t y = border; y < a.height - border; ++y)
        for (int64_t x = border; x < a.width - border; ++x) {
            const double d = static_cast<double>(a.samples[static_cast<size_t>(y * a.width + x)]) -
                             b.samples[static_cast<size_t>((y + dy) * b.width + (x + dx))];
            sum += d;
            sum2 += d * d;
            ++n;
        }
    if (n < 2) return kNaN;
    const double mean = sum / static_cast<double>(n);
    return sum2 / static_cast<double>(n) - mean * mean;
}

// Whether two frames at one exposure line up best unshifted. Returns the best shift when it does
// not.
std::optional<std::pair<int, int>> misalignment(const hdr::RawFrame& a, const hdr::RawFrame& b) {
    constexpr int kReach = 2;
    if (a.width <= 4 * kReach || a.height <= 4 * kReach) return std::nullopt;
    const double still = shiftedDifferenceVariance(a, b, 0, 0, kReach);
    double best = still;
    std::optional<std::pair<int, int>> best_shift;
    for (int dy = -kReach; dy <= kReach; ++dy)
        for (int dx = -kReach; dx <= kReach; ++dx) {
            if (dx == 0 && dy == 0) continue;
            const double v = shiftedDifferenceVariance(a, b, dx, dy, kReach);
            // Markedly better, not by noise: a steady flat field gives equal variances.
            if (v < 0.8 * best) {
                best = v;
                best_shift = std::pair{dx, dy};
            }
        }
    return best_shift;
}

std::string utcNow() {
    const std::time_t now = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
    std::tm tm{};
    gmtime_r(&now, &tm);
    std::ostringstream out;
    out << std::put_time(&tm, "%Y-%m-%dT%H:%M:%SZ");
    return out.str();
}

// Piecewise-linear interpolation weights of z between sorted knots: (index of the left knot,
// weight of the right one).
std::pair<size_t, double> bracketOf(const std::vector<double>& knots, double z) {
    if (z <= knots.front()) return {0, 0.0};
    if (z >= knots.back()) return {knots.size() - 2, 1.0};
    const size_t hi =
        static_cast<size_t>(std::upper_bound(knots.begin(), knots.end(), z) - knots.begin());
    const size_t lo = hi - 1;
    return {lo, (z - knots[lo]) / (knots[hi] - knots[lo])};
}

// Pool adjacent violators: the closest non-decreasing sequence in weighted least squares.
std::vector<double> isotonic(const std::vector<double>& values,
                             const std::vector<double>& weights) {
    struct Block {
        double value, weight;
        size_t count;
    };
    std::vector<Block> blocks;
    for (size_t i = 0; i < values.size(); ++i) {
        blocks.push_back({values[i], std::max(weights[i], 1e-12), 1});
        while (blocks.size() > 1 && blocks[blocks.size() - 2].value > blocks.back().value) {
            const Block last = blocks.back();
            blocks.pop_back();
            Block& prev = blocks.back();
            const double w = prev.weight + last.weight;
            prev.value = (prev.value * prev.weight + last.value * last.weight) / w;
            prev.weight = w;
            prev.count += last.count;
        }
    }
    std::vector<double> out;
    for (const Block& b : blocks) out.insert(out.end(), b.count, b.value);
    return out;
}

}  // namespace

Result<DarkMeasurement> measureDark(const DarkFrames& frames) {
    if (frames.bias.size() < 2)
        return invalid("dark frames: need at least 2 bias frames (a pair), got " +
                       std::to_string(frames.bias.size()));
    if (frames.long_dark.empty()) return invalid("dark frames: need at least 1 long dark frame");
    const hdr::RawFrame& first = frames.bias.front();
    for (size_t i = 0; i < frames.bias.size(); ++i) {
        if (Status ok = sameShape(first, frames.bias[i], "bias frame " + std::to_string(i)); !ok)
            return ok.error();
        if (frames.bias[i].exposure_s != first.exposure_s)
            return invalid("bias frame " + std::to_string(i) + " has exposure " +
                           num(frames.bias[i].exposure_s) + " s, the first " +
                           num(first.exposure_s) + " s");
    }
    for (size_t i = 0; i < frames.long_dark.size(); ++i) {
        if (Status ok =
                sameShape(first, frames.long_dark[i], "long dark frame " + std::to_string(i));
            !ok)
            return ok.error();
        if (frames.long_dark[i].exposure_s != frames.long_dark.front().exposure_s)
            return invalid("long dark frame " + std::to_string(i) +
                           " has another exposure than the first");
    }
    const size_t n = first.samples.size();
    const double full = std::ldexp(1.0, first.bit_depth) - 1.0;

    // Hot pixels first (from the long frames), so that they stay out of everything else.
    std::vector<double> long_mean(n, 0.0);
    for (const hdr::RawFrame& f : frames.long_dark)
        for (size_t i = 0; i < n; ++i) long_mean[i] += f.samples[i];
    for (double& v : long_mean) v /= static_cast<double>(frames.long_dark.size());
    const auto [long_median, long_sigma] = robustCentre(long_mean, 0.3);

    // Black level: the bias frames' mean without outliers, around their most frequent value and
    // within 4 sigmas measured on the lower side, which neither warm pixels nor a curved response
    // (a gamma camera's dark frames pile up at black and trail upwards) can widen.
    const auto [bias_mode, bias_sigma] = [&] {
        std::vector<int64_t> histogram(size_t{1} << 16, 0);
        for (const uint16_t v : first.samples) ++histogram[v];
        const auto mode = static_cast<double>(std::max_element(histogram.begin(), histogram.end()) -
                                              histogram.begin());
        std::vector<double> values(first.samples.begin(), first.samples.end());
        const double low = quantile(values, 0.02275);  // two sigmas below a normal's centre
        return std::pair{mode, std::max(0.25, (mode - low) / 2.0)};
    }();
    DarkMeasurement m;
    m.bias_exposure_s = first.exposure_s;
    m.long_exposure_s = frames.long_dark.front().exposure_s;
    m.hot_threshold_dn = 0.0;
    const double black_guess = bias_mode;
    const double margin = std::max(8.0 * long_sigma, 0.005 * (full - black_guess));
    const double hot_level = long_median + margin;
    for (size_t i = 0; i < n; ++i)
        if (long_mean[i] > hot_level) m.hot_pixels.push_back(static_cast<int64_t>(i));
    const std::string retake =
        "; cap the lens (and shade the camera from stray light) and take them again";
    if (static_cast<double>(m.hot_pixels.size()) > 0.01 * static_cast<double>(n))
        return invalid("the long dark frames are not dark: " +
                       percent(static_cast<double>(m.hot_pixels.size()) / n) +
                       " of the pixels lie more than " + num(margin) + " DN above the median" +
                       retake);
    const std::vector<bool> hot = hotMask(m.hot_pixels, n);
    // Dark signal is noise, independent from pixel to pixel (column or row patterns aside);
    // light through a lens is an image, alike in neighbouring pixels both ways.
    const auto correlation = [&](int64_t dx, int64_t dy) {
        double sa = 0.0, sb = 0.0, saa = 0.0, sbb = 0.0, sab = 0.0, count = 0.0;
        for (int64_t y = 0; y + dy < first.height; ++y)
            for (int64_t x = 0; x + dx < first.width; ++x) {
                const size_t i = static_cast<size_t>(y * first.width + x);
                const size_t j = static_cast<size_t>((y + dy) * first.width + x + dx);
                if (hot[i] || hot[j]) continue;
                const double a = long_mean[i], b = long_mean[j];
                sa += a;
                sb += b;
                saa += a * a;
                sbb += b * b;
                sab += a * b;
                count += 1.0;
            }
        if (count < 2.0) return 0.0;
        const double va = saa / count - (sa / count) * (sa / count);
        const double vb = sbb / count - (sb / count) * (sb / count);
        const double cov = sab / count - (sa / count) * (sb / count);
        return va > 0.0 && vb > 0.0 ? cov / std::sqrt(va * vb) : 0.0;
    };
    const double across = correlation(1, 0), down = correlation(0, 1);
    if (std::min(across, down) > 0.5)
        return invalid(
            "the long dark frames are not dark: neighbouring pixels agree (correlation " +
            num(across, 2) + " across, " + num(down, 2) +
            " down), as in an image, not in dark noise" + retake);
    // Hot pixels are single pixels scattered at random; light through an uncapped lens lands in
    // patches. Most "hot" pixels with a hot neighbour is a lit patch.
    int64_t clustered = 0;
    for (const int64_t p : m.hot_pixels) {
        const int64_t x = p % first.width, y = p / first.width;
        bool neighbour = false;
        for (int64_t dy = -1; dy <= 1 && !neighbour; ++dy)
            for (int64_t dx = -1; dx <= 1 && !neighbour; ++dx) {
                const int64_t nx = x + dx, ny = y + dy;
                if ((dx || dy) && nx >= 0 && ny >= 0 && nx < first.width && ny < first.height)
                    neighbour = hot[static_cast<size_t>(ny * first.width + nx)];
            }
        clustered += neighbour ? 1 : 0;
    }
    if (m.hot_pixels.size() >= 10 &&
        static_cast<double>(clustered) > 0.5 * static_cast<double>(m.hot_pixels.size()))
        return invalid("the long dark frames are not dark: " + std::to_string(clustered) + " of " +
                       std::to_string(m.hot_pixels.size()) +
                       " pixels above the hot-pixel threshold lie next to one another, as light "
                       "does, not hot pixels" +
                       retake);

    double sum = 0.0;
    int64_t count = 0;
    std::vector<double> noise_samples;
    for (const hdr::RawFrame& f : frames.bias)
        for (size_t i = 0; i < n; ++i) {
            if (hot[i]) continue;
            const double v = f.samples[i];
            if (std::abs(v - bias_mode) > 4.0 * bias_sigma) continue;
            sum += v;
            ++count;
        }
    if (count == 0) return invalid("dark frames: no pixel left to measure the black level");
    m.black_level_dn = sum / static_cast<double>(count);
    m.hot_threshold_dn = hot_level - m.black_level_dn;
    m.dark_signal_dn = long_median - m.black_level_dn;

    // The level noise alone reaches in a bias frame: below it noise outweighs the signal, and
    // through a curved response it biases the mean (Jensen's inequality).
    std::vector<double> above;
    above.reserve(n);
    for (size_t i = 0; i < n; ++i)
        if (!hot[i]) above.push_back(first.samples[i] - m.black_level_dn);
    m.noise_floor_dn = std::max(1.0, quantile(above, 0.999));

    // Read noise from pairs of bias frames.
    double variance_sum = 0.0;
    int pairs = 0;
    for (size_t k = 0; k + 1 < frames.bias.size(); k += 2) {
        const hdr::RawFrame& a = frames.bias[k];
        const hdr::RawFrame& b = frames.bias[k + 1];
        std::vector<double> d;
        d.reserve(n);
        for (size_t i = 0; i < n; ++i)
            if (!hot[i]) d.push_back(static_cast<double>(a.samples[i]) - b.samples[i]);
        const auto [d_median, d_sigma] = robustCentre(d, 0.5);
        double s = 0.0, s2 = 0.0;
        int64_t used = 0;
        for (const double v : d) {
            if (std::abs(v - d_median) > 8.0 * d_sigma) continue;  // random telegraph, cosmics
            s += v;
            s2 += v * v;
            ++used;
        }
        if (used < 2) continue;
        const double mean = s / static_cast<double>(used);
        variance_sum += (s2 / static_cast<double>(used) - mean * mean) / 2.0;
        ++pairs;
    }
    const double variance = pairs > 0 ? variance_sum / pairs : 0.0;
    m.read_noise_dn = std::sqrt(std::max(0.0, variance - kQuantizationVariance));

    m.notes.push_back("black level " + num(m.black_level_dn, 6) + " DN: mean of " +
                      std::to_string(frames.bias.size()) + " dark frames of " +
                      num(m.bias_exposure_s) + " s (lens capped)");
    m.notes.push_back(
        "read noise " + num(m.read_noise_dn) + " DN: from " + std::to_string(pairs) +
        " pairs of those frames (half the variance of their difference, less the "
        "1/12 DN^2 of rounding)" +
        (variance <= kQuantizationVariance ? "; below the converter's rounding" : ""));
    m.notes.push_back(std::to_string(m.hot_pixels.size()) + " hot pixels: dark signal more than " +
                      num(m.hot_threshold_dn) + " DN above black in the mean of " +
                      std::to_string(frames.long_dark.size()) + " dark frames of " +
                      num(m.long_exposure_s) + " s (median dark signal " + num(m.dark_signal_dn) +
                      " DN)");
    return m;
}

Result<ResponseCurve> recoverResponse(const std::vector<std::vector<double>>& obs,
                                      std::span<const double> exposures_s,
                                      double black_level_dn,
                                      double noise_floor_dn,
                                      double cut_dn,
                                      const std::function<double(double)>& variance_of,
                                      const CalibrationOptions& options) {
    const size_t levels = exposures_s.size();
    if (levels < 2)
        return makeError(
            ErrorCode::Unsupported,
            "response curve: needs at least two exposures, got " + std::to_string(levels));
    for (const double t : exposures_s)
        if (!(std::isfinite(t) && t > 0.0))
            return invalid("response curve: exposure " + num(t) + " s is not positive");
    if (options.knots < 2 || !(options.smoothness >= 0.0))
        return invalid("response curve: knots must be >= 2 and smoothness >= 0");
    const double low = black_level_dn + noise_floor_dn;
    const auto usable = [&](double z) { return std::isfinite(z) && z > low && z < cut_dn; };

    // Pixels with at least two usable observations, and the knots at quantiles of their samples.
    std::vector<double> samples;
    std::vector<size_t> pixels;
    for (size_t i = 0; i < obs.size(); ++i) {
        if (obs[i].size() != levels)
            return invalid("response curve: pixel " + std::to_string(i) + " has " +
                           std::to_string(obs[i].size()) + " observations for " +
                           std::to_string(levels) + " exposures");
        int good = 0;
        for (const double z : obs[i]) good += usable(z) ? 1 : 0;
        if (good < 2) continue;
        pixels.push_back(i);
        for (const double z : obs[i])
            if (usable(z)) samples.push_back(z);
    }
    if (pixels.size() < 8)
        return makeError(ErrorCode::Unsupported,
                         "response curve: only " + std::to_string(pixels.size()) +
                             " pixels have two exposures between the noise floor (" + num(low) +
                             " DN) and the clip level (" + num(cut_dn) +
                             " DN); the scene needs more contrast or the series more exposures");
    std::sort(samples.begin(), samples.end());
    // Knots: half at quantiles of the samples (where the data is dense), half evenly spread (so
    // that the sparse bright end, where the curve ends, is not left to one long segment).
    const double z_min = samples.front(), z_max = samples.back();
    const auto k_max = static_cast<size_t>(options.knots);
    std::vector<double> candidates;
    for (size_t k = 0; k < k_max; ++k) {
        const double q = static_cast<double>(k) / static_cast<double>(k_max - 1);
        if (k % 2 == 0)
            candidates.push_back(samples[static_cast<size_t>(
                std::round(q * static_cast<double>(samples.size() - 1)))]);
        else
            candidates.push_back(z_min + q * (z_max - z_min));
    }
    candidates.push_back(z_min);
    candidates.push_back(z_max);
    std::sort(candidates.begin(), candidates.end());
    const double spacing = std::max(0.5, (z_max - z_min) / (4.0 * static_cast<double>(k_max)));
    std::vector<double> knots;
    for (const double z : candidates)
        if (knots.empty() || z >= knots.back() + spacing) knots.push_back(z);
    if (knots.size() > 1 && knots.back() < z_max) knots.back() = z_max;
    if (knots.size() < 2)
        return makeError(ErrorCode::Unsupported,
                         "response curve: the usable samples span less than one DN");
    const size_t K = knots.size();

    std::vector<double> log_t(levels);
    for (size_t j = 0; j < levels; ++j) log_t[j] = std::log(exposures_s[j]);
    std::vector<double> knot_weight(K, 0.0);

    // One weighted solve: the normal equations of the knot values with the per-pixel log
    // exposures eliminated in closed form; nullopt when singular.
    const auto solveKnots =
        [&](const std::function<double(double)>& weight) -> std::optional<std::vector<double>> {
        Eigen::MatrixXd H =
            Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(K), static_cast<Eigen::Index>(K));
        Eigen::VectorXd b = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(K));
        std::fill(knot_weight.begin(), knot_weight.end(), 0.0);
        std::vector<double> a_bar(K, 0.0);  // W times the pixel's mean interpolation weights
        std::vector<size_t> touched;
        for (const size_t i : pixels) {
            double w_sum = 0.0, l_bar = 0.0;
            touched.clear();
            for (size_t j = 0; j < levels; ++j) {
                const double z = obs[i][j];
                if (!usable(z)) continue;
                const auto [k, f] = bracketOf(knots, z);
                const double w = weight(z);
                for (const auto& [kk, a] : {std::pair{k, 1.0 - f}, std::pair{k + 1, f}}) {
                    if (a == 0.0) continue;
                    if (std::find(touched.begin(), touched.end(), kk) == touched.end())
                        touched.push_back(kk);
                    a_bar[kk] += w * a;
                    knot_weight[kk] += w * a;
                    b(static_cast<Eigen::Index>(kk)) += w * a * log_t[j];
                }
                // sum w a a^T: the 2x2 block of this observation's two knots.
                const auto ki = static_cast<Eigen::Index>(k);
                H(ki, ki) += w * (1.0 - f) * (1.0 - f);
                H(ki + 1, ki + 1) += w * f * f;
                H(ki, ki + 1) += w * (1.0 - f) * f;
                H(ki + 1, ki) += w * (1.0 - f) * f;
                w_sum += w;
                l_bar += w * log_t[j];
            }
            l_bar /= w_sum;
            // - W abar abar^T and - W abar lbar.
            for (const size_t p : touched) {
                b(static_cast<Eigen::Index>(p)) -= a_bar[p] * l_bar;
                for (const size_t q : touched)
                    H(static_cast<Eigen::Index>(p), static_cast<Eigen::Index>(q)) -=
                        a_bar[p] * a_bar[q] / w_sum;
            }
            for (const size_t p : touched) a_bar[p] = 0.0;
        }

        // Smoothness: second divided differences, scaled to plain second differences for
        // evenly spaced knots, weighted relative to the data's mean curvature of the system.
        if (K >= 3 && options.smoothness > 0.0) {
            const double mean_h = (knots.back() - knots.front()) / static_cast<double>(K - 1);
            const double scale = options.smoothness * H.trace() / static_cast<double>(K);
            for (size_t k = 1; k + 1 < K; ++k) {
                const double h0 = knots[k] - knots[k - 1], h1 = knots[k + 1] - knots[k];
                const double c = 2.0 * mean_h * mean_h / (h0 + h1);
                const double row[3] = {c / h0, -c / h0 - c / h1, c / h1};
                for (int p = 0; p < 3; ++p)
                    for (int q = 0; q < 3; ++q)
                        H(static_cast<Eigen::Index>(k - 1 + p),
                          static_cast<Eigen::Index>(k - 1 + q)) += scale * row[p] * row[q];
            }
        }

        // Gauge: g = 0 at the last knot (X = 1 where the curve ends).
        const auto R = static_cast<Eigen::Index>(K - 1);
        const Eigen::VectorXd solved = H.topLeftCorner(R, R).ldlt().solve(b.head(R));
        if (!solved.allFinite()) return std::nullopt;
        std::vector<double> g(K, 0.0);
        for (Eigen::Index k = 0; k < R; ++k) g[static_cast<size_t>(k)] = solved(k);
        return g;
    };

    // First unweighted; then, where the noise of the samples is known, each sample weighted by
    // the inverse variance of g(z) it implies, var(z) g'(z)^2 (a sample on a steep stretch of the
    // inverse curve, as at a gamma curve's foot, says little about log exposure), with g' from
    // the previous solve.
    auto solved = solveKnots([](double) { return 1.0; });
    if (!solved)
        return makeError(ErrorCode::Unsupported,
                         "response curve: the exposures do not overlap enough to tie the curve "
                         "together (singular system)");
    std::vector<double> g = std::move(*solved);
    if (variance_of && options.refine_iterations <= 0) {
        const double h = 0.02 * (knots.back() - knots.front());
        for (int pass = 0; pass < 2; ++pass) {
            const auto at = [&](double z) {
                z = std::clamp(z, knots.front(), knots.back());
                const auto [k, f] = bracketOf(knots, z);
                return (1.0 - f) * g[k] + f * g[k + 1];
            };
            auto weighted = solveKnots([&](double z) {
                const double lo = std::max(knots.front(), z - h);
                const double hi = std::min(knots.back(), z + h);
                const double slope = hi > lo ? (at(hi) - at(lo)) / (hi - lo) : 0.0;
                // A floor of 0.001 in log exposure: no sample is trusted beyond 0.1 %.
                return 1.0 / (slope * slope * std::max(0.0, variance_of(z)) + 1e-6);
            });
            if (!weighted) break;
            g = std::move(*weighted);
        }
    }

    // Rising: where noise bent the curve back, the closest rising one; then strictly rising.
    int bent = 0;
    for (size_t k = 1; k < K; ++k) bent += g[k] <= g[k - 1] ? 1 : 0;
    if (bent > 0) g = isotonic(g, knot_weight);
    for (size_t k = 1; k < K; ++k) g[k] = std::max(g[k], g[k - 1] + 1e-9);
    const double top = g.back();
    for (double& v : g) v -= top;

    // Refinement in DN. The solve above takes each sample's DN as exact and its log exposure as
    // the noisy side; but the noise is in the DN, and a level where many pixels sit (every
    // exposure puts the background at one level) then tilts g along their scatter. So the curve
    // is refined by maximum likelihood with the residuals in DN: the forward response z = F(x) of
    // log exposure x, piecewise linear between knots evenly spaced in x, and every pixel's log
    // exposure e_i, all at once by Levenberg-Marquardt (Gauss-Newton with the pixels eliminated
    // through the Schur complement, as in bundle adjustment), from the inverse found above.
    if (options.refine_iterations > 0) {
        // A curve of a few dozen knots needs some thousands of pixels, spread over the scene's
        // brightness: up to kRefinedPixels / 64 from each of 64 bins of log exposure (by stage
        // a), so that the few bright pixels all stay and the many background ones are thinned.
        std::vector<size_t> refined;
        {
            std::vector<std::pair<double, size_t>> brightness;
            for (const size_t i : pixels) {
                double e = 0.0;
                int used = 0;
                for (size_t j = 0; j < levels; ++j)
                    if (usable(obs[i][j])) {
                        const auto [k, f] = bracketOf(knots, obs[i][j]);
                        e += (1.0 - f) * g[k] + f * g[k + 1] - log_t[j];
                        ++used;
                    }
                brightness.push_back({e / used, i});
            }
            std::sort(brightness.begin(), brightness.end());
            constexpr size_t kBins = 64;
            const double lo = brightness.front().first, hi = brightness.back().first;
            std::vector<std::vector<size_t>> bins(kBins);
            for (const auto& [e, i] : brightness) {
                const auto bin = static_cast<size_t>(
                    std::clamp((e - lo) / std::max(hi - lo, 1e-12) * kBins, 0.0, kBins - 1.0));
                bins[bin].push_back(i);
            }
            const size_t cap = kRefinedPixels / kBins;
            for (const auto& bin : bins) {
                const size_t stride = std::max<size_t>(1, (bin.size() + cap - 1) / cap);
                for (size_t k = 0; k < bin.size(); k += stride) refined.push_back(bin[k]);
            }
        }
        const auto inverseAt = [&](double z) {
            const auto [k, f] = bracketOf(knots, z);
            return (1.0 - f) * g[k] + f * g[k + 1];
        };
        const size_t P = refined.size();
        // Each sample's inverse variance (1 when unknown), 0 for samples that are not finite or
        // beyond the cut; and the weights of the samples in use (set by `select` below).
        std::vector<double> inverse_variance(P * levels, 0.0), weights(P * levels, 0.0);
        for (size_t p = 0; p < P; ++p)
            for (size_t j = 0; j < levels; ++j) {
                const double z = obs[refined[p]][j];
                if (std::isfinite(z) && z < cut_dn)
                    inverse_variance[p * levels + j] =
                        variance_of ? 1.0 / std::max(1e-3, variance_of(z)) : 1.0;
                if (usable(z)) weights[p * levels + j] = inverse_variance[p * levels + j];
            }
        std::vector<double> e(P, 0.0);
        for (size_t p = 0; p < P; ++p) {
            int used = 0;
            for (size_t j = 0; j < levels; ++j)
                if (usable(obs[refined[p]][j])) {
                    e[p] += inverseAt(obs[refined[p]][j]) - log_t[j];
                    ++used;
                }
            e[p] /= used;
        }
        // Knots of F: evenly over the samples' log exposures, with a margin.
        double x_min = std::numeric_limits<double>::infinity(), x_max = -x_min;
        for (size_t p = 0; p < P; ++p)
            for (size_t j = 0; j < levels; ++j)
                if (usable(obs[refined[p]][j])) {
                    x_min = std::min(x_min, e[p] + log_t[j]);
                    x_max = std::max(x_max, e[p] + log_t[j]);
                }
        const size_t F = K;
        const double margin = 0.02 * (x_max - x_min);
        std::vector<double> fx(F), fz(F);
        for (size_t k = 0; k < F; ++k) {
            fx[k] = x_min - margin +
                    (x_max - x_min + 2.0 * margin) * static_cast<double>(k) /
                        static_cast<double>(F - 1);
            // The inverse of g at fx[k]: g rises, so bisect over the knots.
            double lo = knots.front(), hi = knots.back();
            if (fx[k] <= g.front()) {
                fz[k] = lo;
            } else if (fx[k] >= g.back()) {
                fz[k] = hi;
            } else {
                for (int it = 0; it < 60; ++it) {
                    const double mid = 0.5 * (lo + hi);
                    (inverseAt(mid) < fx[k] ? lo : hi) = mid;
                }
                fz[k] = 0.5 * (lo + hi);
            }
        }
        const auto forward = [&](const std::vector<double>& values, double x, size_t* segment,
                                 double* weight_right, double* slope) {
            const auto [k, f] = bracketOf(fx, x);
            const double d = (values[k + 1] - values[k]) / (fx[k + 1] - fx[k]);
            *segment = k;
            *weight_right = std::clamp(f, 0.0, 1.0);
            *slope = d;
            // Linear beyond the end knots.
            return values[k] + d * (x - fx[k]);
        };
        const double smooth_scale = 1e-6;
        const auto cost = [&](const std::vector<double>& values, const std::vector<double>& ex) {
            double c = 0.0;
            for (size_t p = 0; p < P; ++p)
                for (size_t j = 0; j < levels; ++j) {
                    const double w = weights[p * levels + j];
                    if (w == 0.0) continue;
                    size_t k = 0;
                    double f = 0.0, d = 0.0;
                    const double r =
                        obs[refined[p]][j] - forward(values, ex[p] + log_t[j], &k, &f, &d);
                    c += w * r * r;
                }
            return c;
        };
        // Which samples count, by the model's prediction at the foot: chosen by their own
        // value, those near the noise floor would be the ones that happened to read high (the
        // low ones fall below it and out), which bends the foot of the curve down.
        const auto select = [&] {
            for (size_t p = 0; p < P; ++p)
                for (size_t j = 0; j < levels; ++j) {
                    const size_t i = p * levels + j;
                    if (inverse_variance[i] == 0.0) continue;
                    size_t k = 0;
                    double f = 0.0, d = 0.0;
                    const double predicted = forward(fz, e[p] + log_t[j], &k, &f, &d);
                    weights[i] = predicted > low ? inverse_variance[i] : 0.0;
                }
        };
        double damping = 1e-3;
        const auto n = static_cast<Eigen::Index>(F);
        std::vector<double> touched_value(F, 0.0);
        std::vector<size_t> touched;
        // Chosen once, by the first estimate: re-chosen as the fit moves, the choice itself would
        // become a way to lower the cost (pushing the foot down until its samples drop out).
        select();
        for (int iteration = 0; iteration < options.refine_iterations; ++iteration) {
            const double current = cost(fz, e);
            // The reduced system, row-major while it is summed (the rank-one updates below walk
            // rows).
            std::vector<double> S_sum(F * F, 0.0);
            Eigen::VectorXd rhs = Eigen::VectorXd::Zero(n);
            std::vector<double> D(P, 0.0), bp(P, 0.0);
            // B_p (sparse over knots) is kept per pixel for the back-substitution: entries
            // B_start[p] .. B_start[p + 1] of B_knot and B_value.
            std::vector<size_t> B_start(P + 1, 0), B_knot;
            std::vector<double> B_value;
            for (size_t p = 0; p < P; ++p) {
                B_start[p] = B_knot.size();
                touched.clear();
                for (size_t j = 0; j < levels; ++j) {
                    const double w = weights[p * levels + j];
                    if (w == 0.0) continue;
                    size_t k = 0;
                    double f = 0.0, slope = 0.0;
                    const double r =
                        obs[refined[p]][j] - forward(fz, e[p] + log_t[j], &k, &f, &slope);
                    D[p] += w * slope * slope;
                    bp[p] += w * slope * r;
                    for (const auto& [kk, a] : {std::pair{k, 1.0 - f}, std::pair{k + 1, f}}) {
                        if (std::find(touched.begin(), touched.end(), kk) == touched.end())
                            touched.push_back(kk);
                        touched_value[kk] += w * slope * a;
                        rhs(static_cast<Eigen::Index>(kk)) += w * a * r;
                    }
                    S_sum[k * F + k] += w * (1.0 - f) * (1.0 - f);
                    S_sum[(k + 1) * F + k + 1] += w * f * f;
                    S_sum[k * F + k + 1] += w * (1.0 - f) * f;
                    S_sum[(k + 1) * F + k] += w * (1.0 - f) * f;
                }
                D[p] *= 1.0 + damping;
                if (!(D[p] > 0.0)) {
                    for (const size_t kk : touched) touched_value[kk] = 0.0;
                    continue;
                }
                for (const size_t a : touched) {
                    const double scaled = touched_value[a] / D[p];
                    rhs(static_cast<Eigen::Index>(a)) -= scaled * bp[p];
                    double* row = &S_sum[a * F];
                    for (const size_t b2 : touched) row[b2] -= scaled * touched_value[b2];
                    B_knot.push_back(a);
                    B_value.push_back(touched_value[a]);
                }
                for (const size_t kk : touched) touched_value[kk] = 0.0;
            }
            B_start[P] = B_knot.size();
            Eigen::MatrixXd S(n, n);
            for (size_t a = 0; a < F; ++a)
                for (size_t b2 = 0; b2 < F; ++b2)
                    S(static_cast<Eigen::Index>(a), static_cast<Eigen::Index>(b2)) =
                        S_sum[a * F + b2];
            // A light smoothness on F's second differences (it only steadies knots with
            // little data), and the damping.
            const double lambda = smooth_scale * S.trace() / static_cast<double>(F);
            for (size_t k = 1; k + 1 < F; ++k) {
                const double row[3] = {1.0, -2.0, 1.0};
                const double second = fz[k - 1] - 2.0 * fz[k] + fz[k + 1];
                for (int a = 0; a < 3; ++a) {
                    rhs(static_cast<Eigen::Index>(k - 1 + a)) -= lambda * row[a] * second;
                    for (int b2 = 0; b2 < 3; ++b2)
                        S(static_cast<Eigen::Index>(k - 1 + a),
                          static_cast<Eigen::Index>(k - 1 + b2)) += lambda * row[a] * row[b2];
                }
            }
            for (Eigen::Index k = 0; k < n; ++k) S(k, k) *= 1.0 + damping;
            const Eigen::VectorXd step = S.ldlt().solve(rhs);
            if (!step.allFinite()) break;
            std::vector<double> next_fz(F), next_e(P);
            for (size_t k = 0; k < F; ++k) next_fz[k] = fz[k] + step(static_cast<Eigen::Index>(k));
            for (size_t p = 0; p < P; ++p) {
                double bf = 0.0;
                for (size_t b2 = B_start[p]; b2 < B_start[p + 1]; ++b2)
                    bf += B_value[b2] * step(static_cast<Eigen::Index>(B_knot[b2]));
                next_e[p] = D[p] > 0.0 ? e[p] + (bp[p] - bf) / D[p] : e[p];
            }
            const double next = cost(next_fz, next_e);
            if (next < current) {
                const bool converged = current - next < 1e-7 * current;
                fz = std::move(next_fz);
                e = std::move(next_e);
                damping = std::max(1e-9, damping / 10.0);
                if (converged) break;
            } else {
                damping *= 10.0;
                if (damping > 1e6) break;
            }
        }
        for (size_t k = 1; k < F; ++k)
            if (fz[k] <= fz[k - 1]) {
                std::vector<double> ones(F, 1.0);
                fz = isotonic(fz, ones);
                break;
            }
        for (size_t k = 1; k < F; ++k) fz[k] = std::max(fz[k], fz[k - 1] + 1e-6);
        // Back to the inverse on knots in DN, over the samples' range [low, cut]: F's knots
        // inside it, and its ends found on F.
        const auto inverse = [&](double z) {
            for (size_t k = 0; k + 1 < F; ++k)
                if (z <= fz[k + 1] || k + 2 == F) {
                    const double f = (z - fz[k]) / (fz[k + 1] - fz[k]);
                    return fx[k] + f * (fx[k + 1] - fx[k]);
                }
            return fx.back();
        };
        // The foot starts at the first segment of F that holds a fair share of the samples: a
        // knot with few samples beneath it is placed by the smoothness, not by data.
        std::vector<double> segment_samples(F - 1, 0.0);
        double all_samples = 0.0;
        for (size_t p = 0; p < P; ++p)
            for (size_t j = 0; j < levels; ++j)
                if (weights[p * levels + j] > 0.0) {
                    const auto [k, f] = bracketOf(fx, e[p] + log_t[j]);
                    segment_samples[k] += 1.0;
                    all_samples += 1.0;
                }
        size_t first_segment = 0;
        while (first_segment + 2 < F &&
               segment_samples[first_segment] < 0.2 * all_samples / static_cast<double>(F - 1))
            ++first_segment;
        const double z_lo = std::max(low, fz[first_segment]), z_hi = std::min(cut_dn, fz.back());
        if (z_hi > z_lo + 1.0) {
            std::vector<double> new_knots{z_lo}, new_g{inverse(z_lo)};
            for (size_t k = 0; k < F; ++k)
                if (fz[k] > new_knots.back() + 0.25 && fz[k] < z_hi - 0.25) {
                    new_knots.push_back(fz[k]);
                    new_g.push_back(fx[k]);
                }
            new_knots.push_back(z_hi);
            new_g.push_back(inverse(z_hi));
            knots = std::move(new_knots);
            g = std::move(new_g);
            for (size_t k = 1; k < g.size(); ++k) g[k] = std::max(g[k], g[k - 1] + 1e-9);
            const double last = g.back();
            for (double& v : g) v -= last;
        }
    }

    // How well it explains the data: each pixel's best log exposure, then the residuals in log
    // exposure over the curve's range, each weighted by its precision there (the inverse of
    // var(z) g'(z)^2) when the noise is known, so that the noisy foot does not hide a misfit
    // and does not pass for one.
    const auto curveAt = [&](double z) {
        const auto [k, f] = bracketOf(knots, z);
        return (1.0 - f) * g[k] + f * g[k + 1];
    };
    const double span_h = 0.02 * (knots.back() - knots.front());
    const auto precision = [&](double z) {
        if (!variance_of) return 1.0;
        const double lo = std::max(knots.front(), z - span_h);
        const double hi = std::min(knots.back(), z + span_h);
        const double slope = hi > lo ? (curveAt(hi) - curveAt(lo)) / (hi - lo) : 0.0;
        return 1.0 / (slope * slope * std::max(1e-3, variance_of(z)) + 1e-8);
    };
    const auto inRange = [&](double z) {
        return usable(z) && z >= knots.front() && z <= knots.back();
    };
    double r2 = 0.0, w_sum = 0.0;
    for (const size_t i : pixels) {
        double e = 0.0, w_pixel = 0.0;
        for (size_t j = 0; j < levels; ++j)
            if (inRange(obs[i][j])) {
                const double w = precision(obs[i][j]);
                e += w * (curveAt(obs[i][j]) - log_t[j]);
                w_pixel += w;
            }
        if (!(w_pixel > 0.0)) continue;
        e /= w_pixel;
        for (size_t j = 0; j < levels; ++j)
            if (inRange(obs[i][j])) {
                const double r = curveAt(obs[i][j]) - e - log_t[j];
                const double w = precision(obs[i][j]);
                r2 += w * r * r;
                w_sum += w;
            }
    }

    ResponseCurve curve;
    curve.rms_error_stops = w_sum > 0.0 ? std::sqrt(r2 / w_sum) / std::log(2.0) : 0.0;
    // Below the first knot the data is noise: the curve goes on as the power law
    // X ~ (z - black)^p whose exponent it has near its foot (1 for a linear foot, 2.2 all along
    // a gamma curve, falling towards 1 down a logarithmic one), down to 1 DN above black; the
    // file's linear step to 0 at black is below that.
    {
        // The exponent over the second octave above black from the first knot (the first is
        // the most bent by what is left of the floor's bias).
        const auto curveAtKnots = [&](double z) {
            const auto [k, f] = bracketOf(knots, z);
            return (1.0 - f) * g[k] + f * g[k + 1];
        };
        const double d0 = knots.front() - black_level_dn;
        const double top_d = knots.back() - black_level_dn;
        const double d1 = std::min(2.0 * d0, 0.5 * top_d), d2 = std::min(4.0 * d0, top_d);
        double power = 1.0;
        if (d0 > 0.0 && d2 > d1 && d1 >= d0)
            power = (curveAtKnots(black_level_dn + d2) - curveAtKnots(black_level_dn + d1)) /
                    std::log(d2 / d1);
        power = std::clamp(std::isfinite(power) ? power : 1.0, 0.5, 4.0);
        std::vector<double> below;
        for (double d = d0 / 2.0; d >= 1.0 && below.size() < 24; d /= 2.0) below.push_back(d);
        for (auto it = below.rbegin(); it != below.rend(); ++it) {
            curve.dn.push_back(black_level_dn + *it);
            curve.relative_exposure.push_back(std::exp(g.front() + power * std::log(*it / d0)));
        }
    }
    // Resampled densely, so that linear interpolation of X between knots (the file's rule)
    // follows the solve's log-linear one.
    const double span = knots.back() - knots.front();
    const size_t points = std::clamp<size_t>(static_cast<size_t>(span / 0.5) + 1, 2, 513);
    for (size_t p = 0; p < points; ++p) {
        const double z = p + 1 == points ? knots.back()
                                         : knots.front() + span * static_cast<double>(p) /
                                                               static_cast<double>(points - 1);
        curve.dn.push_back(z);
        curve.relative_exposure.push_back(std::exp(curveAt(z)));
    }
    curve.relative_exposure.back() = 1.0;
    std::ostringstream method;
    method << "flarelab: log-exposure least squares (" << K << " knots, smoothness "
           << options.smoothness << ", " << pixels.size() << " pixels)"
           << (options.refine_iterations > 0
                   ? " refined by maximum likelihood in DN (Levenberg-Marquardt, " +
                         std::to_string(options.refine_iterations) + " iterations at most)"
                   : std::string())
           << ", " << levels << " exposures, samples in (" << num(low) << ", " << num(cut_dn)
           << ") DN" << (bent > 0 ? ", made rising at " + std::to_string(bent) + " knots" : "");
    curve.method = method.str();
    return curve;
}

Result<ResponseMeasurement> measureResponse(std::span<const ExposureLevel> series_in,
                                            double black_level_dn,
                                            double noise_floor_dn,
                                            const std::vector<int64_t>& hot_pixels,
                                            const CalibrationOptions& options) {
    if (series_in.size() < 3)
        return invalid("exposure series: needs at least 3 exposures, got " +
                       std::to_string(series_in.size()));
    if (options.max_pixels < 16 || options.quantiles < 16 || !(options.linear_tolerance > 0.0) ||
        !(options.saturation_tolerance > 0.0))
        return invalid("options: max_pixels and quantiles must be >= 16, tolerances > 0");
    // By exposure, without copying the frames.
    std::vector<const ExposureLevel*> series;
    for (const ExposureLevel& level : series_in) series.push_back(&level);
    std::sort(series.begin(), series.end(), [](const ExposureLevel* a, const ExposureLevel* b) {
        return a->exposure_s < b->exposure_s;
    });
    if (series.front()->frames.empty()) return invalid("exposure series: a level has no frames");
    const hdr::RawFrame& first = series.front()->frames.front();
    for (size_t j = 0; j < series.size(); ++j) {
        const ExposureLevel& level = *series[j];
        if (!(std::isfinite(level.exposure_s) && level.exposure_s > 0.0))
            return invalid("exposure series: exposure " + num(level.exposure_s) +
                           " s is not positive");
        if (j > 0 && level.exposure_s == series[j - 1]->exposure_s)
            return invalid("exposure series: exposure " + num(level.exposure_s) +
                           " s appears twice");
        if (level.frames.empty())
            return invalid("exposure series: no frames at " + num(level.exposure_s) + " s");
        for (size_t k = 0; k < level.frames.size(); ++k)
            if (Status ok =
                    sameShape(first, level.frames[k],
                              "frame " + std::to_string(k) + " at " + num(level.exposure_s) + " s");
                !ok)
                return ok.error();
    }
    const size_t n = first.samples.size();
    const size_t J = series.size();
    const std::vector<bool> hot = hotMask(hot_pixels, n);
    std::vector<double> times(J);
    for (size_t j = 0; j < J; ++j) times[j] = series[j]->exposure_s;

    ResponseMeasurement m;
    // Steady scene?
    for (const ExposureLevel* level : series) {
        if (level->frames.size() < 2) continue;
        if (const auto shift = misalignment(level->frames[0], level->frames[1])) {
            m.steady = false;
            m.steadiness = "not steady: two frames at " + num(level->exposure_s) +
                           " s line up best shifted by (" + std::to_string(shift->first) + ", " +
                           std::to_string(shift->second) +
                           ") pixels; measured from the frames' histograms instead of pixels";
            break;
        }
    }
    if (m.steady) m.steadiness = "steady: frames at one exposure line up unshifted";

    // Observations: obs[i][j], the mean of pixel (or quantile) i at exposure j; with two or more
    // frames at every exposure also its first frame alone (obs_a) and the mean of the others
    // (obs_b), two independent measurements of it.
    bool split = true;
    for (const ExposureLevel* level : series) split = split && level->frames.size() >= 2;
    std::vector<std::vector<double>> obs, obs_a, obs_b;
    const auto addRow = [&](const std::function<double(size_t, size_t)>& value) {
        std::vector<double> mean(J), a(J), b(J);
        for (size_t j = 0; j < J; ++j) {
            const size_t frames = series[j]->frames.size();
            double sum = 0.0;
            for (size_t k = 0; k < frames; ++k) sum += value(j, k);
            mean[j] = sum / static_cast<double>(frames);
            a[j] = value(j, 0);
            b[j] = frames > 1 ? (sum - a[j]) / static_cast<double>(frames - 1) : a[j];
        }
        obs.push_back(std::move(mean));
        obs_a.push_back(std::move(a));
        obs_b.push_back(std::move(b));
    };
    if (m.steady) {
        const auto most = static_cast<size_t>(options.max_pixels);
        const size_t stride = std::max<size_t>(1, (n + most - 1) / most);
        for (size_t p = 0; p < n; p += stride) {
            if (hot[p]) continue;
            addRow([&](size_t j, size_t k) {
                return static_cast<double>(series[j]->frames[k].samples[p]);
            });
        }
    } else {
        // Quantiles of each frame: quantiles[j][k][q].
        const auto Q = static_cast<size_t>(options.quantiles);
        std::vector<std::vector<std::vector<double>>> quantiles(J);
        std::vector<double> values;
        for (size_t j = 0; j < J; ++j)
            for (const hdr::RawFrame& f : series[j]->frames) {
                values.clear();
                for (size_t p = 0; p < n; ++p)
                    if (!hot[p]) values.push_back(f.samples[p]);
                if (values.empty()) return invalid("exposure series: no pixels left (all hot?)");
                std::sort(values.begin(), values.end());
                std::vector<double> row(Q);
                for (size_t q = 0; q < Q; ++q) {
                    const auto rank = static_cast<size_t>((static_cast<double>(q) + 0.5) /
                                                          static_cast<double>(Q) *
                                                          static_cast<double>(values.size()));
                    row[q] = values[std::min(rank, values.size() - 1)];
                }
                quantiles[j].push_back(std::move(row));
            }
        for (size_t q = 0; q < Q; ++q)
            addRow([&](size_t j, size_t k) { return quantiles[j][k][q]; });
    }
    if (obs.empty()) return invalid("exposure series: no pixels left (all hot?)");

    // Clip level: where pixels stop responding to more exposure.
    double top = -std::numeric_limits<double>::infinity();
    for (const auto& row : obs)
        for (const double z : row) top = std::max(top, z);
    std::vector<double> plateau;
    for (const auto& row : obs)
        for (size_t j = 0; j + 1 < J; ++j) {
            const double r = times[j + 1] / times[j];
            if (r < 1.25) continue;
            const double s0 = row[j] - black_level_dn, s1 = row[j + 1] - black_level_dn;
            // Growth of less than half a percent of the range per doubling, in the upper half
            // of the range: a linear pixel would grow by its whole signal, a logarithmic one by
            // a tenth of the range; a pixel at a curved camera's noise floor (a fifth of the
            // range for a steep logarithm) does not grow either, but lies lower.
            if (s0 > 0.5 * (top - black_level_dn) &&
                s1 - s0 < 0.005 * (r - 1.0) * (top - black_level_dn))
                plateau.push_back(row[j + 1]);
        }
    if (plateau.size() < 8)
        return invalid(
            "exposure series: no pixel stops responding to more exposure, so the "
            "saturation level cannot be measured; the longest exposure must clip the "
            "brightest part of the scene (lengthen it)");
    m.clip_dn = median(std::move(plateau));
    const double range = m.clip_dn - black_level_dn;
    if (!(range > 1.25 * noise_floor_dn) || !(range > 8.0))
        return makeError(ErrorCode::Unsupported,
                         "exposure series: the clip level " + num(m.clip_dn) +
                             " DN lies too close to the black level " + num(black_level_dn) +
                             " DN to measure anything");

    // Linearity: each pixel's slope a_i from the middle of the range (10 % to 70 %), the
    // relative deviations s / (a_i t) - 1 binned by signal. Both the bin and the slope an
    // observation is compared with are taken from the pixel's other exposures (leave one out),
    // and from different frames: the bin's predicted signal from the first frames (obs_a), the
    // slope from the others (obs_b). Binned by a noisy figure that also enters the ratio, the
    // ratio would be biased (more pixels scatter into a bright bin from below than from above).
    constexpr int kBins = 20;  // 5 % of the range each; bins 1..18 span 5 .. 95 %
    std::vector<std::vector<double>> deviations(kBins);
    const auto inFit = [&](double z) {
        const double s = z - black_level_dn;
        return s >= 0.1 * range && s <= 0.7 * range;
    };
    // Slope of pixel i through `values` over its fitted exposures other than j; NaN if none.
    const auto slopeWithout = [&](const std::vector<double>& row, size_t i, size_t j) {
        double st = 0.0, tt = 0.0;
        for (size_t k = 0; k < J; ++k) {
            if (k == j || !inFit(obs[i][k])) continue;
            st += (row[k] - black_level_dn) * times[k];
            tt += times[k] * times[k];
        }
        return tt > 0.0 ? st / tt : kNaN;
    };
    struct Comparison {
        double predicted = 0.0;  // from obs_a: the bin
        double ratio = 0.0;      // s / (slope from obs_b * t)
        double signal = 0.0;
    };
    std::vector<Comparison> comparisons;
    for (size_t i = 0; i < obs.size(); ++i)
        for (size_t j = 0; j < J; ++j) {
            const double a = slopeWithout(obs_a[i], i, j);
            const double b = slopeWithout(obs_b[i], i, j);
            if (!(a > 0.0) || !(b > 0.0)) continue;
            const double s = obs[i][j] - black_level_dn;
            comparisons.push_back({a * times[j], s / (b * times[j]), s});
        }
    for (const Comparison& c : comparisons) {
        if (c.predicted < 0.05 * range || c.predicted > 0.95 * range) continue;
        const int bin = std::clamp(static_cast<int>(c.predicted / range * kBins), 0, kBins - 1);
        deviations[static_cast<size_t>(bin)].push_back(c.ratio - 1.0);
    }
    double lowest = std::numeric_limits<double>::infinity(), highest = -lowest;
    for (int bin = 0; bin < kBins; ++bin) {
        auto& d = deviations[static_cast<size_t>(bin)];
        if (d.size() < 10) continue;
        LinearityBin lb;
        lb.signal_dn = (bin + 0.5) * range / kBins;
        lb.samples = static_cast<int64_t>(d.size());
        lb.deviation = median(std::move(d));
        lowest = std::min(lowest, lb.deviation);
        highest = std::max(highest, lb.deviation);
        m.bins.push_back(lb);
    }
    if (m.bins.size() < 3)
        return makeError(ErrorCode::Unsupported,
                         "exposure series: only " + std::to_string(m.bins.size()) +
                             " signal levels between 5 % and 95 % of the range have enough "
                             "samples; the scene needs more contrast or the series more "
                             "exposures");
    m.linearity_error = (highest - lowest) / 2.0;
    m.linear = m.linearity_error <= options.linear_tolerance;
    std::ostringstream words;
    words << "response " << (m.linear ? "linear" : "not linear") << ": linearity error "
          << percent(m.linearity_error) << " (deviation from proportional between 5 % and 95 % "
          << "of the range, " << m.bins.size() << " signal levels; linear below "
          << percent(options.linear_tolerance) << ")";
    m.notes.push_back(words.str());
    m.notes.push_back("scene " + m.steadiness);
    if (!split)
        m.notes.push_back(
            "one frame per exposure: each sample is compared with a prediction that "
            "shares its noise, which biases linearity and saturation; take two or "
            "more frames per exposure");

    if (m.linear) {
        // Saturation: walk up the predicted signal while measured / predicted stays near 1.
        constexpr double kStep = 0.01;
        const int steps = static_cast<int>(1.5 / kStep);
        std::vector<std::vector<std::pair<double, double>>> by_prediction(
            static_cast<size_t>(steps));
        for (const Comparison& c : comparisons) {
            const int k = static_cast<int>((c.predicted / range - 0.5) / kStep);
            if (c.predicted < 0.5 * range || k < 0 || k >= steps) continue;
            by_prediction[static_cast<size_t>(k)].push_back({c.ratio, c.signal});
        }
        double saturation = 0.5 * range;
        bool ended = false;
        for (auto& bin : by_prediction) {
            if (bin.size() < 10) continue;
            std::vector<double> ratio, signal;
            for (const auto& [r, s] : bin) {
                ratio.push_back(r);
                signal.push_back(s);
            }
            // Saturation bends the response down; noise or a slope error may lift a bin, but
            // that is not where the sensor stops.
            if (median(std::move(ratio)) < 1.0 - options.saturation_tolerance) {
                ended = true;
                break;
            }
            saturation = std::max(saturation, median(std::move(signal)));
        }
        m.saturation_dn = std::min(m.clip_dn, black_level_dn + saturation);
        m.notes.push_back("saturation " + num(m.saturation_dn, 6) +
                          " DN: the response stays within " +
                          percent(options.saturation_tolerance) + " of proportional up to it" +
                          (ended ? "" : " (and beyond, up to the clip level)") +
                          "; pixels clip at " + num(m.clip_dn, 6) + " DN");
    } else {
        const double cut = black_level_dn + 0.99 * range;
        // The noise of an observation (a mean of F frames) by its level, from the differences
        // of its first frame and the mean of the others: E[(a - b)^2] = var F / (F - 1), so
        // var(mean) = (a - b)^2 (F - 1) / F^2.
        constexpr int kNoiseBins = 64;
        std::vector<double> noise_sum(kNoiseBins, 0.0), noise_count(kNoiseBins, 0.0);
        const auto noiseBin = [&](double z) {
            return std::clamp(static_cast<int>((z - black_level_dn) / range * kNoiseBins), 0,
                              kNoiseBins - 1);
        };
        if (split && m.steady)
            for (size_t i = 0; i < obs.size(); ++i)
                for (size_t j = 0; j < J; ++j) {
                    const double F = static_cast<double>(series[j]->frames.size());
                    const double d = obs_a[i][j] - obs_b[i][j];
                    const int bin = noiseBin(obs[i][j]);
                    noise_sum[static_cast<size_t>(bin)] += d * d * (F - 1.0) / (F * F);
                    noise_count[static_cast<size_t>(bin)] += 1.0;
                }
        std::vector<std::pair<double, double>> noise;  // (level, variance of a mean)
        for (int bin = 0; bin < kNoiseBins; ++bin)
            if (noise_count[static_cast<size_t>(bin)] >= 20.0)
                noise.push_back(
                    {black_level_dn + (bin + 0.5) * range / kNoiseBins,
                     noise_sum[static_cast<size_t>(bin)] / noise_count[static_cast<size_t>(bin)]});
        std::function<double(double)> variance_of;
        if (noise.size() >= 2)
            variance_of = [noise](double z) {
                if (z <= noise.front().first) return noise.front().second;
                if (z >= noise.back().first) return noise.back().second;
                const auto hi = std::lower_bound(
                    noise.begin(), noise.end(), z,
                    [](const std::pair<double, double>& p, double v) { return p.first < v; });
                const auto lo = hi - 1;
                const double f = (z - lo->first) / (hi->first - lo->first);
                return (1.0 - f) * lo->second + f * hi->second;
            };
        std::vector<double> levels(times.begin(), times.end());
        auto curve =
            recoverResponse(obs, levels, black_level_dn, noise_floor_dn, cut, variance_of, options);
        if (!curve) return curve.error();
        m.saturation_dn = curve->dn.back();
        m.notes.push_back("response curve: " + curve->method + "; it explains the samples to " +
                          num(curve->rms_error_stops, 3) + " stops RMS");
        if (curve->rms_error_stops > 0.1)
            m.notes.push_back(
                "the curve explains the samples poorly (more than 0.1 stops RMS): the camera's "
                "output is not a function of exposure alone (a moving test pattern, a light "
                "that flickers, or automatic exposure or gain left on)");
        m.notes.push_back("saturation " + num(m.saturation_dn, 6) +
                          " DN: where the curve ends, 1 % below the clip level " +
                          num(m.clip_dn, 6) + " DN");
        m.curve = std::move(*curve);
    }
    return m;
}

PhotonTransfer measurePhotonTransfer(std::span<const ExposureLevel> series,
                                     double black_level_dn,
                                     double saturation_dn,
                                     const std::vector<int64_t>& hot_pixels,
                                     const ResponseCurve* curve) {
    PhotonTransfer ptc;
    if (series.empty() || series.front().frames.empty()) {
        ptc.note = "no frames";
        return ptc;
    }
    const hdr::RawFrame& first = series.front().frames.front();
    const size_t n = first.samples.size();
    const std::vector<bool> hot = hotMask(hot_pixels, n);
    // Through the curve (16-bit linear DN, black 0) or as they are.
    std::vector<double> table;
    double black = black_level_dn, top = saturation_dn - black_level_dn;
    if (curve != nullptr) {
        const size_t codes = size_t{1} << std::clamp(first.bit_depth, 8, 16);
        table.resize(codes);
        for (size_t z = 0; z < codes; ++z)
            table[z] = 65535.0 * relativeExposure(*curve, black_level_dn, static_cast<double>(z)) /
                       curve->relative_exposure.back();
        black = 0.0;
        top = 65535.0;
    }
    if (!(top > 1.0)) {
        ptc.note = "no range between black and saturation";
        return ptc;
    }
    const auto value = [&](uint16_t s) {
        return table.empty() ? static_cast<double>(s)
                             : table[std::min<size_t>(s, table.size() - 1)];
    };

    constexpr int kBins = 48;
    const double low = 1.0, log_span = std::log(top / low);
    for (const ExposureLevel& level : series) {
        for (size_t k = 0; k + 1 < level.frames.size(); k += 2) {
            const hdr::RawFrame& a = level.frames[k];
            const hdr::RawFrame& b = level.frames[k + 1];
            if (a.samples.size() != n || b.samples.size() != n) continue;
            std::vector<double> count(kBins, 0.0), sum_m(kBins, 0.0), sum_d(kBins, 0.0),
                sum_d2(kBins, 0.0);
            for (size_t i = 0; i < n; ++i) {
                if (hot[i] || a.samples[i] >= saturation_dn || b.samples[i] >= saturation_dn)
                    continue;
                const double va = value(a.samples[i]), vb = value(b.samples[i]);
                const double mean = 0.5 * (va + vb) - black;
                if (mean < low) continue;
                const int bin = std::clamp(
                    static_cast<int>(std::log(mean / low) / log_span * kBins), 0, kBins - 1);
                const double d = va - vb;
                count[bin] += 1.0;
                sum_m[bin] += mean;
                sum_d[bin] += d;
                sum_d2[bin] += d * d;
            }
            for (int bin = 0; bin < kBins; ++bin) {
                if (count[bin] < 100.0) continue;
                const double c = count[bin];
                const double md = sum_d[bin] / c;
                PhotonTransferPoint p;
                p.signal_dn = sum_m[bin] / c;
                p.variance_dn2 = (sum_d2[bin] / c - md * md) * c / (c - 1.0) / 2.0;
                p.pixels = static_cast<int64_t>(c);
                ptc.points.push_back(p);
            }
        }
    }
    // Weighted straight line var = intercept + slope * signal over the middle of the range; the
    // variance of a variance estimate from n samples is about 2 var^2 / n.
    double sw = 0.0, sx = 0.0, sy = 0.0, sxx = 0.0, sxy = 0.0;
    for (const PhotonTransferPoint& p : ptc.points) {
        if (p.signal_dn < 0.02 * top || p.signal_dn > 0.7 * top || !(p.variance_dn2 > 0.0))
            continue;
        const double w = static_cast<double>(p.pixels) / (p.variance_dn2 * p.variance_dn2);
        sw += w;
        sx += w * p.signal_dn;
        sy += w * p.variance_dn2;
        sxx += w * p.signal_dn * p.signal_dn;
        sxy += w * p.signal_dn * p.variance_dn2;
        ++ptc.fitted_points;
    }
    const double det = sw * sxx - sx * sx;
    if (ptc.fitted_points < 3 || !(det > 0.0)) {
        ptc.note = "photon transfer: only " + std::to_string(ptc.fitted_points) +
                   " usable signal levels between 2 % and 70 % of saturation (pairs of frames "
                   "at one exposure, 100 pixels a level); conversion gain not measured";
        return ptc;
    }
    const double slope = (sw * sxy - sx * sy) / det;
    ptc.intercept_dn2 = (sy - slope * sx) / sw;
    if (!(slope > 0.0) || !std::isfinite(slope)) {
        ptc.note = "photon transfer: the variance does not grow with the signal (slope " +
                   num(slope) +
                   "): no shot noise, as in a synthetic test pattern; conversion gain not "
                   "measured";
        return ptc;
    }
    ptc.electrons_per_dn = 1.0 / slope;
    ptc.note = "conversion gain " + num(ptc.electrons_per_dn) +
               " e-/DN: photon transfer, the slope of variance against signal over " +
               std::to_string(ptc.fitted_points) +
               " signal levels between 2 % and 70 % of saturation (intercept " +
               num(ptc.intercept_dn2) + " DN^2)" + (curve ? ", in linearized 16-bit DN" : "");
    return ptc;
}

Result<CameraCalibration> buildCalibration(const DeviceIdentity& identity,
                                           const DarkFrames& dark,
                                           std::span<const ExposureLevel> series,
                                           const CalibrationOptions& options) {
    auto d = measureDark(dark);
    if (!d) return d.error();
    if (series.empty() || series.front().frames.empty())
        return invalid("exposure series: no frames");
    const hdr::RawFrame& first = series.front().frames.front();
    if (Status ok = sameShape(first, dark.bias.front(), "the dark frames"); !ok)
        return ok.error().withContext(
            "the dark frames and the series must be of one camera "
            "setting");
    for (const ExposureLevel& level : series)
        for (const hdr::RawFrame& f : level.frames)
            if (f.gain != first.gain)
                return invalid("exposure series: frames at gain " + num(f.gain) + " and " +
                               num(first.gain) + "; calibrate at one gain");
    if (dark.bias.front().gain != first.gain)
        return invalid("the dark frames were taken at gain " + num(dark.bias.front().gain) +
                       ", the series at " + num(first.gain));
    auto r = measureResponse(series, d->black_level_dn, d->noise_floor_dn, d->hot_pixels, options);
    if (!r) return r.error();

    CameraCalibration c;
    c.camera_model = identity.model;
    c.camera_serial = identity.serial;
    c.width_px = first.width;
    c.height_px = first.height;
    c.format = first.format;
    c.bit_depth = first.bit_depth;
    c.gain = first.gain;
    c.created_utc = utcNow();
    c.software_version = "flarelab calibrate";
    c.black_level_dn = d->black_level_dn;
    c.saturation_dn = r->saturation_dn;
    c.linear = r->linear;
    c.linearity_error = r->linearity_error;
    c.response_curve = r->curve;
    c.hot_pixels = d->hot_pixels;
    c.notes = d->notes;
    c.notes.insert(c.notes.end(), r->notes.begin(), r->notes.end());
    if (r->steady) {
        const PhotonTransfer ptc =
            measurePhotonTransfer(series, d->black_level_dn, r->saturation_dn, d->hot_pixels,
                                  r->curve ? &*r->curve : nullptr);
        c.notes.push_back(ptc.note);
        c.electrons_per_dn = ptc.electrons_per_dn;
        if (c.linear) {
            c.read_noise_dn = d->read_noise_dn;
        } else if (ptc.electrons_per_dn > 0.0) {
            // In linear DN the dark frames' noise is bent by the curve: the intercept of the
            // linearized photon transfer curve is the read noise there.
            c.read_noise_dn = std::sqrt(std::max(0.0, ptc.intercept_dn2));
        }
        c.read_noise_e = c.read_noise_dn * c.electrons_per_dn;
        c.notes.push_back("read noise " + num(c.read_noise_dn) + " DN = " + num(c.read_noise_e) +
                          " e- at gain " + num(c.gain));
    } else {
        c.notes.push_back(
            "noise: not measured (pairs of frames of a scene that is not steady differ by more "
            "than noise)");
        if (c.linear) c.read_noise_dn = d->read_noise_dn;
    }
    if (Status ok = validateCalibration(c); !ok) return ok.error();
    return c;
}

// ---------------------------------------------------------------------------------------------

Result<std::vector<hdr::RawFrame>> captureFrames(Camera& camera,
                                                 double exposure_s,
                                                 int count,
                                                 double timeout_s) {
    if (Status ok = camera.setExposure(exposure_s); !ok)
        return ok.error().withContext("exposure " + num(exposure_s) + " s");
    std::vector<hdr::RawFrame> frames;
    for (int k = 0; k < count; ++k) {
        auto frame = camera.capture(timeout_s);
        if (!frame)
            return frame.error().withContext("frame " + std::to_string(k + 1) + " of " +
                                             std::to_string(count) + " at " + num(exposure_s) +
                                             " s");
        frames.push_back(std::move(*frame));
    }
    return frames;
}

Result<DarkFrames> captureDarkFrames(Camera& camera, const CalibrationCapture& options) {
    if (options.bias_frames < 2 || options.long_dark_frames < 1)
        return invalid("dark frames: need at least 2 bias frames and 1 long dark frame");
    const CameraCapabilities caps = camera.capabilities();
    DarkFrames dark;
    auto bias = captureFrames(camera, caps.min_exposure_s, options.bias_frames,
                              caps.min_exposure_s + options.timeout_margin_s);
    if (!bias) return bias.error().withContext("bias frames");
    dark.bias = std::move(*bias);
    const double t =
        std::clamp(options.long_dark_exposure_s, caps.min_exposure_s, caps.max_exposure_s);
    auto long_dark =
        captureFrames(camera, t, options.long_dark_frames, t + options.timeout_margin_s);
    if (!long_dark) return long_dark.error().withContext("long dark frames");
    dark.long_dark = std::move(*long_dark);
    return dark;
}

Result<std::vector<double>> planSeriesExposures(Camera& camera,
                                                double black_level_dn,
                                                const CalibrationCapture& options) {
    if (options.levels < 3 || options.frames_per_exposure < 1 || !(options.budget_s > 0.0))
        return invalid("series: levels must be >= 3, frames per exposure >= 1, budget > 0");
    const CameraCapabilities caps = camera.capabilities();
    const double full = std::ldexp(1.0, caps.bit_depth) - 1.0;
    const double range = full - black_level_dn;
    const double t_min = caps.min_exposure_s, t_max = caps.max_exposure_s;
    int probes = 0;
    constexpr int kMaxProbes = 32;
    // The 99.5th percentile of the signal at exposure t, as a fraction of the range.
    const auto levelAt = [&](double t) -> Result<double> {
        ++probes;
        auto frames = captureFrames(camera, t, 1, t + options.timeout_margin_s);
        if (!frames) return frames.error().withContext("series probe");
        const hdr::RawFrame& f = frames->front();
        std::vector<double> signal(f.samples.size());
        for (size_t i = 0; i < signal.size(); ++i) signal[i] = f.samples[i] - black_level_dn;
        return quantile(signal, 0.995) / range;
    };

    // t_top: where the brightest half percent of the scene reaches half the range.
    double t = std::clamp(camera.exposure_s() > 0.0 ? camera.exposure_s() : 1e-3, t_min, t_max);
    double t_top = 0.0;
    while (t_top == 0.0 && probes < kMaxProbes) {
        auto level = levelAt(t);
        if (!level) return level.error();
        if (*level > 0.9) {
            if (t <= t_min) t_top = t;
            t = std::max(t_min, t / 8.0);
        } else if (*level < 0.05) {
            if (t >= t_max) {
                if (*level <= 0.0)
                    return makeError(ErrorCode::Unsupported,
                                     "series: the scene shows no signal even at the longest "
                                     "exposure, " +
                                         num(t_max) + " s: is the light on and the lens uncapped?");
                t_top = t;
            }
            t = std::min(t_max, *level > 0.0 ? t * std::min(64.0, 0.5 / *level) : t * 16.0);
        } else {
            t_top = t;
        }
    }
    if (t_top == 0.0) t_top = t;
    // The foot: down in steps of 8 until that part of the scene lies within 5 % of black (a
    // curved response keeps the dark end far from black for long).
    double t_low = t_top;
    while (t_low > t_min && probes < kMaxProbes) {
        t_low = std::max(t_min, t_low / 8.0);
        auto level = levelAt(t_low);
        if (!level) return level.error();
        if (*level <= 0.05) break;
    }
    // The top: up in steps of 4 until it clips, then twice that, so that a good part of the
    // scene clips and the saturation level shows.
    double t_high = t_top;
    while (t_high < t_max && probes < kMaxProbes) {
        t_high = std::min(t_max, t_high * 4.0);
        auto level = levelAt(t_high);
        if (!level) return level.error();
        if (*level >= 0.98) {
            t_high = std::min(t_max, t_high * 2.0);
            break;
        }
    }
    t_high = std::min(t_high, options.budget_s / (2.0 * options.frames_per_exposure));
    if (!(t_high > t_low))
        return makeError(ErrorCode::Unsupported,
                         "series: the camera's range of exposures and the time budget of " +
                             num(options.budget_s) +
                             " s leave no room for a series (the scene "
                             "wants about " +
                             num(t_top) + " s to reach half the range)");
    // Even steps of at least a factor of 2, at most `levels` exposures, within the budget.
    const double span = std::log(t_high / t_low);
    int count = std::min(options.levels, static_cast<int>(std::floor(span / std::log(2.0))) + 1);
    count = std::max(count, 3);
    std::vector<double> exposures;
    while (count >= 3) {
        exposures.clear();
        double spent = 0.0;
        for (int k = 0; k < count; ++k) {
            const double e = t_low * std::exp(span * k / (count - 1));
            exposures.push_back(std::clamp(e, t_min, t_max));
            spent += exposures.back() * options.frames_per_exposure;
        }
        if (spent <= options.budget_s) break;
        --count;
    }
    if (count < 3)
        return makeError(ErrorCode::Unsupported,
                         "series: fewer than 3 exposures fit the time budget of " +
                             num(options.budget_s) + " s");
    return exposures;
}

Result<std::vector<ExposureLevel>> captureSeries(Camera& camera,
                                                 std::span<const double> exposures_s,
                                                 const CalibrationCapture& options) {
    std::vector<ExposureLevel> series;
    for (const double t : exposures_s) {
        auto frames =
            captureFrames(camera, t, options.frames_per_exposure, t + options.timeout_margin_s);
        if (!frames) return frames.error().withContext("exposure series");
        ExposureLevel level;
        // What the camera applied (read back), not what was asked.
        double applied = 0.0;
        for (const hdr::RawFrame& f : *frames) applied += f.exposure_s;
        level.exposure_s = applied / static_cast<double>(frames->size());
        level.frames = std::move(*frames);
        series.push_back(std::move(level));
    }
    return series;
}

}  // namespace flarelab::drivers
