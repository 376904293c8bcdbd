// ============================================================================
//  flarelab bench: PredictBenchOptions, TableTrade, PredictBenchResult, runPredictBench,
//                  printPredictBench, predictBenchJson (flarelab bench predict)
// ============================================================================
//
// What the planner's figures cost and how far they are from what they stand for, for one model:
//   1. The figure table (predict/figures.h) against drawing each constellation: at seeded random
//      (theta, phi) inside the model's range, the table's flare mean and peak against the model
//      drawn at the capture's size (fit::renderModel), for a few table steps; the table's build
//      time, and drawing one constellation against looking one up (the baseline of the same run).
//   2. With the lens prescription: the model's predicted flare mean (the table) against the
//      simulator's ground truth (drivers/sim_truth.h, the same camera as the capture, noiseless
//      ghosts) at seeded random angles at the capture's roll, and the contrast ratio (eq. 9.3) for
//      a scene whose contrast the true flare cuts to 90 %. And the lab figures
//      (predict/lab_figures.h): the on-axis veiling glare index and the centre-patch image flare
//      from the model's table against the same integrals of the simulator's centre flare,
//      rendered at every node of the table; the light's power is the model's, else the
//      simulated camera's (drivers::simLightPower), the same for both.
//   3. A broadcast: `cameras` cameras on one model around a stadium, the sun over `hours` at
//      `step_s` (predictTimeline), and the switching plan (planSwitching, 10 s shots), best of
//      `repeat`; beside it, drawing one frame per instant and camera, extrapolated from drawing
//      a few.
#pragma once

#include <cstdint>
#include <iosfwd>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/result.h"

namespace flarelab::bench {

struct PredictBenchOptions {
    std::string model_path;
    std::string lens_path;  // empty: no ground-truth part
    int constellations = 100;
    uint64_t seed = 1;
    int cameras = 10;
    double hours = 3.0;
    double step_s = 1.0;
    int repeat = 5;
    bool trade = true;  // the table steps other than the default
};

struct TableTrade {
    double theta_step_deg = 0.0;  // as built (0: the capture's step, at most 0.5)
    double phi_step_deg = 0.0;
    int64_t width = 0;
    double build_ms = 0.0;
    double mean_median_rel_err = 0.0;  // |table - drawn| / drawn over the constellations
    double mean_worst_rel_err = 0.0;
    double mean_worst_err_of_largest = 0.0;  // worst |table - drawn| / largest drawn mean
    double peak_median_rel_err = 0.0;
};

struct PredictBenchResult {
    std::string model;
    int64_t ghosts = 0;
    double valid_from_deg = 0.0, valid_to_deg = 0.0;
    int constellations = 0;
    std::vector<TableTrade> tables;  // tables[0] is the default
    double draw_ms = 0.0;            // one constellation drawn at the capture's size (median)
    double lookup_ns = 0.0;          // one table lookup (median of batches)
    // Against the simulator (with a lens); -1 when not run.
    int truth_angles = 0;
    double energy_median_rel_err = -1.0;  // |predicted mean - true mean| / true mean
    double energy_worst_rel_err = -1.0;
    double model_energy_median_rel_err = -1.0;  // the model drawn itself, without the table
    double contrast_median_abs_err = -1.0;      // |K_pred - K_true| at K_true = 0.9
    double contrast_worst_abs_err = -1.0;
    bool light_power_from_model = false;  // else the simulated camera's
    double light_power_dn_s = 0.0;
    double light_power_rel_err = -1.0;    // the model's against the simulated camera's
    double vgi = -1.0, vgi_truth = -1.0;  // fractions
    double vgi_from_deg = 0.0, vgi_to_deg = 0.0;
    double image_flare = -1.0, image_flare_truth = -1.0;
    bool image_flare_complete = false;
    double centre_flare_median_rel_err = -1.0;  // per node, where the truth is above 1e-3 of its max
    // The broadcast.
    int64_t steps = 0;
    int cameras = 0;
    double timeline_ms = 0.0;         // best of repeat
    double switching_ms = 0.0;        // best of repeat
    double frames_ms_estimate = 0.0;  // steps x cameras frames, from drawing a few
};

Result<PredictBenchResult> runPredictBench(const PredictBenchOptions& options, std::ostream& log);
void printPredictBench(const PredictBenchResult& result, std::ostream& out);
nlohmann::json predictBenchJson(const PredictBenchResult& result);

}  // namespace flarelab::bench
