#include "apps/fit_command.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iomanip>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <vector>

#include "drivers/lens_settings.h"
#include "drivers/path_seeds.h"
#include "drivers/sim_truth.h"
#include "fit/sweep_fit.h"
#include "hdr/digest.h"
#include "hdr/sweep.h"
#include "optics/prescription.h"
#include "render/preview.h"

namespace flarelab::apps {
namespace {

struct FitState {
    std::string sweep;
    std::string output;
    std::string lens_file;
    std::string sensor;
    std::string optimizer = "ceres";
    // The library's defaults, so that the command fits what fitSweep fits.
    int iterations = fit::FrameFitOptions{}.max_iterations;
    int line_search_steps = fit::FrameFitOptions{}.line_search_steps;
    double trust_region_radius = fit::FrameFitOptions{}.trust_region_radius;
    int passes = fit::FrameFitOptions{}.passes;
    int samples = fit::CostOptions{}.max_samples;
    int distance_iterations = fit::CostOptions{}.distance.iterations;
    int degree = -1;
    int every = 1;
    bool paths = false;
    bool link = false;
    int link_max_gap = fit::TrackLinkOptions{}.max_gap_frames;
    double link_gate = fit::TrackLinkOptions{}.gate;
    int shape_passes = fit::ShadingRefitOptions{}.shape_passes;
    int shading_passes = fit::ShadingRefitOptions{}.passes;
    int shape_frames = fit::ShadingRefitOptions{}.shape_frames_per_ghost;
    double shape_outline = fit::ShadingRefitOptions{}.shape_min_outline_in_frame;
    double start_share = fit::SweepFitOptions{}.start_min_share;
    int min_track_frames = fit::SweepFitOptions{}.min_track_frames;
    double min_energy_fraction = fit::SweepFitOptions{}.min_energy_fraction;
    int max_missed = fit::SweepFitOptions{}.max_missed;
    int max_circles = fit::DetectOptions{}.max_circles;
    double transform_fraction = fit::CostOptions{}.transform_fraction;
    double robust_scale = fit::CostOptions{}.robust_scale;
    bool residual_detection = false;
    double light_margin_px = fit::DetectOptions{}.light_margin_px;
    std::optional<double> light_power_dn_s;
    bool keep_samples = false;
    bool quiet = false;
};

struct ScoreState {
    std::string model;
    std::string lens_file;
    std::string sweep;
    std::string images;
    std::vector<double> angles;
    int halfway = fit::ScoreOptions{}.halfway_angles;
    int random = fit::ScoreOptions{}.random_angles;
    int fit_angles = fit::ScoreOptions{}.fit_angles;
    int left_out = fit::ScoreOptions{}.left_out_angles;
    double log_scale = fit::ScoreOptions{}.log_scale;
    std::optional<double> light_mask_px;
    uint64_t seed = 1;
    bool measured = false;
    bool json = false;
};

bool parseSensor(const std::string& text, std::array<double, 2>& out) {
    const auto x = text.find('x');
    if (x == std::string::npos) return false;
    try {
        size_t used = 0;
        out[0] = std::stod(text.substr(0, x), &used);
        if (used != x) return false;
        out[1] = std::stod(text.substr(x + 1), &used);
        if (used != text.size() - x - 1) return false;
    } catch (...) {
        return false;
    }
    return out[0] > 0.0 && out[1] > 0.0 && std::isfinite(out[0]) && std::isfinite(out[1]);
}

int runFit(const FitState& s, std::ostream& out, std::ostream& err) {
    auto sweep = hdr::readSweep(s.sweep);
    if (!sweep) {
        err << "flarelab: fit: " << sweep.error().message << "\n";
        return 1;
    }
    if (const std::string w =
            hdr::clippingWarning(hdr::clippedFrames(*sweep), sweep->frames.size());
        !w.empty())
        err << "flarelab: fit: warning: " << w << "\n";
    std::array<double, 2> sensor{};
    bool have_sensor = false;
    if (!s.sensor.empty()) {
        if (!parseSensor(s.sensor, sensor)) {
            err << "flarelab: fit: --sensor-mm must be WxH in mm, both > 0 (got \"" << s.sensor
                << "\")\n";
            return 2;
        }
        have_sensor = true;
    }
    const hdr::SweepLens& recorded = sweep->header.lens;
    std::optional<optics::Lens> lens;
    std::string sha;
    if (!s.lens_file.empty()) {
        auto digest = hdr::sha256File(s.lens_file);
        if (!digest) {
            err << "flarelab: fit: " << digest.error().message << "\n";
            return 1;
        }
        sha = *digest;
        if (!recorded.prescription_sha256.empty() && sha != recorded.prescription_sha256) {
            err << "flarelab: fit: " << s.lens_file << " is not the lens the sweep was captured "
                << "with (" << recorded.prescription_file << ", sha256 "
                << recorded.prescription_sha256 << ")\n";
            return 2;
        }
        // An older sweep records no sensor size: the one the sweep's pixel pitch gives (times
        // the frame size), not the flags' default; the default (36 x 24 mm) where the two agree
        // to a pixel, since the pitch carries the width's rounding into the height.
        const bool sensor_recorded = recorded.sensor_width_mm && recorded.sensor_height_mm;
        if (!have_sensor && !sensor_recorded) {
            const optics::CameraDescription defaults;
            sensor = {defaults.sensor_width_mm, defaults.sensor_height_mm};
            have_sensor = true;
            if (auto from_pitch = fit::sweepSensorSize(*sweep, nullptr)) {
                const double pitch =
                    (*from_pitch)[0] / static_cast<double>(sweep->header.capture.width_px);
                if (std::abs((*from_pitch)[0] - sensor[0]) > pitch ||
                    std::abs((*from_pitch)[1] - sensor[1]) > pitch)
                    sensor = *from_pitch;
            }
        }
    }
    auto size = fit::sweepSensorSize(*sweep, have_sensor ? &sensor : nullptr);
    if (!size) {
        err << "flarelab: fit: " << size.error().message << "\n";
        return 2;
    }
    if (!s.lens_file.empty()) {
        // The lens as the sweep records its camera settings; the model copies them from the
        // sweep (fit::modelLens).
        auto prescription = optics::loadPrescription(s.lens_file);
        if (!prescription) {
            err << "flarelab: fit: " << prescription.error().message << "\n";
            return 1;
        }
        auto rebuilt =
            drivers::rebuildLens(*prescription, fit::modelLens(recorded, (*size)[0], (*size)[1]));
        if (!rebuilt) {
            err << "flarelab: fit: " << rebuilt.error().message << "\n";
            return 1;
        }
        lens = std::move(rebuilt->lens);
    }
    fit::SweepFitOptions options;
    if (s.optimizer == "ceres") {
        options.frame.optimizer = fit::Optimizer::Ceres;
    } else if (s.optimizer == "gradient-descent") {
        options.frame.optimizer = fit::Optimizer::GradientDescent;
    } else {
        err << "flarelab: fit: --optimizer must be ceres or gradient-descent\n";
        return 2;
    }
    options.frame.max_iterations = s.iterations;
    options.frame.line_search_steps = s.line_search_steps;
    options.frame.trust_region_radius = s.trust_region_radius;
    options.frame.passes = s.passes;
    options.frame.cost.max_samples = s.samples;
    options.frame.cost.distance.iterations = s.distance_iterations;
    options.poly.fixed_degree = s.degree;
    options.keep_samples = s.keep_samples;
    options.frame_stride = s.every;
    options.link.enabled = s.link;
    options.link.max_gap_frames = s.link_max_gap;
    options.link.gate = s.link_gate;
    options.shading.shape_passes = s.shape_passes;
    options.shading.passes = s.shading_passes;
    options.shading.shape_frames_per_ghost = s.shape_frames;
    options.shading.shape_min_outline_in_frame = s.shape_outline;
    options.start_min_share = s.start_share;
    options.min_track_frames = s.min_track_frames;
    options.min_energy_fraction = s.min_energy_fraction;
    options.max_missed = s.max_missed;
    options.detect.max_circles = s.max_circles;
    options.frame.cost.transform_fraction = s.transform_fraction;
    options.frame.cost.robust_scale = s.robust_scale;
    options.residual_detection = s.residual_detection;
    options.detect.light_margin_px = s.light_margin_px;
    if (s.paths) {
        if (!lens) {
            err << "flarelab: fit: --paths needs --lens (the prescription whose ghost paths seed "
                   "the tracks)\n";
            return 2;
        }
        // The lens as the sweep records the capture's settings (above).
        auto seeder = drivers::pathSeeder(*lens);
        if (!seeder) {
            err << "flarelab: fit: " << seeder.error().message << "\n";
            return 1;
        }
        options.path_seeds = std::move(*seeder);
    }
    if (s.light_power_dn_s && !(std::isfinite(*s.light_power_dn_s) && *s.light_power_dn_s > 0.0)) {
        err << "flarelab: fit: --light-power-dn-s must be a finite number > 0\n";
        return 2;
    }
    if (Status ok = fit::checkSweepFitOptions(options); !ok) {
        err << "flarelab: fit: " << ok.error().message << "\n";
        return 2;
    }
    const auto progress = [&](const fit::SweepFitProgress& p) {
        if (s.quiet) return;
        err << "\rfit: frame " << p.frames_done << "/" << p.frames_total << "  " << std::fixed
            << std::setprecision(2) << p.angle_deg << " deg  " << p.live_ghosts << " ghosts   "
            << std::defaultfloat << std::flush;
    };
    fit::SweepFitResult result;
    auto model = fit::fitSweep(*sweep, (*size)[0], (*size)[1], options, progress, &result);
    if (!s.quiet) err << "\n";
    if (!model) {
        err << "flarelab: fit: " << model.error().message << "\n";
        return 1;
    }
    if (lens) {
        model->lens.prescription_file = s.lens_file;
        model->lens.prescription_sha256 = sha;
        if (!model->lens.f_number && lens->camera().f_number > 0.0)
            model->lens.f_number = lens->camera().f_number;
    }
    // A measured power given here overrides what the sweep recorded.
    if (s.light_power_dn_s) model->capture.light_power_dn_s = s.light_power_dn_s;
    if (Status written = fit::writeModel(s.output, *model); !written) {
        err << "flarelab: fit: " << written.error().message << "\n";
        return 1;
    }
    out << "fit: " << model->ghosts.size() << " ghosts from "
        << (sweep->frames.size() + static_cast<size_t>(s.every) - 1) / static_cast<size_t>(s.every)
        << " frames" << (s.every > 1 ? " (one in every " + std::to_string(s.every) + ")" : "")
        << " (" << result.frames_fitted << " frame fits, " << result.evaluations
        << " cost evaluations, " << result.fragments_linked << " track fragments linked) in "
        << std::fixed << std::setprecision(1) << result.time_ms / 1000.0 << " s -> " << s.output
        << "\n";
    if (s.shape_passes > 0)
        out << "fit: shapes refitted for " << result.shape_refitted << " ghosts; "
            << result.shape_unobserved
            << " kept as compressed (their outline mostly outside the frame)\n";
    const fit::SweepFitStages& st = result.stages;
    const std::pair<const char*, double> stages[] = {{"load frames", st.load_ms},
                                                     {"detect", st.detect_ms},
                                                     {"read ahead", st.ahead_ms},
                                                     {"fit frames", st.fit_ms},
                                                     {"follow new tracks back", st.extend_ms},
                                                     {"ghost paths", st.seed_ms},
                                                     {"link fragments", st.link_ms},
                                                     {"track", st.track_ms},
                                                     {"compress", st.compress_ms},
                                                     {"refit shading", st.shading_ms},
                                                     {"refit shapes", st.shape_ms}};
    // The two passes run side by side: their stages are summed over both.
    out << "  stage                    time_s   share\n";
    for (const auto& [name, ms] : stages)
        out << "  " << std::left << std::setw(22) << name << std::right << std::fixed
            << std::setw(8) << std::setprecision(2) << ms / 1000.0 << "  " << std::setw(5)
            << std::setprecision(1) << (st.total_ms > 0.0 ? 100.0 * ms / st.total_ms : 0.0)
            << " %\n";
    out << "  " << std::left << std::setw(22) << "whole fit" << std::right << std::setw(8)
        << std::setprecision(2) << st.total_ms / 1000.0 << "\n"
        << std::defaultfloat;
    return 0;
}

void printSummary(const std::string& name, const fit::ScoreSummary& s, std::ostream& out) {
    out << name << ": " << s.count << " angles, relative L2 median " << std::fixed
        << std::setprecision(4) << s.median << ", worst " << s.worst << " at "
        << std::setprecision(3) << s.worst_angle_deg << " deg; |energy error| median "
        << std::setprecision(2) << 100.0 * s.median_abs_energy_error << " %, worst "
        << 100.0 * s.worst_abs_energy_error << " %; missed light median "
        << 100.0 * s.median_missed_light << " %; log relative L2 median " << std::setprecision(4)
        << s.median_log_rel_l2 << "; median PSNR " << std::setprecision(1) << s.median_psnr_db
        << " dB\n"
        << std::defaultfloat;
}

nlohmann::json summaryJson(const fit::ScoreSummary& s) {
    return {{"count", s.count},
            {"median", s.median},
            {"worst", s.worst},
            {"worst_angle_deg", s.worst_angle_deg},
            {"median_psnr_db", s.median_psnr_db},
            {"median_abs_energy_error", s.median_abs_energy_error},
            {"worst_abs_energy_error", s.worst_abs_energy_error},
            {"median_log_rel_l2", s.median_log_rel_l2},
            {"worst_log_rel_l2", s.worst_log_rel_l2},
            {"median_missed_light", s.median_missed_light},
            {"median_masked_energy_fraction", s.median_masked_energy_fraction}};
}

// The sweep's frames the model was not fitted to: inside its valid range and off its capture
// grid (a sparse fit, `fit --every K`). Refused when the sweep is not the model's.
Result<std::vector<double>> leftOutAngles(const std::string& directory,
                                          const fit::FlareModel& model) {
    auto sweep = hdr::readSweepManifest(directory);
    if (!sweep) return sweep.error();
    const auto& c = sweep->header.capture;
    if (c.width_px != model.capture.width_px || c.height_px != model.capture.height_px ||
        sweep->header.lens.description != model.lens.description)
        return makeError(ErrorCode::InvalidArgument,
                         directory + " is not the sweep the model was fitted to: it holds " +
                             std::to_string(c.width_px) + " x " + std::to_string(c.height_px) +
                             " frames of \"" + sweep->header.lens.description + "\", the model " +
                             std::to_string(model.capture.width_px) + " x " +
                             std::to_string(model.capture.height_px) + " of \"" +
                             model.lens.description + "\"");
    const double step = model.capture.step_deg;
    std::vector<double> out;
    for (const auto& frame : sweep->frames) {
        const double a = frame.angle_deg;
        if (a < model.valid_from_deg - 1e-9 || a > model.valid_to_deg + 1e-9) continue;
        const double k = std::round((a - model.capture.from_deg) / step);
        if (std::abs(a - (model.capture.from_deg + k * step)) <= 1e-6 * std::max(1.0, step))
            continue;  // a fitted frame
        out.push_back(a);
    }
    return out;
}

// truth | model | model - truth, 4 px apart, on one log tone curve: 0 at the truth's peak times
// log_scale... up to the peak (ToneCurve::Log over log2(1 / log_scale) stops, clamped). The
// difference is red where the model is brighter, blue where it is darker; the light's disc is
// outlined in green.
Status writeScoreImages(const fit::ScoreImages& v, double log_scale, const std::string& path) {
    const int64_t w = v.truth.width, h = v.truth.height, gap = 4;
    ImageRGB out(3 * w + 2 * gap, h);
    double peak = 0.0;
    for (float t : v.truth.pixels) peak = std::max(peak, static_cast<double>(t));
    if (!(peak > 0.0)) peak = 1.0;
    for (int64_t y = 0; y < h; ++y) {
        for (int64_t x = 0; x < w; ++x) {
            const float* t = v.truth.at(x, y);
            const float* m = v.model.at(x, y);
            float* a = out.at(x, y);
            float* b = out.at(w + gap + x, y);
            float* d = out.at(2 * (w + gap) + x, y);
            double diff = 0.0;
            for (int c = 0; c < 3; ++c) {
                a[c] = t[c];
                b[c] = m[c];
                diff += (static_cast<double>(m[c]) - t[c]) / 3.0;
            }
            d[0] = static_cast<float>(std::max(diff, 0.0));
            d[2] = static_cast<float>(std::max(-diff, 0.0));
            if (v.light_px) {
                const double r = std::hypot(static_cast<double>(x) + 0.5 - v.light_px->x(),
                                            static_cast<double>(y) + 0.5 - v.light_px->y());
                if (std::abs(r - v.light_mask_px) < 0.5)
                    for (float* p : {a, b, d}) {
                        p[0] = p[2] = 0.0f;
                        p[1] = static_cast<float>(peak);
                    }
            }
        }
    }
    render::ToneMapOptions tone;
    tone.curve = render::ToneCurve::Log;
    tone.exposure_stops = std::clamp(-std::log2(peak), -64.0, 64.0);
    tone.log_range_stops = std::clamp(std::log2(1.0 / log_scale), 1.0, 64.0);
    return render::writePng(out, path, tone);
}

int runScore(const ScoreState& s, std::ostream& out, std::ostream& err) {
    auto model = fit::readModel(s.model);
    if (!model) {
        err << "flarelab: score: " << model.error().message << "\n";
        return 1;
    }
    if (s.measured && s.sweep.empty()) {
        err << "flarelab: score: --measured scores against the frames of the sweep the model "
               "was fitted to: give it with --sweep\n";
        return 2;
    }
    if (s.measured && !s.lens_file.empty()) {
        err << "flarelab: score: --measured scores against the sweep's frames and simulates "
               "nothing: leave --lens out, or --measured to score against the simulator\n";
        return 2;
    }
    if (s.lens_file.empty() && !s.measured) {
        err << "flarelab: score: --lens is required (the prescription to simulate the truth "
               "with), or --measured --sweep S to score against the captured frames\n";
        return 2;
    }
    // The simulator's truth needs the lens the model was fitted with; the measured one none.
    std::optional<optics::Lens> lens;
    if (!s.measured) {
        lens = captureLens(s.lens_file, *model, s.model, err);
        if (!lens) return 1;
        if (!model->lens.prescription_sha256.empty()) {
            auto digest = hdr::sha256File(s.lens_file);
            if (!digest) {
                err << "flarelab: score: " << digest.error().message << "\n";
                return 1;
            }
            if (*digest != model->lens.prescription_sha256) {
                err << "flarelab: score: " << s.lens_file << " is not the lens the model was "
                    << "fitted with (" << model->lens.prescription_file << ", sha256 "
                    << model->lens.prescription_sha256 << ")\n";
                return 2;
            }
        }
    }
    fit::ScoreOptions options;
    options.angles_deg = s.angles;
    options.halfway_angles = s.halfway;
    options.random_angles = s.random;
    options.fit_angles = s.fit_angles;
    options.left_out_angles = s.left_out;
    options.log_scale = s.log_scale;
    options.seed = s.seed;
    if (s.light_mask_px) {
        if (!(std::isfinite(*s.light_mask_px) && *s.light_mask_px >= 0.0)) {
            err << "flarelab: score: --light-mask-px must be a finite number >= 0\n";
            return 2;
        }
        options.light_mask_px = *s.light_mask_px;
    } else if (model->capture.light_discs.empty()) {
        err << "flarelab: score: note: " << s.model << " (model format " << model->format_version
            << ") does not record the light's disc its fit left out; 3% of the frame's diagonal "
               "is left out around the light instead\n";
    }
    if (!(s.log_scale > 0.0 && s.log_scale < 1.0)) {
        err << "flarelab: score: --log-scale must lie in (0, 1)\n";
        return 2;
    }
    if (!s.sweep.empty()) {
        auto left = leftOutAngles(s.sweep, *model);
        if (!left) {
            err << "flarelab: score: " << left.error().message << "\n";
            return 2;
        }
        if (left->empty())
            err << "flarelab: score: note: the model was fitted to every frame of " << s.sweep
                << " in its range: no frame is left out (fit --every K leaves some)\n";
        options.left_out_deg = std::move(*left);
    }
    if (!s.images.empty()) {
        std::error_code ec;
        std::filesystem::create_directories(s.images, ec);
        if (ec) {
            err << "flarelab: score: --images " << s.images << ": " << ec.message() << "\n";
            return 1;
        }
    }
    bool recorded = false;
    const bool colour = fit::fittedInColour(*model, &recorded);
    if (!recorded)
        err << "flarelab: score: note: " << s.model << " (model format " << model->format_version
            << ") does not record the camera's raw format; its ghosts' colour channels "
            << (colour ? "differ, so it is scored against the colour (RGB) truth"
                       : "agree, so it is scored against the monochrome (green) truth")
            << "\n";
    Result<fit::TruthSource> truth = fit::TruthSource{};
    if (s.measured) {
        // Only captured angles have frames: the fitted and the left-out ones.
        options.halfway_angles = 0;
        options.random_angles = 0;
        auto sweep = hdr::readSweepManifest(s.sweep);
        if (!sweep) {
            err << "flarelab: score: " << sweep.error().message << "\n";
            return 2;
        }
        // The frames in the sensor millimetres the fit used: the model's record.
        truth = fit::measuredTruth(*sweep, model->lens.sensor_width_mm,
                                   model->lens.sensor_height_mm);
    } else {
        truth = drivers::simulatedGhostTruth(*lens, model->capture.width_px,
                                             model->capture.height_px, {}, colour);
    }
    if (!truth) {
        err << "flarelab: score: " << truth.error().message << "\n";
        return 1;
    }
    const auto images = [&](const fit::ScoreImages& v) -> Status {
        if (s.images.empty()) return Ok{};
        char name[96];
        std::snprintf(name, sizeof name, "score-%08.3f-%s.png", v.score.angle_deg,
                      fit::angleKindName(v.score.kind));
        return writeScoreImages(v, s.log_scale, (std::filesystem::path(s.images) / name).string());
    };
    auto report = fit::scoreModel(
        *model, *truth, options,
        [&](int done, int total) {
            if (!s.json) err << "\rscore: " << done << "/" << total << std::flush;
        },
        images);
    if (!s.json) err << "\n";
    if (!report) {
        err << "flarelab: score: " << report.error().message << "\n";
        return 1;
    }
    if (s.json) {
        nlohmann::json j;
        j["model"] = s.model;
        j["heldout_rel_l2"] = summaryJson(report->heldout_rel_l2);
        j["fit_rel_l2"] = summaryJson(report->fit_rel_l2);
        nlohmann::json kinds = nlohmann::json::object();
        for (const auto& [kind, summary] : report->by_kind)
            kinds[fit::angleKindName(kind)] = summaryJson(summary);
        j["by_kind"] = kinds;
        j["log_scale"] = s.log_scale;
        nlohmann::json angles = nlohmann::json::array();
        for (const auto& a : report->angles)
            angles.push_back({{"angle_deg", a.angle_deg},
                              {"kind", fit::angleKindName(a.kind)},
                              {"held_out", a.held_out},
                              {"rel_l2", a.rel_l2},
                              {"psnr_db", a.psnr_db},
                              {"truth_energy", a.truth_energy},
                              {"model_energy", a.model_energy},
                              {"energy_error", a.energy_error},
                              {"log_rel_l2", a.log_rel_l2},
                              {"missed_light", a.missed_light},
                              {"masked_energy_fraction", a.masked_energy_fraction},
                              {"light_mask_px", a.light_mask_px}});
        j["angles"] = angles;
        out << j.dump(2) << "\n";
        return 0;
    }
    if (s.measured)
        out << "score: " << s.model << " against the frames of " << s.sweep
            << " (measured: noise included, the sky subtracted, the light's disc left out)\n";
    else
        out << "score: " << s.model << " against " << s.lens_file << " (simulated, ghosts only, "
            << "the light's disc left out)\n";
    out << "  angle_deg  kind      rel_L2  energy_err  log_rel_L2  masked  disc_px  PSNR_dB\n";
    for (const auto& a : report->angles)
        out << "  " << std::setw(9) << std::fixed << std::setprecision(3) << a.angle_deg << "  "
            << std::left << std::setw(8) << fit::angleKindName(a.kind) << std::right << "  "
            << std::setw(6) << std::setprecision(4) << a.rel_l2 << "  " << std::setw(9)
            << std::setprecision(2) << 100.0 * a.energy_error << "%  " << std::setw(10)
            << std::setprecision(4) << a.log_rel_l2 << "  " << std::setw(5) << std::setprecision(1)
            << 100.0 * a.masked_energy_fraction << "%  " << std::setw(7) << std::setprecision(1)
            << a.light_mask_px << "  " << std::setw(7) << a.psnr_db << "\n"
            << std::defaultfloat;
    for (const auto& [kind, summary] : report->by_kind)
        printSummary(std::string(fit::angleKindName(kind)) + " angles", summary, out);
    printSummary("held-out angles (all kinds)", report->heldout_rel_l2, out);
    return 0;
}

}  // namespace

std::optional<optics::Lens> captureLens(const std::string& lens_path,
                                        const fit::FlareModel& model,
                                        const std::string& model_path,
                                        std::ostream& err) {
    auto prescription = optics::loadPrescription(lens_path);
    if (!prescription) {
        err << "flarelab: score: " << prescription.error().message << "\n";
        return std::nullopt;
    }
    auto rebuilt = drivers::rebuildLens(*prescription, model.lens);
    if (!rebuilt) {
        err << "flarelab: score: " << rebuilt.error().message << "\n";
        return std::nullopt;
    }
    if (!rebuilt->assumed.empty()) {
        err << "flarelab: score: note: " << model_path << " (model format " << model.format_version
            << ") does not record the capture's ";
        for (size_t i = 0; i < rebuilt->assumed.size(); ++i)
            err << (i ? ", " : "") << rebuilt->assumed[i];
        err << "; a capture taken otherwise is scored against another lens\n";
    }
    return std::move(rebuilt->lens);
}

void addFitCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto fs = std::make_shared<FitState>();
    CLI::App* fit = app.add_subcommand("fit", "fit every ghost of a sweep and write a model file");
    fit->add_option("SWEEP", fs->sweep, "sweep directory")->required();
    fit->add_option("-o,--output", fs->output, "model file to write")->required();
    fit->add_option("--lens", fs->lens_file,
                    "the lens prescription, recorded in the model (gives the sensor size)");
    fit->add_option("--sensor-mm", fs->sensor, "sensor size WxH in mm (when nothing else says)");
    fit->add_flag("--keep-samples", fs->keep_samples,
                  "keep each parameter's per-frame values in the model, for reports (3 to 5 "
                  "times larger)");
    fit->add_option("--light-power-dn-s", fs->light_power_dn_s,
                    "the rig light's own image summed over the sensor, DN/s at the capture's gain "
                    "(measured apart, e.g. through an ND filter): the lab figures' scale")
        ->check(CLI::PositiveNumber);
    fit->add_option("--optimizer", fs->optimizer, "ceres or gradient-descent")
        ->capture_default_str();
    fit->add_option("--iterations", fs->iterations, "optimizer iterations per ghost and pass")
        ->capture_default_str();
    fit->add_option("--line-search-steps", fs->line_search_steps,
                    "Ceres: line search steps after each trust-region step (0: none, about 1.5 "
                    "times faster than Ceres' 20 and as accurate, docs/fit-scoring.md)")
        ->capture_default_str();
    fit->add_option("--trust-region-radius", fs->trust_region_radius,
                    "Ceres: initial trust-region radius of each ghost's fit (1 / the first "
                    "step's damping, 1e-6 to 1e16)")
        ->capture_default_str();
    fit->add_option("--passes", fs->passes, "passes over a frame's ghosts")->capture_default_str();
    fit->add_option("--samples", fs->samples, "crop samples per side (the fit's resolution)")
        ->capture_default_str();
    fit->add_option("--distance-iterations", fs->distance_iterations,
                    "Newton steps of the Bezier distance")
        ->capture_default_str();
    fit->add_option("--degree", fs->degree,
                    "fixed polynomial degree of every parameter (-1: chosen by cross-validation)")
        ->capture_default_str();
    fit->add_option("--light-margin-px", fs->light_margin_px,
                    "pixels added to the disc around the light left out of the fit (and of the "
                    "score), beyond where the light's glare falls to the noise")
        ->capture_default_str()
        ->check(CLI::Range(0.0, 1000.0));
    fit->add_option("--every", fs->every,
                    "fit one frame in every K (the first, then every K-th): a sparse fit whose "
                    "other frames `score --sweep` holds out")
        ->capture_default_str()
        ->check(CLI::Range(1, 1000));
    fit->add_flag("--paths", fs->paths,
                  "start tracks from the ghost paths of the --lens prescription (one track per "
                  "path) instead of from detections");
    fit->add_flag("--link", fs->link,
                  "link the fragments of one ghost's track over the whole sweep (fewer tracks; "
                  "not more accurate on the lenses measured, docs/track-linking.md)");
    fit->add_option("--link-max-gap", fs->link_max_gap,
                    "with --link: fitted frames a ghost may be missing between two fragments")
        ->capture_default_str()
        ->check(CLI::Range(0, 1000));
    fit->add_option("--link-gate", fs->link_gate,
                    "with --link: largest cost of a link (1: every feature at its tolerance)")
        ->capture_default_str()
        ->check(CLI::Range(1e-3, 1e3));
    fit->add_option("--refit-shading-passes", fs->shading_passes,
                    "passes of the shading refit over the ghosts, brightest first, before the "
                    "shape refit (docs/fit-scoring.md)")
        ->capture_default_str()
        ->check(CLI::Range(1, 100));
    fit->add_option("--refit-shapes", fs->shape_passes,
                    "passes that refit every series of each ghost, its shape's too, to the frames' "
                    "pixels after the shading refit (0: shapes stay as compressed; "
                    "docs/shape-refit.md)")
        ->capture_default_str()
        ->check(CLI::Range(0, 100));
    fit->add_option("--refit-shape-frames", fs->shape_frames,
                    "with --refit-shapes: frames each ghost's refit sees, at most")
        ->capture_default_str()
        ->check(CLI::Range(2, 10000));
    fit->add_option("--refit-shape-outline", fs->shape_outline,
                    "with --refit-shapes: a ghost's shape is refitted only where at least this "
                    "share of its outline lies in the frame (median over its frames)")
        ->capture_default_str()
        ->check(CLI::Range(0.0, 1.0));
    fit->add_option("--start-share", fs->start_share,
                    "the passes start from the probe nearest the sweep's middle of those showing "
                    "at least this share of the most ghosts any probe shows (1: the most)")
        ->capture_default_str()
        ->check(CLI::Range(0.0, 1.0));
    fit->add_option("--min-track-frames", fs->min_track_frames,
                    "tracks of fewer fitted frames are not modelled (docs/fit-scoring.md)")
        ->capture_default_str()
        ->check(CLI::Range(1, 1000));
    fit->add_option("--min-energy-fraction", fs->min_energy_fraction,
                    "a ghost whose light in a frame is below this share of all the ghosts' light "
                    "there ends (0: none ends; below 1)")
        ->capture_default_str()
        ->check(CLI::Range(0.0, 1.0));
    fit->add_option("--max-missed", fs->max_missed,
                    "fitted frames a track may go undetected before it ends")
        ->capture_default_str()
        ->check(CLI::Range(0, 1000));
    fit->add_option("--max-circles", fs->max_circles,
                    "overlapping circular ghosts the detection finds in one frame, at most")
        ->capture_default_str()
        ->check(CLI::Range(0, 1000));
    fit->add_option("--transform-fraction", fs->transform_fraction,
                    "the cost's asinh transform is linear up to this share of the frame's 99th "
                    "percentile (or 3 noise sigmas, the larger), logarithmic above")
        ->capture_default_str()
        ->check(CLI::Range(0.0, 1e6));
    fit->add_option("--robust-scale", fs->robust_scale,
                    "the cost's Cauchy loss scale, in units of the transformed values: larger "
                    "residuals count less (stars, hot pixels, other ghosts' misfit)")
        ->capture_default_str()
        ->check(CLI::Range(1e-3, 1e6));
    fit->add_flag("--residual-detection", fs->residual_detection,
                  "in frames detected in full, detect again in what the fitted ghosts leave and "
                  "start tracks there");
    fit->add_flag("--quiet", fs->quiet, "no progress on stderr");
    fit->callback([fs, &out, &err, &exit_code] { exit_code = runFit(*fs, out, err); });

    auto ss = std::make_shared<ScoreState>();
    CLI::App* score = app.add_subcommand(
        "score",
        "score a model against the simulator's noiseless ghosts at fitted and held-out angles "
        "(or, with --measured, against its sweep's own frames)");
    score->add_option("MODEL", ss->model, "model file")->required();
    score->add_option("--lens", ss->lens_file,
                      "the lens prescription the sweep was simulated with (required unless "
                      "--measured)");
    score->add_option("--angles", ss->angles, "held-out angles to score (deg), comma separated")
        ->delimiter(',');
    score->add_option("--halfway", ss->halfway, "half-way angles scored when --angles is not given")
        ->capture_default_str();
    score->add_option("--random", ss->random, "random angles scored when --angles is not given")
        ->capture_default_str();
    score->add_option("--fitted", ss->fit_angles, "captured angles scored")->capture_default_str();
    score->add_option("--sweep", ss->sweep,
                      "the sweep the model was fitted from: its frames the fit left out (fit "
                      "--every K) are scored as held out");
    score->add_option("--left-out", ss->left_out, "left-out frames scored at most")
        ->capture_default_str();
    score
        ->add_option("--log-scale", ss->log_scale,
                     "the log image's scale, relative to the truth's peak: log(1 + v / s)")
        ->capture_default_str();
    score->add_option("--images", ss->images,
                      "write truth | model | difference per angle as PNG into this directory");
    score->add_option("--light-mask-px", ss->light_mask_px,
                      "radius of the disc around the light left out of the score, pixels "
                      "(default: the disc the fit left out of its frames, as the model records "
                      "it; 3% of the frame's diagonal for a model that does not)");
    score->add_option("--seed", ss->seed, "seed of the random angles")->capture_default_str();
    score->add_flag("--measured", ss->measured,
                    "score against the --sweep's own frames (the sky subtracted, noise "
                    "included) at the fitted and left-out angles, instead of the simulator: for "
                    "a lens without a prescription");
    score->add_flag("--json", ss->json, "print the scores as JSON");
    score->callback([ss, &out, &err, &exit_code] { exit_code = runScore(*ss, out, err); });
}

}  // namespace flarelab::apps
