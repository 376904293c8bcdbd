#include "apps/lens_commands.h"

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <iomanip>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string>

#include "apps/camera_flags.h"
#include "common/units.h"
#include "optics/ghosts.h"
#include "optics/paraxial.h"
#include "optics/prescription.h"

namespace flarelab::apps {
namespace {

using Json = nlohmann::ordered_json;
using namespace flarelab::optics;

// Round for JSON so that documents stay readable and diffs stable (0.1 nm resolution in mm).
double tidy(double v) { return std::round(v * 1e7) / 1e7 + 0.0; }  // + 0.0 turns -0 into 0

std::string fixed(double v, int digits) {
    std::ostringstream out;
    out << std::fixed << std::setprecision(digits) << v;
    return out.str();
}

int runShow(const std::string& file,
            const CameraFlags& flags,
            bool json,
            std::ostream& out,
            std::ostream& err) {
    // Loaded once: the lens for the optics, the prescription for the table as written.
    const auto prescription = loadPrescription(file);
    if (!prescription) {
        err << "flarelab: " << prescription.error().message << "\n";
        return 1;
    }
    const auto lens = makeLens(*prescription, flags, err);
    if (!lens) return 1;
    const auto p = paraxialProperties(*lens, kLambdaD_nm);
    if (!p) {
        err << "flarelab: " << file << ": afocal lens, no focal length\n";
        return 1;
    }
    const auto enumeration = enumerateGhosts(*lens);
    if (!enumeration) {
        err << "flarelab: " << enumeration.error().message << "\n";
        return 1;
    }
    const auto& s = lens->surfaces();
    const double stop_mm = s[lens->stopIndex()].semi_aperture_mm;
    const double efl_rgb[3] = {
        paraxialProperties(*lens, kLambdaRed_nm)->efl_mm,
        paraxialProperties(*lens, kLambdaGreen_nm)->efl_mm,
        paraxialProperties(*lens, kLambdaBlue_nm)->efl_mm,
    };
    const double image_gap = lens->sensorZ_mm() - s.back().z_mm;
    if (json) {
        Json doc;
        doc["name"] = lens->name();
        doc["file"] = file;
        doc["label_focal_length_mm"] =
            lens->labelFocalLength_mm() > 0.0 ? Json(lens->labelFocalLength_mm()) : Json();
        doc["efl_mm"] = tidy(p->efl_mm);
        doc["bfl_mm"] = tidy(p->bfl_mm);
        doc["ffl_mm"] = tidy(p->ffl_mm);
        doc["image_plane_gap_mm"] = tidy(image_gap);
        doc["efl_rgb_mm"] = {tidy(efl_rgb[0]), tidy(efl_rgb[1]), tidy(efl_rgb[2])};
        doc["entrance_pupil_z_mm"] = tidy(p->entrance_pupil_z_mm);
        doc["entrance_pupil_radius_mm"] = tidy(p->entrance_pupil_radius_mm);
        doc["exit_pupil_z_mm"] = tidy(p->exit_pupil_z_mm);
        doc["f_number"] = tidy(p->working_f_number);
        doc["focal_length_for_f_number_mm"] = tidy(lens->camera().focal_length_mm);
        doc["stop_semi_aperture_mm"] = tidy(stop_mm);
        doc["table_stop_semi_aperture_mm"] = tidy(lens->tableStopSemiAperture_mm());
        doc["sensor_mm"] = {lens->camera().sensor_width_mm, lens->camera().sensor_height_mm};
        doc["ghost_paths"] = {{"stop_crossed_once", enumeration->ghosts.size()},
                              {"all_pairs", enumeration->all_pairs}};
        doc["uncoated_surfaces_without_coating_data"] = lens->uncoatedUnspecifiedSurfaces();
        doc["glasses_without_abbe_number"] = lens->nonDispersiveGlasses();
        Json rows = Json::array();
        for (size_t k = 0; k < s.size(); ++k) {
            const Surface& row = prescription->surfaces[k];
            rows.push_back({{"number", k + 1},
                            {"kind", s[k].is_stop ? "stop" : "surface"},
                            {"radius_mm", row.radius_mm},
                            {"thickness_mm", row.thickness_mm},
                            {"ior_d", row.ior_d},
                            {"abbe", row.abbe},
                            {"semi_aperture_mm", tidy(s[k].semi_aperture_mm)},
                            {"coating_wavelength_nm", s[k].coating_wavelength_nm},
                            {"z_mm", tidy(s[k].z_mm)}});
        }
        doc["surfaces"] = rows;
        out << doc.dump(2) << "\n";
        return 0;
    }
    out << lens->name() << "\n"
        << "  file " << file << "\n\n";
    out << "   #  kind      radius_mm  thickness_mm   ior_d   abbe  semi_ap_mm  coat_nm      "
           "z_mm\n";
    for (size_t k = 0; k < s.size(); ++k) {
        const Surface& row = prescription->surfaces[k];
        char line[160];
        std::snprintf(line, sizeof line,
                      "%4zu  %-7s %11.4f %13.4f %7.4f %6.2f %11.4f %8.0f %9.3f\n", k + 1,
                      s[k].is_stop ? "stop" : "surface", row.radius_mm, row.thickness_mm, row.ior_d,
                      row.abbe, s[k].semi_aperture_mm, s[k].coating_wavelength_nm, s[k].z_mm);
        out << line;
    }
    out << "\nparaxial, d line (587.56 nm):\n";
    out << "  effective focal length  " << fixed(p->efl_mm, 3) << " mm";
    if (lens->labelFocalLength_mm() > 0.0)
        out << "   (source's label: " << fixed(lens->labelFocalLength_mm(), 1) << " mm)";
    out << "\n";
    out << "  back focal distance     " << fixed(p->bfl_mm, 3) << " mm   (table's image plane "
        << fixed(image_gap, 3) << " mm behind the last surface)\n";
    out << "  front focal distance    " << fixed(p->ffl_mm, 3) << " mm\n";
    out << "  EFL at 650/550/450 nm   " << fixed(efl_rgb[0], 3) << " / " << fixed(efl_rgb[1], 3)
        << " / " << fixed(efl_rgb[2], 3) << " mm\n";
    out << "  entrance pupil          " << fixed(p->entrance_pupil_z_mm, 3)
        << " mm behind the first vertex, radius " << fixed(p->entrance_pupil_radius_mm, 3)
        << " mm\n";
    out << "  exit pupil              " << fixed(p->exit_pupil_z_mm, 3)
        << " mm behind the first vertex\n";
    out << "  f-number                f/" << fixed(p->working_f_number, 2) << " (stop "
        << fixed(stop_mm, 3) << " mm for f/" << fixed(lens->camera().f_number, 2) << " at "
        << fixed(lens->camera().focal_length_mm, 1) << " mm; table stop "
        << fixed(lens->tableStopSemiAperture_mm(), 3) << " mm)\n";
    out << "  sensor                  " << lens->camera().sensor_width_mm << " x "
        << lens->camera().sensor_height_mm << " mm\n";
    out << "\nghost paths (two reflections): " << enumeration->ghosts.size()
        << " crossing the stop once, " << enumeration->all_pairs << " in all\n";
    if (lens->uncoatedUnspecifiedSurfaces() > 0)
        out << "note: " << lens->uncoatedUnspecifiedSurfaces()
            << " surfaces have no coating in the file and are traced bare "
               "(--coat-unspecified gives them a 550 nm coating)\n";
    if (lens->nonDispersiveGlasses() > 0)
        out << "note: " << lens->nonDispersiveGlasses()
            << " glasses have no Abbe number and are traced without dispersion\n";
    return 0;
}

struct GhostFlags {
    double angle_deg = 0.0;
    double roll_deg = 0.0;
    double wavelength_nm = kLambdaGreen_nm;
    bool all = false;
    double min_power = 0.0;
    int grid = 24;
};

Json optionalNumber(std::optional<double> v) { return v ? Json(tidy(*v)) : Json(); }

int runGhosts(const std::string& file,
              const CameraFlags& flags,
              const GhostFlags& g,
              bool json,
              std::ostream& out,
              std::ostream& err) {
    if (!(g.angle_deg >= 0.0 && g.angle_deg < 90.0)) {
        err << "flarelab: --angle must lie in [0, 90) degrees (the light in front of the camera)\n";
        return 1;
    }
    if (!std::isfinite(g.roll_deg)) {
        err << "flarelab: --roll must be finite\n";
        return 1;
    }
    if (!(g.wavelength_nm >= 200.0 && g.wavelength_nm <= 3000.0)) {
        err << "flarelab: --wavelength-nm must lie in 200..3000\n";
        return 1;
    }
    if (g.grid < 2 || g.grid > 1024) {
        err << "flarelab: --grid must lie in 2..1024\n";
        return 1;
    }
    if (!(g.min_power >= 0.0)) {
        err << "flarelab: --min-power must be >= 0\n";
        return 1;
    }
    const auto lens = loadLens(file, flags, err);
    if (!lens) return 1;
    EnumerationOptions options;
    options.skip_double_stop_crossing = !g.all;
    options.min_relative_power = g.min_power;
    options.cull_light = {g.angle_deg, g.roll_deg};
    options.cull_grid = g.grid;
    const auto enumeration = enumerateGhosts(*lens, options);
    if (!enumeration) {
        err << "flarelab: " << enumeration.error().message << "\n";
        return 1;
    }
    const LightDirectionDeg light{g.angle_deg, g.roll_deg};
    const auto reference = imagingPower(*lens, light, g.grid);
    if (!reference) {
        err << "flarelab: " << reference.error().message << "\n";
        return 1;
    }
    const double tan_theta = std::tan(degToRad(g.angle_deg));
    const double cphi = std::cos(degToRad(g.roll_deg)), sphi = std::sin(degToRad(g.roll_deg));
    const double half_diag = lens->sensorHalfDiagonal_mm();

    Json ghosts = Json::array();
    std::ostringstream table;
    table << "ghost   cross  paraxial x      y   radius |   exact x      y   radius | d_centre "
             "  rel_power  on_sensor\n";
    // Lenses with many surfaces have thousands of ghosts, each traced several times: say how far
    // along the command is when a person is watching, so a long run never looks like a hang.
    const bool show_progress = enumeration->ghosts.size() > 100 && isatty(STDERR_FILENO);
    size_t done = 0;
    for (const GhostPath& path : enumeration->ghosts) {
        if (show_progress)
            err << "\rflarelab: ghost " << ++done << " of " << enumeration->ghosts.size()
                << std::flush;
        const auto par = paraxialGhost(*lens, path, g.wavelength_nm);
        const auto ex = exactGhost(*lens, path, light, g.wavelength_nm);
        const auto power = ghostIntensity(*lens, path, light, *reference);
        if (!power) {
            err << "flarelab: " << power.error().message << "\n";
            return 1;
        }
        std::optional<double> px, py, pr, ex_x, ex_y, ex_r, dcentre;
        if (par) {
            px = par->centre_per_tan_mm * tan_theta * cphi;
            py = par->centre_per_tan_mm * tan_theta * sphi;
            pr = par->radius_mm;
        }
        if (ex) {
            ex_x = ex->centre_mm.x();
            ex_y = ex->centre_mm.y();
            ex_r = ex->radius_mm;
        }
        if (par && ex) dcentre = std::hypot(*px - *ex_x, *py - *ex_y) / half_diag;
        Json entry;
        entry["label"] = pathLabel(path);
        entry["surfaces"] = {path.first + 1, path.second + 1};
        entry["stop_crossings"] = lens->stopCrossings(path);
        entry["paraxial"] = {{"centre_mm", par ? Json{tidy(*px), tidy(*py)} : Json()},
                             {"radius_mm", optionalNumber(pr)}};
        entry["exact"] = {{"centre_mm", ex ? Json{tidy(*ex_x), tidy(*ex_y)} : Json()},
                          {"radius_mm", optionalNumber(ex_r)}};
        entry["centre_difference_half_diagonals"] = optionalNumber(dcentre);
        entry["relative_intensity"] = power->relative_power;
        entry["relative_intensity_rgb"] = {power->relative_power_rgb[0],
                                           power->relative_power_rgb[1],
                                           power->relative_power_rgb[2]};
        entry["on_sensor_fraction"] = tidy(power->on_sensor_fraction);
        ghosts.push_back(entry);

        const auto cell = [](std::optional<double> v, int width, int digits) {
            std::ostringstream s;
            s << std::setw(width);
            // Values that round to zero print as 0, never as -0.
            if (v)
                s << std::fixed << std::setprecision(digits)
                  << (std::abs(*v) < 0.5 * std::pow(10.0, -digits) ? 0.0 : *v);
            else
                s << "-";
            return s.str();
        };
        table << std::left << std::setw(7) << pathLabel(path) << std::right << std::setw(6)
              << lens->stopCrossings(path) << cell(px, 11, 3) << cell(py, 7, 3) << cell(pr, 9, 3)
              << " |" << cell(ex_x, 9, 3) << cell(ex_y, 7, 3) << cell(ex_r, 9, 3) << " |"
              << cell(dcentre ? std::optional<double>(*dcentre * 100.0) : std::nullopt, 8, 3)
              << "% " << std::setw(10) << std::scientific << std::setprecision(2)
              << power->relative_power << std::defaultfloat << std::setw(11) << std::fixed
              << std::setprecision(3) << power->on_sensor_fraction << std::defaultfloat << "\n";
    }
    if (show_progress) err << "\r" << std::string(40, ' ') << "\r" << std::flush;
    if (json) {
        Json doc;
        doc["lens"] = lens->name();
        doc["file"] = file;
        doc["angle_deg"] = g.angle_deg;
        doc["roll_deg"] = g.roll_deg;
        doc["wavelength_nm"] = g.wavelength_nm;
        doc["f_number"] = tidy(lens->camera().f_number);
        doc["sensor_half_diagonal_mm"] = tidy(half_diag);
        doc["counts"] = {{"kept", enumeration->ghosts.size()},
                         {"all_pairs", enumeration->all_pairs},
                         {"double_stop_crossing_skipped", enumeration->double_stop_skipped},
                         {"culled_by_intensity", enumeration->culled.size()}};
        doc["ghosts"] = ghosts;
        Json culled = Json::array();
        for (const CulledGhost& c : enumeration->culled)
            culled.push_back({{"label", pathLabel(c.path)},
                              {"surfaces", {c.path.first + 1, c.path.second + 1}},
                              {"relative_intensity", c.relative_power},
                              {"reason", c.reason}});
        doc["culled"] = culled;
        out << doc.dump(2) << "\n";
        return 0;
    }
    out << lens->name() << " at theta " << g.angle_deg << " deg, roll " << g.roll_deg << " deg, "
        << g.wavelength_nm << " nm, f/" << fixed(lens->camera().f_number, 2) << "\n";
    out << "sensor mm; d_centre in % of the sensor half-diagonal (" << fixed(half_diag, 2)
        << " mm); rel_power: ghost power on the sensor / imaging power (RGB mean)\n\n";
    out << table.str();
    out << "\n"
        << enumeration->ghosts.size() << " ghosts shown; " << enumeration->all_pairs
        << " two-reflection paths in all, " << enumeration->double_stop_skipped
        << " skipped for crossing the stop three times (--all keeps them), "
        << enumeration->culled.size() << " culled below --min-power\n";
    return 0;
}

}  // namespace

void addLensCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    CLI::App* lens = app.add_subcommand("lens", "inspect a lens prescription");
    lens->require_subcommand(1);

    struct ShowState {
        std::string file;
        bool json = false;
        CameraFlags camera;
    };
    auto show_state = std::make_shared<ShowState>();
    CLI::App* show = lens->add_subcommand("show", "surfaces and first-order properties");
    show->add_option("file", show_state->file, "lens prescription (CSV, format v1)")->required();
    show->add_flag("--json", show_state->json, "one JSON document (efl_mm, bfl_mm, ...)");
    addCameraFlags(show, show_state->camera);
    show->callback([show_state, &out, &err, &exit_code] {
        exit_code = runShow(show_state->file, show_state->camera, show_state->json, out, err);
    });

    struct GhostState {
        std::string file;
        bool json = false;
        CameraFlags camera;
        GhostFlags ghost;
    };
    auto ghost_state = std::make_shared<GhostState>();
    CLI::App* ghosts = lens->add_subcommand("ghosts", "two-reflection ghosts at one light angle");
    ghosts->add_option("file", ghost_state->file, "lens prescription (CSV, format v1)")->required();
    ghosts
        ->add_option("--angle", ghost_state->ghost.angle_deg,
                     "light angle theta from the optical axis, degrees [0, 90)")
        ->required();
    ghosts->add_option("--roll", ghost_state->ghost.roll_deg, "light roll phi, degrees");
    ghosts
        ->add_option("--wavelength-nm", ghost_state->ghost.wavelength_nm,
                     "wavelength of the centre and size columns")
        ->capture_default_str();
    ghosts->add_flag("--all", ghost_state->ghost.all, "also paths that cross the stop three times");
    ghosts->add_option("--min-power", ghost_state->ghost.min_power,
                       "cull ghosts below this power relative to the imaging path");
    ghosts->add_option("--grid", ghost_state->ghost.grid, "rays per side for the intensities")
        ->capture_default_str();
    ghosts->add_flag("--json", ghost_state->json, "one JSON document with a `ghosts` array");
    addCameraFlags(ghosts, ghost_state->camera);
    ghosts->callback([ghost_state, &out, &err, &exit_code] {
        exit_code = runGhosts(ghost_state->file, ghost_state->camera, ghost_state->ghost,
                              ghost_state->json, out, err);
    });
}

}  // namespace flarelab::apps
