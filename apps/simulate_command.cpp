#include "apps/simulate_command.h"

#include <chrono>
#include <cmath>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "apps/camera_flags.h"
#include "apps/png_preview.h"
#include "hdr/exr.h"
#include "render/preview.h"
#include "render/scene.h"

namespace flarelab::apps {
namespace {

struct SimulateState {
    std::string lens_file;
    CameraFlags camera;
    double angle_deg = std::nan("");
    double roll_deg = 0.0;
    std::vector<std::string> lights;
    int64_t width = 1920;
    int64_t height = 1080;
    int grid = render::SceneOptions{}.base_grid;
    int max_grid = render::SceneOptions{}.max_grid;
    double grid_bend_px = render::SceneOptions{}.grid_bend_px;
    bool no_starburst = false;
    bool all_paths = false;
    bool reference = false;
    std::string merge = "none";
    int merge_steps = -1;
    double merge_gamma = std::nan("");
    double centre_edge_jump = std::nan("");
    bool adaptive_grid = false;
    bool no_image_window = false;
    std::string exr_path;
    std::string png_path;
    std::optional<double> exposure_stops;  // none: automatic (png_preview.h)
};

// "THETA,PHI" or "THETA,PHI,R,G,B" (degrees; irradiance per channel, default 1).
bool parseLight(const std::string& text, render::Light& light) {
    std::vector<double> values;
    std::stringstream in(text);
    std::string part;
    while (std::getline(in, part, ',')) {
        size_t used = 0;
        try {
            values.push_back(std::stod(part, &used));
        } catch (const std::exception&) {
            return false;
        }
        if (used != part.size()) return false;
    }
    if (values.size() != 2 && values.size() != 5) return false;
    light.theta_deg = values[0];
    light.phi_deg = values[1];
    if (values.size() == 5)
        light.rgb = {static_cast<float>(values[2]), static_cast<float>(values[3]),
                     static_cast<float>(values[4])};
    return true;
}

int run(const SimulateState& s, std::ostream& out, std::ostream& err) {
    const auto lens = loadLens(s.lens_file, s.camera, err);
    if (!lens) return 1;
    std::vector<render::Light> lights;
    if (!std::isnan(s.angle_deg)) lights.push_back({s.angle_deg, s.roll_deg, {1.0f, 1.0f, 1.0f}});
    for (const std::string& text : s.lights) {
        render::Light light;
        if (!parseLight(text, light)) {
            err << "flarelab: --light '" << text << "' is not THETA,PHI or THETA,PHI,R,G,B\n";
            return 1;
        }
        lights.push_back(light);
    }
    render::SceneOptions options;
    options.width = s.width;
    options.height = s.height;
    options.base_grid = s.grid;
    options.max_grid = s.max_grid;
    options.grid_bend_px = s.grid_bend_px;
    options.starburst = !s.no_starburst;
    options.ghosts.skip_double_stop_crossing = !s.all_paths;
    options.tiled = !s.reference;
    options.merge = s.merge == "light"   ? render::kLightMerge
                    : s.merge == "heavy" ? render::kHeavyMerge
                                         : render::kNoMerge;
    if (s.merge_steps >= 0) options.merge.steps = s.merge_steps;
    if (!std::isnan(s.merge_gamma)) options.merge.gamma = s.merge_gamma;
    if (!std::isnan(s.centre_edge_jump)) options.merge.centre_edge_jump = s.centre_edge_jump;
    if (s.adaptive_grid && options.merge.steps == 0) {
        err << "flarelab: --adaptive-grid refines by the merge's test: give a merge (--merge light "
               "or heavy, or --merge-steps 1..7)\n";
        return 1;
    }
    options.adaptive_grid = s.adaptive_grid;
    options.image_window = !s.no_image_window;
    render::SceneStats stats;
    const auto start = std::chrono::steady_clock::now();
    auto image = render::renderScene(*lens, lights, options, &stats);
    if (!image) {
        err << "flarelab: " << image.error().message << "\n";
        return 1;
    }
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    hdr::ExrMetadata meta;
    if (lights.size() == 1) {
        meta.angle_deg = lights[0].theta_deg;
        meta.roll_deg = lights[0].phi_deg;
    }
    meta.lens = lens->name();
    meta.camera = "simulated, f/" + std::to_string(lens->camera().f_number);
    meta.software_version =
        std::string("flarelab simulate (") + (s.reference ? "reference" : "tiled") + ")";
    if (auto written = hdr::writeExr(s.exr_path, *image, meta); !written) {
        err << "flarelab: " << written.error().message << "\n";
        return 1;
    }
    if (!writePngPreview(*image, s.png_path, s.exposure_stops, out, err)) return 1;
    out << "simulate: " << lens->name() << ", " << lights.size() << " light(s)"
        << (stats.lights_behind ? " (" + std::to_string(stats.lights_behind) + " behind)" : "")
        << ", " << stats.ghosts_drawn << " ghost grids (" << stats.ghosts_culled << " culled, "
        << stats.ghosts_off_image << " off the image, " << stats.grids_windowed
        << " windowed to it), " << stats.quads << " quads, "
        << (s.reference ? "reference" : "tiled") << ": trace " << stats.trace_ms << " ms, draw "
        << stats.draw_ms << " ms, total " << seconds << " s -> " << s.exr_path
        << (s.png_path.empty() ? "" : ", " + s.png_path) << "\n";
    return 0;
}

}  // namespace

void addSimulateCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto state = std::make_shared<SimulateState>();
    CLI::App* cmd = app.add_subcommand("simulate", "render a lens's flare under point lights");
    cmd->add_option("--lens", state->lens_file, "lens prescription (CSV, format v1)")->required();
    cmd->add_option("--angle", state->angle_deg, "a white light at this angle from the axis (deg)");
    cmd->add_option("--roll", state->roll_deg, "that light's roll (deg)");
    cmd->add_option("--light", state->lights, "a light THETA,PHI[,R,G,B] (deg; irradiance)");
    cmd->add_option("--width", state->width, "image width in pixels")->capture_default_str();
    cmd->add_option("--height", state->height, "image height in pixels")->capture_default_str();
    cmd->add_option("--grid", state->grid, "base ray-grid size (eq. 13)")->capture_default_str();
    cmd->add_option("--max-grid", state->max_grid,
                    "the most rays a side of a smooth ghost's grid (0: eq. 13's size, no cap)")
        ->check(CLI::Range(0, 2048))
        ->capture_default_str();
    cmd->add_option("--grid-bend", state->grid_bend_px,
                    "pixels: a grid keeps more than --max-grid rays a side where its sensor "
                    "positions, interpolated across a cell, would be off by more")
        ->check(CLI::PositiveNumber)
        ->capture_default_str();
    cmd->add_flag("--no-starburst", state->no_starburst, "ghosts only");
    cmd->add_flag("--all", state->all_paths, "also paths that cross the stop three times");
    cmd->add_flag("--reference", state->reference,
                  "draw ghost by ghost (the baseline) instead of with tiles");
    cmd->add_option("--merge", state->merge,
                    "primitive merge: none (every quad: the truth, slowest), light (4 steps, "
                    "gamma 0.001: the README's timed frames, 72.6 dB (Heliar) and 77.8 dB "
                    "(Canon 200) PSNR against none) or heavy (4, 0.1)")
        ->check(CLI::IsMember({"none", "light", "heavy"}))
        ->capture_default_str();
    cmd->add_option("--merge-steps", state->merge_steps, "merge steps (0..7), overrides --merge")
        ->check(CLI::Range(0, 7));
    cmd->add_option("--merge-gamma", state->merge_gamma,
                    "sine of the largest angle between merged edges, overrides --merge")
        ->check(CLI::NonNegativeNumber);
    cmd->add_option("--centre-edge-jump", state->centre_edge_jump,
                    "largest relative change of light density across an interior edge of a grid "
                    "that is drawn by pixel centre instead of cut by area (0: every edge cut; "
                    "light and heavy merges use 0.01), overrides --merge")
        ->check(CLI::Range(0.0, 1.0));
    cmd->add_flag("--no-image-window", state->no_image_window,
                  "trace every ghost's whole eq. 13 grid, also where only part of it can reach "
                  "the image");
    cmd->add_flag("--adaptive-grid", state->adaptive_grid,
                  "trace each ray grid in coarse blocks and refine only where the merge's test "
                  "fails (needs a merge)");
    cmd->add_option("-o,--output", state->exr_path, "output OpenEXR file")->required();
    cmd->add_option("--png", state->png_path, "also a tone-mapped PNG preview");
    cmd->add_option("--exposure-stops", state->exposure_stops,
                    "PNG exposure in stops (default: automatic, printed)");
    addCameraFlags(cmd, state->camera);
    cmd->callback([state, &out, &err, &exit_code] {
        if (std::isnan(state->angle_deg) && state->lights.empty()) {
            err << "flarelab: simulate needs --angle or at least one --light\n";
            exit_code = 1;
            return;
        }
        exit_code = run(*state, out, err);
    });
}

}  // namespace flarelab::apps
