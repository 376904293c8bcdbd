#include "fit/detect.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <numeric>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

namespace flarelab::fit {

namespace {

// At most this many pixels per channel go into the median and MAD: plenty for a robust level,
// and it keeps a 640 x 427 frame well under a millisecond.
constexpr int64_t kBackgroundSamples = 1 << 13;
// MAD to the standard deviation of a Gaussian.
constexpr double kMadToSigma = 1.4826;
// The light is found when its peak rises this many times above the candidate threshold: the
// largest pixel of a frame of pure noise (about 5 sigma for a million pixels) does not count.
constexpr double kLightThresholdFactor = 2.0;
// The light's disc ends where the azimuthal mean around it falls below this fraction of its peak
// or, once below kLightCoreFraction of it, stops falling (a ghost's plateau under the light at
// angle 0): on the simulated rig the merged core is a lower bound only about 65 times the
// brightest broad ghosts, so a relative level alone would swallow a concentric ghost.
constexpr double kLightRelativeLevel = 1e-3;
constexpr double kLightCoreFraction = 0.25;
// ... but never above this many noise sigmas. A core the merge clips (1.6e4 on the simulated rig,
// noise about 1) puts a thousandth of it at some 15 sigmas; an unclipped one is held to the same.
constexpr double kLightLevelSigmas = 15.0;
constexpr double kLightPlateauRatio = 0.97;
// A light's profile falls below kLightCoreFraction of its peak within this fraction of the
// diagonal (4 px at least); a blob that does not is a broad ghost, the light being out of frame.
constexpr double kLightCoreLimitFraction = 1.0 / 32.0;
// The disc's radius never exceeds this fraction of the image diagonal (before light_min_radius).
constexpr double kLightCapFraction = 0.125;
// A candidate's extents: its pixels whose smoothed value reaches this fraction of the
// component's 90th percentile (and the threshold). A hard edge blurred by the smoothing sits at
// half its level, so 0.25 puts the extent within about 0.7 sigma of it.
constexpr double kBodyFraction = 0.25;
constexpr double kBorderPercentile = 0.9;
constexpr int64_t kQuantileSamples = 1 << 12;
constexpr double kInnerExtentFraction = 0.5;
constexpr double kFalloffFraction = 0.15;

struct RobustLevel {
    double median = 0.0;  // the background: the sky's level
    double sigma = 0.0;   // its noise, not yet floored
};

// The q-quantile (0..1) of `values`, reordering them; 0 for none.
double quantile(std::vector<float>& values, double q) {
    if (values.empty()) return 0.0;
    const size_t k = std::min(
        values.size() - 1, static_cast<size_t>(q * static_cast<double>(values.size() - 1) + 0.5));
    std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k), values.end());
    return values[k];
}

// The sky under the ghosts. The median of the frame is not it: on the simulated rig broad ghosts
// cover more than half the frame at small angles. Ghosts only add light, so the sky is the
// lowest mode of the values:
//   1. a bandwidth h: the noise from horizontal neighbour differences (1.4826 MAD / sqrt 2), which
//      smooth ghosts barely touch;
//   2. the sorted sample's density in windows +-h; the sky's level is the first value whose
//      density is at least that of every value up to 3 h above it (the top of the lowest peak)
//      and at least 1 % of the largest density (not a stray dark pixel), refined to the mean of
//      the values within +-h of it;
//   3. the noise from the values below that level only (1.4826 times their median distance to
//      it), which no ghost reaches.
RobustLevel robustLevel(const ImageRGB& image, int channel) {
    const int64_t n = image.width * image.height;
    const int64_t stride = std::max<int64_t>(1, (n + kBackgroundSamples - 1) / kBackgroundSamples);
    std::vector<float> values;
    std::vector<float> diffs;
    values.reserve(static_cast<size_t>(n / stride + 1));
    diffs.reserve(static_cast<size_t>(n / stride + 1));
    const float* px = image.pixels.data();
    for (int64_t i = 0; i < n; i += stride) {
        const float v = px[i * 3 + channel];
        if (!std::isfinite(v)) continue;
        values.push_back(v);
        if ((i + 1) % image.width != 0) {
            const float w = px[(i + 1) * 3 + channel];
            if (std::isfinite(w)) diffs.push_back(std::abs(w - v));
        }
    }
    RobustLevel level;
    if (values.empty()) return level;
    const double h = kMadToSigma * quantile(diffs, 0.5) / std::sqrt(2.0);
    std::sort(values.begin(), values.end());
    const size_t m = values.size();
    // density[i]: how many values lie within +-h of values[i] (two pointers).
    std::vector<int32_t> density(m);
    size_t lo = 0, hi = 0;
    int32_t densest = 0;
    for (size_t i = 0; i < m; ++i) {
        while (values[lo] < values[i] - h) ++lo;
        while (hi < m && values[hi] <= values[i] + h) ++hi;
        density[i] = static_cast<int32_t>(hi - lo);
        densest = std::max(densest, density[i]);
    }
    // Scan up; `ahead` tracks the largest density within 3 h above i (a monotone deque would be
    // linear; the window rarely holds more than a few hundred values, and we stop at the first).
    size_t sky = 0;
    size_t top = 0;             // one past the last value within 3 h above values[i]
    std::vector<size_t> queue;  // indices with decreasing density, the window's maxima
    size_t head = 0;
    for (size_t i = 0; i < m; ++i) {
        while (top < m && values[top] <= values[i] + 3.0 * h) {
            while (queue.size() > head && density[queue.back()] <= density[top]) queue.pop_back();
            queue.push_back(top);
            ++top;
        }
        while (head < queue.size() && queue[head] < i) ++head;
        const int32_t ahead = head < queue.size() ? density[queue[head]] : 0;
        if (density[i] >= ahead && 100 * static_cast<int64_t>(density[i]) >= densest) {
            sky = i;
            break;
        }
    }
    double sum = 0.0;
    int64_t count = 0;
    for (size_t j = sky; j-- > 0 && values[j] >= values[sky] - h;) sum += values[j], ++count;
    for (size_t j = sky; j < m && values[j] <= values[sky] + h; ++j) sum += values[j], ++count;
    level.median = sum / static_cast<double>(count);
    diffs.clear();
    for (size_t j = 0; j < m && values[j] < level.median; ++j)
        diffs.push_back(static_cast<float>(level.median - values[j]));
    level.sigma = kMadToSigma * quantile(diffs, 0.5);
    return level;
}

Status validateOptions(const DetectOptions& o) {
    auto bad = [](const char* what) {
        return makeError(ErrorCode::InvalidArgument, std::string("detect: ") + what);
    };
    if (!(o.smoothing_px >= 0.0) || !std::isfinite(o.smoothing_px))
        return bad("smoothing_px must be finite and >= 0");
    if (o.smoothing_px > 100.0) return bad("smoothing_px must be <= 100");
    if (!(o.threshold_sigmas > 0.0) || !std::isfinite(o.threshold_sigmas))
        return bad("threshold_sigmas must be finite and > 0");
    if (o.min_area_px < 1) return bad("min_area_px must be >= 1");
    if (!(o.min_energy_sigmas > 0.0) || !std::isfinite(o.min_energy_sigmas))
        return bad("min_energy_sigmas must be finite and > 0");
    if (!(o.min_light_peak >= 0.0) || !std::isfinite(o.min_light_peak))
        return bad("min_light_peak must be finite and >= 0");
    if (!(o.light_margin_px >= 0.0) || !std::isfinite(o.light_margin_px))
        return bad("light_margin_px must be finite and >= 0");
    if (!(o.light_min_radius_px >= 0.0) || !std::isfinite(o.light_min_radius_px))
        return bad("light_min_radius_px must be finite and >= 0");
    if (o.max_candidates < 0) return bad("max_candidates must be >= 0");
    if (o.max_circles < 0) return bad("max_circles must be >= 0");
    if (!(o.min_circle_support > 0.0) || !std::isfinite(o.min_circle_support))
        return bad("min_circle_support must be finite and > 0");
    if (!(o.min_circle_radius_px > 0.0) || !std::isfinite(o.min_circle_radius_px))
        return bad("min_circle_radius_px must be finite and > 0");
    if (!(o.circle_edge_sigmas > 0.0) || !std::isfinite(o.circle_edge_sigmas))
        return bad("circle_edge_sigmas must be finite and > 0");
    if (!(o.min_circle_step >= 0.0) || !std::isfinite(o.min_circle_step))
        return bad("min_circle_step must be finite and >= 0");
    if (o.max_edge_pixels < 16) return bad("max_edge_pixels must be >= 16");
    return Ok{};
}

// The light: centre, radius; marks its disc in `excluded`. `signal` is the channel-summed
// value - background (0 at non-finite pixels), `sigma` its noise.
LightSpot findLight(const std::vector<float>& signal,
                    int64_t width,
                    int64_t height,
                    double sigma,
                    const DetectOptions& options,
                    std::vector<uint8_t>& excluded) {
    LightSpot light;
    const auto peak_it = std::max_element(signal.begin(), signal.end());
    const double peak = *peak_it;
    if (!(peak > kLightThresholdFactor * options.threshold_sigmas * sigma) ||
        peak < options.min_light_peak)
        return light;
    const int64_t peak_index = peak_it - signal.begin();
    const int64_t px = peak_index % width;
    const int64_t py = peak_index / width;

    const double diagonal = std::hypot(static_cast<double>(width), static_cast<double>(height));
    const double cap = kLightCapFraction * diagonal;
    const int64_t reach = static_cast<int64_t>(std::ceil(cap)) + 1;

    // Centre: the signal-weighted centroid of the pixels at half the peak or more near it (a
    // saturated core is a plateau, whose first maximum is its corner).
    const int64_t core_reach = std::min<int64_t>(reach, 32);
    double sw = 0.0, sx = 0.0, sy = 0.0;
    for (int64_t y = std::max<int64_t>(0, py - core_reach);
         y <= std::min(height - 1, py + core_reach); ++y) {
        for (int64_t x = std::max<int64_t>(0, px - core_reach);
             x <= std::min(width - 1, px + core_reach); ++x) {
            const double v = signal[static_cast<size_t>(y * width + x)];
            if (v < 0.5 * peak) continue;
            sw += v;
            sx += v * (static_cast<double>(x) + 0.5);
            sy += v * (static_cast<double>(y) + 0.5);
        }
    }
    const double cx = sx / sw;
    const double cy = sy / sw;

    // Radial profile: the mean signal in rings one pixel wide.
    const int64_t bins = reach + 1;
    std::vector<double> ring_sum(static_cast<size_t>(bins), 0.0);
    std::vector<int64_t> ring_count(static_cast<size_t>(bins), 0);
    const int64_t x_lo = std::max<int64_t>(0, static_cast<int64_t>(std::floor(cx - reach)));
    const int64_t x_hi = std::min(width - 1, static_cast<int64_t>(std::ceil(cx + reach)));
    const int64_t y_lo = std::max<int64_t>(0, static_cast<int64_t>(std::floor(cy - reach)));
    const int64_t y_hi = std::min(height - 1, static_cast<int64_t>(std::ceil(cy + reach)));
    for (int64_t y = y_lo; y <= y_hi; ++y) {
        const double dy = static_cast<double>(y) + 0.5 - cy;
        for (int64_t x = x_lo; x <= x_hi; ++x) {
            const double dx = static_cast<double>(x) + 0.5 - cx;
            const auto r = static_cast<int64_t>(std::sqrt(dx * dx + dy * dy));
            if (r >= bins) continue;
            ring_sum[static_cast<size_t>(r)] += signal[static_cast<size_t>(y * width + x)];
            ++ring_count[static_cast<size_t>(r)];
        }
    }
    // A thousandth of the peak, but no more than kLightLevelSigmas noise sigmas: an unclipped
    // core (1e11 above a sky whose noise is 1, with the brackets capture plans) would end the
    // disc a few pixels out, inside its own glare, which the fit would then take for ghosts.
    const double level = std::max(std::min(kLightRelativeLevel * peak, kLightLevelSigmas * sigma),
                                  options.threshold_sigmas * sigma);
    const double core_limit = std::max(4.0, kLightCoreLimitFraction * diagonal);
    double grown = cap;
    double lowest = std::numeric_limits<double>::infinity();
    for (int64_t r = 0; r < bins; ++r) {
        if (ring_count[static_cast<size_t>(r)] == 0) continue;
        const double mean = ring_sum[static_cast<size_t>(r)] /
                            static_cast<double>(ring_count[static_cast<size_t>(r)]);
        // Not a point: a broad ghost's brightest pixel, with the light out of the frame.
        if (static_cast<double>(r) > core_limit && lowest >= kLightCoreFraction * peak)
            return light;
        const bool below = mean < level;
        const bool plateau = mean < kLightCoreFraction * peak && mean > kLightPlateauRatio * lowest;
        if (below || plateau) {
            grown = static_cast<double>(r);
            break;
        }
        lowest = std::min(lowest, mean);
    }
    const double radius =
        std::max(std::min(grown + options.light_margin_px, cap), options.light_min_radius_px);

    light.found = true;
    light.centre_px = {cx, cy};
    light.radius_px = radius;
    light.peak = peak;
    const double r2 = radius * radius;
    const int64_t ry = static_cast<int64_t>(std::ceil(radius)) + 1;
    for (int64_t y = std::max<int64_t>(0, static_cast<int64_t>(cy) - ry);
         y <= std::min(height - 1, static_cast<int64_t>(cy) + ry); ++y) {
        const double dy = static_cast<double>(y) + 0.5 - cy;
        for (int64_t x = std::max<int64_t>(0, static_cast<int64_t>(cx) - ry);
             x <= std::min(width - 1, static_cast<int64_t>(cx) + ry); ++x) {
            const double dx = static_cast<double>(x) + 0.5 - cx;
            if (dx * dx + dy * dy <= r2) excluded[static_cast<size_t>(y * width + x)] = 1;
        }
    }
    return light;
}

// ---------------------------------------------------------------------------
// Circles on the light line (DetectOptions::circles)
// ---------------------------------------------------------------------------

// Edge pixels vote only where their gradient points at the centre within this cosine (about
// 20 degrees), weighted from 0 there to 1 exactly radial.
constexpr double kCircleCos = 0.94;
// Candidate centres reach this many frame sizes beyond the image centre's half diagonal along
// the line; radii go up to this many diagonals.
constexpr double kCentreReachFrames = 1.0;
constexpr double kRadiusReachDiagonals = 1.5;
// Two circles closer than this in centre and radius (px) are one (the better supported kept).
constexpr double kCircleSeparationPx = 4.0;
// Edge pixels this close to excluded pixels (the light's disc has an edge of its own) do not vote.
constexpr int kExcludedMarginPx = 3;
// A circle needs at least this many (estimated) edge pixels and this much visible arc.
constexpr double kMinCircleVotes = 12.0;
constexpr double kMinVisibleArcPx = 12.0;
// The rim's value is sampled this far inside and outside the circle (px, plus the smoothing).
constexpr double kRimOffsetPx = 2.0;

struct Circle {
    Eigen::Vector2d centre_px = Eigen::Vector2d::Zero();
    double radius_px = 0.0;
    double support = 0.0;
};

// Points of a circle inside the frame and outside the excluded pixels, `step_px` apart.
template <typename F>
void forVisibleArc(const Circle& c,
                   int64_t width,
                   int64_t height,
                   const std::vector<uint8_t>& excluded,
                   double step_px,
                   F&& f) {
    const int n =
        static_cast<int>(std::clamp(std::ceil(2.0 * M_PI * c.radius_px / step_px), 16.0, 8192.0));
    // The points' directions by a rotation from one to the next, taken afresh from the cosine
    // and sine every 32 points (within some 1e-14 of them; the trigonometric functions had been
    // 7 % of a fit's time).
    const double step = 2.0 * M_PI / n, cs = std::cos(step), ss = std::sin(step);
    double ca = 1.0, sa = 0.0;
    for (int k = 0; k < n; ++k) {
        if (k % 32 == 0) {
            const double a = 2.0 * M_PI * (static_cast<double>(k) + 0.5) / n;
            ca = std::cos(a);
            sa = std::sin(a);
        } else {
            const double next_ca = ca * cs - sa * ss;
            sa = sa * cs + ca * ss;
            ca = next_ca;
        }
        const double x = c.centre_px.x() + c.radius_px * ca;
        const double y = c.centre_px.y() + c.radius_px * sa;
        if (!(x >= 0.0 && y >= 0.0 && x < static_cast<double>(width) &&
              y < static_cast<double>(height)))
            continue;
        const auto ix = static_cast<int64_t>(x), iy = static_cast<int64_t>(y);
        if (excluded[static_cast<size_t>(iy * width + ix)]) continue;
        f(ca, sa, n);
    }
}

std::vector<Circle> detectCircles(const cv::Mat& smoothed,  // CV_32F signal, smoothed
                                  double smoothed_sigma,
                                  const std::vector<uint8_t>& excluded,
                                  const LightSpot& light,
                                  const render::SensorToImage& map,
                                  const DetectOptions& options) {
    std::vector<Circle> circles;
    const int width = smoothed.cols, height = smoothed.rows;
    if (width < 8 || height < 8 || options.max_circles == 0) return circles;

    // The light line: a point (the image centre) and a unit direction.
    const Eigen::Vector2d origin(map.centre_x_px, map.centre_y_px);
    Eigen::Vector2d dir(1.0, 0.0);
    if (light.found && (light.centre_px - origin).norm() > 2.0)
        dir = (light.centre_px - origin).normalized();
    if (dir.x() < 0.0) dir = -dir;

    // Edge pixels: significant and relatively steep gradients of the smoothed signal.
    cv::Mat gx, gy;
    cv::Sobel(smoothed, gx, CV_32F, 1, 0, 3, 1.0 / 8.0, 0.0, cv::BORDER_REFLECT);
    cv::Sobel(smoothed, gy, CV_32F, 0, 1, 3, 1.0 / 8.0, 0.0, cv::BORDER_REFLECT);
    // White noise of sigma s through the normalized Sobel: s sqrt(12) / 8 per component.
    const double grad_noise = smoothed_sigma * std::sqrt(12.0) / 8.0;
    const double grad_threshold = options.circle_edge_sigmas * grad_noise;
    const double level_floor = options.threshold_sigmas * smoothed_sigma;
    cv::Mat excl(height, width, CV_8U, const_cast<uint8_t*>(excluded.data()));
    cv::Mat near_excl;
    cv::dilate(excl, near_excl,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * kExcludedMarginPx + 1,
                                                                     2 * kExcludedMarginPx + 1)));
    struct Edge {
        float x, y, gx, gy;  // position (pixel centre), unit gradient
    };
    std::vector<Edge> edges;
    for (int y = 1; y < height - 1; ++y) {
        const float* rx = gx.ptr<float>(y);
        const float* ry = gy.ptr<float>(y);
        const float* s = smoothed.ptr<float>(y);
        const uint8_t* e = near_excl.ptr<uint8_t>(y);
        for (int x = 1; x < width - 1; ++x) {
            if (e[x]) continue;
            const double g = std::hypot(static_cast<double>(rx[x]), static_cast<double>(ry[x]));
            if (!(g > grad_threshold)) continue;
            if (!(g > options.min_circle_step * std::max<double>(s[x], level_floor))) continue;
            edges.push_back({static_cast<float>(x + 0.5), static_cast<float>(y + 0.5),
                             static_cast<float>(rx[x] / g), static_cast<float>(ry[x] / g)});
        }
    }
    if (edges.size() < 8) return circles;
    // Even subsampling keeps votes proportional to edge length.
    const size_t max_edges = static_cast<size_t>(options.max_edge_pixels);
    double fraction = 1.0;
    if (edges.size() > max_edges) {
        fraction = static_cast<double>(max_edges) / static_cast<double>(edges.size());
        std::vector<Edge> kept;
        kept.reserve(max_edges);
        for (size_t k = 0; k < max_edges; ++k)
            kept.push_back(edges[static_cast<size_t>(static_cast<double>(k) / fraction)]);
        edges.swap(kept);
    }

    // Accumulator: centre t (px along the line from the origin) by radius r, 1 px bins.
    const double diagonal = std::hypot(static_cast<double>(width), static_cast<double>(height));
    const double t_reach = 0.5 * diagonal + kCentreReachFrames * std::max(width, height);
    const int nt = static_cast<int>(2.0 * t_reach) + 1;
    const int nr = static_cast<int>(kRadiusReachDiagonals * diagonal) + 2;
    cv::Mat acc = cv::Mat::zeros(nt, nr, CV_32F);
    const double c2 = kCircleCos * kCircleCos;
    const double alpha = std::acos(kCircleCos);
    const Eigen::Vector2d normal(-dir.y(), dir.x());
    for (const Edge& e : edges) {
        // The centres the gradient can point at: t = s + |h| cot(psi) over the angles psi in
        // (0, pi) within alpha of the gradient's (mirrored to the edge's side of the line).
        const Eigen::Vector2d rel(e.x - origin.x(), e.y - origin.y());
        const double s = rel.dot(dir);
        const double hh = -rel.dot(normal);
        int i_lo = 0, i_hi = nt - 1;
        if (std::abs(hh) > 1e-6) {
            const Eigen::Vector2d g(e.gx, e.gy);
            double gamma = std::atan2(g.dot(normal), g.dot(dir));
            if (hh < 0.0) gamma = -gamma;
            double lo = M_PI, hi = 0.0;
            for (double shift : {-2.0 * M_PI, 0.0, 2.0 * M_PI}) {
                const double a = std::max(gamma + shift - alpha, 1e-9);
                const double b = std::min(gamma + shift + alpha, M_PI - 1e-9);
                if (a < b) lo = std::min(lo, a), hi = std::max(hi, b);
            }
            if (lo >= hi) continue;
            const double t_lo = s + std::abs(hh) / std::tan(hi);
            const double t_hi = s + std::abs(hh) / std::tan(lo);
            i_lo = static_cast<int>(std::clamp(std::floor(t_lo + t_reach) - 1.0, 0.0, nt - 1.0));
            i_hi = static_cast<int>(std::clamp(std::ceil(t_hi + t_reach) + 1.0, 0.0, nt - 1.0));
        }
        for (int i = i_lo; i <= i_hi; ++i) {
            const double t = static_cast<double>(i) - t_reach;
            const double dx = e.x - (origin.x() + t * dir.x());
            const double dy = e.y - (origin.y() + t * dir.y());
            const double dot = -(dx * e.gx + dy * e.gy);  // gradient points inward, at the centre
            if (dot <= 0.0) continue;
            const double d2 = dx * dx + dy * dy;
            if (dot * dot < c2 * d2) continue;
            const double d = std::sqrt(d2);
            const double w = (dot / d - kCircleCos) / (1.0 - kCircleCos);
            const double rb = d - 0.5;  // bin j holds radius j + 0.5 at its centre... linear split
            const int j = static_cast<int>(rb);
            if (rb < 0.0 || j + 1 >= nr) continue;
            const double f = rb - j;
            float* row = acc.ptr<float>(i);
            row[j] += static_cast<float>(w * (1.0 - f));
            row[j + 1] += static_cast<float>(w * f);
        }
    }
    cv::Mat sm;
    cv::blur(acc, sm, cv::Size(3, 3), cv::Point(-1, -1), cv::BORDER_CONSTANT);
    // Bin (i, j): centre t = i - t_reach, radius j + 0.5. Local maxima of the smoothed votes.
    const double min_votes = kMinCircleVotes * fraction / 9.0;
    std::vector<Circle> found;
    for (int i = 1; i < nt - 1; ++i) {
        const float* r0 = sm.ptr<float>(i - 1);
        const float* r1 = sm.ptr<float>(i);
        const float* r2 = sm.ptr<float>(i + 1);
        for (int j = 1; j < nr - 1; ++j) {
            const float v = r1[j];
            if (v < min_votes) continue;
            if (v < r1[j - 1] || v <= r1[j + 1] || v < r0[j - 1] || v < r0[j] || v < r0[j + 1] ||
                v <= r2[j - 1] || v <= r2[j] || v <= r2[j + 1])
                continue;
            // Sub-bin refinement: parabolas through the neighbours.
            auto vertex = [](double a, double b, double c) {
                const double den = a - 2.0 * b + c;
                return den < 0.0 ? std::clamp(0.5 * (a - c) / den, -0.5, 0.5) : 0.0;
            };
            const double di = vertex(r0[j], v, r2[j]);
            const double dj = vertex(r1[j - 1], v, r1[j + 1]);
            const double t = static_cast<double>(i) + di - t_reach;
            Circle c;
            c.centre_px = origin + t * dir;
            c.radius_px = static_cast<double>(j) + 0.5 + dj;
            if (c.radius_px < options.min_circle_radius_px) continue;
            // Votes of the 3 x 3 window over the visible arc, in edge pixels (not sampled).
            double arc = 0.0;
            forVisibleArc(c, width, height, excluded, 1.0,
                          [&](double, double, int n) { arc += 2.0 * M_PI * c.radius_px / n; });
            if (arc < kMinVisibleArcPx) continue;
            const double votes = 9.0 * v / fraction;
            if (votes < kMinCircleVotes) continue;
            c.support = votes / arc;
            if (c.support >= options.min_circle_support && std::isfinite(c.support))
                found.push_back(c);
        }
    }
    std::sort(found.begin(), found.end(),
              [](const Circle& a, const Circle& b) { return a.support > b.support; });
    for (const Circle& c : found) {
        bool distinct = true;
        for (const Circle& k : circles)
            if ((k.centre_px - c.centre_px).norm() <
                    std::max(kCircleSeparationPx, 0.1 * k.radius_px) &&
                std::abs(k.radius_px - c.radius_px) <
                    std::max(kCircleSeparationPx, 0.1 * k.radius_px)) {
                distinct = false;
                break;
            }
        if (distinct) circles.push_back(c);
        if (circles.size() >= static_cast<size_t>(options.max_circles)) break;
    }
    return circles;
}

}  // namespace

Result<FrameDetection> detectGhosts(const FitFrame& frame, const DetectOptions& options) {
    if (auto valid = validateOptions(options); !valid) return valid.error();
    const ImageRGB& image = frame.image;
    if (image.empty()) return makeError(ErrorCode::InvalidArgument, "detect: the image is empty");
    if (image.pixels.size() != static_cast<size_t>(image.width * image.height * 3))
        return makeError(ErrorCode::InvalidArgument,
                         "detect: the image holds a wrong number of values");
    if (!(frame.mapping.px_per_mm_x > 0.0) || !(frame.mapping.px_per_mm_y > 0.0) ||
        !std::isfinite(frame.mapping.px_per_mm_x) || !std::isfinite(frame.mapping.px_per_mm_y))
        return makeError(ErrorCode::InvalidArgument,
                         "detect: the frame's mapping must have finite px_per_mm > 0");
    const int64_t width = image.width;
    const int64_t height = image.height;
    const int64_t n = width * height;
    const int channels = frame.channels == 1 ? 1 : 3;

    FrameDetection detection;
    detection.excluded.assign(static_cast<size_t>(n), 0);

    // 1. Background and noise per channel.
    std::array<RobustLevel, 3> levels{};
    for (int c = 0; c < channels; ++c) levels[static_cast<size_t>(c)] = robustLevel(image, c);
    for (int c = channels; c < 3; ++c) levels[static_cast<size_t>(c)] = levels[0];

    // The signal: value - background summed over the fitted channels; 0 (and left out) where a
    // value is not finite.
    std::vector<float> signal(static_cast<size_t>(n));
    std::array<double, 3> largest{};  // largest |value - background| per channel
    for (int64_t i = 0; i < n; ++i) {
        const float* p = image.pixels.data() + i * 3;
        double s = 0.0;
        bool finite = true;
        for (int c = 0; c < channels; ++c) {
            const double d = static_cast<double>(p[c]) - levels[static_cast<size_t>(c)].median;
            if (!std::isfinite(d)) {
                finite = false;
                break;
            }
            largest[static_cast<size_t>(c)] =
                std::max(largest[static_cast<size_t>(c)], std::abs(d));
            s += d;
        }
        if (!finite) {
            detection.excluded[static_cast<size_t>(i)] = 1;
            s = 0.0;
        }
        signal[static_cast<size_t>(i)] = static_cast<float>(s);
    }
    // The floor keeps sigma > 0 on a constant, black or noise-free frame: a millionth of the
    // level, at least the smallest normal double, and where the frame shows no noise above a
    // millionth of its level, a billionth of the largest excursion. A frame with noise keeps its
    // own: the unclipped core of a planned bracket lies 1e11 above a sky whose noise is 1, and a
    // billionth of it had raised every threshold some seventyfold (no ghost found on the Heliar
    // from 6 to 10 deg while the light was in view).
    for (int c = 0; c < 3; ++c) {
        const auto& level = levels[static_cast<size_t>(std::min(c, channels - 1))];
        const double level_floor =
            std::max(1e-6 * std::abs(level.median), std::numeric_limits<double>::min());
        const double floor =
            level.sigma > level_floor
                ? level_floor
                : std::max(level_floor,
                           1e-9 * largest[static_cast<size_t>(std::min(c, channels - 1))]);
        detection.background[static_cast<size_t>(c)] = level.median;
        detection.noise_sigma[static_cast<size_t>(c)] = std::max(level.sigma, floor);
    }
    double sigma_sum2 = 0.0;  // independent channels: the variances add
    for (int c = 0; c < channels; ++c)
        sigma_sum2 += detection.noise_sigma[static_cast<size_t>(c)] *
                      detection.noise_sigma[static_cast<size_t>(c)];
    const double sigma_sum = std::sqrt(sigma_sum2);

    // 2. The light.
    if (options.find_light)
        detection.light = findLight(signal, width, height, sigma_sum, options, detection.excluded);

    // 3. Candidates: smoothed signal above the threshold, outside the excluded pixels. The
    // threshold uses the smoothed noise: white noise through the kernel k has sigma * sum(k^2)
    // (the 2-D kernel is the outer product of the 1-D one).
    const cv::Mat signal_mat(static_cast<int>(height), static_cast<int>(width), CV_32F,
                             signal.data());
    cv::Mat smoothed;
    double smoothed_sigma = sigma_sum;
    if (options.smoothing_px > 0.0) {
        int ksize = static_cast<int>(std::lround(options.smoothing_px * 8.0 + 1.0)) | 1;
        ksize = std::max(ksize, 3);
        cv::GaussianBlur(signal_mat, smoothed, cv::Size(ksize, ksize), options.smoothing_px,
                         options.smoothing_px, cv::BORDER_REFLECT);
        const cv::Mat kernel = cv::getGaussianKernel(ksize, options.smoothing_px, CV_64F);
        smoothed_sigma = sigma_sum * kernel.dot(kernel);
    } else {
        smoothed = signal_mat;
    }
    const double threshold = options.threshold_sigmas * smoothed_sigma;
    cv::Mat mask(static_cast<int>(height), static_cast<int>(width), CV_8U);
    for (int64_t y = 0; y < height; ++y) {
        const float* s = smoothed.ptr<float>(static_cast<int>(y));
        uint8_t* m = mask.ptr<uint8_t>(static_cast<int>(y));
        const uint8_t* e = detection.excluded.data() + y * width;
        for (int64_t x = 0; x < width; ++x) m[x] = (s[x] > threshold && !e[x]) ? 255 : 0;
    }
    cv::Mat labels, stats, centroids;
    const int label_count =
        cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S);
    if (label_count <= 1 || options.max_candidates == 0) return detection;

    // Pixels by label (a counting sort), so each component's values can be ranked.
    std::vector<int64_t> first(static_cast<size_t>(label_count) + 1, 0);
    for (int l = 1; l < label_count; ++l)
        first[static_cast<size_t>(l) + 1] =
            first[static_cast<size_t>(l)] + stats.at<int>(l, cv::CC_STAT_AREA);
    std::vector<int64_t> order(static_cast<size_t>(first[static_cast<size_t>(label_count)]));
    {
        std::vector<int64_t> next(first.begin(), first.end() - 1);
        for (int64_t y = 0; y < height; ++y) {
            const int* row = labels.ptr<int>(static_cast<int>(y));
            for (int64_t x = 0; x < width; ++x)
                if (row[x] > 0)
                    order[static_cast<size_t>(next[static_cast<size_t>(row[x])]++)] = y * width + x;
        }
    }

    const auto& map = frame.mapping;
    const double px_mm = 1.0 / std::min(map.px_per_mm_x, map.px_per_mm_y);
    std::vector<float> values;
    std::vector<int> cand_labels;  // each candidate's component
    for (int l = 1; l < label_count; ++l) {
        const int64_t area = stats.at<int>(l, cv::CC_STAT_AREA);
        if (area < options.min_area_px) continue;
        const auto* begin = order.data() + first[static_cast<size_t>(l)];
        const auto* end = order.data() + first[static_cast<size_t>(l) + 1];

        GhostCandidate cand;
        cand.area_px = area;
        cand.x0 = stats.at<int>(l, cv::CC_STAT_LEFT);
        cand.y0 = stats.at<int>(l, cv::CC_STAT_TOP);
        cand.x1 = cand.x0 + stats.at<int>(l, cv::CC_STAT_WIDTH) - 1;
        cand.y1 = cand.y0 + stats.at<int>(l, cv::CC_STAT_HEIGHT) - 1;
        cand.peak.fill(-std::numeric_limits<double>::infinity());
        double total = 0.0, wx = 0.0, wy = 0.0, wsum = 0.0, gx = 0.0, gy = 0.0;
        for (const int64_t* it = begin; it != end; ++it) {
            const int64_t i = *it;
            const float* p = image.pixels.data() + i * 3;
            for (int c = 0; c < channels; ++c) {
                const double d = p[c] - detection.background[static_cast<size_t>(c)];
                cand.energy[static_cast<size_t>(c)] += d;
                cand.peak[static_cast<size_t>(c)] = std::max(cand.peak[static_cast<size_t>(c)], d);
            }
            const double s = signal[static_cast<size_t>(i)];
            total += s;
            const double x = static_cast<double>(i % width) + 0.5;
            const double y = static_cast<double>(i / width) + 0.5;
            gx += x;
            gy += y;
            if (s > 0.0) {
                wsum += s;
                wx += s * x;
                wy += s * y;
            }
        }
        for (int c = channels; c < 3; ++c) {
            cand.energy[static_cast<size_t>(c)] = cand.energy[0];
            cand.peak[static_cast<size_t>(c)] = cand.peak[0];
        }
        // Energy test: the component's energy against its own noise, sigma sqrt(area).
        if (!(total > options.min_energy_sigmas * sigma_sum * std::sqrt(static_cast<double>(area))))
            continue;
        const double cx = wsum > 0.0 ? wx / wsum : gx / static_cast<double>(area);
        const double cy = wsum > 0.0 ? wy / wsum : gy / static_cast<double>(area);
        cand.centroid_px = {cx, cy};

        // Extents: from the centroid to the outer edges of the body pixels (smoothed value at
        // kBodyFraction of the component's 90th percentile or more), so the smoothing's fringe
        // around a bright ghost does not inflate them.
        // Quantiles on at most kQuantileSamples of its pixels: a frame-wide ghost stays cheap.
        const int64_t step = std::max<int64_t>(1, (area + kQuantileSamples - 1) / kQuantileSamples);
        values.clear();
        for (const int64_t* it = begin; it < end; it += step)
            values.push_back(smoothed.ptr<float>()[*it]);
        const double body_level =
            std::max(threshold, kBodyFraction * quantile(values, kBorderPercentile));
        int64_t bx0 = cand.x1, bx1 = cand.x0, by0 = cand.y1, by1 = cand.y0;
        for (const int64_t* it = begin; it != end; ++it) {
            if (smoothed.ptr<float>()[*it] < body_level) continue;
            const int64_t x = *it % width;
            const int64_t y = *it / width;
            bx0 = std::min(bx0, x);
            bx1 = std::max(bx1, x);
            by0 = std::min(by0, y);
            by1 = std::max(by1, y);
        }
        if (bx0 > bx1 || by0 > by1) {  // no body pixel (cannot happen at the 90th percentile)
            bx0 = cand.x0, bx1 = cand.x1, by0 = cand.y0, by1 = cand.y1;
        }
        // Half a pixel at least: the centroid lies within the component, not always the body.
        cand.left_px = std::max(0.5, cx - static_cast<double>(bx0));
        cand.right_px = std::max(0.5, static_cast<double>(bx1 + 1) - cx);
        cand.up_px = std::max(0.5, cy - static_cast<double>(by0));
        cand.down_px = std::max(0.5, static_cast<double>(by1 + 1) - cy);

        // Initial shape, sensor mm. The model's top and bottom are symmetric about its centre, so
        // the centre's y is the middle of the vertical extent, not the centroid.
        auto& shape = cand.initial.shape;
        shape.centre_x_mm = (cx - map.centre_x_px) / map.px_per_mm_x;
        shape.centre_y_mm =
            (cy + 0.5 * (cand.down_px - cand.up_px) - map.centre_y_px) / map.px_per_mm_y;
        shape.left_mm = cand.left_px / map.px_per_mm_x;
        shape.right_mm = cand.right_px / map.px_per_mm_x;
        shape.half_height_mm = 0.5 * (cand.up_px + cand.down_px) / map.px_per_mm_y;
        shape.left_handle_x_mm = render::kCircleHandle * shape.left_mm;
        shape.left_handle_y_mm = render::kCircleHandle * shape.half_height_mm;
        shape.right_handle_x_mm = render::kCircleHandle * shape.right_mm;
        shape.right_handle_y_mm = render::kCircleHandle * shape.half_height_mm;

        // Initial shading: the border from a high percentile of the component, the inside from
        // the median within half the extents around the centroid (any pixel there, lit or not:
        // a ring's dark middle is its inside).
        auto& shading = cand.initial.shading;
        const double ax = kInnerExtentFraction * 0.5 * (cand.left_px + cand.right_px);
        const double ay = kInnerExtentFraction * 0.5 * (cand.up_px + cand.down_px);
        for (int c = 0; c < channels; ++c) {
            values.clear();
            for (const int64_t* it = begin; it < end; it += step)
                values.push_back(image.pixels[static_cast<size_t>(*it * 3 + c)]);
            shading.border_rgb[static_cast<size_t>(c)] =
                std::max(0.0, quantile(values, kBorderPercentile) -
                                  detection.background[static_cast<size_t>(c)]);
            values.clear();
            const auto ix0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(cx - ax)));
            const auto ix1 = std::min(width - 1, static_cast<int64_t>(std::floor(cx + ax)));
            const auto iy0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(cy - ay)));
            const auto iy1 = std::min(height - 1, static_cast<int64_t>(std::floor(cy + ay)));
            const int64_t grid =
                std::max<int64_t>(1, static_cast<int64_t>(std::sqrt(static_cast<double>(step))));
            for (int64_t y = iy0; y <= iy1; y += grid) {
                const double ny = (static_cast<double>(y) + 0.5 - cy) / ay;
                for (int64_t x = ix0; x <= ix1; x += grid) {
                    const double nx = (static_cast<double>(x) + 0.5 - cx) / ax;
                    if (nx * nx + ny * ny > 1.0 ||
                        detection.excluded[static_cast<size_t>(y * width + x)])
                        continue;
                    values.push_back(image.pixels[static_cast<size_t>((y * width + x) * 3 + c)]);
                }
            }
            const double inner = values.empty() ? shading.border_rgb[static_cast<size_t>(c)]
                                                : quantile(values, 0.5) -
                                                      detection.background[static_cast<size_t>(c)];
            shading.inner_rgb[static_cast<size_t>(c)] =
                std::isfinite(inner) ? std::max(0.0, inner) : 0.0;
        }
        for (int c = channels; c < 3; ++c) {
            shading.border_rgb[static_cast<size_t>(c)] = shading.border_rgb[0];
            shading.inner_rgb[static_cast<size_t>(c)] = shading.inner_rgb[0];
        }
        const double min_extent_mm =
            std::min({shape.left_mm, shape.right_mm, shape.half_height_mm});
        shading.inner_falloff_mm = std::max(kFalloffFraction * min_extent_mm, px_mm);
        shading.outer_falloff_mm = shading.inner_falloff_mm;
        shading.inner_exponent = 1.0;
        shading.outer_exponent = 1.0;
        detection.candidates.push_back(cand);
        cand_labels.push_back(l);
    }

    // 4. Circles: a component holding two or more of them (overlapping ghosts) is replaced by them.
    if (options.circles) {
        const std::vector<Circle> circles = detectCircles(
            smoothed, smoothed_sigma, detection.excluded, detection.light, map, options);
        const double offset = kRimOffsetPx + options.smoothing_px;
        std::vector<int> circle_label(circles.size(), 0);
        std::vector<int> circles_in(static_cast<size_t>(label_count), 0);
        for (size_t k = 0; k < circles.size(); ++k) {
            const Circle& c = circles[k];
            Circle inner = c;
            inner.radius_px = std::max(0.5, c.radius_px - offset);
            std::vector<int> votes(static_cast<size_t>(label_count), 0);
            forVisibleArc(
                inner, width, height, detection.excluded, 2.0, [&](double ca, double sa, int) {
                    const auto x = static_cast<int>(inner.centre_px.x() + inner.radius_px * ca);
                    const auto y = static_cast<int>(inner.centre_px.y() + inner.radius_px * sa);
                    ++votes[static_cast<size_t>(labels.at<int>(y, x))];
                });
            votes[0] = 0;
            const auto best = std::max_element(votes.begin(), votes.end());
            if (*best > 0) {
                circle_label[k] = static_cast<int>(best - votes.begin());
                ++circles_in[static_cast<size_t>(circle_label[k])];
            }
        }
        std::vector<uint8_t> kept_label(static_cast<size_t>(label_count), 0);
        for (int l : cand_labels) kept_label[static_cast<size_t>(l)] = 1;
        std::vector<GhostCandidate> merged;
        for (size_t k = 0; k < detection.candidates.size(); ++k)
            if (circles_in[static_cast<size_t>(cand_labels[k])] < 2)
                merged.push_back(std::move(detection.candidates[k]));
        for (size_t k = 0; k < circles.size(); ++k) {
            const int l = circle_label[k];
            if (l == 0 || !kept_label[static_cast<size_t>(l)] ||
                circles_in[static_cast<size_t>(l)] < 2)
                continue;
            const Circle& c = circles[k];
            GhostCandidate cand;
            cand.centroid_px = c.centre_px;
            const double r = c.radius_px;
            cand.x0 = std::clamp<int64_t>(static_cast<int64_t>(std::floor(c.centre_px.x() - r)), 0,
                                          width - 1);
            cand.x1 = std::clamp<int64_t>(static_cast<int64_t>(std::floor(c.centre_px.x() + r)), 0,
                                          width - 1);
            cand.y0 = std::clamp<int64_t>(static_cast<int64_t>(std::floor(c.centre_px.y() - r)), 0,
                                          height - 1);
            cand.y1 = std::clamp<int64_t>(static_cast<int64_t>(std::floor(c.centre_px.y() + r)), 0,
                                          height - 1);
            int64_t area = 0;
            for (int64_t y = cand.y0; y <= cand.y1; ++y) {
                const double dy = static_cast<double>(y) + 0.5 - c.centre_px.y();
                const double h2 = r * r - dy * dy;
                if (h2 < 0.0) continue;
                const double h = std::sqrt(h2);
                const int64_t xa = std::max<int64_t>(
                    0, static_cast<int64_t>(std::ceil(c.centre_px.x() - h - 0.5)));
                const int64_t xb = std::min<int64_t>(
                    width - 1, static_cast<int64_t>(std::floor(c.centre_px.x() + h - 0.5)));
                if (xb >= xa) area += xb - xa + 1;
            }
            cand.area_px = std::max<int64_t>(1, area);
            cand.left_px = cand.right_px = cand.up_px = cand.down_px = r;
            // The ghost's own level: the jump of the value across its rim (median over the arc),
            // which the ghosts it overlaps do not change.
            std::array<double, 3> jump{};
            for (int ch = 0; ch < channels; ++ch) {
                values.clear();
                forVisibleArc(c, width, height, detection.excluded, 1.0,
                              [&](double ca, double sa, int) {
                                  const double xi = c.centre_px.x() + (r - offset) * ca;
                                  const double yi = c.centre_px.y() + (r - offset) * sa;
                                  const double xo = c.centre_px.x() + (r + offset) * ca;
                                  const double yo = c.centre_px.y() + (r + offset) * sa;
                                  if (!(xi >= 0 && yi >= 0 && xo >= 0 && yo >= 0 && xi < width &&
                                        xo < width && yi < height && yo < height))
                                      return;
                                  const int64_t ii =
                                      static_cast<int64_t>(yi) * width + static_cast<int64_t>(xi);
                                  const int64_t io =
                                      static_cast<int64_t>(yo) * width + static_cast<int64_t>(xo);
                                  if (detection.excluded[static_cast<size_t>(ii)] ||
                                      detection.excluded[static_cast<size_t>(io)])
                                      return;
                                  values.push_back(image.pixels[static_cast<size_t>(ii * 3 + ch)] -
                                                   image.pixels[static_cast<size_t>(io * 3 + ch)]);
                              });
                const double q = quantile(values, 0.5);
                jump[static_cast<size_t>(ch)] = std::isfinite(q) ? std::max(0.0, q) : 0.0;
            }
            for (int ch = channels; ch < 3; ++ch) jump[static_cast<size_t>(ch)] = jump[0];
            for (int ch = 0; ch < 3; ++ch) {
                cand.energy[static_cast<size_t>(ch)] =
                    jump[static_cast<size_t>(ch)] * static_cast<double>(cand.area_px);
                cand.peak[static_cast<size_t>(ch)] = jump[static_cast<size_t>(ch)];
            }
            auto& shape = cand.initial.shape;
            shape.centre_x_mm = (c.centre_px.x() - map.centre_x_px) / map.px_per_mm_x;
            shape.centre_y_mm = (c.centre_px.y() - map.centre_y_px) / map.px_per_mm_y;
            shape.left_mm = shape.right_mm = r / map.px_per_mm_x;
            shape.half_height_mm = r / map.px_per_mm_y;
            shape.left_handle_x_mm = shape.right_handle_x_mm =
                render::kCircleHandle * shape.left_mm;
            shape.left_handle_y_mm = shape.right_handle_y_mm =
                render::kCircleHandle * shape.half_height_mm;
            auto& shading = cand.initial.shading;
            shading.border_rgb = jump;
            shading.inner_rgb = jump;
            shading.inner_falloff_mm = std::max(1.5, options.smoothing_px) * px_mm;
            shading.outer_falloff_mm = shading.inner_falloff_mm;
            shading.inner_exponent = 1.0;
            shading.outer_exponent = 1.0;
            merged.push_back(std::move(cand));
        }
        detection.candidates = std::move(merged);
    }

    auto totalEnergy = [](const GhostCandidate& g) {
        return g.energy[0] + g.energy[1] + g.energy[2];
    };
    std::stable_sort(detection.candidates.begin(), detection.candidates.end(),
                     [&](const GhostCandidate& a, const GhostCandidate& b) {
                         return totalEnergy(a) > totalEnergy(b);
                     });
    if (detection.candidates.size() > static_cast<size_t>(options.max_candidates))
        detection.candidates.resize(static_cast<size_t>(options.max_candidates));
    return detection;
}

}  // namespace flarelab::fit
