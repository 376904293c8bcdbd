// ============================================================================
//  flarelab bench: BracketBenchOptions, BracketBenchRow, runBracketBench, printBracketBench,
//                  bracketBenchJson (flarelab bench bracket)
// ============================================================================
//
// Auto-bracketing (drivers/auto_bracket.h) against fixed brackets (today's default 0.25 / 1 /
// 4 s), on the simulated rig (a SimHead carrying a SimCamera, simulated time) with every lens
// given, from several first angles and noise seeds. For each case the plan is made at the first
// angle, as capture would, and then scored at that angle and at angles further along the sweep
// (first + each of sweep_offsets_deg), where it was not made, with the simulator's noise-free
// truth (SimCamera::meanRate_e_s):
//   - core clipped: the pixel where the truth is brightest (the light's core, or where it has
//     left the frame its brightest ghost) reads saturated in the shortest exposure (the merge's
//     rule: within 1 % of the range of white). Counted over the angles.
//   - saturated: the fraction of the frame that reads saturated in the shortest exposure (the
//     merged radiance there is only a lower bound); its maximum over the angles.
//   - floor SNR: the ghosts' noise floor is the scene's 5th percentile of the true electron rate
//     (light, background and dark current); its signal-to-noise ratio in the longest exposure,
//     from the true shot, read and rounding noise, S / sqrt(S + read^2 + K^2 / 12) electrons. At
//     the first angle, where the plan is made, and the minimum over the angles (the floor sinks
//     as the light's veiling glare leaves the frame); the floor is reached at 10 or more
//     (BracketPlanOptions::floor_snr).
//   - the time the bracket's exposures take.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <ostream>
#include <string>
#include <vector>

#include "common/result.h"
#include "drivers/auto_bracket.h"

namespace flarelab::bench {

struct BracketBenchOptions {
    std::vector<std::string> lens_files;  // empty: every *.csv in lens_dir
    std::string lens_dir = "data/lenses";
    double f_number = 0.0;  // 0: each file's own
    std::vector<double> first_angles_deg = {0.0, 10.0};
    std::vector<double> sweep_offsets_deg = {0.0, 2.0, 5.0, 10.0, 20.0, 30.0};
    std::vector<uint64_t> seeds = {2, 3};
    int64_t width = 640;
    int64_t height = 427;
    // The simulated camera's shortest exposure; 0: its default (10 us, as real cameras).
    double min_exposure_s = 0.0;
    std::vector<double> fixed_s = {0.25, 1.0, 4.0};
    drivers::BracketPlanOptions plan;
};

struct BracketScore {
    int core_clipped = 0;             // angles where the core clipped in the shortest exposure
    bool first_core_clipped = false;  // at the first angle
    int angles = 0;                   // angles scored
    double saturated_fraction = 0.0;  // of the shortest exposure, the most over the angles
    double first_floor_snr = 0.0;     // of the longest exposure, at the first angle
    double floor_snr = 0.0;           // of the longest exposure, the least over the angles
    double total_s = 0.0;             // the bracket's exposure time
};

struct BracketBenchRow {
    std::string lens;
    double f_number = 0.0;
    double first_angle_deg = 0.0;
    uint64_t seed = 0;
    std::vector<double> plan_s;  // the auto bracket
    bool plan_core_unclipped = false;
    bool plan_floor_reached = false;
    int probes = 0;
    BracketScore automatic;
    BracketScore fixed;
    std::vector<std::string> reasons;
};

// InvalidArgument naming a bad option; otherwise errors of the lens files and the simulated rig.
Result<std::vector<BracketBenchRow>> runBracketBench(const BracketBenchOptions& options,
                                                     std::ostream& log);

// A row per case, then totals: cases where the core clipped anywhere and where the floor was
// missed anywhere, for each bracketing.
void printBracketBench(const std::vector<BracketBenchRow>& rows,
                       const BracketBenchOptions& options,
                       std::ostream& out);
nlohmann::json bracketBenchJson(const std::vector<BracketBenchRow>& rows);

}  // namespace flarelab::bench
