// ============================================================================
//  flarelab bench: OracleBenchOptions, OracleGhostRow, OracleAngleRow, OracleLensRow,
//                  OracleBenchReport, runOracleBench, printOracleBench, oracleBenchJson
// ============================================================================
//
// `flarelab bench oracle`: how close the ghost model can come to each real ghost, per lens, so that
// a fit's error can be split into what the model cannot draw and what the fit or the tracking
// lose. For every ghost path of the lens (the simulator's enumeration) at each angle, the path
// alone is rendered by the simulated camera's truth (drivers/sim_truth.h: noiseless, in the
// frames' unit), detected and fitted as one ghost with the fit's own detection and frame fit
// (fit/detect.h, fit/frame_fit.h) from its brightest detection, and the fitted ghost drawn as the
// model draws it is compared with the path's image:
//   ghost floor  relative L2 of the one fitted ghost against its path's image (1 when nothing
//                was detected: the model would draw nothing);
//   frame floor  the fitted ghosts of an angle summed against all paths together, outside the
//                light's disc, as `flarelab score` compares (fit/score.h): the error of a model
//                whose every ghost were fitted alone, with perfect tracking and compression.
// Paths with less than min_share both of the angle's ghost light and of its squared L2 norm are
// not fitted (their light is reported as `unfitted_share`, and it counts in the frame floor as
// missed). Noiseless only: the
// frames' noise would add the fit's own error to the floor.
#pragma once

#include <cstdint>
#include <ostream>
#include <string>
#include <vector>

#include "common/result.h"
#include "fit/detect.h"
#include "fit/frame_fit.h"

namespace flarelab::bench {

struct OracleBenchOptions {
    std::vector<std::string> lens_files;
    std::vector<double> angles_deg = {2.0, 8.0, 15.0, 25.0};
    int64_t width = 640;  // the frames' size, as `flarelab capture --sim` takes them
    int64_t height = 427;
    double min_share = 1e-3;  // in [0, 1)
    std::string images;       // when set, truth | fitted ghost per path and angle, PNG, here
    // The truth in colour (red, green, blue at 650, 550, 450 nm: a Bayer capture's), fitted in
    // three channels with one shape per ghost; else the monochrome camera's green. Against the
    // mono floor, the colour floor tells what one shape for three colours costs where
    // dispersion separates them.
    bool colour = false;
    fit::DetectOptions detect;
    fit::FrameFitOptions frame;
};

struct OracleGhostRow {
    std::string lens;
    double angle_deg = 0.0;
    std::string path;       // optics::pathLabel
    double share = 0.0;     // of the angle's ghost light
    double l2_share = 0.0;  // of its squared L2 norm
    int candidates = 0;  // detections of the path alone (more than one: it falls apart in pieces)
    bool sharpened = false;  // the restart with pixel-wide falloffs won
    double rel_l2 = 1.0;
};

struct OracleAngleRow {
    std::string lens;
    double angle_deg = 0.0;
    int paths_lit = 0;     // paths that put light in the frame
    int paths_fitted = 0;  // of them, those at min_share or more
    double unfitted_share = 0.0;
    double frame_rel_l2 = 0.0;
    double time_s = 0.0;
};

struct OracleLensRow {
    std::string lens;
    int ghosts_fitted = 0;               // over all angles
    double median_ghost_rel_l2 = 0.0;    // of the fitted paths
    double weighted_ghost_rel_l2 = 0.0;  // their mean weighted by their light
    double worst_ghost_rel_l2 = 0.0;
    std::string worst_ghost;  // "PATH at A deg"
    double median_frame_rel_l2 = 0.0;
    double worst_frame_rel_l2 = 0.0;
};

struct OracleBenchReport {
    bool colour = false;  // OracleBenchOptions::colour
    std::vector<OracleGhostRow> ghosts;
    std::vector<OracleAngleRow> angles;
    std::vector<OracleLensRow> lenses;
};

// InvalidArgument for options out of range (no lens, no angle, an angle outside [0, 90), a size
// outside 16..8192, min_share outside [0, 1)); a lens file's errors, named.
Result<OracleBenchReport> runOracleBench(const OracleBenchOptions& options, std::ostream& log);
void printOracleBench(const OracleBenchReport& report, std::ostream& out);  // Markdown tables
std::string oracleBenchJson(const OracleBenchReport& report);

}  // namespace flarelab::bench
