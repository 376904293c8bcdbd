// adaptive_grid_bench: adaptive ray grids (render/ghost_quads.h adaptiveQuads) against tracing
// the whole grid, as a trade of rays and time against image error.
//
//   adaptive_grid_bench [--width W --height H --grid N --repeat R --json FILE] [LENS...]
//
// For every lens (default: every data/lenses/*.csv of the source tree), three light angles (on
// the axis, 0.4 and 0.9 of the half-diagonal field, roll 30 degrees) and the light and heavy
// merges, renders the ghost image (no starburst, default culling, tiled) with the whole grid
// traced and merged and with adaptive grids, and prints a Markdown table: rays traced, trace and
// total milliseconds (best of R), and the PSNR of each against the whole grid without merge (the
// area-integrated full-grid image) and of the adaptive image against the merged one. Exit status
// 0 when every lens could be read and rendered: the tool measures, the reader judges.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <limits>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "optics/lens.h"
#include "optics/prescription.h"
#include "render/metrics.h"
#include "render/scene.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;

struct Run {
    ImageRGB image;
    render::SceneStats stats;
    double total_ms = std::numeric_limits<double>::infinity();
    double trace_ms = std::numeric_limits<double>::infinity();
};

Result<Run> timed(const optics::Lens& lens,
                  const render::Light& light,
                  const render::SceneOptions& options,
                  int repeat) {
    Run best;
    for (int r = 0; r < repeat; ++r) {
        render::SceneStats stats;
        const auto start = Clock::now();
        auto image = render::renderScene(lens, std::span(&light, 1), options, &stats);
        const double ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
        if (!image) return image.error();
        best.trace_ms = std::min(best.trace_ms, stats.trace_ms);
        if (ms < best.total_ms) {
            best.total_ms = ms;
            best.stats = stats;
        }
        best.image = std::move(*image);
    }
    return best;
}

std::string fixed(double v, int digits = 1) {
    if (!std::isfinite(v)) return v > 0 ? "inf" : "n/a";
    std::ostringstream s;
    s << std::fixed << std::setprecision(digits) << v;
    return s.str();
}

double psnrOf(const ImageRGB& test, const ImageRGB& reference) {
    const auto p = render::psnr(test, reference);
    return p ? *p : std::numeric_limits<double>::quiet_NaN();
}

int usage() {
    std::cerr << "usage: adaptive_grid_bench [--width W] [--height H] [--grid N] [--repeat R] "
                 "[--json FILE] [LENS...]\n";
    return 2;
}

}  // namespace
}  // namespace flarelab::bench

int main(int argc, char** argv) {
    using namespace flarelab;
    using namespace flarelab::bench;
    int64_t width = 1920, height = 1080;
    int grid = 256, repeat = 3;
    std::string json_path;
    std::vector<std::string> lens_files;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        const auto value = [&]() -> std::optional<long> {
            if (i + 1 >= argc) return std::nullopt;
            try {
                size_t used = 0;
                const long v = std::stol(argv[++i], &used);
                if (used != std::string(argv[i]).size()) return std::nullopt;
                return v;
            } catch (const std::exception&) {
                return std::nullopt;
            }
        };
        if (a == "--json") {
            if (i + 1 >= argc) return usage();
            json_path = argv[++i];
        } else if (a == "--width" || a == "--height" || a == "--grid" || a == "--repeat") {
            const auto v = value();
            const long lo = a == "--grid" ? 2 : 1;
            const long hi = a == "--grid" ? 2048 : a == "--repeat" ? 100 : 16384;
            if (!v || *v < lo || *v > hi) {
                std::cerr << "adaptive_grid_bench: " << a << " must be an integer in " << lo << ".."
                          << hi << "\n";
                return 2;
            }
            if (a == "--width") width = *v;
            if (a == "--height") height = *v;
            if (a == "--grid") grid = static_cast<int>(*v);
            if (a == "--repeat") repeat = static_cast<int>(*v);
        } else if (!a.empty() && a[0] == '-') {
            return usage();
        } else {
            lens_files.push_back(a);
        }
    }
    if (lens_files.empty()) {
        for (const auto& e :
             std::filesystem::directory_iterator(std::string(FLARELAB_SOURCE_DIR) + "/data/lenses"))
            if (e.path().extension() == ".csv") lens_files.push_back(e.path().string());
        std::sort(lens_files.begin(), lens_files.end());
    }

    nlohmann::ordered_json doc;
    doc["settings"] = {
        {"width", width}, {"height", height}, {"base_grid", grid}, {"repeat", repeat}};
    doc["rows"] = nlohmann::ordered_json::array();
    std::cout << "| lens | angle deg | merge | rays whole | rays adaptive | ray share | trace ms "
                 "whole | trace ms adaptive | total ms whole | total ms adaptive | PSNR whole dB "
                 "| PSNR adaptive dB | adaptive vs whole merged dB |\n"
              << "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    for (const std::string& file : lens_files) {
        auto prescription = optics::loadPrescription(file);
        if (!prescription) {
            std::cerr << "adaptive_grid_bench: " << prescription.error().message << "\n";
            return 1;
        }
        auto lens = optics::Lens::make(*prescription, optics::CameraDescription{});
        if (!lens) {
            std::cerr << "adaptive_grid_bench: " << file << ": " << lens.error().message << "\n";
            return 1;
        }
        const auto& camera = lens->camera();
        const double half_diagonal =
            0.5 * std::hypot(camera.sensor_width_mm, camera.sensor_height_mm);
        const double field_deg =
            std::atan(half_diagonal / camera.focal_length_mm) * 180.0 / 3.14159265358979323846;
        const std::string name = std::filesystem::path(file).stem().string();
        for (const double fraction : {0.0, 0.4, 0.9}) {
            const render::Light light{fraction * field_deg, 30.0, {1.0f, 1.0f, 1.0f}};
            render::SceneOptions base;
            base.width = width;
            base.height = height;
            base.base_grid = grid;
            base.starburst = false;
            render::SceneOptions truth_options = base;
            truth_options.merge = render::kNoMerge;
            truth_options.max_grid = 0;  // the truth: every grid at its eq. 13 size
            auto truth = timed(*lens, light, truth_options, 1);
            if (!truth) {
                std::cerr << "adaptive_grid_bench: " << name << ": " << truth.error().message
                          << "\n";
                return 1;
            }
            for (const auto& [merge_name, merge] : {std::pair{"light", render::kLightMerge},
                                                    std::pair{"heavy", render::kHeavyMerge}}) {
                render::SceneOptions whole_options = base;
                whole_options.merge = merge;
                render::SceneOptions adaptive_options = whole_options;
                adaptive_options.adaptive_grid = true;
                auto whole = timed(*lens, light, whole_options, repeat);
                auto adaptive = whole ? timed(*lens, light, adaptive_options, repeat) : whole;
                if (!whole || !adaptive) {
                    std::cerr << "adaptive_grid_bench: " << name << ": "
                              << (whole ? adaptive : whole).error().message << "\n";
                    return 1;
                }
                const double p_whole = psnrOf(whole->image, truth->image);
                const double p_adaptive = psnrOf(adaptive->image, truth->image);
                const double p_between = psnrOf(adaptive->image, whole->image);
                const double share = whole->stats.rays > 0
                                         ? static_cast<double>(adaptive->stats.rays) /
                                               static_cast<double>(whole->stats.rays)
                                         : std::numeric_limits<double>::quiet_NaN();
                std::cout << "| " << name << " | " << fixed(light.theta_deg, 2) << " | "
                          << merge_name << " | " << whole->stats.rays << " | "
                          << adaptive->stats.rays << " | " << fixed(share, 3) << " | "
                          << fixed(whole->trace_ms) << " | " << fixed(adaptive->trace_ms) << " | "
                          << fixed(whole->total_ms) << " | " << fixed(adaptive->total_ms) << " | "
                          << fixed(p_whole) << " | " << fixed(p_adaptive) << " | "
                          << fixed(p_between) << " |\n"
                          << std::flush;
                const auto finite = [](double v) -> nlohmann::ordered_json {
                    return std::isfinite(v) ? nlohmann::ordered_json(v) : nullptr;
                };
                doc["rows"].push_back({{"lens", name},
                                       {"theta_deg", light.theta_deg},
                                       {"merge", merge_name},
                                       {"rays_whole", whole->stats.rays},
                                       {"rays_adaptive", adaptive->stats.rays},
                                       {"trace_ms_whole", whole->trace_ms},
                                       {"trace_ms_adaptive", adaptive->trace_ms},
                                       {"total_ms_whole", whole->total_ms},
                                       {"total_ms_adaptive", adaptive->total_ms},
                                       {"psnr_whole_db", finite(p_whole)},
                                       {"psnr_adaptive_db", finite(p_adaptive)},
                                       {"psnr_adaptive_vs_whole_db", finite(p_between)}});
            }
        }
    }
    if (!json_path.empty()) {
        std::ofstream out(json_path);
        out << doc.dump(2) << "\n";
        if (!out) {
            std::cerr << "adaptive_grid_bench: cannot write " << json_path << "\n";
            return 1;
        }
    }
    return 0;
}
