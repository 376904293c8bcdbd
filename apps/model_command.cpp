#include "apps/model_command.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "apps/png_preview.h"
#include "fit/model_eval.h"
#include "fit/model_file.h"
#include "hdr/exr.h"
#include "render/preview.h"

namespace flarelab::apps {
namespace {

struct ShowState {
    std::string path;
    bool json = false;
};

struct RenderState {
    std::string path;
    double angle_deg = std::nan("");
    double roll_deg = std::nan("");  // NaN: the capture's roll
    int64_t width = 0;               // 0: the capture's size
    int64_t height = 0;
    double intensity_scale = 1.0;
    std::string exr_path;
    std::string png_path;
    std::optional<double> exposure_stops;  // none: automatic (png_preview.h)
    bool exact = false;
};

int runShow(const ShowState& state, std::ostream& out, std::ostream& err) {
    const auto model = fit::readModel(state.path);
    if (!model) {
        err << "flarelab: " << model.error().message << "\n";
        return 1;
    }
    if (state.json) {
        const auto json = fit::modelToJson(*model);
        if (!json) {
            err << "flarelab: " << json.error().message << "\n";
            return 1;
        }
        out << *json;
        if (json->empty() || json->back() != '\n') out << "\n";
        return 0;
    }
    out << fit::describeModel(*model, state.path);
    return 0;
}

// The model drawn at one head angle by the tile engine, in the unit of the frames it was fitted to
// (multiplied by --intensity), to an EXR and or a PNG.
int runRender(const RenderState& s, std::ostream& out, std::ostream& err) {
    if (s.exr_path.empty() && s.png_path.empty()) {
        err << "flarelab: model render: give -o FILE.exr, --png FILE.png or both\n";
        return 2;
    }
    const auto model = fit::readModel(s.path);
    if (!model) {
        err << "flarelab: " << model.error().message << "\n";
        return 1;
    }
    const int64_t width = s.width > 0 ? s.width : model->capture.width_px;
    const int64_t height = s.height > 0 ? s.height : model->capture.height_px;
    const double roll = std::isnan(s.roll_deg) ? model->capture.roll_deg : s.roll_deg;
    fit::ModelRenderOptions options;
    options.intensity_scale = s.intensity_scale;
    options.frame_tolerance = true;  // the frame's error budget, not each ghost's
    if (s.exact) options.evaluation = render::GhostEvaluation::Exact;
    const auto start = std::chrono::steady_clock::now();
    auto image = fit::renderModel(*model, s.angle_deg, roll, width, height, options);
    if (!image) {
        err << "flarelab: model render: " << image.error().message << "\n";
        return 1;
    }
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    const auto ghosts = fit::modelGhostsAt(*model, s.angle_deg, roll);
    if (!s.exr_path.empty()) {
        hdr::ExrMetadata meta;
        meta.angle_deg = s.angle_deg;
        meta.roll_deg = roll;
        meta.lens = model->lens.description;
        meta.camera = model->capture.camera;
        meta.software_version = "flarelab model render";
        if (auto written = hdr::writeExr(s.exr_path, *image, meta); !written) {
            err << "flarelab: " << written.error().message << "\n";
            return 1;
        }
    }
    if (!writePngPreview(*image, s.png_path, s.exposure_stops, out, err)) return 1;
    out << "model render: " << (ghosts ? ghosts->size() : 0) << " ghosts at " << s.angle_deg
        << " deg, roll " << roll << " deg, " << width << "x" << height << ", " << ms << " ms -> "
        << (s.exr_path.empty() ? s.png_path
                               : s.exr_path + (s.png_path.empty() ? "" : ", " + s.png_path))
        << "\n";
    return 0;
}

}  // namespace

void addModelCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    CLI::App* model = app.add_subcommand("model", "inspect flare model files");
    model->require_subcommand(1);

    auto show_state = std::make_shared<ShowState>();
    CLI::App* show = model->add_subcommand(
        "show", "lens, capture, valid range and per ghost the parameters' degrees and residuals");
    show->add_option("MODEL", show_state->path, "flare model file (binary protobuf)")->required();
    show->add_flag("--json", show_state->json,
                   "print the model in its JSON form (the protobuf JSON mapping)");
    show->callback(
        [show_state, &out, &err, &exit_code] { exit_code = runShow(*show_state, out, err); });

    auto render_state = std::make_shared<RenderState>();
    CLI::App* render =
        model->add_subcommand("render", "draw the model's ghosts at a head angle (EXR and/or PNG)");
    render->add_option("MODEL", render_state->path, "flare model file (binary protobuf)")
        ->required();
    render
        ->add_option("--angle", render_state->angle_deg,
                     "head angle (deg), inside the model's valid range")
        ->required();
    render->add_option("--roll", render_state->roll_deg, "roll (deg); default: the capture's");
    render->add_option("--width", render_state->width, "image width; default: the capture's")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}));
    render->add_option("--height", render_state->height, "image height; default: the capture's")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}));
    render
        ->add_option("--intensity", render_state->intensity_scale,
                     "multiplies every ghost's intensity (a light of another power)")
        ->check(CLI::NonNegativeNumber)
        ->capture_default_str();
    render->add_flag("--exact", render_state->exact,
                     "every pixel of every ghost by the exact evaluation (the reference; seconds "
                     "per frame) instead of the fast one");
    render->add_option("-o,--output", render_state->exr_path, "OpenEXR file");
    render->add_option("--png", render_state->png_path, "tone-mapped PNG preview");
    render->add_option("--exposure-stops", render_state->exposure_stops,
                       "PNG exposure in stops (default: automatic, printed)");
    render->callback(
        [render_state, &out, &err, &exit_code] { exit_code = runRender(*render_state, out, err); });
}

}  // namespace flarelab::apps
