// ============================================================================
//  flarelab bench: FitBenchOptions, OptimizerRow, TradeRow, FitBenchReport, runFitBench
// ============================================================================
//
// `flarelab bench fit`: the fitting backend's speed against its accuracy, on simulated sweeps
// whose ground truth the simulator knows (drivers/sim_truth.h).
//
// Optimizers. On the same frames from the same detected start, Ceres (Levenberg-Marquardt) and
// the thesis's gradient descent (fit/frame_fit.h): Ceres runs to convergence; the baseline then
// runs until it reaches Ceres' final cost (or its epoch limit). Reported per frame: cost
// evaluations, time, final cost, and the frame model's relative L2 against the noiseless truth.
//
// Trade. A whole sweep fitted and scored (fit/score.h) for each setting of one knob at a time,
// the others at their defaults: optimizer iterations, distance iterations (Newton steps), crop
// resolution (samples per side), polynomial degree (chosen by cross-validation or fixed), the
// shading refit (off, or on a fifth of its frames per ghost; its passes; its series' minimum
// degree; fit/shading_refit.h), and angular step (each --sweep given; e.g. the same lens captured
// at 0.2, 0.5, 1 and 2 degrees). Reported per setting: fit time and the median and worst held-out
// relative L2. The first row (the defaults) is the baseline every ratio refers to, measured in the
// same run. `knobs` limits the trade to some knobs (the baseline is always run).
#pragma once

#include <ostream>
#include <string>
#include <vector>

#include "common/result.h"
#include "fit/sweep_fit.h"

namespace flarelab::bench {

struct FitBenchOptions {
    std::vector<std::string> sweeps;  // the first is the main sweep; all of one lens
    std::string lens_file;
    int optimizer_frames = 5;  // frames of the main sweep for the optimizer table, >= 0
    bool trade = true;
    bool frames = true;              // the per-frame table (one sweep fit)
    bool quick = false;              // the trade over fewer settings and angles (a smoke test)
    std::vector<std::string> knobs;  // trade rows of these knobs only (tradeKnobs()); empty: all
    fit::SweepFitOptions fit;        // the defaults the trade varies from
};

struct OptimizerRow {
    double angle_deg = 0.0;
    std::string optimizer;
    int ghosts = 0;
    int64_t evaluations = 0;
    double time_ms = 0.0;
    double initial_cost = 0.0;
    double final_cost = 0.0;
    double initial_rel_l2 = 0.0;  // the detected start against the noiseless truth
    double rel_l2 = 0.0;          // the fitted frame's ghosts against the noiseless truth
};

struct TradeRow {
    std::string knob;     // "baseline", "iterations", ...
    std::string setting;  // "20", "fixed 2", "1.0 deg"
    int ghosts = 0;
    double fit_s = 0.0;
    double heldout_median = 0.0;
    double heldout_worst = 0.0;
    double fit_median = 0.0;
};

// The per-frame fits of a whole sweep (its tracks' samples, before compression) against truth.
struct FrameRow {
    double angle_deg = 0.0;
    int ghosts = 0;
    double rel_l2 = 0.0;
};

struct FitBenchReport {
    std::vector<OptimizerRow> optimizers;
    std::vector<FrameRow> frames;
    std::vector<TradeRow> trade;
};

// The trade's knob names, in the order the trade runs them.
const std::vector<std::string>& tradeKnobs();

Result<FitBenchReport> runFitBench(const FitBenchOptions& options, std::ostream& log);
void printFitBench(const FitBenchReport& report, std::ostream& out);  // Markdown tables
std::string fitBenchJson(const FitBenchReport& report);

}  // namespace flarelab::bench
