#include "bench/predict_bench.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ostream>
#include <random>
#include <tuple>

#include "drivers/lens_settings.h"
#include "drivers/sim_truth.h"
#include "fit/model_eval.h"
#include "fit/model_file.h"
#include "optics/prescription.h"
#include "drivers/sim_camera.h"
#include "predict/figures.h"
#include "predict/lab_figures.h"
#include "predict/predictor.h"
#include "predict/switching.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;

double msSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

double median(std::vector<double> v) {
    if (v.empty()) return 0.0;
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
}

double worst(const std::vector<double>& v) {
    return v.empty() ? 0.0 : *std::max_element(v.begin(), v.end());
}

struct Constellation {
    double theta_deg, phi_deg;
};

}  // namespace

Result<PredictBenchResult> runPredictBench(const PredictBenchOptions& o, std::ostream& log) {
    if (o.constellations < 1 || o.cameras < 1 || o.repeat < 1 || !(o.hours > 0.0) ||
        !(o.step_s >= 0.001))
        return makeError(ErrorCode::InvalidArgument,
                         "bench predict: constellations, cameras and repeat must be >= 1, hours > "
                         "0, step_s >= 0.001");
    auto model = fit::readModel(o.model_path);
    if (!model) return model.error();
    PredictBenchResult r;
    r.model = o.model_path;
    r.ghosts = static_cast<int64_t>(model->ghosts.size());
    std::tie(r.valid_from_deg, r.valid_to_deg) = predict::coveredTheta(*model);
    r.constellations = o.constellations;
    const int64_t width = model->capture.width_px, height = model->capture.height_px;

    // 1. The table against drawing each constellation.
    std::mt19937_64 rng(o.seed);
    std::uniform_real_distribution<double> theta(r.valid_from_deg, r.valid_to_deg),
        phi(-180.0, 180.0);
    std::vector<Constellation> cs;
    std::vector<predict::FlareFigures> drawn;
    std::vector<double> draw_ms;
    for (int k = 0; k < o.constellations; ++k) {
        const Constellation c{theta(rng), phi(rng)};
        const auto start = Clock::now();
        auto image = fit::renderModel(*model, c.theta_deg, c.phi_deg, width, height);
        draw_ms.push_back(msSince(start));
        if (!image) return image.error();
        cs.push_back(c);
        drawn.push_back(predict::flareFigures(*image));
    }
    r.draw_ms = median(draw_ms);
    double largest = 0.0;
    for (const auto& f : drawn) largest = std::max(largest, f.mean);
    std::vector<predict::FigureTableOptions> configs(1);
    if (o.trade) {
        for (double theta_step : {0.0, 1.0})
            for (double phi_step : {5.0, 15.0, 45.0}) {
                predict::FigureTableOptions t;
                t.theta_step_deg = theta_step;
                t.phi_step_deg = phi_step;
                if (theta_step == 0.0 && phi_step == 5.0) continue;  // the default
                configs.push_back(t);
            }
        predict::FigureTableOptions fine;  // a quarter of the capture's step
        fine.theta_step_deg = std::min(0.5, model->capture.step_deg) / 4.0;
        configs.push_back(fine);
        predict::FigureTableOptions wide;
        wide.width = 480;
        configs.push_back(wide);
    }
    std::optional<predict::FlareFigureTable> default_table;
    for (const auto& config : configs) {
        const auto start = Clock::now();
        auto table = predict::FlareFigureTable::build(*model, config);
        const double ms = msSince(start);
        if (!table) return table.error();
        TableTrade t;
        t.theta_step_deg = (table->thetaToDeg() - table->thetaFromDeg()) /
                           static_cast<double>(table->thetaCount() - 1);
        t.phi_step_deg = config.phi_step_deg;
        t.width = config.width;
        t.build_ms = ms;
        std::vector<double> mean_err, peak_err;
        for (size_t k = 0; k < cs.size(); ++k) {
            const auto f = table->at(cs[k].theta_deg, cs[k].phi_deg);
            if (!f) return makeError(ErrorCode::Internal, "bench predict: a lookup missed");
            const double d = std::abs(f->mean - drawn[k].mean);
            if (drawn[k].mean > 0.0) mean_err.push_back(d / drawn[k].mean);
            if (drawn[k].max > 0.0)
                peak_err.push_back(std::abs(f->max - drawn[k].max) / drawn[k].max);
            if (largest > 0.0)
                t.mean_worst_err_of_largest = std::max(t.mean_worst_err_of_largest, d / largest);
        }
        t.mean_median_rel_err = median(mean_err);
        t.mean_worst_rel_err = worst(mean_err);
        t.peak_median_rel_err = median(peak_err);
        r.tables.push_back(t);
        log << "bench predict: table " << t.theta_step_deg << " x " << t.phi_step_deg << " deg, "
            << t.width << " px: " << ms << " ms, mean error median " << t.mean_median_rel_err
            << "\n";
        if (!default_table) default_table = std::move(*table);
    }
    // A lookup against a drawing: batches of lookups, the median batch.
    {
        std::vector<double> batch_ns;
        volatile double sink = 0.0;
        for (int b = 0; b < 7; ++b) {
            const auto start = Clock::now();
            for (const auto& c : cs) sink = sink + default_table->at(c.theta_deg, c.phi_deg)->mean;
            batch_ns.push_back(msSince(start) * 1e6 / static_cast<double>(cs.size()));
        }
        r.lookup_ns = median(batch_ns);
    }

    // 2. Against the simulator.
    if (!o.lens_path.empty()) {
        auto prescription = optics::loadPrescription(o.lens_path);
        if (!prescription) return prescription.error();
        auto lens = drivers::rebuildLens(*prescription, model->lens);
        if (!lens) return lens.error();
        auto truth = drivers::simulatedGhostTruth(lens->lens, width, height, {},
                                                  fit::fittedInColour(*model));
        if (!truth) return truth.error();
        std::vector<double> energy, model_energy, contrast;
        const int angles = std::min(o.constellations, 40);
        for (int k = 0; k < angles; ++k) {
            const double a = theta(rng);
            auto frame = (*truth)(a);
            if (!frame) return frame.error();
            const double true_mean = predict::flareFigures(frame->image).mean;
            if (!(true_mean > 0.0)) continue;
            const double predicted = default_table->at(a, model->capture.roll_deg)->mean;
            auto image = fit::renderModel(*model, a, model->capture.roll_deg, width, height);
            if (!image) return image.error();
            energy.push_back(std::abs(predicted - true_mean) / true_mean);
            model_energy.push_back(std::abs(predict::flareFigures(*image).mean - true_mean) /
                                   true_mean);
            // The scene whose contrast the true flare cuts to 90 %: S / (S + 2F) = 0.9.
            const double s = 18.0 * true_mean;
            contrast.push_back(std::abs(predict::contrastRatio(0.0, s, predicted) - 0.9));
        }
        r.truth_angles = static_cast<int>(energy.size());
        r.energy_median_rel_err = median(energy);
        r.energy_worst_rel_err = worst(energy);
        r.model_energy_median_rel_err = median(model_energy);
        r.contrast_median_abs_err = median(contrast);
        r.contrast_worst_abs_err = worst(contrast);

        // The lab figures: the model's centre flare (the table's) against the simulator's at the
        // same angles, averaged over the same disc (1.5 table pixels about the centre).
        drivers::SimCameraOptions sim;
        sim.width_px = width;
        sim.height_px = height;
        if (fit::fittedInColour(*model)) sim.format = hdr::RawFormat::BayerRGGB;
        const auto sim_power = drivers::simLightPower(lens->lens, sim);
        if (!sim_power)
            return makeError(ErrorCode::Internal, "bench predict: the lens passes no light");
        r.light_power_from_model = model->capture.light_power_dn_s.has_value();
        r.light_power_dn_s = model->capture.light_power_dn_s.value_or(*sim_power);
        if (r.light_power_from_model)
            r.light_power_rel_err = std::abs(r.light_power_dn_s - *sim_power) / *sim_power;
        fit::FlareModel scaled = *model;
        scaled.capture.light_power_dn_s = r.light_power_dn_s;
        auto lab = predict::labFigures(scaled, *default_table);
        if (!lab) return lab.error();
        if (lab->scaled) {
            const double radius_px = 1.5 * static_cast<double>(width) /
                                     static_cast<double>(predict::FigureTableOptions{}.width);
            std::vector<double> truth_centre;
            for (double t : lab->theta_deg) {
                // A light at theta on the side the model covers (playback.h).
                const double a = t >= model->valid_from_deg && t <= model->valid_to_deg ? t : -t;
                auto frame = (*truth)(a);
                if (!frame) return frame.error();
                double sum = 0.0;
                int n = 0;
                for (int64_t y = 0; y < height; ++y)
                    for (int64_t x = 0; x < width; ++x) {
                        const double dx = x + 0.5 - 0.5 * width, dy = y + 0.5 - 0.5 * height;
                        if (dx * dx + dy * dy > radius_px * radius_px) continue;
                        const float* p = frame->image.at(x, y);
                        sum += 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2];
                        ++n;
                    }
                truth_centre.push_back(n > 0 ? sum / n : 0.0);
            }
            auto truth_lab = predict::labFiguresOfCentre(scaled, lab->theta_deg, truth_centre);
            if (!truth_lab) return truth_lab.error();
            r.vgi = lab->vgi;
            r.vgi_truth = truth_lab->vgi;
            r.vgi_from_deg = lab->vgi_from_deg;
            r.vgi_to_deg = lab->vgi_to_deg;
            r.image_flare = lab->image_flare;
            r.image_flare_truth = truth_lab->image_flare;
            r.image_flare_complete = lab->image_flare_complete;
            const double top = *std::max_element(truth_centre.begin(), truth_centre.end());
            std::vector<double> errors;
            for (size_t i = 0; i < truth_centre.size(); ++i)
                if (truth_centre[i] > 1e-3 * top)
                    errors.push_back(std::abs(lab->centre_flare[i] - truth_centre[i]) /
                                     truth_centre[i]);
            r.centre_flare_median_rel_err = errors.empty() ? -1.0 : median(errors);
        }
    }

    // 3. A broadcast: cameras on a circle around a stadium's centre, looking at it, in Vienna on
    // the longest day from 18:30 local time; the sun sets in the west-north-west.
    predict::SceneSun sun;
    sun.site.latitude_deg = 48.2073;
    sun.site.longitude_deg = 16.4205;
    sun.site.elevation_m = 160.0;
    sun.from = *predict::parseIso8601("2026-06-21T18:30:00+02:00");
    sun.step = std::chrono::microseconds(std::llround(o.step_s * 1e6));
    sun.to = sun.from + std::chrono::microseconds(std::llround(o.hours * 3600e6));
    sun.intensity.relative = 20.0;
    std::vector<predict::SceneCamera> scene_cameras;
    for (int c = 0; c < o.cameras; ++c) {
        predict::SceneCamera camera;
        camera.name = "camera " + std::to_string(c + 1);
        camera.model_path = o.model_path;
        camera.exposure_s = 0.02;
        camera.scene_min_dn = 40.0;
        camera.scene_max_dn = 3500.0;
        const double a = 2.0 * 3.14159265358979 * c / o.cameras;
        auto pose =
            predict::poseLookingAt({60.0 * std::cos(a), 40.0 * std::sin(a), 15.0}, {0.0, 0.0, 5.0});
        if (!pose) return pose.error();
        camera.pose = *pose;
        scene_cameras.push_back(camera);
    }
    auto cameras = predict::prepareCameras(scene_cameras);
    if (!cameras) return cameras.error();
    r.cameras = o.cameras;
    std::vector<double> timeline_ms, switching_ms;
    for (int k = 0; k < o.repeat; ++k) {
        auto start = Clock::now();
        auto timeline = predict::predictTimeline(sun, *cameras, {}, predict::RangePolicy::Refuse);
        timeline_ms.push_back(msSince(start));
        if (!timeline) return timeline.error();
        r.steps = static_cast<int64_t>(timeline->sun.positions.size());
        start = Clock::now();
        const auto series =
            predict::switchingFigures(*timeline, predict::SwitchFigure::ContrastLoss);
        predict::SwitchingOptions options;
        options.threshold = 0.02;
        options.min_dwell_steps = std::max<int64_t>(1, std::llround(10.0 / o.step_s));
        auto plan = predict::planSwitching(series, options);
        switching_ms.push_back(msSince(start));
        if (!plan) return plan.error();
    }
    r.timeline_ms = *std::min_element(timeline_ms.begin(), timeline_ms.end());
    r.switching_ms = *std::min_element(switching_ms.begin(), switching_ms.end());
    std::vector<double> frame_ms;
    for (int k = 0; k < 3; ++k) {
        predict::SunLight light{predict::sunDirection(80.0, 280.0), sun.intensity, {1, 1, 1}};
        const auto start = Clock::now();
        auto frame =
            predict::drawCameraFrame((*cameras)[0], {}, light, predict::RangePolicy::Clamp);
        frame_ms.push_back(msSince(start));
        if (!frame) return frame.error();
    }
    r.frames_ms_estimate =
        median(frame_ms) * static_cast<double>(r.steps) * static_cast<double>(o.cameras);
    return r;
}

void printPredictBench(const PredictBenchResult& r, std::ostream& out) {
    char line[512];
    out << "bench predict: " << r.model << " (" << r.ghosts << " ghosts, " << r.valid_from_deg
        << " to " << r.valid_to_deg << " deg), " << r.constellations
        << " random constellations drawn at the capture's size\n";
    out << "| table theta x phi step (deg) | width | build ms | mean err median | mean err worst | "
           "worst / largest mean | peak err median |\n|---|---|---|---|---|---|---|\n";
    for (const auto& t : r.tables) {
        std::snprintf(line, sizeof line,
                      "| %.3g x %.3g | %lld | %.0f | %.4f | %.4f | %.4f | %.4f |\n",
                      t.theta_step_deg, t.phi_step_deg, static_cast<long long>(t.width), t.build_ms,
                      t.mean_median_rel_err, t.mean_worst_rel_err, t.mean_worst_err_of_largest,
                      t.peak_median_rel_err);
        out << line;
    }
    std::snprintf(line, sizeof line,
                  "one constellation drawn: %.2f ms; looked up: %.0f ns (%.3g times faster)\n",
                  r.draw_ms, r.lookup_ns, r.draw_ms * 1e6 / std::max(r.lookup_ns, 1e-3));
    out << line;
    if (r.truth_angles > 0) {
        std::snprintf(line, sizeof line,
                      "against the simulator, %d angles: flare mean error median %.4f, worst "
                      "%.4f (the model drawn itself: median %.4f); contrast ratio at 0.9: error "
                      "median %.4f, worst %.4f\n",
                      r.truth_angles, r.energy_median_rel_err, r.energy_worst_rel_err,
                      r.model_energy_median_rel_err, r.contrast_median_abs_err,
                      r.contrast_worst_abs_err);
        out << line;
    }
    if (r.vgi_truth >= 0.0) {
        std::snprintf(
            line, sizeof line,
            "lab figures (light power %.4g DN/s, %s): veiling glare index %.4g %% against the "
            "simulator's %.4g %% (%.3g to %.3g deg), image flare %.4g %% against %.4g %%%s; centre "
            "flare error median %.3f\n",
            r.light_power_dn_s,
            r.light_power_from_model ? "the model's" : "the simulated camera's", 100.0 * r.vgi,
            100.0 * r.vgi_truth, r.vgi_from_deg, r.vgi_to_deg, 100.0 * r.image_flare,
            100.0 * r.image_flare_truth, r.image_flare_complete ? "" : " (the model ends inside the frame)",
            r.centre_flare_median_rel_err);
        out << line;
    }
    std::snprintf(line, sizeof line,
                  "broadcast: %d cameras x %lld steps: timeline %.1f ms, switching plan %.1f ms "
                  "(best of the runs); drawing every frame instead: about %.0f s\n",
                  r.cameras, static_cast<long long>(r.steps), r.timeline_ms, r.switching_ms,
                  r.frames_ms_estimate / 1000.0);
    out << line;
}

nlohmann::json predictBenchJson(const PredictBenchResult& r) {
    nlohmann::json tables = nlohmann::json::array();
    for (const auto& t : r.tables)
        tables.push_back({{"theta_step_deg", t.theta_step_deg},
                          {"phi_step_deg", t.phi_step_deg},
                          {"width", t.width},
                          {"build_ms", t.build_ms},
                          {"mean_median_rel_err", t.mean_median_rel_err},
                          {"mean_worst_rel_err", t.mean_worst_rel_err},
                          {"mean_worst_err_of_largest", t.mean_worst_err_of_largest},
                          {"peak_median_rel_err", t.peak_median_rel_err}});
    return {{"model", r.model},
            {"ghosts", r.ghosts},
            {"valid_deg", {r.valid_from_deg, r.valid_to_deg}},
            {"constellations", r.constellations},
            {"tables", tables},
            {"draw_ms", r.draw_ms},
            {"lookup_ns", r.lookup_ns},
            {"truth_angles", r.truth_angles},
            {"energy_median_rel_err", r.energy_median_rel_err},
            {"energy_worst_rel_err", r.energy_worst_rel_err},
            {"model_energy_median_rel_err", r.model_energy_median_rel_err},
            {"contrast_median_abs_err", r.contrast_median_abs_err},
            {"contrast_worst_abs_err", r.contrast_worst_abs_err},
            {"light_power_from_model", r.light_power_from_model},
            {"light_power_dn_s", r.light_power_dn_s},
            {"light_power_rel_err", r.light_power_rel_err},
            {"vgi", r.vgi},
            {"vgi_truth", r.vgi_truth},
            {"vgi_deg", {r.vgi_from_deg, r.vgi_to_deg}},
            {"image_flare", r.image_flare},
            {"image_flare_truth", r.image_flare_truth},
            {"image_flare_complete", r.image_flare_complete},
            {"centre_flare_median_rel_err", r.centre_flare_median_rel_err},
            {"steps", r.steps},
            {"cameras", r.cameras},
            {"timeline_ms", r.timeline_ms},
            {"switching_ms", r.switching_ms},
            {"frames_ms_estimate", r.frames_ms_estimate}};
}

}  // namespace flarelab::bench
