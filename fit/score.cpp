#include "fit/score.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>

namespace flarelab::fit {
namespace {

ScoreSummary summarize(const std::vector<AngleScore>& scores, bool held_out) {
    std::vector<double> values, psnr;
    ScoreSummary s;
    for (const AngleScore& a : scores) {
        if (a.held_out != held_out) continue;
        values.push_back(a.rel_l2);
        psnr.push_back(a.psnr_db);
        if (s.count == 0 || a.rel_l2 > s.worst) {
            s.worst = a.rel_l2;
            s.worst_angle_deg = a.angle_deg;
        }
        ++s.count;
    }
    if (values.empty()) return s;
    const auto median = [](std::vector<double> v) {
        std::sort(v.begin(), v.end());
        const size_t n = v.size();
        return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
    };
    s.median = median(values);
    s.median_psnr_db = median(psnr);
    return s;
}

// `count` items of `v` spread evenly (all of them when count >= size).
std::vector<double> spread(const std::vector<double>& v, int count) {
    if (count <= 0 || v.empty()) return {};
    if (static_cast<size_t>(count) >= v.size()) return v;
    std::vector<double> out;
    for (int i = 0; i < count; ++i) {
        const size_t k = count == 1
                             ? v.size() / 2
                             : static_cast<size_t>(std::llround(static_cast<double>(i) *
                                                                static_cast<double>(v.size() - 1) /
                                                                static_cast<double>(count - 1)));
        if (out.empty() || out.back() != v[k]) out.push_back(v[k]);
    }
    return out;
}

}  // namespace

Result<std::pair<std::vector<double>, std::vector<double>>> scoreAngles(
    const FlareModel& model, const ScoreOptions& options) {
    if (options.halfway_angles < 0 || options.random_angles < 0 || options.fit_angles < 0)
        return makeError(ErrorCode::InvalidArgument, "score: angle counts must be >= 0");
    const double from = model.valid_from_deg, to = model.valid_to_deg;
    const double step = model.capture.step_deg;
    if (!(step > 0.0))
        return makeError(ErrorCode::InvalidArgument, "score: the model's step is not > 0");
    std::vector<double> captured;
    for (int64_t i = 0;; ++i) {
        const double a = model.capture.from_deg + static_cast<double>(i) * step;
        if (a > to + 1e-9 || i > 1'000'000) break;
        if (a >= from - 1e-9) captured.push_back(std::clamp(a, from, to));
    }
    std::vector<double> held;
    if (!options.angles_deg.empty()) {
        for (double a : options.angles_deg) {
            if (!std::isfinite(a) || a < from || a > to)
                return makeError(ErrorCode::InvalidArgument,
                                 "score: angle " + std::to_string(a) +
                                     " deg lies outside the model's valid range");
            held.push_back(a);
        }
    } else {
        std::vector<double> halfway;
        for (size_t i = 0; i + 1 < captured.size(); ++i)
            halfway.push_back(0.5 * (captured[i] + captured[i + 1]));
        held = spread(halfway, options.halfway_angles);
        std::mt19937_64 rng(options.seed);
        std::uniform_real_distribution<double> uniform(from, to);
        for (int i = 0; i < options.random_angles; ++i) held.push_back(uniform(rng));
    }
    std::sort(held.begin(), held.end());
    return std::make_pair(spread(captured, options.fit_angles), held);
}

Result<AngleScore> compareImages(const ImageRGB& model,
                                 const ImageRGB& truth,
                                 std::optional<Eigen::Vector2d> light_px,
                                 double light_mask_px) {
    if (model.width != truth.width || model.height != truth.height)
        return makeError(ErrorCode::InvalidArgument, "score: model and truth differ in size");
    double num = 0.0, den = 0.0, peak = 0.0, energy = 0.0;
    int64_t count = 0;
    const double r2 = light_mask_px * light_mask_px;
    for (int64_t y = 0; y < truth.height; ++y) {
        for (int64_t x = 0; x < truth.width; ++x) {
            if (light_px) {
                const double dx = static_cast<double>(x) + 0.5 - light_px->x();
                const double dy = static_cast<double>(y) + 0.5 - light_px->y();
                if (dx * dx + dy * dy <= r2) continue;
            }
            const float* m = model.at(x, y);
            const float* t = truth.at(x, y);
            for (int c = 0; c < 3; ++c) {
                const double d = static_cast<double>(m[c]) - t[c];
                num += d * d;
                den += static_cast<double>(t[c]) * t[c];
                peak = std::max(peak, static_cast<double>(t[c]));
                energy += t[c];
            }
            count += 3;
        }
    }
    AngleScore s;
    s.truth_energy = energy;
    if (!std::isfinite(num) || !std::isfinite(den))
        return makeError(ErrorCode::Internal, "score: the images hold non-finite values");
    s.rel_l2 = den > 0.0 ? std::sqrt(num / den) : (num > 0.0 ? 1.0 : 0.0);
    const double mse = count > 0 ? num / static_cast<double>(count) : 0.0;
    s.psnr_db = mse > 0.0 && peak > 0.0 ? 10.0 * std::log10(peak * peak / mse)
                                        : std::numeric_limits<double>::infinity();
    if (!std::isfinite(s.psnr_db)) s.psnr_db = 999.0;  // identical images: reported as 999 dB
    return s;
}

Result<ScoreReport> scoreModel(const FlareModel& model,
                               const TruthSource& truth,
                               const ScoreOptions& options,
                               const std::function<void(int, int)>& progress) {
    auto angles = scoreAngles(model, options);
    if (!angles) return angles.error();
    const int64_t w = model.capture.width_px, h = model.capture.height_px;
    const double mask = options.light_mask_px >= 0.0
                            ? options.light_mask_px
                            : 0.03 * std::hypot(static_cast<double>(w), static_cast<double>(h));
    ScoreReport report;
    const int total = static_cast<int>(angles->first.size() + angles->second.size());
    int done = 0;
    for (int pass = 0; pass < 2; ++pass) {
        const auto& list = pass == 0 ? angles->first : angles->second;
        for (double angle : list) {
            auto t = truth(angle);
            if (!t)
                return t.error().withContext("score: truth at " + std::to_string(angle) + " deg");
            if (t->image.width != w || t->image.height != h)
                return makeError(ErrorCode::Internal, "score: the truth is not the capture's size");
            auto drawn = renderModel(model, angle, model.capture.roll_deg, w, h, options.render);
            if (!drawn) return drawn.error();
            auto s = compareImages(*drawn, t->image, t->light_px, mask);
            if (!s) return s.error();
            s->angle_deg = angle;
            s->held_out = pass == 1;
            report.angles.push_back(*s);
            if (progress) progress(++done, total);
        }
    }
    report.fit_rel_l2 = summarize(report.angles, false);
    report.heldout_rel_l2 = summarize(report.angles, true);
    return report;
}

}  // namespace flarelab::fit
