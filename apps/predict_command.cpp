#include "apps/predict_command.h"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "fit/model_eval.h"
#include "hdr/exr.h"
#include "predict/predictor.h"
#include "predict/report.h"
#include "predict/scene.h"
#include "render/preview.h"

namespace flarelab::apps {
namespace {

struct PredictState {
    std::string scene_path;
    std::string out_dir;
    bool json = false;
    double table_theta_step_deg = 0.0;
    double table_phi_step_deg = 10.0;
    int64_t table_width = 240;
    double exposure_stops = 0.0;
};

using Clock = std::chrono::steady_clock;

double msSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

std::string fmt(double v, const char* format = "%.6g") {
    if (!std::isfinite(v)) return "";
    char text[48];
    std::snprintf(text, sizeof text, format, v);
    return text;
}

// A JSON number, or null where the figure is unknown.
nlohmann::json num(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(); }

nlohmann::json figuresJson(const predict::FlareFigures& f) {
    return {{"min", num(f.min)},
            {"max", num(f.max)},
            {"mean", num(f.mean)},
            {"log_average", num(f.log_average)},
            {"total", num(f.total)}};
}

// A file name made of the letters, digits, '-' and '_' of `name` (others become '_').
std::string fileStem(const std::string& name) {
    std::string s;
    for (char c : name)
        s += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_') ? c : '_';
    return s.empty() ? "camera" : s;
}

// CSV field: quoted when it holds a comma, quote or line break.
std::string csv(const std::string& s) {
    if (s.find_first_of(",\"\n\r") == std::string::npos) return s;
    std::string q = "\"";
    for (char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
    return q + "\"";
}

double median(std::vector<double> v) {
    v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return !std::isfinite(x); }),
            v.end());
    if (v.empty()) return std::nan("");
    std::nth_element(v.begin(), v.begin() + static_cast<long>(v.size() / 2), v.end());
    return v[v.size() / 2];
}

double maximum(const std::vector<double>& v) {
    double m = std::nan("");
    for (double x : v)
        if (std::isfinite(x) && !(x <= m)) m = x;
    return m;
}

// Each ghost's parameter `name` along theta at roll 0, one series per ghost (at most 24, the
// brightest at their peak), evaluated from the model's series.
predict::ReportPlot parameterPlot(const fit::FlareModel& model,
                                  const std::string& parameter,
                                  const std::string& label) {
    predict::ReportPlot plot;
    plot.title = parameter + " along theta";
    plot.x_label = "theta (deg)";
    plot.y_label = label;
    int index = -1;
    for (int i = 0; i < fit::kGhostParameterCount; ++i)
        if (parameter == fit::ghostParameterInfo(i).name) index = i;
    if (index < 0) return plot;
    const double from = model.valid_from_deg, to = model.valid_to_deg;
    const int n = 121;
    std::vector<std::pair<int64_t, predict::ReportSeries>> series;
    std::vector<double> peak;
    for (int k = 0; k < n; ++k) {
        const double a = from + (to - from) * k / (n - 1);
        const auto ghosts = fit::modelGhostsAt(model, a, model.capture.roll_deg);
        if (!ghosts) continue;
        for (const auto& g : *ghosts) {
            size_t s = 0;
            while (s < series.size() && series[s].first != g.id) ++s;
            if (s == series.size()) {
                predict::ReportSeries fresh;
                fresh.name = "ghost " + std::to_string(g.id);
                series.push_back({g.id, fresh});
                peak.push_back(0.0);
            }
            const fit::GhostParameters p = fit::ghostParameters(g.state);
            series[s].second.x.push_back(a);
            series[s].second.y.push_back(p[static_cast<size_t>(index)]);
            peak[s] = std::max(peak[s], fit::roughGhostEnergy(g.state));
        }
    }
    std::vector<size_t> order(series.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return peak[a] > peak[b]; });
    for (size_t i = 0; i < order.size() && i < 24; ++i)
        plot.series.push_back(std::move(series[order[i]].second));
    return plot;
}

int run(const PredictState& s, std::ostream& out, std::ostream& err) {
    const auto fail = [&](const Error& e) {
        err << "flarelab: predict: " << e.message << "\n";
        return e.code == ErrorCode::ParseError || e.code == ErrorCode::InvalidArgument ? 2 : 1;
    };
    auto scene = predict::loadScene(s.scene_path);
    if (!scene) return fail(scene.error());
    std::error_code ec;
    std::filesystem::create_directories(std::filesystem::path(s.out_dir) / "frames", ec);
    if (ec) {
        err << "flarelab: predict: " << s.out_dir << ": cannot create: " << ec.message() << "\n";
        return 1;
    }
    predict::FigureTableOptions table_options;
    table_options.theta_step_deg = s.table_theta_step_deg;
    table_options.phi_step_deg = s.table_phi_step_deg;
    table_options.width = s.table_width;
    auto start = Clock::now();
    auto cameras = predict::prepareCameras(scene->cameras, table_options);
    if (!cameras) return fail(cameras.error());
    const double tables_ms = msSince(start);

    nlohmann::json report;
    report["scene"] = s.scene_path;
    report["notes"] = scene->notes;
    for (const std::string& note : scene->notes) err << "flarelab: predict: note: " << note << "\n";
    report["out_of_range"] = predict::rangePolicyName(scene->out_of_range);
    report["unit"] = "DN of each camera (eq. 8.3 of the thesis)";
    predict::Report html;
    html.title = "Flare prediction: " + std::filesystem::path(s.scene_path).filename().string();

    // Fixed lights, per camera.
    predict::ReportSection summary;
    summary.title = "Cameras and fixed lights";
    summary.paragraphs.push_back(
        "Figures are in each camera's DN: the model's DN/s scaled by eq. 8.3 (exposure, gain, "
        "f-number, the light's irradiance over the rig light's). Mean and total add over the "
        "lights; the peak of several lights is an upper bound. Lights outside a model's range "
        "are " +
        std::string(scene->out_of_range == predict::RangePolicy::Clamp
                        ? "drawn at the nearest angle the model covers (clamped)."
                        : "refused: their flare is unknown and the camera's figures with them."));
    predict::ReportTable lights_table;
    lights_table.title = "Each light at each camera";
    lights_table.header = {"camera",    "light",      "state",      "theta (deg)",
                           "phi (deg)", "flare mean", "flare peak", "flare total"};
    predict::ReportTable cameras_table;
    cameras_table.title = "Each camera, fixed lights together";
    cameras_table.header = {"camera", "model",      "f-number",   "exposure (s)",
                            "image",  "flare mean", "flare peak", "contrast ratio (eq. 9.3)",
                            "notes"};
    std::string figures_csv =
        "camera,light,state,theta_deg,phi_deg,model_theta_deg,flare_min,flare_max,flare_mean,"
        "flare_log_average,flare_total\n";
    nlohmann::json cameras_json = nlohmann::json::array();
    std::vector<predict::CameraFigures> fixed;
    for (const predict::PreparedCamera& camera : *cameras) {
        auto figures = predict::fixedLightFigures(camera, scene->lights, scene->out_of_range);
        if (!figures) return fail(figures.error());
        nlohmann::json cj;
        cj["name"] = camera.scene.name;
        cj["model"] = camera.scene.model_path;
        cj["model_valid_deg"] = {camera.model.valid_from_deg, camera.model.valid_to_deg};
        cj["ghosts"] = camera.model.ghosts.size();
        cj["f_number"] = camera.exposure.f_number;
        cj["exposure_s"] = camera.exposure.exposure_s;
        cj["gain"] = camera.exposure.gain;
        cj["width_px"] = camera.width;
        cj["height_px"] = camera.height;
        cj["notes"] = camera.notes;
        cj["known"] = figures->known;
        cj["fixed_lights"] = figuresJson(figures->sum);
        cj["contrast_ratio"] =
            figures->contrast_ratio ? nlohmann::json(*figures->contrast_ratio) : nlohmann::json();
        nlohmann::json lights_json = nlohmann::json::array();
        for (const predict::LightFigures& lf : figures->lights) {
            const bool placed = lf.placed.state != predict::LightState::AtCamera;
            lights_json.push_back(
                {{"light", lf.light},
                 {"state", predict::lightStateName(lf.placed.state)},
                 {"theta_deg", placed ? num(lf.placed.constellation.theta_deg) : nlohmann::json()},
                 {"phi_deg", placed ? num(lf.placed.constellation.phi_deg) : nlohmann::json()},
                 {"model_theta_deg",
                  lf.placed.drawn() ? num(lf.placed.model_theta_deg) : nlohmann::json()},
                 {"figures", figuresJson(lf.figures)}});
            lights_table.rows.push_back(
                {camera.scene.name, lf.light, predict::lightStateName(lf.placed.state),
                 placed ? fmt(lf.placed.constellation.theta_deg, "%.2f") : "",
                 placed ? fmt(lf.placed.constellation.phi_deg, "%.1f") : "",
                 lf.placed.drawn() ? fmt(lf.figures.mean) : "",
                 lf.placed.drawn() ? fmt(lf.figures.max) : "",
                 lf.placed.drawn() ? fmt(lf.figures.total) : ""});
            figures_csv += csv(camera.scene.name) + "," + csv(lf.light) + "," +
                           predict::lightStateName(lf.placed.state) + "," +
                           (placed ? fmt(lf.placed.constellation.theta_deg) : "") + "," +
                           (placed ? fmt(lf.placed.constellation.phi_deg) : "") + "," +
                           (lf.placed.drawn() ? fmt(lf.placed.model_theta_deg) : "") + "," +
                           fmt(lf.figures.min) + "," + fmt(lf.figures.max) + "," +
                           fmt(lf.figures.mean) + "," + fmt(lf.figures.log_average) + "," +
                           fmt(lf.figures.total) + "\n";
        }
        cj["lights"] = lights_json;
        cameras_json.push_back(cj);
        std::string notes;
        for (const auto& n : camera.notes) notes += (notes.empty() ? "" : "; ") + n;
        cameras_table.rows.push_back(
            {camera.scene.name, std::filesystem::path(camera.scene.model_path).filename().string(),
             fmt(camera.exposure.f_number), fmt(camera.exposure.exposure_s),
             std::to_string(camera.width) + "x" + std::to_string(camera.height),
             figures->known ? fmt(figures->sum.mean) : "unknown",
             figures->known ? fmt(figures->sum.max) : "unknown",
             figures->contrast_ratio ? fmt(*figures->contrast_ratio, "%.4f") : "", notes});
        fixed.push_back(*figures);
    }
    report["cameras"] = cameras_json;
    summary.tables.push_back(cameras_table);
    if (!scene->lights.empty()) summary.tables.push_back(lights_table);
    if (!scene->notes.empty()) {
        summary.paragraphs.push_back("Notes from the glTF import:");
        for (const std::string& note : scene->notes) summary.paragraphs.push_back(note);
    }
    html.sections.push_back(summary);

    // The models: the flare of the rig's light along theta, and the ghosts' parameters.
    for (size_t c = 0; c < cameras->size(); ++c) {
        const predict::PreparedCamera& camera = (*cameras)[c];
        bool seen = false;
        for (size_t d = 0; d < c; ++d)
            seen |= (*cameras)[d].scene.model_path == camera.scene.model_path;
        if (seen) continue;
        predict::ReportSection section;
        section.title =
            "Model " + std::filesystem::path(camera.scene.model_path).filename().string();
        section.paragraphs.push_back(
            camera.model.lens.description + ": " + std::to_string(camera.model.ghosts.size()) +
            " ghosts, valid from " + fmt(camera.model.valid_from_deg) + " to " +
            fmt(camera.model.valid_to_deg) +
            " deg. The curves are the model's series evaluated along theta (the per-frame fits "
            "they compress are not stored in model files; their residuals are, in `flarelab model "
            "show`).");
        predict::ReportPlot flare;
        flare.title = "Flare of the rig's light along theta (model units, DN/s)";
        flare.x_label = "theta (deg)";
        flare.y_label = "flare mean";
        flare.log_y = true;
        for (double phi : {0.0, 90.0}) {
            predict::ReportSeries mean;
            mean.name = "mean, phi " + fmt(phi) + " deg";
            for (int64_t i = 0; i < camera.table.thetaCount(); ++i) {
                const double theta = camera.table.thetaAt(i);
                const auto f = camera.table.at(theta, phi);
                mean.x.push_back(theta);
                mean.y.push_back(f ? f->mean : std::nan(""));
            }
            flare.series.push_back(mean);
        }
        section.plots.push_back(flare);
        section.plots.push_back(parameterPlot(camera.model, "centre_x_mm", "mm"));
        section.plots.push_back(parameterPlot(camera.model, "half_height_mm", "mm"));
        section.plots.push_back(parameterPlot(camera.model, "ln_inner_rgb[1]", "ln(DN/s)"));
        html.sections.push_back(section);
    }

    // The sun: timeline and switching plan.
    std::optional<predict::Timeline> timeline;
    double timeline_ms = 0.0, plan_ms = 0.0;
    if (scene->sun) {
        start = Clock::now();
        auto t =
            predict::predictTimeline(*scene->sun, *cameras, scene->lights, scene->out_of_range);
        if (!t) return fail(t.error());
        timeline_ms = msSince(start);
        timeline = std::move(*t);
        const size_t steps = timeline->sun.positions.size();
        const double step_s = std::chrono::duration<double>(timeline->sun.step).count();
        std::string tcsv = "time_utc,sun_zenith_deg,sun_azimuth_deg";
        for (const auto& camera : *cameras)
            for (const char* column : {" flare_mean", " flare_peak", " contrast_loss", " sun"})
                tcsv += "," + csv(camera.scene.name + column);
        tcsv += "\n";
        for (size_t i = 0; i < steps; ++i) {
            const auto& p = timeline->sun.positions[i];
            tcsv += predict::formatIso8601(timeline->sun.instant(i)) + "," +
                    fmt(p.zenith_deg, "%.5f") + "," + fmt(p.azimuth_deg, "%.5f");
            for (const auto& ct : timeline->cameras)
                tcsv += "," + fmt(ct.flare_mean[i]) + "," + fmt(ct.flare_peak[i]) + "," +
                        fmt(ct.contrast_loss[i]) + "," + predict::lightStateName(ct.sun_state[i]);
            tcsv += "\n";
        }
        if (auto w = predict::writeTextFileAtomically(
                (std::filesystem::path(s.out_dir) / "timeline.csv").string(), tcsv);
            !w)
            return fail(w.error());

        predict::ReportSection section;
        section.title = "The sun from " + predict::formatIso8601(scene->sun->from) + " to " +
                        predict::formatIso8601(scene->sun->to);
        section.paragraphs.push_back(
            std::to_string(steps) + " steps of " + fmt(step_s) +
            " s (timeline.csv). Sun position: NREL SPA. "
            "A step is unknown for a camera when the sun or a fixed light lies outside its model "
            "and the scene refuses extrapolation.");
        predict::ReportTable counts;
        counts.title = "Where the sun stood for each camera (steps)";
        counts.header = {
            "camera",  "below horizon",      "behind camera",   "in the model's range", "clamped",
            "refused", "flare mean, median", "flare mean, max", "contrast loss, max"};
        nlohmann::json tj = nlohmann::json::array();
        predict::ReportPlot mean_plot, loss_plot;
        mean_plot.title = "Flare mean along the day";
        mean_plot.x_label = "hours from " + predict::formatIso8601(scene->sun->from);
        mean_plot.y_label = "flare mean (DN)";
        mean_plot.log_y = true;
        loss_plot.title = "Contrast loss along the day (1 - eq. 9.3)";
        loss_plot.x_label = mean_plot.x_label;
        loss_plot.y_label = "contrast loss";
        std::vector<double> hours(steps);
        for (size_t i = 0; i < steps; ++i) hours[i] = static_cast<double>(i) * step_s / 3600.0;
        for (size_t c = 0; c < cameras->size(); ++c) {
            const auto& ct = timeline->cameras[c];
            const std::string& name = (*cameras)[c].scene.name;
            counts.rows.push_back(
                {name, std::to_string(ct.steps_sun_down), std::to_string(ct.steps_behind),
                 std::to_string(ct.steps_drawn), std::to_string(ct.steps_clamped),
                 std::to_string(ct.steps_refused), fmt(median(ct.flare_mean)),
                 fmt(maximum(ct.flare_mean)), fmt(maximum(ct.contrast_loss), "%.4f")});
            tj.push_back({{"camera", name},
                          {"steps_sun_down", ct.steps_sun_down},
                          {"steps_behind_camera", ct.steps_behind},
                          {"steps_drawn", ct.steps_drawn},
                          {"steps_clamped", ct.steps_clamped},
                          {"steps_refused", ct.steps_refused},
                          {"flare_mean_median", num(median(ct.flare_mean))},
                          {"flare_mean_max", num(maximum(ct.flare_mean))},
                          {"flare_peak_max", num(maximum(ct.flare_peak))},
                          {"contrast_loss_max", num(maximum(ct.contrast_loss))}});
            predict::ReportSeries m{name, hours, ct.flare_mean};
            mean_plot.series.push_back(m);
            bool any_loss = false;
            for (double v : ct.contrast_loss) any_loss |= std::isfinite(v);
            if (any_loss)
                loss_plot.series.push_back(predict::ReportSeries{name, hours, ct.contrast_loss});
        }
        report["timeline"] = {{"from_utc", predict::formatIso8601(scene->sun->from)},
                              {"to_utc", predict::formatIso8601(scene->sun->to)},
                              {"step_s", step_s},
                              {"steps", steps},
                              {"cameras", tj},
                              {"ms", timeline_ms}};
        section.tables.push_back(counts);
        std::optional<predict::ReportPlot> plan_plot_kept;

        if (scene->switching) {
            const auto& sw = *scene->switching;
            predict::SwitchingOptions options;
            options.threshold = sw.threshold;
            options.min_dwell_steps = std::max<int64_t>(
                1, static_cast<int64_t>(std::ceil(sw.min_dwell_s / step_s - 1e-9)));
            start = Clock::now();
            const auto series = predict::switchingFigures(*timeline, sw.figure);
            auto plan = predict::planSwitching(series, options);
            if (!plan) return fail(plan.error());
            plan_ms = msSince(start);
            if (sw.figure == predict::SwitchFigure::ContrastLoss)
                loss_plot.threshold = sw.threshold;
            predict::ReportPlot plan_plot;
            plan_plot.title =
                "Switching plan (" + std::string(predict::switchFigureName(sw.figure)) +
                " <= " + fmt(sw.threshold) + ", shots of at least " + fmt(sw.min_dwell_s) + " s)";
            plan_plot.x_label = mean_plot.x_label;
            plan_plot.y_label = "camera";
            for (const auto& camera : *cameras) plan_plot.y_categories.push_back(camera.scene.name);
            predict::ReportSeries chosen;
            chosen.name = "camera on air";
            chosen.steps = true;
            predict::ReportTable plan_table;
            plan_table.title = "Shots";
            plan_table.header = {"camera", "from", "to", "seconds", "steps over the threshold"};
            std::string pcsv = "camera,from_utc,to_utc,seconds,steps_over\n";
            nlohmann::json segments = nlohmann::json::array();
            for (const auto& seg : plan->segments) {
                int64_t over = 0;
                for (int64_t t = seg.first_step; t < seg.end_step; ++t)
                    over += !(series[static_cast<size_t>(seg.camera)][static_cast<size_t>(t)] <=
                              sw.threshold);
                const std::string name = (*cameras)[static_cast<size_t>(seg.camera)].scene.name;
                const std::string a = predict::formatIso8601(
                    timeline->sun.instant(static_cast<size_t>(seg.first_step)));
                const std::string b = predict::formatIso8601(
                    timeline->sun.instant(static_cast<size_t>(seg.end_step)));
                const double seconds = static_cast<double>(seg.end_step - seg.first_step) * step_s;
                plan_table.rows.push_back({name, a, b, fmt(seconds), std::to_string(over)});
                pcsv += csv(name) + "," + a + "," + b + "," + fmt(seconds) + "," +
                        std::to_string(over) + "\n";
                segments.push_back(
                    {{"camera", name}, {"from_utc", a}, {"to_utc", b}, {"steps_over", over}});
                chosen.x.push_back(hours[static_cast<size_t>(seg.first_step)]);
                chosen.y.push_back(seg.camera);
            }
            chosen.x.push_back(static_cast<double>(steps) * step_s / 3600.0);
            chosen.y.push_back(plan->segments.back().camera);
            plan_plot.series.push_back(chosen);
            nlohmann::json none = nlohmann::json::array();
            predict::ReportTable none_table;
            none_table.title = "No clean camera";
            none_table.header = {"from", "to", "seconds"};
            for (const auto& gap : plan->no_clean_camera) {
                const std::string a = predict::formatIso8601(
                    timeline->sun.instant(static_cast<size_t>(gap.first_step)));
                const std::string b = predict::formatIso8601(
                    timeline->sun.instant(static_cast<size_t>(gap.end_step)));
                none.push_back({{"from_utc", a}, {"to_utc", b}});
                none_table.rows.push_back(
                    {a, b, fmt(static_cast<double>(gap.end_step - gap.first_step) * step_s)});
            }
            report["switching"] = {{"figure", predict::switchFigureName(sw.figure)},
                                   {"threshold", sw.threshold},
                                   {"min_dwell_s", sw.min_dwell_s},
                                   {"steps_over", plan->steps_over},
                                   {"cuts", plan->cuts},
                                   {"segments", segments},
                                   {"no_clean_camera", none},
                                   {"ms", plan_ms}};
            if (auto w = predict::writeTextFileAtomically(
                    (std::filesystem::path(s.out_dir) / "plan.csv").string(), pcsv);
                !w)
                return fail(w.error());
            section.paragraphs.push_back(
                "Switching plan: " + std::to_string(plan->segments.size()) + " shot(s), " +
                std::to_string(plan->cuts) + " cut(s), " + std::to_string(plan->steps_over) +
                " step(s) over the threshold; " + std::to_string(plan->no_clean_camera.size()) +
                " interval(s) with no clean camera (plan.csv).");
            plan_plot_kept = plan_plot;
            section.tables.push_back(plan_table);
            if (!none_table.rows.empty()) section.tables.push_back(none_table);
        }
        section.plots.push_back(mean_plot);
        if (!loss_plot.series.empty()) section.plots.push_back(loss_plot);
        if (plan_plot_kept) section.plots.push_back(*plan_plot_kept);
        html.sections.push_back(section);
    }

    // Frames: each camera at each chosen instant, or once with the fixed lights.
    predict::ReportSection frames_section;
    frames_section.title = "Frames";
    frames_section.paragraphs.push_back(
        "Each frame is the flare alone in the camera's DN (EXR beside each PNG); the PNG shows the "
        "camera's white (scene_max_dn, else the frame's peak) as white" +
        (s.exposure_stops != 0.0 ? ", " + fmt(s.exposure_stops) + " stops brighter" : "") + ".");
    nlohmann::json frames_json = nlohmann::json::array();
    std::vector<std::optional<predict::UtcInstant>> instants;
    if (scene->frames.empty() || !scene->sun) instants.push_back(std::nullopt);
    for (const auto& t : scene->frames) instants.push_back(t);
    double frames_ms = 0.0;
    for (const auto& instant : instants) {
        std::optional<predict::SunLight> sun;
        std::string when;
        if (instant && scene->sun) {
            auto p = predict::sunPosition(scene->sun->site, *instant);
            if (!p) return fail(p.error().withContext("frames"));
            when = predict::formatIso8601(*instant);
            if (p->elevation_deg > 0.0)
                sun = predict::SunLight{predict::sunDirection(p->zenith_deg, p->azimuth_deg),
                                        scene->sun->intensity, scene->sun->colour};
        }
        for (size_t c = 0; c < cameras->size(); ++c) {
            const predict::PreparedCamera& camera = (*cameras)[c];
            start = Clock::now();
            auto frame = predict::drawCameraFrame(camera, scene->lights, sun, scene->out_of_range);
            if (!frame) return fail(frame.error());
            frames_ms += msSince(start);
            // Numbered: two names may differ only in what a file name cannot hold.
            std::string stem = std::to_string(c + 1) + "-" + fileStem(camera.scene.name);
            if (!when.empty()) {
                std::string t = when;
                std::replace(t.begin(), t.end(), ':', '-');
                stem += "_" + t;
            }
            const std::string png = "frames/" + stem + ".png";
            const std::string exr = "frames/" + stem + ".exr";
            hdr::ExrMetadata meta;
            meta.camera = camera.scene.name;
            meta.lens = camera.model.lens.description;
            meta.software_version = "flarelab predict";
            if (auto w = hdr::writeExr((std::filesystem::path(s.out_dir) / exr).string(),
                                       frame->image, meta);
                !w)
                return fail(w.error());
            // As the camera would show it: its white (the scene's brightest DN, else the
            // frame's peak) at 1, then --exposure-stops.
            const predict::FlareFigures f = predict::flareFigures(frame->image);
            const double white = camera.scene.scene_max_dn.value_or(std::max(1e-30, f.max));
            render::ToneMapOptions tone;
            tone.exposure_stops = std::clamp(s.exposure_stops - std::log2(white), -64.0, 64.0);
            if (auto w = render::writePng(frame->image,
                                          (std::filesystem::path(s.out_dir) / png).string(), tone);
                !w)
                return fail(w.error());
            int refused = 0;
            for (const auto& l : frame->lights)
                refused += l.state == predict::LightState::OutsideRange;
            frames_section.images.push_back(
                {camera.scene.name + (when.empty() ? "" : " at " + when) + ": flare mean " +
                     fmt(f.mean) + ", peak " + fmt(f.max) +
                     (refused > 0 ? " (" + std::to_string(refused) +
                                        " light(s) outside the model's range not drawn)"
                                  : ""),
                 png});
            nlohmann::json lights = nlohmann::json::array();
            for (const auto& l : frame->lights) lights.push_back(predict::lightStateName(l.state));
            frames_json.push_back(
                {{"camera", camera.scene.name},
                 {"time_utc", when.empty() ? nlohmann::json() : nlohmann::json(when)},
                 {"png", png},
                 {"exr", exr},
                 {"figures", figuresJson(f)},
                 {"light_states", lights}});
        }
    }
    report["frames"] = frames_json;
    html.sections.push_back(frames_section);
    report["timings_ms"] = {{"tables", tables_ms},
                            {"timeline", timeline_ms},
                            {"switching", plan_ms},
                            {"frames", frames_ms}};

    const std::filesystem::path dir(s.out_dir);
    const std::string json_text = report.dump(2) + "\n";
    for (const auto& [name, text] :
         {std::pair<std::string, std::string>{"figures.csv", figures_csv},
          {"report.json", json_text},
          {"report.html", predict::reportHtml(html)}})
        if (auto w = predict::writeTextFileAtomically((dir / name).string(), text); !w)
            return fail(w.error());
    if (s.json) {
        out << json_text;
        return 0;
    }
    out << "predict: " << cameras->size() << " cameras, " << scene->lights.size() << " fixed lights"
        << (scene->sun ? ", the sun" : "") << " -> " << s.out_dir << "/report.html\n";
    for (size_t c = 0; c < cameras->size(); ++c) {
        const auto& f = fixed[c];
        out << "  " << (*cameras)[c].scene.name << ": fixed lights' flare mean "
            << (f.known ? fmt(f.sum.mean) : "unknown") << " DN, peak "
            << (f.known ? fmt(f.sum.max) : "unknown") << " DN"
            << (f.contrast_ratio ? ", contrast ratio " + fmt(*f.contrast_ratio, "%.4f") : "")
            << "\n";
    }
    if (report.contains("switching"))
        out << "  switching: " << report["switching"]["segments"].size() << " shots, "
            << report["switching"]["steps_over"].get<int64_t>() << " steps over the threshold\n";
    out << "  tables " << fmt(tables_ms, "%.0f") << " ms, timeline " << fmt(timeline_ms, "%.1f")
        << " ms, switching " << fmt(plan_ms, "%.1f") << " ms, frames " << fmt(frames_ms, "%.0f")
        << " ms\n";
    return 0;
}

}  // namespace

void addPredictCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto s = std::make_shared<PredictState>();
    CLI::App* cmd = app.add_subcommand(
        "predict",
        "flare figures, a sun timeline with a camera switching plan, frames and a report for a "
        "scene file (docs/predict.md)");
    cmd->add_option("SCENE", s->scene_path, "scene file (JSON, flarelab-scene version 1)")
        ->required();
    cmd->add_option("-o,--output", s->out_dir, "report folder (created)")->required();
    cmd->add_flag("--json", s->json, "print report.json instead of the summary");
    cmd->add_option("--table-theta-step", s->table_theta_step_deg,
                    "figure table's theta step, deg (0: the capture's, at most 0.5)")
        ->check(CLI::Range(0.0, 10.0))
        ->capture_default_str();
    cmd->add_option("--table-phi-step", s->table_phi_step_deg,
                    "figure table's roll step, deg (divides 360)")
        ->check(CLI::Range(0.5, 90.0))
        ->capture_default_str();
    cmd->add_option("--table-width", s->table_width, "figure table's drawing width, px")
        ->check(CLI::Range(int64_t{8}, int64_t{4096}))
        ->capture_default_str();
    cmd->add_option("--exposure-stops", s->exposure_stops,
                    "frames' PNG exposure, stops above the camera's white (scene_max_dn)")
        ->capture_default_str();
    cmd->callback([s, &out, &err, &exit_code] { exit_code = run(*s, out, err); });
}

}  // namespace flarelab::apps
