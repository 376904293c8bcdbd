#include "bench/oracle_bench.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <iomanip>
#include <limits>
#include <nlohmann/json.hpp>
#include <sstream>

#include "drivers/sim_camera.h"
#include "drivers/sim_truth.h"
#include "fit/model_eval.h"
#include "fit/score.h"
#include "optics/ghosts.h"
#include "optics/prescription.h"
#include "render/ghost_shape.h"
#include "render/preview.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;

Error invalid(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "bench oracle: " + what);
}

double median(std::vector<double> v) {
    if (v.empty()) return 0.0;
    std::sort(v.begin(), v.end());
    const size_t n = v.size();
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

double energy(const ImageRGB& image) {
    double sum = 0.0;
    for (float v : image.pixels) sum += v;
    return sum;
}

double squares(const ImageRGB& image) {
    double sum = 0.0;
    for (float v : image.pixels) sum += static_cast<double>(v) * v;
    return sum;
}

// A start for a path the detector finds nothing in: a circle over the pixels at 5 % of the
// image's peak or more (summed over the channels), as bright as their mean in each channel, with
// a pixel-wide outer falloff.
fit::GhostState litStart(const ImageRGB& image, const render::SensorToImage& m) {
    const auto total = [&](int64_t x, int64_t y) {
        const float* p = image.at(x, y);
        return static_cast<double>(p[0]) + p[1] + p[2];
    };
    double peak = 0.0;
    for (int64_t y = 0; y < image.height; ++y)
        for (int64_t x = 0; x < image.width; ++x) peak = std::max(peak, total(x, y));
    double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
    std::array<double, 3> sum{};
    int64_t count = 0;
    for (int64_t y = 0; y < image.height; ++y)
        for (int64_t x = 0; x < image.width; ++x) {
            const double v = total(x, y);
            if (!(v >= 0.05 * peak) || !(v > 0.0)) continue;
            x0 = std::min(x0, static_cast<double>(x));
            x1 = std::max(x1, static_cast<double>(x + 1));
            y0 = std::min(y0, static_cast<double>(y));
            y1 = std::max(y1, static_cast<double>(y + 1));
            for (size_t c = 0; c < 3; ++c) sum[c] += image.at(x, y)[c];
            ++count;
        }
    fit::GhostState s;
    if (count == 0) return s;
    const double radius_mm =
        0.5 * std::max({(x1 - x0) / m.px_per_mm_x, (y1 - y0) / m.px_per_mm_y, 2.0 / m.px_per_mm_x});
    s.shape =
        render::circleGhostShape((0.5 * (x0 + x1) - m.centre_x_px) / m.px_per_mm_x,
                                 (0.5 * (y0 + y1) - m.centre_y_px) / m.px_per_mm_y, radius_mm);
    for (size_t c = 0; c < 3; ++c)
        s.shading.border_rgb[c] = s.shading.inner_rgb[c] = sum[c] / static_cast<double>(count);
    s.shading.inner_falloff_mm = 0.25 * radius_mm;
    s.shading.outer_falloff_mm = 1.0 / m.px_per_mm_x;
    return s;
}

void add(ImageRGB& into, const ImageRGB& image) {
    for (size_t i = 0; i < into.pixels.size(); ++i) into.pixels[i] += image.pixels[i];
}

}  // namespace

Result<OracleBenchReport> runOracleBench(const OracleBenchOptions& options, std::ostream& log) {
    if (options.lens_files.empty()) return invalid("no lens given");
    if (options.angles_deg.empty()) return invalid("no angle given");
    for (double a : options.angles_deg)
        if (!std::isfinite(a) || a < 0.0 || a >= 90.0)
            return invalid("angles must lie in [0, 90) deg");
    if (options.width < 16 || options.width > 8192 || options.height < 16 || options.height > 8192)
        return invalid("width and height must lie in 16..8192");
    if (!(options.min_share >= 0.0 && options.min_share < 1.0))
        return invalid("min_share must lie in [0, 1)");
    if (Status ok = fit::checkFrameFitOptions(options.frame); !ok) return ok.error();

    OracleBenchReport report;
    report.colour = options.colour;
    const int64_t w = options.width, h = options.height;
    const double mask_px = 0.03 * std::hypot(static_cast<double>(w), static_cast<double>(h));
    for (const std::string& file : options.lens_files) {
        auto prescription = optics::loadPrescription(file);
        if (!prescription) return prescription.error();
        auto lens = optics::Lens::make(*prescription, optics::CameraDescription{});
        if (!lens) return lens.error().withContext(file);
        const std::string name = std::filesystem::path(file).stem().string();
        auto enumeration = optics::enumerateGhosts(*lens, drivers::simRenderDefaults().ghosts);
        if (!enumeration) return enumeration.error().withContext(file);
        auto all = drivers::simulatedGhostTruth(*lens, w, h, {}, options.colour);
        if (!all) return all.error().withContext(file);
        // One truth source per path, each a simulated camera drawing that path alone.
        std::vector<fit::TruthSource> alone;
        for (const optics::GhostPath& path : enumeration->ghosts) {
            auto source = drivers::simulatedGhostTruth(*lens, w, h, {path}, options.colour);
            if (!source) return source.error().withContext(file);
            alone.push_back(std::move(*source));
        }
        const auto& camera = lens->camera();
        std::vector<double> ghost_errors, frame_errors, weights;
        OracleLensRow lens_row;
        lens_row.lens = name;
        for (double angle : options.angles_deg) {
            const auto t0 = Clock::now();
            auto truth = (*all)(angle);
            if (!truth) return truth.error().withContext(file);
            const double total = energy(truth->image);
            const double total_squares = squares(truth->image);
            OracleAngleRow angle_row;
            angle_row.lens = name;
            angle_row.angle_deg = angle;
            ImageRGB model(w, h);
            double fitted_light = 0.0;
            for (size_t p = 0; p < alone.size(); ++p) {
                auto image = alone[p](angle);
                if (!image) return image.error().withContext(file);
                const double light = energy(image->image);
                if (!(light > 0.0)) continue;
                ++angle_row.paths_lit;
                const double share = total > 0.0 ? light / total : 0.0;
                // A small bright ghost weighs more in the L2 norm than in the light.
                const double l2_share =
                    total_squares > 0.0 ? squares(image->image) / total_squares : 0.0;
                if (share < options.min_share && l2_share < options.min_share) continue;
                ++angle_row.paths_fitted;
                fitted_light += light;
                OracleGhostRow row;
                row.lens = name;
                row.angle_deg = angle;
                row.path = optics::pathLabel(enumeration->ghosts[p]);
                row.share = share;
                row.l2_share = l2_share;
                auto frame = fit::frameFromImage(image->image, angle, camera.sensor_width_mm,
                                                 camera.sensor_height_mm);
                if (!frame) return frame.error().withContext(name + " " + row.path);
                // The path alone has no light: its brightest blob is the ghost itself, which the
                // detector would otherwise leave out as the light's disc (a speck a few pixels
                // across was fitted from no samples at all).
                fit::DetectOptions detect = options.detect;
                detect.find_light = false;
                auto detection = fit::detectGhosts(*frame, detect);
                if (!detection) return detection.error();
                // The truth has no sky: a path that fills the frame is light, not background
                // (the sweep fit pins the sky to the sweep's lowest the same way).
                detection->background = {0.0, 0.0, 0.0};
                row.candidates = static_cast<int>(detection->candidates.size());
                {
                    // Starts: a circle over the pixels at 5 % of the peak or more, and the
                    // brightest detection when there is one; with none (a veil over the frame),
                    // also a circle over the whole frame; with more than one (a ghost larger than
                    // the frame, or one in pieces), also a circle over all of them and one over
                    // the whole frame. The lowest cost wins: the floor is the model's, not a
                    // start's.
                    std::vector<fit::GhostState> starts;
                    const fit::GhostState lit = litStart(image->image, frame->mapping);
                    starts.push_back(lit);
                    if (detection->candidates.empty()) {
                        fit::GhostState veil = lit;
                        veil.shape = render::circleGhostShape(
                            0.0, 0.0, std::hypot(camera.sensor_width_mm, camera.sensor_height_mm));
                        starts.push_back(veil);
                    } else {
                        starts.insert(starts.begin(), detection->candidates[0].initial);
                    }
                    if (detection->candidates.size() > 1) {
                        const auto& m = frame->mapping;
                        double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
                        for (const auto& c : detection->candidates) {
                            x0 = std::min(x0, static_cast<double>(c.x0));
                            x1 = std::max(x1, static_cast<double>(c.x1 + 1));
                            y0 = std::min(y0, static_cast<double>(c.y0));
                            y1 = std::max(y1, static_cast<double>(c.y1 + 1));
                        }
                        fit::GhostState covering = starts[0];
                        covering.shape = render::circleGhostShape(
                            (0.5 * (x0 + x1) - m.centre_x_px) / m.px_per_mm_x,
                            (0.5 * (y0 + y1) - m.centre_y_px) / m.px_per_mm_y,
                            0.5 * std::max((x1 - x0) / m.px_per_mm_x, (y1 - y0) / m.px_per_mm_y));
                        starts.push_back(covering);
                        fit::GhostState veil = starts[0];
                        veil.shape = render::circleGhostShape(
                            0.0, 0.0, std::hypot(camera.sensor_width_mm, camera.sensor_height_mm));
                        starts.push_back(veil);
                    }
                    std::vector<fit::GhostState> ghosts;
                    double best_cost = std::numeric_limits<double>::infinity();
                    const auto tryStart = [&](const fit::GhostState& start) -> Status {
                        std::vector<fit::GhostState> trial = {start};
                        auto fitted = fit::fitFrame(*frame, *detection, trial, options.frame);
                        if (!fitted) return fitted.error().withContext(name + " " + row.path);
                        if (fitted->final_cost < best_cost) {
                            best_cost = fitted->final_cost;
                            ghosts = trial;
                        }
                        return Ok{};
                    };
                    for (const fit::GhostState& start : starts)
                        if (Status ok = tryStart(start); !ok) return ok.error();
                    // And the best with both falloffs a pixel wide: a soft edge is a local
                    // minimum the frame fit can settle in (a wide falloff covers an edge that is
                    // a little off), where the model can draw a sharp one.
                    fit::GhostState sharp = ghosts.front();
                    const double pixel_mm = 1.0 / frame->mapping.px_per_mm_x;
                    sharp.shading.inner_falloff_mm = pixel_mm;
                    sharp.shading.outer_falloff_mm = pixel_mm;
                    const double cost_before = best_cost;
                    if (Status ok = tryStart(sharp); !ok) return ok.error();
                    row.sharpened = best_cost < cost_before;
                    const ImageRGB drawn = fit::renderGhostStates(ghosts, frame->mapping, w, h);
                    if (!options.images.empty()) {
                        ImageRGB pair(2 * w + 4, h);
                        double peak = 0.0;
                        for (int64_t y = 0; y < h; ++y)
                            for (int64_t x = 0; x < w; ++x)
                                for (int c = 0; c < 3; ++c) {
                                    pair.at(x, y)[c] = image->image.at(x, y)[c];
                                    pair.at(w + 4 + x, y)[c] = drawn.at(x, y)[c];
                                    peak = std::max(peak, double{image->image.at(x, y)[c]});
                                }
                        render::ToneMapOptions tone;
                        tone.curve = render::ToneCurve::Log;
                        tone.exposure_stops = std::clamp(-std::log2(peak), -64.0, 64.0);
                        tone.log_range_stops = 10.0;
                        std::ostringstream file_name;
                        file_name << name << "-" << std::fixed << std::setprecision(2) << angle
                                  << "-" << row.path << ".png";
                        std::filesystem::create_directories(options.images);
                        if (Status ok = render::writePng(
                                pair,
                                (std::filesystem::path(options.images) / file_name.str()).string(),
                                tone);
                            !ok)
                            return ok.error();
                    }
                    auto score = fit::compareImages(drawn, image->image, std::nullopt, 0.0);
                    if (!score) return score.error();
                    row.rel_l2 = score->rel_l2;
                    add(model, drawn);
                }
                ghost_errors.push_back(row.rel_l2);
                weights.push_back(light);
                if (row.rel_l2 >= lens_row.worst_ghost_rel_l2) {
                    lens_row.worst_ghost_rel_l2 = row.rel_l2;
                    std::ostringstream where;
                    where << row.path << " at " << angle << " deg";
                    lens_row.worst_ghost = where.str();
                }
                report.ghosts.push_back(row);
            }
            angle_row.unfitted_share =
                total > 0.0 ? std::max(0.0, 1.0 - fitted_light / total) : 0.0;
            auto frame_score = fit::compareImages(model, truth->image, truth->light_px, mask_px);
            if (!frame_score) return frame_score.error();
            angle_row.frame_rel_l2 = frame_score->rel_l2;
            angle_row.time_s = std::chrono::duration<double>(Clock::now() - t0).count();
            frame_errors.push_back(angle_row.frame_rel_l2);
            lens_row.worst_frame_rel_l2 =
                std::max(lens_row.worst_frame_rel_l2, angle_row.frame_rel_l2);
            log << "bench oracle: " << name << " at " << std::setprecision(6) << angle
                << " deg: " << angle_row.paths_fitted << " of " << angle_row.paths_lit
                << " lit paths fitted, frame floor " << std::fixed << std::setprecision(4)
                << angle_row.frame_rel_l2 << " (" << std::setprecision(1) << angle_row.time_s
                << " s)\n"
                << std::defaultfloat;
            report.angles.push_back(angle_row);
        }
        lens_row.ghosts_fitted = static_cast<int>(ghost_errors.size());
        lens_row.median_ghost_rel_l2 = median(ghost_errors);
        double sw = 0.0, swe = 0.0;
        for (size_t i = 0; i < ghost_errors.size(); ++i) {
            sw += weights[i];
            swe += weights[i] * ghost_errors[i];
        }
        lens_row.weighted_ghost_rel_l2 = sw > 0.0 ? swe / sw : 0.0;
        lens_row.median_frame_rel_l2 = median(frame_errors);
        report.lenses.push_back(lens_row);
    }
    return report;
}

void printOracleBench(const OracleBenchReport& report, std::ostream& out) {
    out << "| lens | paths fitted (all angles) | ghost floor median | light-weighted | worst | "
           "frame floor median | worst |\n|---|---|---|---|---|---|---|\n";
    for (const auto& l : report.lenses)
        out << "| " << l.lens << " | " << l.ghosts_fitted << " | " << std::fixed
            << std::setprecision(3) << l.median_ghost_rel_l2 << " | " << l.weighted_ghost_rel_l2
            << " | " << l.worst_ghost_rel_l2 << " (" << l.worst_ghost << ") | "
            << l.median_frame_rel_l2 << " | " << l.worst_frame_rel_l2 << " |\n"
            << std::defaultfloat;
    out << "\n| lens | angle (deg) | lit paths | fitted | light not fitted | frame floor |\n"
           "|---|---|---|---|---|---|\n";
    for (const auto& a : report.angles)
        out << "| " << a.lens << " | " << a.angle_deg << " | " << a.paths_lit << " | "
            << a.paths_fitted << " | " << std::fixed << std::setprecision(4) << a.unfitted_share
            << " | " << std::setprecision(3) << a.frame_rel_l2 << " |\n"
            << std::defaultfloat;
}

std::string oracleBenchJson(const OracleBenchReport& report) {
    nlohmann::json j;
    j["colour"] = report.colour;
    j["lenses"] = nlohmann::json::array();
    for (const auto& l : report.lenses)
        j["lenses"].push_back({{"lens", l.lens},
                               {"ghosts_fitted", l.ghosts_fitted},
                               {"median_ghost_rel_l2", l.median_ghost_rel_l2},
                               {"weighted_ghost_rel_l2", l.weighted_ghost_rel_l2},
                               {"worst_ghost_rel_l2", l.worst_ghost_rel_l2},
                               {"worst_ghost", l.worst_ghost},
                               {"median_frame_rel_l2", l.median_frame_rel_l2},
                               {"worst_frame_rel_l2", l.worst_frame_rel_l2}});
    j["angles"] = nlohmann::json::array();
    for (const auto& a : report.angles)
        j["angles"].push_back({{"lens", a.lens},
                               {"angle_deg", a.angle_deg},
                               {"paths_lit", a.paths_lit},
                               {"paths_fitted", a.paths_fitted},
                               {"unfitted_share", a.unfitted_share},
                               {"frame_rel_l2", a.frame_rel_l2},
                               {"time_s", a.time_s}});
    j["ghosts"] = nlohmann::json::array();
    for (const auto& g : report.ghosts)
        j["ghosts"].push_back({{"lens", g.lens},
                               {"angle_deg", g.angle_deg},
                               {"path", g.path},
                               {"share", g.share},
                               {"l2_share", g.l2_share},
                               {"candidates", g.candidates},
                               {"sharpened", g.sharpened},
                               {"rel_l2", g.rel_l2}});
    return j.dump(2);
}

}  // namespace flarelab::bench
