#include "predict/prediction.h"

#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "fit/model_eval.h"
#include "hdr/exr.h"
#include "predict/report.h"
#include "predict/scene.h"
#include "render/preview.h"

namespace flarelab::predict {
namespace {

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

nlohmann::json figuresJson(const FlareFigures& f) {
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
bool modelKeptSamples(const fit::FlareModel& model) {
    for (const fit::ModelGhost& g : model.ghosts)
        for (const fit::ModelParameter& p : g.parameters)
            if (!p.sample_values.empty()) return true;
    return false;
}

ReportPlot parameterPlot(const fit::FlareModel& model,
                         const std::string& parameter,
                         const std::string& label) {
    ReportPlot plot;
    plot.title = parameter + " along theta";
    plot.x_label = "theta (deg)";
    plot.y_label = label;
    int index = -1;
    for (int i = 0; i < fit::kGhostParameterCount; ++i)
        if (parameter == fit::ghostParameterInfo(i).name) index = i;
    if (index < 0) return plot;
    const double from = model.valid_from_deg, to = model.valid_to_deg;
    const int n = 121;
    std::vector<std::pair<int64_t, ReportSeries>> series;
    std::vector<double> peak;
    for (int k = 0; k < n; ++k) {
        const double a = from + (to - from) * k / (n - 1);
        const auto ghosts = fit::modelGhostsAt(model, a, model.capture.roll_deg);
        if (!ghosts) continue;
        for (const auto& g : *ghosts) {
            size_t s = 0;
            while (s < series.size() && series[s].first != g.id) ++s;
            if (s == series.size()) {
                ReportSeries fresh;
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
    std::vector<ReportSeries> fitted;
    for (size_t i = 0; i < order.size() && i < 24; ++i) {
        const int64_t id = series[order[i]].first;
        plot.series.push_back(std::move(series[order[i]].second));
        // The per-frame values the series was fitted to, when the model kept them.
        for (const fit::ModelGhost& ghost : model.ghosts) {
            if (ghost.id != id) continue;
            for (const fit::ModelParameter& p : ghost.parameters)
                if (p.name == parameter && !p.sample_values.empty())
                    fitted.push_back(ReportSeries{"ghost " + std::to_string(id) + ", fitted",
                                                  p.sample_angles_deg, p.sample_values, false,
                                                  true});
        }
    }
    for (ReportSeries& f : fitted) plot.series.push_back(std::move(f));
    return plot;
}

constexpr const char* kStopped = "stopped before the prediction ended";

// `text` with every `from` replaced by `to`.
std::string replaced(std::string text, const std::string& from, const std::string& to) {
    if (from.empty()) return text;
    for (size_t at = text.find(from); at != std::string::npos; at = text.find(from, at + to.size()))
        text.replace(at, from.size(), to);
    return text;
}

// prepareCameras, and with a stop check (a server's) one model at a time, asking between them:
// the cameras that share a model are prepared together, so each table is still built once. An
// error is then the first of the first model's cameras that fails, not of the scene's order.
Result<std::vector<PreparedCamera>> prepare(const std::vector<SceneCamera>& cameras,
                                            const FigureTableOptions& table,
                                            const std::function<bool()>& stopped) {
    if (!stopped) return prepareCameras(cameras, table);
    std::vector<std::optional<PreparedCamera>> placed(cameras.size());
    for (size_t first = 0; first < cameras.size(); ++first) {
        if (placed[first]) continue;
        if (stopped()) return makeError(ErrorCode::Unsupported, kStopped);
        std::vector<size_t> group;
        std::vector<SceneCamera> sharing;
        for (size_t c = first; c < cameras.size(); ++c)
            if (cameras[c].model_path == cameras[first].model_path) {
                group.push_back(c);
                sharing.push_back(cameras[c]);
            }
        // The table asks too, between its angles: a table takes seconds.
        std::atomic<bool> stopped_in_table{false};
        FigureTableOptions stoppable = table;
        stoppable.stop_requested = [&] {
            if (!stopped()) return false;
            stopped_in_table = true;
            return true;
        };
        auto prepared = prepareCameras(sharing, stoppable);
        if (!prepared && stopped_in_table) return makeError(ErrorCode::Unsupported, kStopped);
        if (!prepared) return prepared.error();
        for (size_t k = 0; k < group.size(); ++k) placed[group[k]] = std::move((*prepared)[k]);
    }
    std::vector<PreparedCamera> out;
    out.reserve(cameras.size());
    for (auto& camera : placed) out.push_back(std::move(*camera));
    return out;
}

}  // namespace

Result<PredictionOutput> predictScene(const std::string& scene_path,
                                      const std::string& out_dir,
                                      const PredictOptions& options) {
    namespace fs = std::filesystem;
    const std::string label = options.scene_label.empty() ? scene_path : options.scene_label;
    std::string scene_dir = fs::path(scene_path).parent_path().string();
    if (scene_dir.empty()) scene_dir = ".";
    // What the caller's client may see: the scene by its label, the files beside it by their
    // names below the scene's folder.
    const auto shown = [&](const std::string& text) {
        if (!options.paths_relative_to_scene) return text;
        return replaced(replaced(text, scene_path, label), scene_dir + "/", "");
    };
    const auto fail = [&](const Error& e) { return Error{e.code, shown(e.message)}; };
    const auto stopped = [&] { return options.stop_requested && options.stop_requested(); };
    const Error stop = makeError(ErrorCode::Unsupported, kStopped);

    auto scene = loadScene(scene_path);
    if (!scene) return fail(scene.error());
    if (options.max_timeline_samples > 0 && scene->sun) {
        const int64_t steps = (scene->sun->to - scene->sun->from) / scene->sun->step + 1;
        const int64_t cameras = static_cast<int64_t>(scene->cameras.size());
        if (steps > options.max_timeline_samples / cameras)
            return makeError(
                ErrorCode::InvalidArgument,
                label + ": sun: " + std::to_string(steps) + " steps for " +
                    std::to_string(cameras) + " camera(s) are more than the " +
                    std::to_string(options.max_timeline_samples) +
                    " steps x cameras allowed; take a longer step_s or a shorter span");
    }
    std::error_code ec;
    fs::create_directories(fs::path(out_dir) / "frames", ec);
    if (ec) return makeError(ErrorCode::IoError, out_dir + ": cannot create: " + ec.message());
    PredictionOutput output;
    output.notes = scene->notes;
    for (std::string& note : output.notes) note = shown(note);
    output.fixed_lights = static_cast<int64_t>(scene->lights.size());
    output.sun = scene->sun.has_value();
    auto start = Clock::now();
    auto cameras = prepare(scene->cameras, options.table, options.stop_requested);
    if (!cameras) return fail(cameras.error());
    const double tables_ms = msSince(start);
    // Each camera once per instant of `frames`, or once with the fixed lights.
    const int64_t instants_drawn = static_cast<int64_t>(scene->frames.size()) +
                                   ((scene->frames.empty() || !scene->sun) ? 1 : 0);
    if (options.max_frame_pixels > 0) {
        int64_t pixels = 0;
        for (const PreparedCamera& camera : *cameras) pixels += camera.width * camera.height;
        if (pixels > options.max_frame_pixels / instants_drawn)
            return makeError(
                ErrorCode::InvalidArgument,
                label + ": frames: " + std::to_string(instants_drawn) + " instant(s) of " +
                    std::to_string(cameras->size()) + " camera(s) would draw " +
                    std::to_string(pixels * instants_drawn) + " pixels, more than the " +
                    std::to_string(options.max_frame_pixels) +
                    " allowed; give fewer frames or smaller width_px and height_px");
    }
    if (stopped()) return stop;

    nlohmann::json report;
    report["scene"] = label;
    report["notes"] = output.notes;
    if (options.on_note)
        for (const std::string& note : output.notes) options.on_note(note);
    report["out_of_range"] = rangePolicyName(scene->out_of_range);
    report["unit"] = "DN of each camera (eq. 8.3 of the thesis)";
    Report html;
    html.title = "Flare prediction: " + fs::path(label).filename().string();
    // Fixed lights, per camera.
    ReportSection summary;
    summary.title = "Cameras and fixed lights";
    summary.paragraphs.push_back(
        "Figures are in each camera's DN: the model's DN/s scaled by eq. 8.3 (exposure, gain, "
        "f-number, the light's irradiance over the rig light's). Mean and total add over the "
        "lights; the peak of several lights is an upper bound. Lights outside a model's range "
        "are " +
        std::string(scene->out_of_range == RangePolicy::Clamp
                        ? "drawn at the nearest angle the model covers (clamped)."
                        : "refused: their flare is unknown and the camera's figures with them."));
    ReportTable lights_table;
    lights_table.title = "Each light at each camera";
    lights_table.header = {"camera",    "light",      "state",      "theta (deg)",
                           "phi (deg)", "flare mean", "flare peak", "flare total"};
    ReportTable cameras_table;
    cameras_table.title = "Each camera, fixed lights together";
    cameras_table.header = {"camera", "model",      "f-number",   "exposure (s)",
                            "image",  "flare mean", "flare peak", "contrast ratio (eq. 9.3)", "glare indicator",
                            "notes"};
    std::string figures_csv =
        "camera,light,state,theta_deg,phi_deg,model_theta_deg,flare_min,flare_max,flare_mean,"
        "flare_log_average,flare_total\n";
    nlohmann::json cameras_json = nlohmann::json::array();
    for (const PreparedCamera& camera : *cameras) {
        if (stopped()) return stop;
        auto figures = fixedLightFigures(camera, scene->lights, scene->out_of_range);
        if (!figures) return fail(figures.error());
        PredictedCamera predicted;
        predicted.name = camera.scene.name;
        predicted.model = shown(camera.scene.model_path);
        predicted.model_valid_from_deg = camera.model.valid_from_deg;
        predicted.model_valid_to_deg = camera.model.valid_to_deg;
        predicted.ghosts = static_cast<int64_t>(camera.model.ghosts.size());
        predicted.exposure = camera.exposure;
        predicted.width_px = camera.width;
        predicted.height_px = camera.height;
        for (const std::string& note : camera.notes) predicted.notes.push_back(shown(note));
        predicted.fixed = *figures;
        nlohmann::json cj;
        cj["name"] = camera.scene.name;
        cj["model"] = predicted.model;
        cj["model_valid_deg"] = {camera.model.valid_from_deg, camera.model.valid_to_deg};
        cj["ghosts"] = camera.model.ghosts.size();
        cj["f_number"] = camera.exposure.f_number;
        cj["exposure_s"] = camera.exposure.exposure_s;
        cj["gain"] = camera.exposure.gain;
        cj["width_px"] = camera.width;
        cj["height_px"] = camera.height;
        cj["notes"] = predicted.notes;
        cj["known"] = figures->known;
        cj["fixed_lights"] = figuresJson(figures->sum);
        cj["contrast_ratio"] =
            figures->contrast_ratio ? nlohmann::json(*figures->contrast_ratio) : nlohmann::json();
        cj["glare_indicator"] =
            figures->glare_indicator ? nlohmann::json(*figures->glare_indicator) : nlohmann::json();
        nlohmann::json lights_json = nlohmann::json::array();
        for (const LightFigures& lf : figures->lights) {
            const bool placed = lf.placed.state != LightState::AtCamera;
            lights_json.push_back(
                {{"light", lf.light},
                 {"state", lightStateName(lf.placed.state)},
                 {"theta_deg", placed ? num(lf.placed.constellation.theta_deg) : nlohmann::json()},
                 {"phi_deg", placed ? num(lf.placed.constellation.phi_deg) : nlohmann::json()},
                 {"model_theta_deg",
                  lf.placed.drawn() ? num(lf.placed.model_theta_deg) : nlohmann::json()},
                 {"figures", figuresJson(lf.figures)}});
            lights_table.rows.push_back(
                {camera.scene.name, lf.light, lightStateName(lf.placed.state),
                 placed ? fmt(lf.placed.constellation.theta_deg, "%.2f") : "",
                 placed ? fmt(lf.placed.constellation.phi_deg, "%.1f") : "",
                 lf.placed.drawn() ? fmt(lf.figures.mean) : "",
                 lf.placed.drawn() ? fmt(lf.figures.max) : "",
                 lf.placed.drawn() ? fmt(lf.figures.total) : ""});
            figures_csv += csv(camera.scene.name) + "," + csv(lf.light) + "," +
                           lightStateName(lf.placed.state) + "," +
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
        for (const auto& n : predicted.notes) notes += (notes.empty() ? "" : "; ") + n;
        cameras_table.rows.push_back(
            {camera.scene.name, fs::path(camera.scene.model_path).filename().string(),
             fmt(camera.exposure.f_number), fmt(camera.exposure.exposure_s),
             std::to_string(camera.width) + "x" + std::to_string(camera.height),
             figures->known ? fmt(figures->sum.mean) : "unknown",
             figures->known ? fmt(figures->sum.max) : "unknown",
             figures->contrast_ratio ? fmt(*figures->contrast_ratio, "%.4f") : "",
             figures->glare_indicator ? fmt(*figures->glare_indicator, "%.4g") : "", notes});
        output.cameras.push_back(std::move(predicted));
    }
    report["cameras"] = cameras_json;
    summary.tables.push_back(cameras_table);
    if (!scene->lights.empty()) summary.tables.push_back(lights_table);
    if (!output.notes.empty()) {
        summary.paragraphs.push_back("Notes from the glTF import:");
        for (const std::string& note : output.notes) summary.paragraphs.push_back(note);
    }
    html.sections.push_back(summary);

    // The models: the flare of the rig's light along theta, the lab figures, and the ghosts'
    // parameters.
    std::string lab_csv = "model,theta_deg,centre_flare_dn_s,pst\n";
    nlohmann::json models_json = nlohmann::json::array();
    for (size_t c = 0; c < cameras->size(); ++c) {
        const PreparedCamera& camera = (*cameras)[c];
        bool seen = false;
        for (size_t d = 0; d < c; ++d)
            seen |= (*cameras)[d].scene.model_path == camera.scene.model_path;
        if (seen) continue;
        ReportSection section;
        section.title = "Model " + fs::path(camera.scene.model_path).filename().string();
        section.paragraphs.push_back(
            camera.model.lens.description + ": " + std::to_string(camera.model.ghosts.size()) +
            " ghosts, valid from " + fmt(camera.model.valid_from_deg) + " to " +
            fmt(camera.model.valid_to_deg) +
            " deg. The curves are the model's series evaluated along theta" +
            (modelKeptSamples(camera.model)
                 ? std::string(", the dots the per-frame fits they compress.")
                 : std::string(" (the model kept no per-frame fits, `flarelab fit "
                               "--keep-samples`; their residuals are in `flarelab model "
                               "show`).")));
        ReportPlot flare;
        flare.title = "Flare of the rig's light along theta (model units, DN/s)";
        flare.x_label = "theta (deg)";
        flare.y_label = "flare mean";
        flare.log_y = true;
        for (double phi : {0.0, 90.0}) {
            ReportSeries mean;
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
        auto lab = labFigures(camera.model, camera.table, options.lab);
        if (!lab) return fail(lab.error());
        nlohmann::json lab_json;
        lab_json["model"] = shown(camera.scene.model_path);
        lab_json["black_spot_deg"] = options.lab.black_spot_deg;
        lab_json["scaled"] = lab->scaled;
        for (size_t i = 0; i < lab->theta_deg.size(); ++i) {
            lab_csv += csv(shown(camera.scene.model_path)) + "," + fmt(lab->theta_deg[i]) + "," +
                       fmt(lab->centre_flare[i]) + "," +
                       (lab->scaled ? fmt(lab->pst[i]) : std::string()) + "\n";
        }
        if (lab->scaled) {
            lab_json["veiling_glare_index"] = num(lab->vgi);
            lab_json["vgi_theta_deg"] = {lab->vgi_from_deg, lab->vgi_to_deg};
            lab_json["image_flare"] = num(lab->image_flare);
            lab_json["image_flare_complete"] = lab->image_flare_complete;
            lab_json["frame_field_deg"] = lab->frame_field_deg;
            lab_json["light_power_dn_s"] = *camera.model.capture.light_power_dn_s;
            nlohmann::json field = nlohmann::json::array();
            std::string off_axis;
            for (const LabFieldPoint& point : lab->field) {
                field.push_back({{"image_height", point.height},
                                 {"field_deg", point.field_deg},
                                 {"veiling_glare_index", num(point.vgi)},
                                 {"image_flare", num(point.image_flare)}});
                off_axis += std::string(off_axis.empty() ? "" : "; ") + "at image height " +
                            fmt(point.height) + " (" + fmt(point.field_deg, "%.1f") +
                            " deg) " + fmt(100.0 * point.vgi, "%.3g") + " % and " +
                            fmt(100.0 * point.image_flare, "%.3g") + " %";
            }
            lab_json["off_axis"] = field;
            section.paragraphs.push_back(
                "Lab figures of the ghosts (predict/lab_figures.h; scatter is not in a model, so "
                "a bench measures more): veiling glare index on axis (ISO 9358's ratio, a black "
                "spot of " + fmt(options.lab.black_spot_deg) + " deg in a bright field from " +
                fmt(lab->vgi_from_deg) + " to " + fmt(lab->vgi_to_deg) + " deg) " +
                fmt(100.0 * lab->vgi, "%.3g") + " %; image flare at the centre patch of a chart "
                "filling the frame (ISO 18844's black-patch method) " +
                fmt(100.0 * lab->image_flare, "%.3g") + " %" +
                (lab->image_flare_complete
                     ? std::string(".")
                     : " (the model stops at " + fmt(lab->vgi_to_deg) +
                           " deg, short of the frame's corner at " +
                           fmt(lab->frame_field_deg, "%.1f") + " deg: a lower bound).") +
                (off_axis.empty() ? std::string()
                                  : " Off axis, the index and the image flare " + off_axis +
                                        " (the white falling as cos^4; roll sampled at the "
                                        "table's step).") +
                " Point source transmittance along theta below (lab.csv).");
            ReportPlot pst;
            pst.title = "Point source transmittance along theta (ghosts, roll 0)";
            pst.x_label = "theta (deg)";
            pst.y_label = "PST";
            pst.log_y = true;
            pst.series.push_back(ReportSeries{"PST", lab->theta_deg, lab->pst});
            section.plots.push_back(pst);
        } else {
            lab_json["missing"] = lab->missing;
            section.paragraphs.push_back(
                "No lab figures (PST, veiling glare index, image flare): the model lacks " +
                lab->missing +
                " (the light's power comes from the sweep of a simulated rig, or from `flarelab "
                "fit --light-power-dn-s` measured apart).");
        }
        models_json.push_back(lab_json);
        section.plots.push_back(parameterPlot(camera.model, "centre_x_mm", "mm"));
        section.plots.push_back(parameterPlot(camera.model, "half_height_mm", "mm"));
        section.plots.push_back(parameterPlot(camera.model, "ln_inner_rgb[1]", "ln(DN/s)"));
        html.sections.push_back(section);
    }

    // The sun: timeline and switching plan.
    std::optional<Timeline> timeline;
    double timeline_ms = 0.0, plan_ms = 0.0;
    if (scene->sun) {
        if (stopped()) return stop;
        start = Clock::now();
        auto t = predictTimeline(*scene->sun, *cameras, scene->lights, scene->out_of_range);
        if (!t) return fail(t.error());
        timeline_ms = msSince(start);
        timeline = std::move(*t);
        const size_t steps = timeline->sun.positions.size();
        const double step_s = std::chrono::duration<double>(timeline->sun.step).count();
        std::string tcsv = "time_utc,sun_zenith_deg,sun_azimuth_deg";
        for (const auto& camera : *cameras)
            for (const char* column :
                 {" flare_mean", " flare_peak", " contrast_loss", " glare_indicator", " sun"})
                tcsv += "," + csv(camera.scene.name + column);
        tcsv += "\n";
        for (size_t i = 0; i < steps; ++i) {
            const auto& p = timeline->sun.positions[i];
            tcsv += formatIso8601(timeline->sun.instant(i)) + "," + fmt(p.zenith_deg, "%.5f") +
                    "," + fmt(p.azimuth_deg, "%.5f");
            for (const auto& ct : timeline->cameras)
                tcsv += "," + fmt(ct.flare_mean[i]) + "," + fmt(ct.flare_peak[i]) + "," +
                        fmt(ct.contrast_loss[i]) + "," + fmt(ct.glare_indicator[i]) + "," +
                        lightStateName(ct.sun_state[i]);
            tcsv += "\n";
        }
        if (auto w = writeTextFileAtomically((fs::path(out_dir) / "timeline.csv").string(), tcsv);
            !w)
            return fail(w.error());
        output.files.push_back("timeline.csv");
        TimelineSummary summary_of_timeline;
        summary_of_timeline.from_utc = formatIso8601(scene->sun->from);
        summary_of_timeline.to_utc = formatIso8601(scene->sun->to);
        summary_of_timeline.step_s = step_s;
        summary_of_timeline.steps = static_cast<int64_t>(steps);

        ReportSection section;
        section.title = "The sun from " + formatIso8601(scene->sun->from) + " to " +
                        formatIso8601(scene->sun->to);
        section.paragraphs.push_back(
            std::to_string(steps) + " steps of " + fmt(step_s) +
            " s (timeline.csv). Sun position: NREL SPA. "
            "A step is unknown for a camera when the sun or a fixed light lies outside its model "
            "and the scene refuses extrapolation.");
        ReportTable counts;
        counts.title = "Where the sun stood for each camera (steps)";
        counts.header = {
            "camera",  "below horizon",      "behind camera",   "in the model's range", "clamped",
            "refused", "flare mean, median", "flare mean, max", "contrast loss, max"};
        nlohmann::json tj = nlohmann::json::array();
        ReportPlot mean_plot, loss_plot, glare_plot;
        mean_plot.title = "Flare mean along the day";
        mean_plot.x_label = "hours from " + formatIso8601(scene->sun->from);
        mean_plot.y_label = "flare mean (DN)";
        mean_plot.log_y = true;
        loss_plot.title = "Contrast loss along the day (1 - eq. 9.3)";
        loss_plot.x_label = mean_plot.x_label;
        loss_plot.y_label = "contrast loss";
        glare_plot.title = "Glare indicator along the day (flare mean over the scene's log-average)";
        glare_plot.x_label = mean_plot.x_label;
        glare_plot.y_label = "glare indicator";
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
            summary_of_timeline.cameras.push_back(
                {name, ct.steps_sun_down, ct.steps_behind, ct.steps_drawn, ct.steps_clamped,
                 ct.steps_refused, median(ct.flare_mean), maximum(ct.flare_mean),
                 maximum(ct.flare_peak), maximum(ct.contrast_loss)});
            tj.push_back({{"camera", name},
                          {"steps_sun_down", ct.steps_sun_down},
                          {"steps_behind_camera", ct.steps_behind},
                          {"steps_drawn", ct.steps_drawn},
                          {"steps_clamped", ct.steps_clamped},
                          {"steps_refused", ct.steps_refused},
                          {"flare_mean_median", num(median(ct.flare_mean))},
                          {"flare_mean_max", num(maximum(ct.flare_mean))},
                          {"flare_peak_max", num(maximum(ct.flare_peak))},
                          {"contrast_loss_max", num(maximum(ct.contrast_loss))},
                          {"glare_indicator_max", num(maximum(ct.glare_indicator))}});
            summary_of_timeline.cameras.back().glare_indicator_max = maximum(ct.glare_indicator);
            ReportSeries m{name, hours, ct.flare_mean};
            mean_plot.series.push_back(m);
            bool any_loss = false;
            for (double v : ct.contrast_loss) any_loss |= std::isfinite(v);
            if (any_loss) loss_plot.series.push_back(ReportSeries{name, hours, ct.contrast_loss});
            bool any_glare = false;
            for (double v : ct.glare_indicator) any_glare |= std::isfinite(v);
            if (any_glare)
                glare_plot.series.push_back(ReportSeries{name, hours, ct.glare_indicator});
        }
        report["timeline"] = {{"from_utc", formatIso8601(scene->sun->from)},
                              {"to_utc", formatIso8601(scene->sun->to)},
                              {"step_s", step_s},
                              {"steps", steps},
                              {"cameras", tj},
                              {"ms", timeline_ms}};
        output.timeline = std::move(summary_of_timeline);
        section.tables.push_back(counts);
        std::optional<ReportPlot> plan_plot_kept;

        if (scene->switching) {
            const auto& sw = *scene->switching;
            SwitchingOptions switching_options;
            switching_options.threshold = sw.threshold;
            switching_options.min_dwell_steps = std::max<int64_t>(
                1, static_cast<int64_t>(std::ceil(sw.min_dwell_s / step_s - 1e-9)));
            start = Clock::now();
            const auto series = switchingFigures(*timeline, sw.figure);
            auto plan = planSwitching(series, switching_options);
            if (!plan) return fail(plan.error());
            plan_ms = msSince(start);
            if (sw.figure == SwitchFigure::ContrastLoss) loss_plot.threshold = sw.threshold;
            if (sw.figure == SwitchFigure::GlareIndicator) glare_plot.threshold = sw.threshold;
            ReportPlot plan_plot;
            plan_plot.title = "Switching plan (" + std::string(switchFigureName(sw.figure)) +
                              " <= " + fmt(sw.threshold) + ", shots of at least " +
                              fmt(sw.min_dwell_s) + " s)";
            plan_plot.x_label = mean_plot.x_label;
            plan_plot.y_label = "camera";
            for (const auto& camera : *cameras) plan_plot.y_categories.push_back(camera.scene.name);
            ReportSeries chosen;
            chosen.name = "camera on air";
            chosen.steps = true;
            ReportTable plan_table;
            plan_table.title = "Shots";
            plan_table.header = {"camera", "from", "to", "seconds", "steps over the threshold"};
            std::string pcsv = "camera,from_utc,to_utc,seconds,steps_over\n";
            nlohmann::json segments = nlohmann::json::array();
            SwitchingSummary summary_of_plan;
            summary_of_plan.figure = sw.figure;
            summary_of_plan.threshold = sw.threshold;
            summary_of_plan.min_dwell_s = sw.min_dwell_s;
            summary_of_plan.steps_over = plan->steps_over;
            summary_of_plan.cuts = plan->cuts;
            for (const auto& seg : plan->segments) {
                int64_t over = 0;
                for (int64_t t = seg.first_step; t < seg.end_step; ++t)
                    over += !(series[static_cast<size_t>(seg.camera)][static_cast<size_t>(t)] <=
                              sw.threshold);
                const std::string name = (*cameras)[static_cast<size_t>(seg.camera)].scene.name;
                const std::string a =
                    formatIso8601(timeline->sun.instant(static_cast<size_t>(seg.first_step)));
                const std::string b =
                    formatIso8601(timeline->sun.instant(static_cast<size_t>(seg.end_step)));
                const double seconds = static_cast<double>(seg.end_step - seg.first_step) * step_s;
                plan_table.rows.push_back({name, a, b, fmt(seconds), std::to_string(over)});
                pcsv += csv(name) + "," + a + "," + b + "," + fmt(seconds) + "," +
                        std::to_string(over) + "\n";
                segments.push_back(
                    {{"camera", name}, {"from_utc", a}, {"to_utc", b}, {"steps_over", over}});
                summary_of_plan.shots.push_back({name, seg.camera, a, b, seconds, over});
                chosen.x.push_back(hours[static_cast<size_t>(seg.first_step)]);
                chosen.y.push_back(seg.camera);
            }
            chosen.x.push_back(static_cast<double>(steps) * step_s / 3600.0);
            chosen.y.push_back(plan->segments.back().camera);
            plan_plot.series.push_back(chosen);
            nlohmann::json none = nlohmann::json::array();
            ReportTable none_table;
            none_table.title = "No clean camera";
            none_table.header = {"from", "to", "seconds"};
            for (const auto& gap : plan->no_clean_camera) {
                const std::string a =
                    formatIso8601(timeline->sun.instant(static_cast<size_t>(gap.first_step)));
                const std::string b =
                    formatIso8601(timeline->sun.instant(static_cast<size_t>(gap.end_step)));
                const double seconds = static_cast<double>(gap.end_step - gap.first_step) * step_s;
                none.push_back({{"from_utc", a}, {"to_utc", b}});
                none_table.rows.push_back({a, b, fmt(seconds)});
                summary_of_plan.no_clean_camera.push_back({a, b, seconds});
            }
            report["switching"] = {{"figure", switchFigureName(sw.figure)},
                                   {"threshold", sw.threshold},
                                   {"min_dwell_s", sw.min_dwell_s},
                                   {"steps_over", plan->steps_over},
                                   {"cuts", plan->cuts},
                                   {"segments", segments},
                                   {"no_clean_camera", none},
                                   {"ms", plan_ms}};
            if (auto w = writeTextFileAtomically((fs::path(out_dir) / "plan.csv").string(), pcsv);
                !w)
                return fail(w.error());
            output.files.push_back("plan.csv");
            output.switching = std::move(summary_of_plan);
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
        if (!glare_plot.series.empty()) section.plots.push_back(glare_plot);
        if (plan_plot_kept) section.plots.push_back(*plan_plot_kept);
        html.sections.push_back(section);
    }

    // Frames: each camera at each chosen instant, or once with the fixed lights.
    ReportSection frames_section;
    frames_section.title = "Frames";
    frames_section.paragraphs.push_back(
        "Each frame is the flare alone in the camera's DN (EXR beside each PNG); the PNG shows the "
        "camera's white (scene_max_dn, else the frame's peak) as white" +
        (options.exposure_stops != 0.0 ? ", " + fmt(options.exposure_stops) + " stops brighter"
                                       : "") +
        ".");
    nlohmann::json frames_json = nlohmann::json::array();
    std::vector<std::optional<UtcInstant>> instants;
    if (scene->frames.empty() || !scene->sun) instants.push_back(std::nullopt);
    for (const auto& t : scene->frames) instants.push_back(t);
    double frames_ms = 0.0;
    for (const auto& instant : instants) {
        std::optional<SunLight> sun;
        std::string when;
        if (instant && scene->sun) {
            auto p = sunPosition(scene->sun->site, *instant);
            if (!p) return fail(p.error().withContext("frames"));
            when = formatIso8601(*instant);
            if (p->elevation_deg > 0.0)
                sun = SunLight{sunDirection(p->zenith_deg, p->azimuth_deg), scene->sun->intensity,
                               scene->sun->colour};
        }
        for (size_t c = 0; c < cameras->size(); ++c) {
            const PreparedCamera& camera = (*cameras)[c];
            start = Clock::now();
            if (stopped()) return stop;
            auto frame = drawCameraFrame(camera, scene->lights, sun, scene->out_of_range);
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
            if (auto w = hdr::writeExr((fs::path(out_dir) / exr).string(), frame->image, meta); !w)
                return fail(w.error());
            // As the camera would show it: its white (the scene's brightest DN, else the
            // frame's peak) at 1, then --exposure-stops.
            const FlareFigures f = flareFigures(frame->image);
            const double white = camera.scene.scene_max_dn.value_or(std::max(1e-30, f.max));
            render::ToneMapOptions tone;
            tone.exposure_stops =
                std::clamp(options.exposure_stops - std::log2(white), -64.0, 64.0);
            if (auto w = render::writePng(frame->image, (fs::path(out_dir) / png).string(), tone);
                !w)
                return fail(w.error());
            output.files.push_back(exr);
            output.files.push_back(png);
            int refused = 0;
            for (const auto& l : frame->lights) refused += l.state == LightState::OutsideRange;
            frames_section.images.push_back(
                {camera.scene.name + (when.empty() ? "" : " at " + when) + ": flare mean " +
                     fmt(f.mean) + ", peak " + fmt(f.max) +
                     (refused > 0 ? " (" + std::to_string(refused) +
                                        " light(s) outside the model's range not drawn)"
                                  : ""),
                 png});
            nlohmann::json lights = nlohmann::json::array();
            for (const auto& l : frame->lights) lights.push_back(lightStateName(l.state));
            PredictedFrame predicted{camera.scene.name, when, png, exr, f, {}};
            for (const auto& l : frame->lights) predicted.light_states.push_back(l.state);
            output.frames.push_back(std::move(predicted));
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
    output.timings = {tables_ms, timeline_ms, plan_ms, frames_ms};
    report["models"] = models_json;
    report["timings_ms"] = {{"tables", tables_ms},
                            {"timeline", timeline_ms},
                            {"switching", plan_ms},
                            {"frames", frames_ms}};

    const fs::path dir(out_dir);
    output.report_json = report.dump(2) + "\n";
    for (const auto& [name, text] :
         {std::pair<std::string, std::string>{"figures.csv", figures_csv},
          {"lab.csv", lab_csv},
          {"report.json", output.report_json},
          {"report.html", reportHtml(html)}}) {
        if (auto w = writeTextFileAtomically((dir / name).string(), text); !w)
            return fail(w.error());
        output.files.push_back(name);
    }

    std::string& out = output.summary;
    out = "predict: " + std::to_string(cameras->size()) + " cameras, " +
          std::to_string(scene->lights.size()) + " fixed lights" + (scene->sun ? ", the sun" : "") +
          " -> " + out_dir + "/report.html\n";
    for (const PredictedCamera& camera : output.cameras) {
        const CameraFigures& f = camera.fixed;
        out += "  " + camera.name + ": fixed lights' flare mean " +
               (f.known ? fmt(f.sum.mean) : "unknown") + " DN, peak " +
               (f.known ? fmt(f.sum.max) : "unknown") + " DN" +
               (f.contrast_ratio ? ", contrast ratio " + fmt(*f.contrast_ratio, "%.4f") : "") +
               "\n";
    }
    if (output.switching)
        out += "  switching: " + std::to_string(output.switching->shots.size()) + " shots, " +
               std::to_string(output.switching->steps_over) + " steps over the threshold\n";
    out += "  tables " + fmt(tables_ms, "%.0f") + " ms, timeline " + fmt(timeline_ms, "%.1f") +
           " ms, switching " + fmt(plan_ms, "%.1f") + " ms, frames " + fmt(frames_ms, "%.0f") +
           " ms\n";
    return output;
}

}  // namespace flarelab::predict
