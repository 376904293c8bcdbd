#include "daemon/predict_call.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <set>
#include <string>
#include <system_error>

#include "common/durable_io.h"
#include "common/file_descriptor.h"
#include "daemon/log.h"
#include "predict/prediction.h"
#include "predict/scene.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;
using grpc::Status;
using grpc::StatusCode;

constexpr const char* kDefaultSceneName = "scene.json";
// The scene's own file beside the client's: a leading '.' is no name a client may give.
constexpr const char* kSceneFile = ".scene.json";
constexpr const char* kFolderPrefix = "p-";

Status invalid(const std::string& message) { return Status(StatusCode::INVALID_ARGUMENT, message); }

// Why `name` cannot be a file of the request; empty when it can.
std::string nameProblem(const std::string& name, size_t max_bytes) {
    if (name.empty()) return "must not be empty";
    if (name.size() > max_bytes)
        return "must be at most " + std::to_string(max_bytes) + " characters, not " +
               std::to_string(name.size());
    if (name.front() == '.') return "must not start with '.'";
    for (const char c : name) {
        const bool ok = (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') ||
                        (c >= '0' && c <= '9') || c == '.' || c == '_' || c == '-';
        if (!ok) return "may hold only the characters A-Z a-z 0-9 . _ -";
    }
    return "";
}

// `text` cut to a length a message can carry, for names a client chose.
std::string quoted(const std::string& text) {
    std::string out;
    for (const char c : text.substr(0, 80)) {
        const auto u = static_cast<unsigned char>(c);
        out += (u < 0x20 || u == 0x7f) ? '?' : c;
    }
    return "\"" + out + (text.size() > 80 ? "...\"" : "\"");
}

// Why the scene's `path` cannot be read for the client; empty when it names a file of `names`.
std::string pathProblem(const std::string& path, const std::set<std::string>& names) {
    const std::string what = quoted(path);
    if (fs::path(path).is_absolute())
        return what +
               " is an absolute path; the daemon reads no file of its own for a client: "
               "give the file's name here and the file in the request's files";
    for (const auto& part : fs::path(path))
        if (part == "..")
            return what + " holds \"..\"; give a plain file name of the request's files";
    if (path.find('/') != std::string::npos)
        return what + " holds a '/'; give a plain file name of the request's files";
    if (names.count(path) == 0) {
        std::string listed;
        size_t shown = 0;
        for (const std::string& n : names) {
            if (++shown > 8) {
                listed += ", ...";
                break;
            }
            listed += (listed.empty() ? "" : ", ") + n;
        }
        return what + " is no file of the request (files: " + (listed.empty() ? "none" : listed) +
               ")";
    }
    return "";
}

std::string sceneName(const v1::PredictRequest& request) {
    return request.scene_name().empty() ? kDefaultSceneName : request.scene_name();
}

// `text` with every `from` replaced by `to`.
std::string replaced(std::string text, const std::string& from, const std::string& to) {
    if (from.empty()) return text;
    for (size_t at = text.find(from); at != std::string::npos; at = text.find(from, at + to.size()))
        text.replace(at, from.size(), to);
    return text;
}

void setFigures(const predict::FlareFigures& f, v1::FlareFigures* out) {
    out->set_min(f.min);
    out->set_max(f.max);
    out->set_mean(f.mean);
    out->set_log_average(f.log_average);
    out->set_total(f.total);
}

void fillResponse(const predict::PredictionOutput& p, v1::PredictResponse* out) {
    for (size_t c = 0; c < p.cameras.size(); ++c) {
        const predict::PredictedCamera& camera = p.cameras[c];
        v1::PredictedCamera* pc = out->add_cameras();
        pc->set_name(camera.name);
        pc->set_model(camera.model);
        pc->set_model_valid_from_deg(camera.model_valid_from_deg);
        pc->set_model_valid_to_deg(camera.model_valid_to_deg);
        pc->set_ghosts(static_cast<uint32_t>(camera.ghosts));
        pc->set_f_number(camera.exposure.f_number);
        pc->set_exposure_s(camera.exposure.exposure_s);
        pc->set_gain(camera.exposure.gain);
        pc->set_width_px(static_cast<uint32_t>(camera.width_px));
        pc->set_height_px(static_cast<uint32_t>(camera.height_px));
        for (const std::string& note : camera.notes) pc->add_notes(note);
        pc->set_known(camera.fixed.known);
        setFigures(camera.fixed.sum, pc->mutable_fixed_lights());
        if (camera.fixed.contrast_ratio) pc->set_contrast_ratio(*camera.fixed.contrast_ratio);
        if (camera.fixed.glare_indicator) pc->set_glare_indicator(*camera.fixed.glare_indicator);
        for (const predict::LightFigures& lf : camera.fixed.lights) {
            v1::PredictedLight* pl = pc->add_lights();
            pl->set_name(lf.light);
            pl->set_state(predict::lightStateName(lf.placed.state));
            if (lf.placed.state != predict::LightState::AtCamera) {
                pl->set_theta_deg(lf.placed.constellation.theta_deg);
                pl->set_phi_deg(lf.placed.constellation.phi_deg);
            }
            if (lf.placed.drawn()) pl->set_model_theta_deg(lf.placed.model_theta_deg);
            setFigures(lf.figures, pl->mutable_figures());
        }
        if (p.timeline && c < p.timeline->cameras.size()) {
            const predict::CameraTimelineSummary& t = p.timeline->cameras[c];
            v1::CameraTimelineSummary* pt = pc->mutable_timeline();
            pt->set_steps_sun_down(static_cast<uint64_t>(t.steps_sun_down));
            pt->set_steps_behind_camera(static_cast<uint64_t>(t.steps_behind_camera));
            pt->set_steps_drawn(static_cast<uint64_t>(t.steps_drawn));
            pt->set_steps_clamped(static_cast<uint64_t>(t.steps_clamped));
            pt->set_steps_refused(static_cast<uint64_t>(t.steps_refused));
            pt->set_flare_mean_median(t.flare_mean_median);
            pt->set_flare_mean_max(t.flare_mean_max);
            pt->set_flare_peak_max(t.flare_peak_max);
            pt->set_contrast_loss_max(t.contrast_loss_max);
            pt->set_glare_indicator_max(t.glare_indicator_max);
        }
    }
    if (p.timeline) {
        v1::PredictedTimeline* t = out->mutable_timeline();
        t->set_from_utc(p.timeline->from_utc);
        t->set_to_utc(p.timeline->to_utc);
        t->set_step_s(p.timeline->step_s);
        t->set_step_count(static_cast<uint64_t>(p.timeline->steps));
    }
    if (p.switching) {
        const predict::SwitchingSummary& s = *p.switching;
        v1::PredictedSwitching* ps = out->mutable_switching();
        ps->set_figure(predict::switchFigureName(s.figure));
        ps->set_threshold(s.threshold);
        ps->set_min_dwell_s(s.min_dwell_s);
        ps->set_steps_over(static_cast<uint64_t>(s.steps_over));
        ps->set_cuts(static_cast<uint64_t>(s.cuts));
        for (const predict::PlannedShot& shot : s.shots) {
            v1::PredictedShot* out_shot = ps->add_shots();
            out_shot->set_camera(shot.camera);
            out_shot->set_from_utc(shot.from_utc);
            out_shot->set_to_utc(shot.to_utc);
            out_shot->set_seconds(shot.seconds);
            out_shot->set_steps_over(static_cast<uint64_t>(shot.steps_over));
        }
        for (const predict::PlannedGap& gap : s.no_clean_camera) {
            v1::PredictedInterval* out_gap = ps->add_no_clean_camera();
            out_gap->set_from_utc(gap.from_utc);
            out_gap->set_to_utc(gap.to_utc);
            out_gap->set_seconds(gap.seconds);
        }
    }
    for (const predict::PredictedFrame& frame : p.frames) {
        v1::PredictedFrame* pf = out->add_frames();
        pf->set_camera(frame.camera);
        pf->set_time_utc(frame.time_utc);
        pf->set_png(frame.png);
        pf->set_exr(frame.exr);
        setFigures(frame.figures, pf->mutable_figures());
        for (const predict::LightState state : frame.light_states)
            pf->add_light_states(predict::lightStateName(state));
    }
    for (const std::string& note : p.notes) out->add_notes(note);
    out->set_report_json(p.report_json);
}

// Writes a client's file into the private folder: a new file (never over one, never through a
// link), mode 0600.
Status writeNew(const std::string& path, const std::string& content) {
    FileDescriptor fd(
        ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0600));
    if (!fd.valid())
        return Status(StatusCode::UNAVAILABLE,
                      "cannot create a prediction's file: " + osMessage(errno));
    if (const int error = writeAll(fd.get(), path, content.data(), content.size()); error != 0)
        return Status(StatusCode::UNAVAILABLE,
                      "cannot write a prediction's file: " + osMessage(error));
    if (const int error = fd.close(); error != 0)
        return Status(StatusCode::UNAVAILABLE,
                      "cannot write a prediction's file: " + osMessage(error));
    return Status::OK;
}

// The private folder of one call, removed with everything in it when the call ends.
struct WorkFolder {
    std::string path;
    ~WorkFolder() {
        if (path.empty()) return;
        std::error_code ec;
        fs::remove_all(path, ec);
        if (ec)
            logEvent(LogLevel::Warn, "predict.cleanup_failed",
                     {{"folder", path}, {"error", ec.message()}});
    }
};

}  // namespace

Status checkPredictRequest(const v1::PredictRequest& request, const PredictLimits& limits) {
    const std::string scene_name = sceneName(request);
    if (const std::string problem = nameProblem(scene_name, limits.max_name_bytes);
        !problem.empty())
        return invalid("scene_name: " + problem + " (got " + quoted(request.scene_name()) + ")");

    const v1::PredictOptions& o = request.options();
    const double theta = o.table_theta_step_deg();
    if (!(std::isfinite(theta) && (theta == 0.0 || (theta >= 0.1 && theta <= 10.0))))
        return invalid(
            "options.table_theta_step_deg: must be 0 (the capture's step) or in "
            "[0.1, 10] (got " +
            std::to_string(theta) + ")");
    const double phi = o.table_phi_step_deg();
    const double turns = std::isfinite(phi) && phi > 0.0 ? 360.0 / phi : 0.0;
    if (!(phi == 0.0 || (std::isfinite(phi) && phi >= 2.0 && phi <= 90.0 &&
                         std::abs(turns - std::round(turns)) < 1e-9)))
        return invalid(
            "options.table_phi_step_deg: must be 0 (10) or in [2, 90] dividing 360 "
            "(got " +
            std::to_string(phi) + ")");
    if (o.table_width_px() != 0 && (o.table_width_px() < 8 || o.table_width_px() > 480))
        return invalid("options.table_width_px: must be 0 (240) or in 8..480 (got " +
                       std::to_string(o.table_width_px()) + ")");
    if (!(std::isfinite(o.black_spot_deg()) && o.black_spot_deg() >= 0.0 &&
          o.black_spot_deg() <= 20.0))
        return invalid("options.black_spot_deg: must be 0 (1) or in (0, 20] (got " +
                       std::to_string(o.black_spot_deg()) + ")");
    if (!(std::isfinite(o.exposure_stops()) && std::abs(o.exposure_stops()) <= 64.0))
        return invalid("options.exposure_stops: must lie in [-64, 64] (got " +
                       std::to_string(o.exposure_stops()) + ")");

    if (static_cast<size_t>(request.files_size()) > limits.max_files)
        return invalid("files: " + std::to_string(request.files_size()) + " files, more than the " +
                       std::to_string(limits.max_files) + " a prediction may take");
    if (request.scene_json().empty()) return invalid("scene_json: must not be empty");
    if (request.scene_json().size() > limits.max_scene_bytes)
        return invalid("scene_json: " + std::to_string(request.scene_json().size()) +
                       " bytes, more than the " + std::to_string(limits.max_scene_bytes) +
                       " a scene may have");
    size_t bytes = request.scene_json().size();
    std::set<std::string> names;
    for (int i = 0; i < request.files_size(); ++i) {
        const v1::NamedFile& file = request.files(i);
        const std::string field = "files[" + std::to_string(i) + "].name";
        if (const std::string problem = nameProblem(file.name(), limits.max_name_bytes);
            !problem.empty())
            return invalid(field + ": " + problem + " (got " + quoted(file.name()) + ")");
        if (!names.insert(file.name()).second)
            return invalid(field + ": " + quoted(file.name()) + " is given twice");
        bytes += file.name().size() + file.content().size();
    }
    if (bytes > limits.max_input_bytes)
        return Status(StatusCode::RESOURCE_EXHAUSTED,
                      "files: " + std::to_string(bytes) + " bytes with the scene, more than the " +
                          std::to_string(limits.max_input_bytes) + " a prediction may take");

    // The scene, read as `flarelab predict` reads it, but with its paths as the client gave them
    // (no folder to join them to), so that each can be held against the request's files.
    auto scene = predict::parseScene(request.scene_json(), scene_name, "");
    if (!scene) return invalid(scene.error().message);
    for (size_t c = 0; c < scene->cameras.size(); ++c)
        if (const std::string problem = pathProblem(scene->cameras[c].model_path, names);
            !problem.empty())
            return invalid(scene_name + ": cameras[" + std::to_string(c) + "].model: " + problem);
    if (scene->gltf)
        if (const std::string problem = pathProblem(scene->gltf->path, names); !problem.empty())
            return invalid(scene_name + ": gltf.file: " + problem);
    if (scene->sun) {
        const int64_t steps = (scene->sun->to - scene->sun->from) / scene->sun->step + 1;
        const auto cameras = static_cast<int64_t>(scene->cameras.size());
        if (steps > limits.max_timeline_samples / cameras)
            return invalid(scene_name + ": sun: " + std::to_string(steps) + " steps for " +
                           std::to_string(cameras) + " camera(s) are more than the " +
                           std::to_string(limits.max_timeline_samples) +
                           " steps x cameras a daemon predicts; take a longer step_s or a "
                           "shorter span");
    }
    return Status::OK;
}

Status runPredict(const v1::PredictRequest& request,
                  const PredictLimits& limits,
                  const std::string& work_root,
                  const std::function<bool()>& stop_requested,
                  v1::PredictResponse* response) {
    if (Status ok = checkPredictRequest(request, limits); !ok.ok()) return ok;
    const std::string scene_name = sceneName(request);

    std::error_code ec;
    fs::create_directories(work_root, ec);
    if (!ec) fs::permissions(work_root, fs::perms::owner_all, ec);
    if (ec)
        return Status(StatusCode::UNAVAILABLE,
                      "cannot make the daemon's prediction folder: " + ec.message());
    std::string made = (fs::path(work_root) / (std::string(kFolderPrefix) + "XXXXXX")).string();
    if (!::mkdtemp(made.data()))  // mode 0700
        return Status(StatusCode::UNAVAILABLE,
                      "cannot make a prediction's folder: " + osMessage(errno));
    const WorkFolder folder{made};
    const std::string in_dir = folder.path + "/in";
    const std::string out_dir = folder.path + "/out";
    if (::mkdir(in_dir.c_str(), 0700) != 0 || ::mkdir(out_dir.c_str(), 0700) != 0)
        return Status(StatusCode::UNAVAILABLE,
                      "cannot make a prediction's folder: " + osMessage(errno));
    for (const v1::NamedFile& file : request.files())
        if (Status ok = writeNew(in_dir + "/" + file.name(), file.content()); !ok.ok()) return ok;
    const std::string scene_path = in_dir + "/" + kSceneFile;
    if (Status ok = writeNew(scene_path, request.scene_json()); !ok.ok()) return ok;

    const v1::PredictOptions& o = request.options();
    predict::PredictOptions options;
    options.table.theta_step_deg = o.table_theta_step_deg();
    options.table.phi_step_deg = o.table_phi_step_deg() == 0.0 ? 10.0 : o.table_phi_step_deg();
    options.table.width = o.table_width_px() == 0 ? 240 : o.table_width_px();
    options.exposure_stops = o.exposure_stops();
    if (o.black_spot_deg() > 0.0) options.lab.black_spot_deg = o.black_spot_deg();
    options.scene_label = scene_name;
    options.paths_relative_to_scene = true;
    options.max_timeline_samples = limits.max_timeline_samples;
    options.max_frame_pixels = limits.max_frame_pixels;
    options.stop_requested = stop_requested;
    // Nothing of the daemon's folders goes back to the client.
    const auto scrubbed = [&](const std::string& text) {
        return replaced(replaced(replaced(text, out_dir + "/", ""), in_dir + "/", ""), folder.path,
                        "(prediction folder)");
    };
    auto predicted = predict::predictScene(scene_path, out_dir, options);
    if (!predicted) {
        const Error& e = predicted.error();
        if (stop_requested && stop_requested())
            return Status(StatusCode::CANCELLED,
                          "the prediction stopped: the client went away or the daemon stops");
        switch (e.code) {
            case ErrorCode::IoError:
                return Status(StatusCode::UNAVAILABLE, scrubbed(e.message));
            case ErrorCode::Internal:
                return Status(StatusCode::INTERNAL, scrubbed(e.message));
            default:  // what the scene, a model or a glTF file was refused for
                return invalid(scrubbed(e.message));
        }
    }
    fillResponse(*predicted, response);
    response->set_summary(scrubbed(predicted->summary));

    // The files asked for, read back as the prediction wrote them.
    size_t bytes = 0;
    for (const std::string& name : predicted->files) {
        const bool frame = name.rfind("frames/", 0) == 0;
        if (frame ? !o.return_frames() : (!o.return_report_files() || name == "report.json"))
            continue;
        const std::string path = out_dir + "/" + name;
        auto file = openRegularFile(path);
        if (!file)
            return Status(StatusCode::INTERNAL,
                          "cannot read back " + name + ": " + scrubbed(file.error().message));
        bytes += static_cast<size_t>(file->size);
        if (bytes > limits.max_output_bytes)
            return Status(StatusCode::RESOURCE_EXHAUSTED,
                          "outputs: the files asked for take more than the " +
                              std::to_string(limits.max_output_bytes) +
                              " bytes a response carries; ask without return_frames (or "
                              "return_report_files), or for fewer or smaller frames");
        std::string content(static_cast<size_t>(file->size), '\0');
        size_t done = 0;
        while (done < content.size()) {
            const ssize_t n = ::read(file->fd.get(), content.data() + done, content.size() - done);
            if (n < 0 && errno == EINTR) continue;
            if (n <= 0)
                return Status(StatusCode::INTERNAL, "cannot read back " + name + ": " +
                                                        (n < 0 ? osMessage(errno) : "it shrank"));
            done += static_cast<size_t>(n);
        }
        v1::NamedFile* out = response->add_outputs();
        out->set_name(name);
        out->set_content(std::move(content));
    }
    return Status::OK;
}

void clearPredictWork(const std::string& work_root) {
    std::error_code ec;
    for (auto it = fs::directory_iterator(work_root, ec); !ec && it != fs::directory_iterator();
         it.increment(ec)) {
        const std::string name = it->path().filename().string();
        if (name.rfind(kFolderPrefix, 0) != 0) continue;
        std::error_code removed;
        fs::remove_all(it->path(), removed);
        logEvent(LogLevel::Info, "predict.leftover_removed",
                 {{"folder", it->path().string()},
                  {"error", removed ? removed.message() : std::string()}});
    }
}

}  // namespace flarelab::daemon
