#include "apps/sweep_command.h"

#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "apps/daemon_commands.h"
#include "hdr/sweep.h"

namespace flarelab::apps {
namespace {

using Json = nlohmann::ordered_json;

struct InfoState {
    std::string directory;
    bool check = false;
    bool strict = false;
    bool json = false;
};

Json optionalNumber(const std::optional<double>& value) {
    return value ? Json(*value) : Json(nullptr);
}

// "0.001 0.01 0.1"
std::string joined(const std::vector<double>& values) {
    std::ostringstream out;
    for (size_t i = 0; i < values.size(); ++i) out << (i ? " " : "") << values[i];
    return out.str();
}

// Frames whose shortest exposure saturated more than hdr::kClippedFraction of the samples.
Json clippedJson(const hdr::Sweep& s) {
    const hdr::ClippedFrames c = hdr::clippedFrames(s);
    return Json{{"fraction", c.fraction},
                {"frames", c.frames},
                {"frames_with_stats", c.with_stats},
                {"worst_fraction", c.worst_fraction},
                {"worst_angle_deg", c.worst_angle_deg}};
}

Json toJson(const hdr::Sweep& s, bool checked) {
    const hdr::SweepHeader& h = s.header;
    Json lens = {
        {"description", h.lens.description},
        {"serial", h.lens.serial},
        {"focal_length_mm", optionalNumber(h.lens.focal_length_mm)},
        {"f_number", optionalNumber(h.lens.f_number)},
        {"aperture_blades", h.lens.aperture_blades ? Json(*h.lens.aperture_blades) : Json(nullptr)},
        {"blade_rotation_deg", optionalNumber(h.lens.blade_rotation_deg)},
        {"stop_semi_aperture_mm", optionalNumber(h.lens.stop_semi_aperture_mm)},
        {"coat_unspecified_surfaces", h.lens.coat_unspecified_surfaces
                                          ? Json(*h.lens.coat_unspecified_surfaces)
                                          : Json(nullptr)},
        {"sensor_width_mm", optionalNumber(h.lens.sensor_width_mm)},
        {"sensor_height_mm", optionalNumber(h.lens.sensor_height_mm)},
        {"prescription_file", h.lens.prescription_file},
        {"prescription_sha256", h.lens.prescription_sha256}};
    Json camera = {{"description", h.camera.description},
                   {"serial", h.camera.serial},
                   {"pixel_pitch_um", optionalNumber(h.camera.pixel_pitch_um)},
                   {"bit_depth", h.camera.bit_depth ? Json(*h.camera.bit_depth) : Json(nullptr)},
                   {"raw_format", h.camera.raw_format
                                      ? Json(std::string(hdr::rawFormatName(*h.camera.raw_format)))
                                      : Json(nullptr)}};
    Json capture = {{"from_deg", h.capture.from_deg}, {"to_deg", h.capture.to_deg},
                    {"step_deg", h.capture.step_deg}, {"roll_deg", h.capture.roll_deg},
                    {"width_px", h.capture.width_px}, {"height_px", h.capture.height_px}};
    Json brackets = {{"exposure_times_s", h.capture.exposure_times_s},
                     {"gain", optionalNumber(h.capture.gain)}};
    std::vector<double> angles;
    size_t with_raw = 0;
    for (const hdr::SweepFrame& f : s.frames) {
        angles.push_back(f.angle_deg);
        with_raw += f.raw_files.empty() ? 0 : 1;
    }
    return Json{{"directory", s.directory},
                {"format_version", h.format_version},
                {"software_version", h.software_version},
                {"created_utc", h.created_utc},
                {"lens", lens},
                {"camera", camera},
                {"capture", capture},
                {"brackets", brackets},
                {"frames", s.frames.size()},
                {"angles_deg", angles},
                {"frames_with_raw", with_raw},
                {"checked", checked},
                {"warnings", s.warnings},
                {"clipped", clippedJson(s)}};
}

void printText(const hdr::Sweep& s, bool checked, std::ostream& out) {
    const hdr::SweepHeader& h = s.header;
    out << "sweep " << s.directory << " (format " << h.format_version;
    if (!h.software_version.empty()) out << ", written by " << h.software_version;
    if (!h.created_utc.empty()) out << ", started " << h.created_utc;
    out << ")\n";

    out << "lens: " << (h.lens.description.empty() ? "(not described)" : h.lens.description);
    if (!h.lens.serial.empty()) out << ", serial " << h.lens.serial;
    if (h.lens.focal_length_mm) out << ", " << *h.lens.focal_length_mm << " mm";
    if (h.lens.f_number) out << ", f/" << *h.lens.f_number;
    if (h.lens.aperture_blades)
        out << (*h.lens.aperture_blades == 0
                    ? std::string(", circular stop")
                    : ", " + std::to_string(*h.lens.aperture_blades) + " blades");
    if (h.lens.blade_rotation_deg && h.lens.aperture_blades.value_or(0) != 0)
        out << " rotated " << *h.lens.blade_rotation_deg << " deg";
    if (h.lens.stop_semi_aperture_mm)
        out << ", stop semi-aperture " << *h.lens.stop_semi_aperture_mm << " mm";
    if (h.lens.coat_unspecified_surfaces)
        out << ", unspecified surfaces " << (*h.lens.coat_unspecified_surfaces ? "coated" : "bare");
    if (h.lens.sensor_width_mm && h.lens.sensor_height_mm)
        out << ", sensor " << *h.lens.sensor_width_mm << " x " << *h.lens.sensor_height_mm << " mm";
    if (!h.lens.prescription_file.empty()) out << ", prescription " << h.lens.prescription_file;
    out << "\n";

    out << "camera: " << (h.camera.description.empty() ? "(not described)" : h.camera.description);
    if (!h.camera.serial.empty()) out << ", serial " << h.camera.serial;
    if (h.camera.pixel_pitch_um) out << ", " << *h.camera.pixel_pitch_um << " um pixels";
    if (h.camera.bit_depth) out << ", " << *h.camera.bit_depth << " bit";
    if (h.camera.raw_format) out << ", raw format " << hdr::rawFormatName(*h.camera.raw_format);
    out << "\n";

    const hdr::SweepCapture& c = h.capture;
    out << "capture: " << c.from_deg << " to " << c.to_deg << " deg in steps of " << c.step_deg
        << " deg, roll " << c.roll_deg << " deg, " << c.width_px << "x" << c.height_px
        << " pixels\n";
    out << "brackets: ";
    if (c.exposure_times_s.empty())
        out << "none";
    else
        out << c.exposure_times_s.size() << " exposures of " << joined(c.exposure_times_s) << " s";
    if (c.gain) out << ", gain " << *c.gain;
    out << "\n";

    out << "frames: " << s.frames.size();
    if (!s.frames.empty()) {
        size_t with_raw = 0;
        for (const hdr::SweepFrame& f : s.frames) with_raw += f.raw_files.empty() ? 0 : 1;
        out << ", " << s.frames.front().angle_deg << " to " << s.frames.back().angle_deg << " deg";
        if (with_raw) out << ", " << with_raw << " with raw brackets";
    }
    out << "\n";
    out << (checked ? "checked: every frame read and matches the manifest\n"
                    : "checked: manifest only (--check reads every frame)\n");
    for (const std::string& warning : s.warnings) out << "warning: " << warning << "\n";
    if (const std::string w = hdr::clippingWarning(hdr::clippedFrames(s), s.frames.size());
        !w.empty())
        out << "warning: " << w << "\n";
}

int runInfo(const InfoState& state, std::ostream& out, std::ostream& err) {
    const bool check = state.check || state.strict;
    hdr::ReadSweepOptions options;
    options.extra_exr_files_are_errors = state.strict;
    const auto sweep =
        check ? hdr::readSweep(state.directory, options) : hdr::readSweepManifest(state.directory);
    if (!sweep) {
        err << "flarelab: " << sweep.error().message << "\n";
        return 1;
    }
    if (state.json)
        out << toJson(*sweep, check).dump(2) << "\n";
    else
        printText(*sweep, check, out);
    return 0;
}

}  // namespace

void addSweepCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    CLI::App* sweep =
        app.add_subcommand("sweep", "inspect sweep directories, start sweeps on flarelabd");
    sweep->require_subcommand(1);
    addSweepStartCommand(*sweep, out, err, exit_code);

    auto info_state = std::make_shared<InfoState>();
    CLI::App* info = sweep->add_subcommand("info", "lens, camera, bracket and angles of a sweep");
    info->add_option("DIR", info_state->directory, "sweep directory (holds manifest.json)")
        ->required();
    info->add_flag("--check", info_state->check,
                   "also read every frame and check it against the manifest");
    info->add_flag("--strict", info_state->strict,
                   "like --check, and EXR files the manifest does not list are errors");
    info->add_flag("--json", info_state->json,
                   "one JSON document (frames, angles_deg, lens, camera, brackets, ...)");
    info->callback(
        [info_state, &out, &err, &exit_code] { exit_code = runInfo(*info_state, out, err); });
}

}  // namespace flarelab::apps
