#include "bench/fit_bench.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>
#include <iomanip>
#include <iterator>
#include <nlohmann/json.hpp>
#include <sstream>

#include "common/check.h"
#include "drivers/sim_truth.h"
#include "fit/model_eval.h"
#include "fit/score.h"
#include "optics/prescription.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point start) {
    return std::chrono::duration<double>(Clock::now() - start).count();
}

Result<optics::Lens> loadBenchLens(const std::string& path) {
    auto prescription = optics::loadPrescription(path);
    if (!prescription) return prescription.error();
    return optics::Lens::make(*prescription, optics::CameraDescription{});
}

struct Scored {
    TradeRow row;
};

Result<TradeRow> fitAndScore(const hdr::Sweep& sweep,
                             const optics::Lens& lens,
                             const fit::SweepFitOptions& options,
                             const fit::ScoreOptions& score,
                             const std::string& knob,
                             const std::string& setting,
                             std::ostream& log) {
    const auto start = Clock::now();
    fit::SweepFitResult result;
    auto model = fit::fitSweep(sweep, lens.camera().sensor_width_mm, lens.camera().sensor_height_mm,
                               options, {}, &result);
    if (!model) return model.error().withContext(knob + " " + setting);
    TradeRow row;
    row.knob = knob;
    row.setting = setting;
    row.fit_s = secondsSince(start);
    row.ghosts = static_cast<int>(model->ghosts.size());
    auto truth = drivers::simulatedGhostTruth(
        lens, model->capture.width_px, model->capture.height_px, {}, fit::fittedInColour(*model));
    if (!truth) return truth.error();
    auto report = fit::scoreModel(*model, *truth, score);
    if (!report) return report.error().withContext(knob + " " + setting);
    row.heldout_median = report->heldout_rel_l2.median;
    row.heldout_worst = report->heldout_rel_l2.worst;
    row.fit_median = report->fit_rel_l2.median;
    log << "bench fit: " << knob << " " << setting << ": " << row.ghosts << " ghosts, "
        << std::fixed << std::setprecision(1) << row.fit_s << " s, held-out rel L2 median "
        << std::setprecision(4) << row.heldout_median << " worst " << row.heldout_worst << "\n"
        << std::defaultfloat;
    return row;
}

}  // namespace

const std::vector<std::string>& tradeKnobs() {
    static const std::vector<std::string> knobs = {"iterations",
                                                   "line search steps",
                                                   "trust region radius",
                                                   "distance iterations",
                                                   "samples per side",
                                                   "degree",
                                                   "shading refit frames",
                                                   "shading refit passes",
                                                   "shading refit min degree",
                                                   "shape refit passes",
                                                   "light margin",
                                                   "angular step"};
    return knobs;
}

Result<FitBenchReport> runFitBench(const FitBenchOptions& options, std::ostream& log) {
    if (options.sweeps.empty())
        return makeError(ErrorCode::InvalidArgument, "bench fit: give at least one sweep");
    for (const std::string& knob : options.knobs)
        if (std::find(tradeKnobs().begin(), tradeKnobs().end(), knob) == tradeKnobs().end()) {
            std::string known;
            for (const std::string& k : tradeKnobs()) known += (known.empty() ? "" : ", ") + k;
            return makeError(ErrorCode::InvalidArgument,
                             "bench fit: unknown knob '" + knob + "' (known: " + known + ")");
        }
    if (options.optimizer_frames < 0)
        return makeError(ErrorCode::InvalidArgument, "bench fit: optimizer_frames must be >= 0");
    auto lens = loadBenchLens(options.lens_file);
    if (!lens) return lens.error();
    auto sweep = hdr::readSweep(options.sweeps.front());
    if (!sweep) return sweep.error();
    if (sweep->frames.empty())
        return makeError(ErrorCode::InvalidArgument, "bench fit: empty sweep");
    const double sw = lens->camera().sensor_width_mm, sh = lens->camera().sensor_height_mm;
    const bool colour =
        sweep->header.camera.raw_format && hdr::isBayer(*sweep->header.camera.raw_format);
    auto truth = drivers::simulatedGhostTruth(*lens, sweep->header.capture.width_px,
                                              sweep->header.capture.height_px, {}, colour);
    if (!truth) return truth.error();
    FitBenchReport report;

    // Optimizers on the same frames from the same start.
    const size_t n = sweep->frames.size();
    for (int k = 0; k < options.optimizer_frames; ++k) {
        const size_t index =
            options.optimizer_frames == 1
                ? n / 2
                : static_cast<size_t>(
                      std::llround((0.1 + 0.8 * k / (options.optimizer_frames - 1.0)) * (n - 1)));
        auto frame = fit::loadFitFrame(*sweep, index, sw, sh);
        if (!frame) return frame.error();
        auto detection = fit::detectGhosts(*frame, options.fit.detect);
        if (!detection) return detection.error();
        std::vector<fit::GhostState> start;
        for (const auto& c : detection->candidates) start.push_back(c.initial);
        auto t = (*truth)(frame->angle_deg);
        if (!t) return t.error();
        // The disc the fit leaves out of this frame.
        const double mask = detection->light.found ? detection->light.radius_px : 0.0;
        auto initial = fit::compareImages(
            fit::renderGhostStates(start, frame->mapping, frame->image.width, frame->image.height),
            t->image, t->light_px, mask);
        if (!initial) return initial.error();
        double target = 0.0;
        for (const fit::Optimizer optimizer :
             {fit::Optimizer::Ceres, fit::Optimizer::GradientDescent}) {
            fit::FrameFitOptions fo = options.fit.frame;
            fo.optimizer = optimizer;
            if (optimizer == fit::Optimizer::GradientDescent) {
                fo.max_iterations = options.quick ? 10 : 400;
                fo.target_cost = target;
                fo.function_tolerance = 0.0;
            }
            std::vector<fit::GhostState> ghosts = start;
            auto fitted = fit::fitFrame(*frame, *detection, ghosts, fo);
            if (!fitted) return fitted.error();
            if (optimizer == fit::Optimizer::Ceres) target = fitted->final_cost;
            const auto drawn = fit::renderGhostStates(ghosts, frame->mapping, frame->image.width,
                                                      frame->image.height);
            auto s = fit::compareImages(drawn, t->image, t->light_px, mask);
            if (!s) return s.error();
            OptimizerRow row;
            row.angle_deg = frame->angle_deg;
            row.optimizer = fit::optimizerName(optimizer);
            row.ghosts = static_cast<int>(ghosts.size());
            row.evaluations = fitted->evaluations;
            row.time_ms = fitted->time_ms;
            row.initial_cost = fitted->initial_cost;
            row.final_cost = fitted->final_cost;
            row.rel_l2 = s->rel_l2;
            row.initial_rel_l2 = initial->rel_l2;
            log << "bench fit: " << row.optimizer << " at " << row.angle_deg
                << " deg: " << row.ghosts << " ghosts, " << row.evaluations << " evaluations, "
                << row.time_ms << " ms, cost " << row.initial_cost << " -> " << row.final_cost
                << ", rel L2 " << row.initial_rel_l2 << " -> " << row.rel_l2 << "\n";
            report.optimizers.push_back(row);
        }
    }
    if (options.frames) {
        fit::FrameSource source;
        for (const auto& f : sweep->frames) source.angles_deg.push_back(f.angle_deg);
        const hdr::Sweep& sw_ref = *sweep;
        source.load = [&sw_ref, sw, sh](size_t i) { return fit::loadFitFrame(sw_ref, i, sw, sh); };
        auto result = fit::fitSweepFrames(source, options.fit);
        if (!result) return result.error();
        const size_t step = std::max<size_t>(1, n / 30);
        for (size_t i = 0; i < n; i += step) {
            const double angle = sweep->frames[i].angle_deg;
            // The disc the fit left out of this frame, as a score of its model would.
            double mask = 0.0;
            for (const fit::ModelLightDisc& disc : result->light_discs)
                if (disc.angle_deg == angle) mask = disc.radius_px;
            std::vector<fit::GhostState> states;
            for (const auto& track : result->tracks)
                for (const auto& sample : track.samples)
                    if (sample.angle_deg == angle) states.push_back(sample.state);
            auto t = (*truth)(angle);
            if (!t) return t.error();
            render::SensorToImage m;
            m.px_per_mm_x = static_cast<double>(t->image.width) / sw;
            m.px_per_mm_y = static_cast<double>(t->image.height) / sh;
            m.centre_x_px = 0.5 * static_cast<double>(t->image.width);
            m.centre_y_px = 0.5 * static_cast<double>(t->image.height);
            auto s = fit::compareImages(
                fit::renderGhostStates(states, m, t->image.width, t->image.height), t->image,
                t->light_px, mask);
            if (!s) return s.error();
            report.frames.push_back({angle, static_cast<int>(states.size()), s->rel_l2});
            log << "bench fit: per-frame fit at " << angle << " deg: " << states.size()
                << " ghosts, rel L2 " << s->rel_l2 << "\n";
        }
    }
    if (!options.trade) return report;

    // The trade: one knob at a time from the defaults.
    fit::ScoreOptions score;
    if (options.quick) {
        score.halfway_angles = 4;
        score.random_angles = 1;
        score.fit_angles = 4;
    }
    const auto run = [&](const hdr::Sweep& s, const fit::SweepFitOptions& o,
                         const std::string& knob, const std::string& setting) -> Status {
        auto row = fitAndScore(s, *lens, o, score, knob, setting, log);
        if (!row) return row.error();
        report.trade.push_back(*row);
        return Ok{};
    };
    if (Status ok = run(*sweep, options.fit, "baseline", "defaults"); !ok) return ok.error();
    const auto wants = [&](const std::string& knob) {
        return options.knobs.empty() ||
               std::find(options.knobs.begin(), options.knobs.end(), knob) != options.knobs.end();
    };
    // One knob at a time: each setting applied to the defaults, then fitted and scored. The
    // shading refit (fit/shading_refit.h): off, and on a fifth of its frames; its passes; its
    // series' minimum degree; the shape refit's passes.
    struct Knob {
        std::string name;
        std::vector<int> quick, full;
        std::function<void(fit::SweepFitOptions&, int)> set;
        std::function<std::string(int)> label;
    };
    const auto number = [](int v) { return std::to_string(v); };
    const int fifth = std::max(2, options.fit.shading.frames_per_ghost / 5);
    const Knob knobs[] = {
        {"iterations", {5}, {3, 8, 40}, [](auto& o, int v) { o.frame.max_iterations = v; }, number},
        {"line search steps",
         {20},
         {2, 5, 20},
         [](auto& o, int v) { o.frame.line_search_steps = v; },
         number},
        {"trust region radius",
         {1},
         {0, 1, 2},
         [](auto& o, int v) { o.frame.trust_region_radius = std::pow(10.0, v); },
         [](int v) { return "1e" + std::to_string(v); }},
        {"distance iterations",
         {1},
         {1, 2, 8},
         [](auto& o, int v) { o.frame.cost.distance.iterations = v; },
         number},
        {"samples per side",
         {24},
         {16, 32, 96},
         [](auto& o, int v) { o.frame.cost.max_samples = v; },
         number},
        {"degree",
         {1},
         {1, 3, 6},
         [](auto& o, int v) { o.poly.fixed_degree = v; },
         [](int v) { return "fixed " + std::to_string(v); }},
        {"shading refit frames",
         {0},
         {0, fifth},
         [](auto& o, int v) { o.shading.frames_per_ghost = v; },
         [](int v) { return v == 0 ? std::string("off") : std::to_string(v); }},
        {"shading refit passes",
         {2},
         {2, 4, 8},
         [](auto& o, int v) { o.shading.passes = v; },
         number},
        {"shading refit min degree",
         {3},
         {0, 3, 5},
         [](auto& o, int v) { o.shading.min_degree = v; },
         number},
        {"shape refit passes",
         {1},
         {0, 1, 2, 4},
         [](auto& o, int v) { o.shading.shape_passes = v; },
         number},
        // Pixels added to the light's disc (fit --light-margin-px): more leaves the glare out,
        // and the data near the light with it; the score leaves out the same disc.
        {"light margin",
         {10},
         {0, 10, 20},
         [](auto& o, int v) { o.detect.light_margin_px = v; },
         [](int v) { return std::to_string(v) + " px"; }},
    };
    // The table and the names `--knob` accepts are one list, both ways ("angular step" is the
    // other sweeps, below).
    for (const std::string& name : tradeKnobs())
        FLARELAB_CHECK(name == "angular step" ||
                       std::any_of(std::begin(knobs), std::end(knobs),
                                   [&](const Knob& k) { return k.name == name; }));
    for (const Knob& k : knobs) {
        FLARELAB_CHECK(std::find(tradeKnobs().begin(), tradeKnobs().end(), k.name) !=
                       tradeKnobs().end());
        if (!wants(k.name)) continue;
        for (int v : options.quick ? k.quick : k.full) {
            auto o = options.fit;
            k.set(o, v);
            if (Status ok = run(*sweep, o, k.name, k.label(v)); !ok) return ok.error();
        }
    }
    for (size_t i = 1; i < options.sweeps.size() && wants("angular step"); ++i) {
        auto other = hdr::readSweep(options.sweeps[i]);
        if (!other) return other.error();
        std::ostringstream setting;
        setting << other->header.capture.step_deg << " deg";
        if (Status ok = run(*other, options.fit, "angular step", setting.str()); !ok)
            return ok.error();
    }
    return report;
}

void printFitBench(const FitBenchReport& r, std::ostream& out) {
    if (!r.optimizers.empty()) {
        out << "| angle (deg) | optimizer | ghosts | cost evaluations | time (ms) | initial cost | "
               "final cost | rel L2 vs truth, start | fitted "
               "|\n|---|---|---|---|---|---|---|---|---|\n";
        for (const auto& o : r.optimizers)
            out << "| " << std::fixed << std::setprecision(1) << o.angle_deg << " | " << o.optimizer
                << " | " << o.ghosts << " | " << o.evaluations << " | " << std::setprecision(0)
                << o.time_ms << " | " << std::setprecision(1) << o.initial_cost << " | "
                << o.final_cost << " | " << std::setprecision(4) << o.initial_rel_l2 << " | "
                << o.rel_l2 << " |\n"
                << std::defaultfloat;
        out << "\n";
    }
    if (!r.trade.empty()) {
        const double base_time = r.trade.front().fit_s;
        out << "| knob | setting | ghosts | fit time (s) | time / baseline | held-out rel L2 "
               "median | "
               "worst | fitted angles median |\n|---|---|---|---|---|---|---|---|\n";
        for (const auto& t : r.trade)
            out << "| " << t.knob << " | " << t.setting << " | " << t.ghosts << " | " << std::fixed
                << std::setprecision(1) << t.fit_s << " | " << std::setprecision(2)
                << (base_time > 0.0 ? t.fit_s / base_time : 0.0) << " | " << std::setprecision(4)
                << t.heldout_median << " | " << t.heldout_worst << " | " << t.fit_median << " |\n"
                << std::defaultfloat;
    }
}

std::string fitBenchJson(const FitBenchReport& r) {
    nlohmann::json j;
    j["optimizers"] = nlohmann::json::array();
    for (const auto& o : r.optimizers)
        j["optimizers"].push_back({{"angle_deg", o.angle_deg},
                                   {"optimizer", o.optimizer},
                                   {"ghosts", o.ghosts},
                                   {"evaluations", o.evaluations},
                                   {"time_ms", o.time_ms},
                                   {"initial_cost", o.initial_cost},
                                   {"final_cost", o.final_cost},
                                   {"initial_rel_l2", o.initial_rel_l2},
                                   {"rel_l2", o.rel_l2}});
    j["trade"] = nlohmann::json::array();
    for (const auto& t : r.trade)
        j["trade"].push_back({{"knob", t.knob},
                              {"setting", t.setting},
                              {"ghosts", t.ghosts},
                              {"fit_s", t.fit_s},
                              {"heldout_median", t.heldout_median},
                              {"heldout_worst", t.heldout_worst},
                              {"fit_median", t.fit_median}});
    return j.dump(2);
}

}  // namespace flarelab::bench
