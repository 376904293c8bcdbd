#include "bench/playback_bench.h"

#include <tbb/info.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <ostream>
#include <vector>

#include "fit/model_eval.h"
#include "fit/model_file.h"
#include "fit/score.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;

double millisecondsSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// The angle of the valid range where the model draws the most ghosts (the first of 201 evenly
// spaced angles that has the most): the heaviest frame the model asks for.
double busiestAngle(const fit::FlareModel& model, double roll_deg) {
    double best_angle = model.valid_from_deg;
    size_t best = 0;
    constexpr int kSteps = 200;
    for (int i = 0; i <= kSteps; ++i) {
        const double angle =
            model.valid_from_deg + (model.valid_to_deg - model.valid_from_deg) * i / double(kSteps);
        const auto ghosts = fit::modelGhostsAt(model, angle, roll_deg);
        if (ghosts && ghosts->size() > best) {
            best = ghosts->size();
            best_angle = angle;
        }
    }
    return best_angle;
}

}  // namespace

Result<PlaybackBenchResult> runPlaybackBench(const PlaybackBenchOptions& o, std::ostream& log) {
    if (o.frames < 1 || o.frames > 10000)
        return makeError(ErrorCode::InvalidArgument, "bench playback: frames must lie in 1..10000");
    if (o.exact_seeds < 1 || o.exact_seeds > 64 || o.exact_iterations < 0 ||
        o.exact_iterations > 64)
        return makeError(ErrorCode::InvalidArgument,
                         "bench playback: exact seeds must lie in 1..64, iterations in 0..64");
    if (o.width < 1 || o.height < 1 || o.width > 32768 || o.height > 32768)
        return makeError(ErrorCode::InvalidArgument,
                         "bench playback: width and height must lie in 1..32768");
    const auto model = fit::readModel(o.model_path);
    if (!model) return model.error();
    PlaybackBenchResult r;
    r.width = o.width;
    r.height = o.height;
    r.roll_deg = std::isnan(o.roll_deg) ? model->capture.roll_deg : o.roll_deg;
    r.angle_deg = std::isnan(o.angle_deg) ? busiestAngle(*model, r.roll_deg) : o.angle_deg;
    const auto ghosts = fit::modelGhostsAt(*model, r.angle_deg, r.roll_deg);
    if (!ghosts) return ghosts.error();
    r.ghosts = static_cast<int64_t>(ghosts->size());
    r.threads = tbb::info::default_concurrency();
    r.frames = o.frames;

    fit::ModelRenderOptions fast;
    fast.smooth_tolerance = o.smooth_tolerance;
    fast.frame_tolerance = o.frame_tolerance;
    fast.tiles.dense_tile_px = o.dense_tile_px;
    fast.tiles.coarse_tile_px = o.coarse_tile_px;
    std::vector<double> times;
    ImageRGB image;
    render::TileStats stats;
    fast.stats = &stats;
    double best = std::numeric_limits<double>::infinity();
    for (int i = 0; i <= o.frames; ++i) {
        stats = {};
        const auto start = Clock::now();
        auto frame = fit::renderModel(*model, r.angle_deg, r.roll_deg, o.width, o.height, fast);
        const double ms = millisecondsSince(start);
        if (!frame) return frame.error();
        if (i == 0)
            r.first_frame_ms = ms;
        else
            times.push_back(ms);
        if (i > 0 && ms < best) {
            best = ms;
            r.tiles_smooth = stats.ghost_tiles_smooth;
            r.tiles_edge = stats.ghost_tiles_edge;
            r.build_ms = stats.build_ms;
            r.traverse_ms = stats.traverse_ms;
        }
        image = std::move(*frame);
    }
    std::sort(times.begin(), times.end());
    r.frame_ms = times.front();
    r.frame_median_ms = times[times.size() / 2];
    log << "bench playback: " << r.ghosts << " ghosts at " << r.angle_deg << " deg, " << o.width
        << "x" << o.height << ": fast " << r.frame_ms << " ms (best of " << times.size()
        << "; tiles built and ghosts classified " << r.build_ms << " ms, drawn " << r.traverse_ms
        << " ms; dense tiles x ghosts interpolated " << r.tiles_smooth << ", per pixel "
        << r.tiles_edge << ")\n";
    for (const float v : image.pixels) r.peak = std::max(r.peak, static_cast<double>(v));
    if (!o.exact) return r;

    fit::ModelRenderOptions exact;
    exact.evaluation = render::GhostEvaluation::Exact;
    exact.distance = render::FastDistanceOptions{o.exact_iterations, o.exact_seeds};
    const auto start = Clock::now();
    const auto reference =
        fit::renderModel(*model, r.angle_deg, r.roll_deg, o.width, o.height, exact);
    r.exact_ms = millisecondsSince(start);
    if (!reference) return reference.error();
    double peak = 0.0, diff2 = 0.0, ref2 = 0.0, worst = 0.0;
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        const double e = reference->pixels[i], f = image.pixels[i];
        peak = std::max(peak, std::abs(e));
        worst = std::max(worst, std::abs(f - e));
        diff2 += (f - e) * (f - e);
        ref2 += e * e;
    }
    // The same on score's tone mapping (fit::toneMapScore, 1e-3 of the peak at its default), where
    // dim ghosts count: what a person sees in a log view of the frame.
    double log_diff2 = 0.0, log_ref2 = 0.0;
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        const double e = fit::toneMapScore(reference->pixels[i], peak, o.log_scale);
        const double f = fit::toneMapScore(image.pixels[i], peak, o.log_scale);
        log_diff2 += (f - e) * (f - e);
        log_ref2 += e * e;
    }
    r.log_rel_l2 = log_ref2 > 0.0 ? std::sqrt(log_diff2 / log_ref2) : std::sqrt(log_diff2);
    r.peak = peak;
    r.max_abs_err = worst;
    r.max_rel_err = peak > 0.0 ? worst / peak : worst;
    r.rel_l2 = ref2 > 0.0 ? std::sqrt(diff2 / ref2) : std::sqrt(diff2);
    log << "bench playback: exact " << r.exact_ms << " ms, max_rel_err " << r.max_rel_err
        << ", rel_l2 " << r.rel_l2 << ", log_rel_l2 " << r.log_rel_l2 << "\n";
    return r;
}

void printPlaybackBench(const PlaybackBenchResult& r, std::ostream& out) {
    out << "| ghosts | angle (deg) | size | threads | frame_ms (best) | median | first | exact_ms "
           "| "
           "max_rel_err | rel_l2 | log_rel_l2 |\n|---|---|---|---|---|---|---|---|---|---|---|\n";
    out << "| " << r.ghosts << " | " << r.angle_deg << " | " << r.width << "x" << r.height << " | "
        << r.threads << " | " << r.frame_ms << " | " << r.frame_median_ms << " | "
        << r.first_frame_ms << " | " << r.exact_ms << " | " << r.max_rel_err << " | " << r.rel_l2
        << " | " << r.log_rel_l2 << " |\n";
}

nlohmann::json playbackBenchJson(const PlaybackBenchResult& r) {
    return {{"angle_deg", r.angle_deg},
            {"roll_deg", r.roll_deg},
            {"width", r.width},
            {"height", r.height},
            {"ghosts", r.ghosts},
            {"frames", r.frames},
            {"frame_ms", r.frame_ms},
            {"frame_median_ms", r.frame_median_ms},
            {"first_frame_ms", r.first_frame_ms},
            {"exact_ms", r.exact_ms},
            {"max_rel_err", r.max_rel_err},
            {"max_abs_err", r.max_abs_err},
            {"rel_l2", r.rel_l2},
            {"log_rel_l2", r.log_rel_l2},
            {"peak", r.peak},
            {"threads", r.threads},
            {"tiles_smooth", r.tiles_smooth},
            {"tiles_edge", r.tiles_edge},
            {"build_ms", r.build_ms},
            {"traverse_ms", r.traverse_ms}};
}

}  // namespace flarelab::bench
