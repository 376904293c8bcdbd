#include "predict/figures.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <numbers>
#include <span>
#include <string>
#include <vector>

#include "common/check.h"
#include "fit/model_eval.h"

namespace flarelab::predict {
namespace {

double luminance(const float* rgb) { return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]; }

// The figures of a frame's luminances (the header's definitions); all 0 for none.
FlareFigures figuresOf(std::span<const double> y) {
    FlareFigures f;
    if (y.empty()) return f;
    double min = std::numeric_limits<double>::infinity(), max = 0.0, sum = 0.0;
    for (double v : y) {
        // A renderer never writes a negative value; clamp one that rounding left at -0.
        v = std::max(0.0, v);
        min = std::min(min, v);
        max = std::max(max, v);
        sum += v;
    }
    const double n = static_cast<double>(y.size());
    f.min = min;
    f.max = max;
    f.mean = sum / n;
    f.total = sum;
    if (max > 0.0) {
        const double floor = kLogAverageFloor * max;
        double log_sum = 0.0;
        for (double v : y) log_sum += std::log(std::max(floor, v));
        f.log_average = std::exp(log_sum / n);
    }
    return f;
}

}  // namespace

FlareFigures flareFigures(const ImageRGB& image) {
    std::vector<double> y(static_cast<size_t>(image.width * image.height));
    for (size_t k = 0; k < y.size(); ++k) y[k] = luminance(image.pixels.data() + 3 * k);
    return figuresOf(y);
}

double contrastRatio(double scene_min, double scene_max, double flare) {
    FLARELAB_CHECK(scene_min >= 0.0 && scene_max >= scene_min && scene_max > 0.0);
    FLARELAB_CHECK(flare >= 0.0);
    const double s = scene_max + scene_min;
    return s / (s + 2.0 * flare);
}

double glareIndicator(double scene_log_average, double flare_mean) {
    FLARELAB_CHECK(scene_log_average > 0.0 && std::isfinite(scene_log_average));
    FLARELAB_CHECK(flare_mean >= 0.0);
    return flare_mean / scene_log_average;
}

std::pair<double, double> coveredTheta(const fit::FlareModel& model) {
    const double lo = model.valid_from_deg, hi = model.valid_to_deg;
    if (hi <= 0.0) return {-hi, -lo};
    if (lo < 0.0) return {0.0, std::max(-lo, hi)};
    return {lo, hi};
}

Result<FlareFigureTable> FlareFigureTable::build(const fit::FlareModel& model,
                                                 const FigureTableOptions& options) {
    if (!(options.theta_step_deg >= 0.0 && options.theta_step_deg <= 10.0))
        return makeError(ErrorCode::InvalidArgument,
                         "figure table: theta_step_deg must lie in [0, 10] (0: the capture's)");
    const double phi_turns = 360.0 / options.phi_step_deg;
    if (!(options.phi_step_deg > 0.0 && options.phi_step_deg <= 90.0) ||
        std::abs(phi_turns - std::round(phi_turns)) > 1e-9)
        return makeError(ErrorCode::InvalidArgument,
                         "figure table: phi_step_deg must lie in (0, 90] and divide 360");
    if (options.width < 8 || options.width > 4096)
        return makeError(ErrorCode::InvalidArgument, "figure table: width must lie in 8..4096");
    if (options.field_points.size() > 8)
        return makeError(ErrorCode::InvalidArgument, "figure table: at most 8 field points");
    for (double h : options.field_points)
        if (!(h > 0.0 && h <= 1.0))
            return makeError(ErrorCode::InvalidArgument,
                             "figure table: field points must lie in (0, 1] (of the half-diagonal)");
    if (!(model.lens.sensor_width_mm > 0.0 && model.lens.sensor_height_mm > 0.0))
        return makeError(ErrorCode::InvalidArgument, "figure table: the model has no sensor size");
    // theta >= 0; a model of negative head angles covers |angle| (playback.h).
    const auto [from, to] = coveredTheta(model);
    if (!(to > from))
        return makeError(ErrorCode::InvalidArgument,
                         "figure table: the model covers no range of angles at or above 0");
    double step = options.theta_step_deg > 0.0 ? options.theta_step_deg
                                               : std::min(0.5, model.capture.step_deg);
    if (!(step > 0.0)) step = 0.5;
    FlareFigureTable t;
    t.theta_from_deg_ = from;
    t.theta_to_deg_ = to;
    t.theta_count_ = static_cast<int64_t>(std::ceil((to - from) / step - 1e-9)) + 1;
    t.theta_step_deg_ = (to - from) / static_cast<double>(t.theta_count_ - 1);
    t.phi_step_deg_ = options.phi_step_deg;
    t.phi_count_ = static_cast<int64_t>(std::round(phi_turns));
    t.capture_pixels_ =
        static_cast<double>(model.capture.width_px) * static_cast<double>(model.capture.height_px);
    const int64_t width = options.width;
    const int64_t height =
        std::max<int64_t>(1, std::llround(static_cast<double>(width) * model.lens.sensor_height_mm /
                                          model.lens.sensor_width_mm));
    t.nodes_.resize(static_cast<size_t>(t.theta_count_ * t.phi_count_));
    t.centre_.resize(static_cast<size_t>(t.theta_count_));
    t.field_points_ = options.field_points;
    t.field_.assign(t.field_points_.size(),
                    std::vector<double>(static_cast<size_t>(t.theta_count_ * t.phi_count_), 0.0));
    // One drawing per theta serves every roll: the ghosts at roll 0 on a square canvas as wide
    // as the frame's diagonal, and for each roll the canvas pixels that the frame, turned the
    // other way, covers (a pixel p of the frame at roll phi sees the canvas at R(-phi) p).
    const double px_per_mm = static_cast<double>(width) / model.lens.sensor_width_mm;
    const double half_w = 0.5 * static_cast<double>(width);
    const double half_h = 0.5 * static_cast<double>(height);
    const int64_t side = static_cast<int64_t>(std::ceil(2.0 * std::hypot(half_w, half_h))) + 2;
    render::SensorToImage mapping;
    mapping.px_per_mm_x = mapping.px_per_mm_y = px_per_mm;
    mapping.centre_x_px = mapping.centre_y_px = 0.5 * static_cast<double>(side);
    std::atomic<bool> failed{false};
    Error first_error;
    std::atomic_flag error_taken = ATOMIC_FLAG_INIT;
    tbb::parallel_for(int64_t{0}, t.theta_count_, [&](int64_t i) {
        if (failed.load(std::memory_order_relaxed)) return;
        if (options.stop_requested && options.stop_requested()) {
            if (!error_taken.test_and_set())
                first_error = makeError(ErrorCode::Unsupported, "stopped");
            failed.store(true);
            return;
        }
        const double theta = t.thetaAt(i);
        // The roll that shows the light at phi 0 (model_eval.h: a negative head angle is the
        // light at |angle| turned half a turn).
        double angle = theta, roll = 0.0;
        if (!(theta >= model.valid_from_deg && theta <= model.valid_to_deg)) {
            angle = -theta;
            roll = 180.0;
        }
        auto ghosts = fit::modelGhostsAt(model, angle, roll);
        if (!ghosts) {
            if (!error_taken.test_and_set()) first_error = ghosts.error();
            failed.store(true);
            return;
        }
        std::vector<fit::GhostState> states;
        for (const auto& g : *ghosts) states.push_back(g.state);
        const ImageRGB canvas = fit::renderGhostStates(states, mapping, side, side);
        std::vector<double> y(static_cast<size_t>(side * side));
        for (size_t k = 0; k < y.size(); ++k) y[k] = luminance(canvas.pixels.data() + 3 * k);
        // The image centre: roll turns about it, so one value serves every phi. The pixels within
        // 1.5 of it (a few), averaged.
        double centre_sum = 0.0;
        int centre_count = 0;
        for (int64_t v = 0; v < side; ++v)
            for (int64_t u = 0; u < side; ++u) {
                const double dx = static_cast<double>(u) + 0.5 - mapping.centre_x_px;
                const double dy = static_cast<double>(v) + 0.5 - mapping.centre_y_px;
                if (dx * dx + dy * dy <= 2.25) {
                    centre_sum += std::max(0.0, y[static_cast<size_t>(v * side + u)]);
                    ++centre_count;
                }
            }
        t.centre_[static_cast<size_t>(i)] = centre_count > 0 ? centre_sum / centre_count : 0.0;
        // The field points: the frame's point p at roll phi sees the canvas at R(-phi) p,
        // sampled bilinearly.
        for (size_t k = 0; k < t.field_points_.size(); ++k) {
            const double px = t.field_points_[k] * half_w, py = t.field_points_[k] * half_h;
            for (int64_t j = 0; j < t.phi_count_; ++j) {
                const double phi = t.phiAt(j) * std::numbers::pi / 180.0;
                const double c = std::cos(phi), s = std::sin(phi);
                const double u = c * px + s * py + mapping.centre_x_px - 0.5;
                const double v = -s * px + c * py + mapping.centre_y_px - 0.5;
                const int64_t u0 = std::clamp<int64_t>(static_cast<int64_t>(std::floor(u)), 0,
                                                       side - 2);
                const int64_t v0 = std::clamp<int64_t>(static_cast<int64_t>(std::floor(v)), 0,
                                                       side - 2);
                const double a = std::clamp(u - static_cast<double>(u0), 0.0, 1.0);
                const double b = std::clamp(v - static_cast<double>(v0), 0.0, 1.0);
                const auto at = [&](int64_t x, int64_t yy) {
                    return std::max(0.0, y[static_cast<size_t>(yy * side + x)]);
                };
                t.field_[k][static_cast<size_t>(i * t.phi_count_ + j)] =
                    (1 - a) * (1 - b) * at(u0, v0) + a * (1 - b) * at(u0 + 1, v0) +
                    (1 - a) * b * at(u0, v0 + 1) + a * b * at(u0 + 1, v0 + 1);
            }
        }
        std::vector<double> inside;
        inside.reserve(y.size());
        for (int64_t j = 0; j < t.phi_count_; ++j) {
            const double phi = t.phiAt(j) * std::numbers::pi / 180.0;
            const double c = std::cos(phi), s = std::sin(phi);
            inside.clear();
            for (int64_t v = 0; v < side; ++v) {
                const double qy = static_cast<double>(v) + 0.5 - mapping.centre_y_px;
                for (int64_t u = 0; u < side; ++u) {
                    const double qx = static_cast<double>(u) + 0.5 - mapping.centre_x_px;
                    const double px = c * qx - s * qy, py = s * qx + c * qy;
                    if (std::abs(px) <= half_w && std::abs(py) <= half_h)
                        inside.push_back(y[static_cast<size_t>(v * side + u)]);
                }
            }
            FlareFigures f = figuresOf(inside);
            f.total = f.mean * t.capture_pixels_;
            t.nodes_[static_cast<size_t>(i * t.phi_count_ + j)] = f;
        }
    });
    if (failed.load()) return first_error.withContext("figure table");
    return t;
}

double FlareFigureTable::thetaAt(int64_t i) const {
    return i == theta_count_ - 1 ? theta_to_deg_
                                 : theta_from_deg_ + static_cast<double>(i) * theta_step_deg_;
}

std::optional<FlareFigures> FlareFigureTable::at(double theta_deg, double phi_deg) const {
    if (!(theta_deg >= theta_from_deg_ && theta_deg <= theta_to_deg_) || !std::isfinite(phi_deg))
        return std::nullopt;
    const double u = (theta_deg - theta_from_deg_) / theta_step_deg_;
    const int64_t i = std::min<int64_t>(static_cast<int64_t>(u), theta_count_ - 2);
    const double a = std::clamp(u - static_cast<double>(i), 0.0, 1.0);
    double p = std::fmod(phi_deg, 360.0);
    if (p < 0.0) p += 360.0;
    const double v = p / phi_step_deg_;
    const int64_t j = std::min<int64_t>(static_cast<int64_t>(v), phi_count_ - 1);
    const double b = std::clamp(v - static_cast<double>(j), 0.0, 1.0);
    const int64_t j1 = (j + 1) % phi_count_;
    const auto mix = [&](double FlareFigures::*field) {
        return (1 - a) * (1 - b) * node(i, j).*field + (1 - a) * b * node(i, j1).*field +
               a * (1 - b) * node(i + 1, j).*field + a * b * node(i + 1, j1).*field;
    };
    FlareFigures f;
    f.min = mix(&FlareFigures::min);
    f.max = mix(&FlareFigures::max);
    f.mean = mix(&FlareFigures::mean);
    f.log_average = mix(&FlareFigures::log_average);
    f.total = mix(&FlareFigures::total);
    return f;
}

}  // namespace flarelab::predict
