#include "apps/model_command.h"

#include <algorithm>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "fit/model_file.h"

namespace flarelab::apps {
namespace {

struct ShowState {
    std::string path;
    bool json = false;
};

// "0.001 0.01 0.1"
std::string joined(const std::vector<double>& values) {
    std::ostringstream out;
    for (size_t i = 0; i < values.size(); ++i) out << (i ? " " : "") << values[i];
    return out.str();
}

std::string orNotDescribed(const std::string& text) {
    return text.empty() ? "(not described)" : text;
}

// "mm, bounds -18..18, 2 pieces over -2..3 deg, degrees 1 3, residual rms <= 0.5, max 1.5"
void printParameter(const fit::ModelParameter& p, std::ostream& out) {
    out << "    " << p.name << " [" << (p.unit.empty() ? "-" : p.unit) << "]";
    if (p.lower_bound || p.upper_bound) {
        out << ", bounds ";
        if (p.lower_bound)
            out << *p.lower_bound;
        else
            out << "-inf";
        out << "..";
        if (p.upper_bound)
            out << *p.upper_bound;
        else
            out << "inf";
    }
    out << ": " << p.pieces.size() << (p.pieces.size() == 1 ? " piece" : " pieces") << ", degree"
        << (p.pieces.size() == 1 ? " " : "s ");
    double rms = 0.0;
    double max = 0.0;
    for (size_t i = 0; i < p.pieces.size(); ++i) {
        const fit::ModelPiece& piece = p.pieces[i];
        out << (i ? " " : "") << piece.coefficients.size() - 1;
        rms = std::max(rms, piece.residual_rms);
        max = std::max(max, piece.residual_max);
    }
    out << ", residual rms " << (p.pieces.size() == 1 ? "" : "<= ") << rms << ", max " << max
        << "\n";
}

void printText(const std::string& path, const fit::FlareModel& m, std::ostream& out) {
    out << "model " << path << " (format " << m.format_version;
    if (!m.software_version.empty()) out << ", written by " << m.software_version;
    if (!m.created_utc.empty()) out << ", created " << m.created_utc;
    out << ")\n";

    const fit::ModelLens& lens = m.lens;
    out << "lens: " << orNotDescribed(lens.description);
    if (lens.focal_length_mm) out << ", " << *lens.focal_length_mm << " mm";
    if (lens.f_number) out << ", f/" << *lens.f_number;
    out << ", sensor " << lens.sensor_width_mm << " x " << lens.sensor_height_mm << " mm\n";
    out << "prescription: "
        << (lens.prescription_file.empty() ? std::string("none") : lens.prescription_file);
    if (!lens.prescription_sha256.empty()) out << " (sha256 " << lens.prescription_sha256 << ")";
    out << "\n";

    const fit::ModelCapture& c = m.capture;
    out << "capture: " << c.from_deg << " to " << c.to_deg << " deg in steps of " << c.step_deg
        << " deg, roll " << c.roll_deg << " deg, " << c.width_px << "x" << c.height_px
        << " pixels, camera " << orNotDescribed(c.camera) << "\n";
    out << "brackets: ";
    if (c.exposure_times_s.empty())
        out << "none";
    else
        out << c.exposure_times_s.size() << " exposures of " << joined(c.exposure_times_s) << " s";
    out << "\n";
    out << "valid range: " << m.valid_from_deg << " to " << m.valid_to_deg << " deg\n";

    out << "ghosts: " << m.ghosts.size() << "\n";
    for (const fit::ModelGhost& g : m.ghosts) {
        out << "  ghost " << g.id;
        if (!g.name.empty()) out << " (" << g.name << ")";
        const fit::ModelPiece& first = g.parameters.front().pieces.front();
        const fit::ModelPiece& last = g.parameters.front().pieces.back();
        out << ": " << first.angle_from_deg << " to " << last.angle_to_deg << " deg, "
            << g.fit.frames_fitted << " frames fitted (" << g.fit.first_angle_deg << " to "
            << g.fit.last_angle_deg << " deg), " << g.parameters.size()
            << (g.parameters.size() == 1 ? " parameter" : " parameters") << "\n";
        for (const fit::ModelParameter& p : g.parameters) printParameter(p, out);
    }
}

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
    printText(state.path, *model, out);
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
}

}  // namespace flarelab::apps
