#include "fit/score.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <random>
#include <string>

namespace flarelab::fit {
namespace {

double median(std::vector<double> v) {
    if (v.empty()) return 0.0;
    std::sort(v.begin(), v.end());
    const size_t n = v.size();
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// The scores that `keep` selects, summarized.
template <typename Keep>
ScoreSummary summarize(const std::vector<AngleScore>& scores, Keep keep) {
    std::vector<double> values, psnr, energy, log_l2, masked, missed;
    ScoreSummary s;
    for (const AngleScore& a : scores) {
        if (!keep(a)) continue;
        values.push_back(a.rel_l2);
        psnr.push_back(a.psnr_db);
        energy.push_back(std::abs(a.energy_error));
        log_l2.push_back(a.log_rel_l2);
        masked.push_back(a.masked_energy_fraction);
        missed.push_back(a.missed_light);
        if (s.count == 0 || a.rel_l2 > s.worst) {
            s.worst = a.rel_l2;
            s.worst_angle_deg = a.angle_deg;
        }
        s.worst_abs_energy_error = std::max(s.worst_abs_energy_error, std::abs(a.energy_error));
        s.worst_log_rel_l2 = std::max(s.worst_log_rel_l2, a.log_rel_l2);
        ++s.count;
    }
    s.median = median(values);
    s.median_psnr_db = median(psnr);
    s.median_abs_energy_error = median(energy);
    s.median_log_rel_l2 = median(log_l2);
    s.median_masked_energy_fraction = median(masked);
    s.median_missed_light = median(missed);
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

const char* angleKindName(AngleKind kind) {
    switch (kind) {
        case AngleKind::Fitted:
            return "fitted";
        case AngleKind::LeftOut:
            return "left-out";
        case AngleKind::Halfway:
            return "half-way";
        case AngleKind::Random:
            return "random";
        case AngleKind::Given:
            return "given";
    }
    return "?";
}

Result<std::vector<ScoredAngle>> scoreAngles(const FlareModel& model, const ScoreOptions& options) {
    if (options.halfway_angles < 0 || options.random_angles < 0 || options.fit_angles < 0 ||
        options.left_out_angles < 0)
        return makeError(ErrorCode::InvalidArgument, "score: angle counts must be >= 0");
    const double from = model.valid_from_deg, to = model.valid_to_deg;
    const double step = model.capture.step_deg;
    if (!(step > 0.0))
        return makeError(ErrorCode::InvalidArgument, "score: the model's step is not > 0");
    const auto inside = [&](double a, const char* what) -> Status {
        if (!std::isfinite(a) || a < from - 1e-9 || a > to + 1e-9)
            return makeError(ErrorCode::InvalidArgument,
                             std::string("score: ") + what + " angle " + std::to_string(a) +
                                 " deg lies outside the model's valid range " +
                                 std::to_string(from) + " to " + std::to_string(to) + " deg");
        return Ok{};
    };
    std::vector<double> captured;
    for (int64_t i = 0;; ++i) {
        const double a = model.capture.from_deg + static_cast<double>(i) * step;
        if (a > to + 1e-9 || i > 1'000'000) break;
        if (a >= from - 1e-9) captured.push_back(std::clamp(a, from, to));
    }
    std::vector<ScoredAngle> out;
    for (double a : spread(captured, options.fit_angles)) out.push_back({a, AngleKind::Fitted});
    std::vector<ScoredAngle> held;
    // An angle within this of one already taken is not scored twice.
    constexpr double kSameDeg = 1e-6;
    const auto add = [&](double a, AngleKind kind) {
        for (const ScoredAngle& h : held)
            if (std::abs(h.angle_deg - a) <= kSameDeg) return;
        held.push_back({a, kind});
    };
    std::vector<double> left_out;
    for (double a : options.left_out_deg) {
        if (Status ok = inside(a, "left-out"); !ok) return ok.error();
        left_out.push_back(std::clamp(a, from, to));
    }
    std::sort(left_out.begin(), left_out.end());
    for (double a : spread(left_out, options.left_out_angles)) add(a, AngleKind::LeftOut);
    if (!options.angles_deg.empty()) {
        for (double a : options.angles_deg) {
            if (Status ok = inside(a, "given"); !ok) return ok.error();
            add(std::clamp(a, from, to), AngleKind::Given);
        }
    } else {
        // Half-way angles that are frames the fit left out are that kind's, scored or not.
        std::vector<double> halfway;
        for (size_t i = 0; i + 1 < captured.size(); ++i) {
            const double a = 0.5 * (captured[i] + captured[i + 1]);
            if (std::none_of(left_out.begin(), left_out.end(),
                             [&](double l) { return std::abs(l - a) <= kSameDeg; }))
                halfway.push_back(a);
        }
        for (double a : spread(halfway, options.halfway_angles)) add(a, AngleKind::Halfway);
        std::mt19937_64 rng(options.seed);
        std::uniform_real_distribution<double> uniform(from, to);
        for (int i = 0; i < options.random_angles; ++i) add(uniform(rng), AngleKind::Random);
    }
    std::sort(held.begin(), held.end(),
              [](const ScoredAngle& a, const ScoredAngle& b) { return a.angle_deg < b.angle_deg; });
    out.insert(out.end(), held.begin(), held.end());
    return out;
}

double toneMapScore(double v, double peak, double log_scale) {
    if (!(peak > 0.0) || !(log_scale > 0.0)) return 0.0;
    const double s = log_scale * peak;
    return std::log1p(std::max(v, 0.0) / s) / std::log1p(peak / s);
}

Result<AngleScore> compareImages(const ImageRGB& model,
                                 const ImageRGB& truth,
                                 std::optional<Eigen::Vector2d> light_px,
                                 double light_mask_px,
                                 double log_scale) {
    if (model.width != truth.width || model.height != truth.height)
        return makeError(ErrorCode::InvalidArgument, "score: model and truth differ in size");
    if (!(log_scale > 0.0) || !std::isfinite(log_scale))
        return makeError(ErrorCode::InvalidArgument, "score: log_scale must be > 0");
    // Pass 1: the plain sums and the peak; pass 2 the log image, which needs the peak.
    const double r2 = light_mask_px * light_mask_px;
    const auto masked = [&](int64_t x, int64_t y) {
        if (!light_px) return false;
        const double dx = static_cast<double>(x) + 0.5 - light_px->x();
        const double dy = static_cast<double>(y) + 0.5 - light_px->y();
        return dx * dx + dy * dy <= r2;
    };
    double num = 0.0, den = 0.0, peak = 0.0, energy = 0.0, model_energy = 0.0, in_mask = 0.0,
           under = 0.0;
    int64_t count = 0;
    for (int64_t y = 0; y < truth.height; ++y) {
        for (int64_t x = 0; x < truth.width; ++x) {
            const float* m = model.at(x, y);
            const float* t = truth.at(x, y);
            if (masked(x, y)) {
                for (int c = 0; c < 3; ++c) in_mask += t[c];
                continue;
            }
            for (int c = 0; c < 3; ++c) {
                const double d = static_cast<double>(m[c]) - t[c];
                num += d * d;
                den += static_cast<double>(t[c]) * t[c];
                peak = std::max(peak, static_cast<double>(t[c]));
                energy += t[c];
                model_energy += m[c];
                under += std::max(0.0, static_cast<double>(t[c]) - m[c]);
            }
            count += 3;
        }
    }
    if (!std::isfinite(num) || !std::isfinite(den) || !std::isfinite(model_energy) ||
        !std::isfinite(in_mask))
        return makeError(ErrorCode::Internal, "score: the images hold non-finite values");
    double log_num = 0.0, log_den = 0.0;
    if (peak > 0.0) {
        for (int64_t y = 0; y < truth.height; ++y) {
            for (int64_t x = 0; x < truth.width; ++x) {
                if (masked(x, y)) continue;
                const float* m = model.at(x, y);
                const float* t = truth.at(x, y);
                for (int c = 0; c < 3; ++c) {
                    const double lt = toneMapScore(t[c], peak, log_scale);
                    const double lm = toneMapScore(m[c], peak, log_scale);
                    log_num += (lm - lt) * (lm - lt);
                    log_den += lt * lt;
                }
            }
        }
    }
    AngleScore s;
    s.truth_energy = energy;
    s.model_energy = model_energy;
    s.rel_l2 = den > 0.0 ? std::sqrt(num / den) : (num > 0.0 ? 1.0 : 0.0);
    s.energy_error =
        energy > 0.0 ? (model_energy - energy) / energy : (model_energy > 0.0 ? 1.0 : 0.0);
    // A black truth: anything the model draws is all error, as for rel_l2.
    s.log_rel_l2 = log_den > 0.0 ? std::sqrt(log_num / log_den) : (num > 0.0 ? 1.0 : 0.0);
    s.masked_energy_fraction = energy + in_mask > 0.0 ? in_mask / (energy + in_mask) : 0.0;
    s.missed_light = energy > 0.0 ? under / energy : 0.0;
    s.light_mask_px = light_px ? light_mask_px : 0.0;
    const double mse = count > 0 ? num / static_cast<double>(count) : 0.0;
    s.psnr_db = mse > 0.0 && peak > 0.0 ? 10.0 * std::log10(peak * peak / mse)
                                        : std::numeric_limits<double>::infinity();
    if (!std::isfinite(s.psnr_db)) s.psnr_db = 999.0;  // identical images: reported as 999 dB
    return s;
}

std::optional<double> lightDiscRadius(const FlareModel& model, double angle_deg) {
    const std::vector<ModelLightDisc>& discs = model.capture.light_discs;
    if (discs.empty()) return std::nullopt;
    const auto after = std::lower_bound(
        discs.begin(), discs.end(), angle_deg,
        [](const ModelLightDisc& d, double angle) { return d.angle_deg < angle; });
    if (after == discs.end()) return discs.back().radius_px;
    if (after == discs.begin() || after->angle_deg == angle_deg) return after->radius_px;
    const ModelLightDisc& a = *(after - 1);
    const ModelLightDisc& b = *after;
    if (!(a.radius_px > 0.0) || !(b.radius_px > 0.0)) return std::max(a.radius_px, b.radius_px);
    const double t = (angle_deg - a.angle_deg) / (b.angle_deg - a.angle_deg);
    return a.radius_px + t * (b.radius_px - a.radius_px);
}

Result<ScoreReport> scoreModel(const FlareModel& model,
                               const TruthSource& truth,
                               const ScoreOptions& options,
                               const std::function<void(int, int)>& progress,
                               const std::function<Status(const ScoreImages&)>& images) {
    if (!(options.log_scale > 0.0) || !std::isfinite(options.log_scale))
        return makeError(ErrorCode::InvalidArgument, "score: log_scale must be > 0");
    auto angles = scoreAngles(model, options);
    if (!angles) return angles.error();
    const int64_t w = model.capture.width_px, h = model.capture.height_px;
    const double default_mask = 0.03 * std::hypot(static_cast<double>(w), static_cast<double>(h));
    ScoreReport report;
    const int total = static_cast<int>(angles->size());
    int done = 0;
    for (const ScoredAngle& angle : *angles) {
        auto t = truth(angle.angle_deg);
        if (!t)
            return t.error().withContext("score: truth at " + std::to_string(angle.angle_deg) +
                                         " deg");
        if (t->image.width != w || t->image.height != h)
            return makeError(ErrorCode::Internal, "score: the truth is not the capture's size");
        auto drawn =
            renderModel(model, angle.angle_deg, model.capture.roll_deg, w, h, options.render);
        if (!drawn) return drawn.error();
        const double mask = options.light_mask_px >= 0.0
                                ? options.light_mask_px
                                : lightDiscRadius(model, angle.angle_deg).value_or(default_mask);
        auto s = compareImages(*drawn, t->image, t->light_px, mask, options.log_scale);
        if (!s) return s.error();
        s->angle_deg = angle.angle_deg;
        s->kind = angle.kind;
        s->held_out = angle.kind != AngleKind::Fitted;
        report.angles.push_back(*s);
        if (images) {
            if (Status ok = images({report.angles.back(), *drawn, t->image, t->light_px, mask});
                !ok)
                return ok.error();
        }
        if (progress) progress(++done, total);
    }
    report.fit_rel_l2 = summarize(report.angles, [](const AngleScore& a) { return !a.held_out; });
    report.heldout_rel_l2 =
        summarize(report.angles, [](const AngleScore& a) { return a.held_out; });
    for (AngleKind kind : kAngleKinds) {
        ScoreSummary s =
            summarize(report.angles, [kind](const AngleScore& a) { return a.kind == kind; });
        if (s.count > 0) report.by_kind.emplace_back(kind, s);
    }
    return report;
}

namespace {

constexpr size_t kSkyProbes = 9;  // frames whose lowest background is the sky

struct DetectedFrame {
    FitFrame frame;
    FrameDetection detection;
};

// Frame `index` of the sweep and its detection; errors name the frame's file.
Result<DetectedFrame> loadAndDetect(const hdr::Sweep& sweep,
                                    size_t index,
                                    double sensor_width_mm,
                                    double sensor_height_mm,
                                    const DetectOptions& detect) {
    auto frame = loadFitFrame(sweep, index, sensor_width_mm, sensor_height_mm);
    if (!frame) return frame.error();
    auto detection = detectGhosts(*frame, detect);
    if (!detection) return detection.error().withContext(sweep.frames[index].exr_file);
    return DetectedFrame{std::move(*frame), std::move(*detection)};
}

}  // namespace

Result<TruthSource> measuredTruth(const hdr::Sweep& sweep,
                                  double sensor_width_mm,
                                  double sensor_height_mm,
                                  const DetectOptions& detect) {
    if (!(sensor_width_mm > 0.0 && sensor_height_mm > 0.0 && std::isfinite(sensor_width_mm) &&
          std::isfinite(sensor_height_mm)))
        return makeError(ErrorCode::InvalidArgument,
                         "measured truth: the sensor size must be finite and > 0");
    const size_t n = sweep.frames.size();
    if (n == 0)
        return makeError(ErrorCode::InvalidArgument,
                         "measured truth: sweep " + sweep.directory + " holds no frames");
    // Only the sky and the light are taken from a frame's detection: no circles sought.
    DetectOptions light_only = detect;
    light_only.max_circles = 0;
    // The sky: the lowest background of frames spread over the sweep, as the fit takes it
    // (fit/sweep_fit.h). A frame's own background may hold a veil larger than the frame, which
    // is ghost light the model draws. Bad detection options are refused here, at the first probe.
    std::array<double, 3> sky = {std::numeric_limits<double>::infinity(),
                                 std::numeric_limits<double>::infinity(),
                                 std::numeric_limits<double>::infinity()};
    const size_t probes = std::min<size_t>(n, kSkyProbes);
    for (size_t i = 0; i < probes; ++i) {
        const size_t index = probes == 1 ? n / 2 : i * (n - 1) / (probes - 1);
        auto probe = loadAndDetect(sweep, index, sensor_width_mm, sensor_height_mm, light_only);
        if (!probe) return probe.error().withContext("measured truth");
        for (size_t c = 0; c < 3; ++c) sky[c] = std::min(sky[c], probe->detection.background[c]);
    }
    auto shared = std::make_shared<const hdr::Sweep>(sweep);
    return TruthSource([shared, sensor_width_mm, sensor_height_mm, light_only,
                        sky](double angle_deg) -> Result<TruthFrame> {
        const auto& frames = shared->frames;
        const auto at = std::find_if(frames.begin(), frames.end(), [&](const hdr::SweepFrame& f) {
            return std::abs(f.angle_deg - angle_deg) <= 1e-6;
        });
        if (at == frames.end()) {
            char angle[32];
            std::snprintf(angle, sizeof angle, "%.6g", angle_deg);
            return makeError(ErrorCode::InvalidArgument,
                             "measured truth: sweep " + shared->directory +
                                 " holds no frame captured at " + angle +
                                 " deg (only captured angles can be scored against the frames)");
        }
        auto got = loadAndDetect(*shared, static_cast<size_t>(at - frames.begin()),
                                 sensor_width_mm, sensor_height_mm, light_only);
        if (!got) return got.error();
        TruthFrame truth;
        truth.image = std::move(got->frame.image);
        for (size_t i = 0; i < truth.image.pixels.size(); ++i) {
            float& v = truth.image.pixels[i];
            v = static_cast<float>(v - sky[i % 3]);
        }
        if (got->detection.light.found) truth.light_px = got->detection.light.centre_px;
        return truth;
    });
}

}  // namespace flarelab::fit
