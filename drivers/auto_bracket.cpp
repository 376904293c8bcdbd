#include "drivers/auto_bracket.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "drivers/calibration_measure.h"
#include "hdr/merge.h"

namespace flarelab::drivers {
namespace {

// The merge's saturation margin (hdr/merge.h MergeOptions): a sample this close to white is
// dropped as saturated.
constexpr double kSaturationMargin = 0.01;
constexpr double kQuantizationVariance = 1.0 / 12.0;

std::string num(double x, int digits = 3) {
    std::ostringstream out;
    out << std::setprecision(digits) << x;
    return out.str();
}

std::string percent(double fraction) { return num(100.0 * fraction, 3) + " %"; }

// One probe frame, reduced to what the plan needs.
struct Probe {
    hdr::RawFrame frame;
    double exposure_s = 0.0;  // as applied
    double range = 0.0;       // white - black
    double peak = 0.0;        // the brightest pixel above black, of the range
    bool clipped = false;     // the brightest pixel is saturated (the merge's rule)
};

// The signal above black of every pixel (hot pixels, when a calibration is given, repaired by
// applyCalibration; a few left in do not move a low percentile).
std::vector<double> signals(const Probe& p) {
    std::vector<double> out;
    out.reserve(p.frame.samples.size());
    for (const uint16_t s : p.frame.samples) out.push_back(s - p.frame.black_level_dn);
    return out;
}

double percentileOf(std::vector<double> values, double q) {
    if (values.empty()) return 0.0;
    const auto k = static_cast<size_t>(std::clamp(q * static_cast<double>(values.size()), 0.0,
                                                  static_cast<double>(values.size() - 1)));
    std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k), values.end());
    return values[k];
}

// The signal S (DN) whose signal-to-noise ratio is `snr` under var = read^2 + 1/12 + S / K:
// S^2 = snr^2 (S / K + read^2 + 1/12).
double signalForSnr(double snr, double read_dn, double electrons_per_dn) {
    const double a = snr * snr / electrons_per_dn;
    const double floor_variance = read_dn * read_dn + kQuantizationVariance;
    return 0.5 * (a + std::sqrt(a * a + 4.0 * snr * snr * floor_variance));
}

double snrOf(double signal_dn, double read_dn, double electrons_per_dn) {
    if (!(signal_dn > 0.0)) return 0.0;
    return signal_dn /
           std::sqrt(signal_dn / electrons_per_dn + read_dn * read_dn + kQuantizationVariance);
}

}  // namespace

Result<BracketPlan> planBrackets(Camera& camera, const BracketPlanOptions& o) {
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "bracket plan options: " + what);
    };
    if (!(o.core_level > 0.0 && o.core_level < 1.0)) return bad("core_level must lie in (0, 1)");
    if (!(o.floor_percentile > 0.0 && o.floor_percentile <= 0.5))
        return bad("floor_percentile must lie in (0, 0.5]");
    if (!(o.floor_snr > 0.0 && std::isfinite(o.floor_snr))) return bad("floor_snr must be > 0");
    if (!(o.floor_headroom >= 1.0 && std::isfinite(o.floor_headroom)))
        return bad("floor_headroom must be >= 1");
    if (!(o.well_level > 0.0 && o.well_level < 1.0)) return bad("well_level must lie in (0, 1)");
    if (!(o.well_snr > 0.0 && std::isfinite(o.well_snr))) return bad("well_snr must be > 0");
    if (!(o.max_ratio > 1.0 && std::isfinite(o.max_ratio))) return bad("max_ratio must be > 1");
    if (o.max_exposures < 1 || o.max_exposures > 255)
        return bad("max_exposures must lie in 1..255");
    if (!(o.budget_s > 0.0 && std::isfinite(o.budget_s))) return bad("budget_s must be > 0");
    if (o.max_probes < 4) return bad("max_probes must be >= 4");
    if (!(o.timeout_margin_s > 0.0)) return bad("timeout_margin_s must be > 0");

    const CameraCapabilities caps = camera.capabilities();
    const double t_min = caps.min_exposure_s;
    const double t_max = std::min(caps.max_exposure_s, o.budget_s);
    if (!(t_min > 0.0) || !(t_max >= t_min))
        return makeError(ErrorCode::Unsupported,
                         "bracket plan: the camera's shortest exposure " + num(t_min) +
                             " s is not positive or exceeds the longest the budget allows, " +
                             num(t_max) + " s");
    BracketPlan plan;
    plan.gain = camera.gain();

    const auto probe = [&](double t) -> Result<Probe> {
        if (plan.probes >= o.max_probes)
            return makeError(ErrorCode::Unsupported,
                             "bracket plan: " + std::to_string(o.max_probes) +
                                 " probes were not enough to find the brackets (is the scene "
                                 "steady?)");
        ++plan.probes;
        if (Status ok = camera.setExposure(t); !ok)
            return ok.error().withContext("bracket probe at " + num(t) + " s");
        auto frame = camera.capture(t + o.timeout_margin_s);
        if (!frame) return frame.error().withContext("bracket probe at " + num(t) + " s");
        Probe p;
        if (o.calibration != nullptr) {
            auto applied = applyCalibration(*frame, *o.calibration);
            if (!applied) return applied.error().withContext("bracket probe");
            p.frame = std::move(*applied);
        } else {
            p.frame = std::move(*frame);
        }
        p.exposure_s = p.frame.exposure_s > 0.0 ? p.frame.exposure_s : t;
        p.range = p.frame.white_level_dn - p.frame.black_level_dn;
        if (!(p.range > 0.0))
            return makeError(ErrorCode::Unsupported,
                             "bracket plan: the camera's frames have white level " +
                                 num(p.frame.white_level_dn) + " at or below black level " +
                                 num(p.frame.black_level_dn));
        uint16_t top = 0;
        for (const uint16_t s : p.frame.samples) top = std::max(top, s);
        p.peak = (top - p.frame.black_level_dn) / p.range;
        p.clipped = top >= p.frame.white_level_dn - kSaturationMargin * p.range;
        return p;
    };

    // 1. The core: the shortest exposure.
    double t = std::clamp(camera.exposure_s() > 0.0 ? camera.exposure_s() : 1e-3, t_min, t_max);
    double t_short = 0.0;
    Probe at_short;
    while (t_short == 0.0) {
        auto p = probe(t);
        if (!p) return p.error();
        if (p->clipped) {
            if (t <= t_min) {
                t_short = t_min;
                at_short = std::move(*p);
                break;
            }
            t = std::max(t_min, t / 16.0);
        } else if (p->peak < 0.05) {
            if (t >= t_max) {
                t_short = t_max;
                at_short = std::move(*p);
                break;
            }
            t = std::min(t_max, t * std::min(64.0, 0.25 / std::max(p->peak, 1e-6)));
        } else {
            t_short = std::clamp(p->exposure_s * o.core_level / p->peak, t_min, t_max);
            // Checked: a response that is not quite linear, or noise, may still clip it.
            for (int check = 0; check < 4; ++check) {
                auto q = probe(t_short);
                if (!q) return q.error();
                at_short = std::move(*q);
                if ((!at_short.clipped && at_short.peak <= std::min(0.99, 1.25 * o.core_level)) ||
                    t_short <= t_min)
                    break;
                t_short = std::max(t_min, t_short / 2.0);
            }
        }
    }
    plan.core_peak = at_short.peak;
    plan.core_unclipped = !at_short.clipped;
    if (at_short.clipped)
        plan.reasons.push_back(
            "cannot keep the light's core from clipping: even the camera's "
            "shortest exposure, " +
            num(t_min) +
            " s, saturates the brightest pixel (stop the lens down, add a "
            "neutral density filter or dim the light)");
    else if (at_short.peak < 0.05)
        plan.reasons.push_back("shortest " + num(t_short) +
                               " s: the camera's longest exposure and the budget leave the "
                               "brightest pixel at " +
                               percent(at_short.peak) + " of the range (is the light on?)");
    else
        plan.reasons.push_back("shortest " + num(t_short) +
                               " s: the brightest pixel (the light's core) at " +
                               percent(at_short.peak) + " of the range there, aimed at " +
                               percent(o.core_level) + " to leave room along the sweep");

    // 2. The floor: the scene's dark level, and how long it takes to record it.
    double read_dn = at_short.frame.read_noise_dn;
    double electrons_per_dn = at_short.frame.electrons_per_dn;
    const bool noise_known = read_dn > 0.0 && electrons_per_dn > 0.0;
    Probe at_floor = at_short;
    double floor_signal = percentileOf(signals(at_floor), o.floor_percentile);
    const auto measurable = [&](double s, const Probe& p) {
        return s >= std::max({noise_known ? 10.0 * read_dn : 0.0, 0.01 * p.range, 2.0});
    };
    while (!measurable(floor_signal, at_floor) && at_floor.exposure_s < t_max &&
           plan.probes + 2 <= o.max_probes) {
        const double target = std::max(0.05 * at_floor.range, noise_known ? 20.0 * read_dn : 0.0);
        const double factor = floor_signal > 0.0 ? std::min(64.0, target / floor_signal) : 16.0;
        auto p = probe(std::min(t_max, at_floor.exposure_s * std::max(factor, 2.0)));
        if (!p) return p.error();
        at_floor = std::move(*p);
        floor_signal = percentileOf(signals(at_floor), o.floor_percentile);
    }
    plan.floor_rate_dn_s = floor_signal > 0.0 ? floor_signal / at_floor.exposure_s : 0.0;
    std::string noise_source = "from the camera";
    if (o.calibration != nullptr && o.calibration->electrons_per_dn > 0.0)
        noise_source = "from the calibration";
    if (!noise_known) {
        // Photon transfer on a pair of frames at the floor probe.
        std::string why = "no second probe left";
        if (plan.probes < o.max_probes) {
            auto second = probe(at_floor.exposure_s);
            if (!second) return second.error();
            ExposureLevel level;
            level.exposure_s = at_floor.exposure_s;
            level.frames = {at_floor.frame, second->frame};
            const PhotonTransfer ptc =
                measurePhotonTransfer(std::span(&level, 1), at_floor.frame.black_level_dn,
                                      at_floor.frame.white_level_dn, {}, nullptr);
            if (ptc.electrons_per_dn > 0.0) {
                electrons_per_dn = ptc.electrons_per_dn;
                read_dn = std::sqrt(std::max(0.0, ptc.intercept_dn2 - kQuantizationVariance));
                noise_source = "measured from a pair of probe frames";
            } else {
                why = ptc.note;
            }
        }
        if (!(electrons_per_dn > 0.0)) {
            electrons_per_dn = 1.0;
            read_dn = 2.0;
            noise_source = "assumed (the merge's fallback; " + why + ")";
        }
    }
    plan.read_noise_dn = read_dn;
    plan.electrons_per_dn = electrons_per_dn;

    const double floor_needed = signalForSnr(o.floor_snr, read_dn, electrons_per_dn);
    double t_long = t_max;
    if (plan.floor_rate_dn_s > 0.0) t_long = floor_needed * o.floor_headroom / plan.floor_rate_dn_s;
    plan.floor_reached = plan.floor_rate_dn_s > 0.0 && t_long <= t_max;
    t_long = std::clamp(t_long, t_short, t_max);
    if (plan.floor_rate_dn_s > 0.0)
        plan.reasons.push_back(
            "floor: the scene's " + num(100.0 * o.floor_percentile) + "th percentile lies " +
            num(plan.floor_rate_dn_s) + " DN/s above black (probe of " + num(at_floor.exposure_s) +
            " s); aimed at a floor " + num(o.floor_headroom) +
            " times dimmer (the sweep leaves the light's glare behind), "
            "recorded at signal-to-noise " +
            num(o.floor_snr) + " from " + num(floor_needed) + " DN (read noise " + num(read_dn) +
            " DN, " + num(electrons_per_dn) + " e-/DN, " + noise_source + ")");
    else
        plan.reasons.push_back("floor: the scene's " + num(100.0 * o.floor_percentile) +
                               "th percentile shows no signal above black even at " +
                               num(at_floor.exposure_s) +
                               " s (a dark scene without veiling glare)");

    // The merge takes exposures at most hdr::kMaxExposureRatio apart. Where the core and the
    // floor lie further apart than that, the floor wins: the ghosts are what a sweep is for, and
    // the light's own disc is left out of fit and score. (Seen on the lensbaby: 10 ns to 27 s,
    // which the merge refused.)
    constexpr double kMergeSpan = 0.999 * hdr::kMaxExposureRatio;
    if (t_long > kMergeSpan * t_short) {
        t_short = t_long / kMergeSpan;
        plan.core_unclipped = false;
        plan.reasons.push_back("shortest raised to " + num(t_short) +
                               " s: the merge takes exposures at most " +
                               num(hdr::kMaxExposureRatio) +
                               " times apart, and the floor comes first; the light's core clips");
    }

    // 3. The steps between, then the budget.
    const double high = o.well_level;
    const double low = signalForSnr(o.well_snr, read_dn, electrons_per_dn) / at_short.range;
    double ratio = std::clamp(high / low, 1.0 + 1e-6, o.max_ratio);
    const auto build = [&](double longest) {
        std::vector<double> times;
        if (!(longest > t_short * (1.0 + 1e-9))) return std::vector<double>{t_short};
        const double span = std::log(longest / t_short);
        int n = static_cast<int>(std::ceil(span / std::log(ratio) - 1e-9)) + 1;
        n = std::clamp(n, 2, o.max_exposures);
        for (int k = 0; k < n; ++k)
            times.push_back(std::clamp(t_short * std::exp(span * k / (n - 1)), t_min, t_max));
        return times;
    };
    const auto total = [](const std::vector<double>& times) {
        double sum = 0.0;
        for (const double x : times) sum += x;
        return sum;
    };
    std::vector<double> times = build(t_long);
    bool over_budget = false;
    while (total(times) > o.budget_s && t_long > t_short) {
        over_budget = true;
        t_long = std::max(t_short, t_long / 1.05);
        times = build(t_long);
    }
    if (over_budget) plan.floor_reached = false;
    plan.exposure_times_s = times;
    plan.ratio = times.size() > 1 ? times[1] / times[0] : 1.0;
    plan.floor_snr = snrOf(plan.floor_rate_dn_s * times.back(), read_dn, electrons_per_dn);

    if (plan.floor_reached) {
        plan.reasons.push_back("longest " + num(times.back()) +
                               " s: records the first angle's floor at "
                               "signal-to-noise " +
                               num(plan.floor_snr) + ", one " + num(o.floor_headroom) +
                               " times dimmer at " +
                               num(snrOf(plan.floor_rate_dn_s / o.floor_headroom * times.back(),
                                         read_dn, electrons_per_dn)));
    } else {
        std::string why = over_budget ? "the budget of " + num(o.budget_s) + " s per bracket"
                                      : "the camera's longest exposure, " + num(t_max) + " s";
        plan.reasons.push_back("cannot reach the ghosts' noise floor: " + why +
                               " stops the longest exposure at " + num(times.back()) +
                               " s, where the first angle's floor's signal-to-noise ratio is " +
                               num(plan.floor_snr) + " (goal " + num(o.floor_snr) + " at a floor " +
                               num(o.floor_headroom) + " times dimmer)");
    }
    plan.reasons.push_back(
        std::to_string(times.size()) + " exposures, a factor " + num(plan.ratio) +
        " apart (at most " + num(ratio) + ", so that every radiance lies between " + percent(low) +
        " and " + percent(high) + " of the range, signal-to-noise " + num(o.well_snr) +
        " or more, in one of them" +
        (plan.ratio > ratio * 1.001
             ? "; more than that: " + std::to_string(o.max_exposures) + " exposures at most"
             : "") +
        "), " + num(total(times)) + " s of exposure");
    return plan;
}

}  // namespace flarelab::drivers
