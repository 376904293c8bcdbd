// ============================================================================
//  flarelab bench: ResponseBenchOptions, ResponseBenchRow, runResponseBench,
//                  printResponseBench, responseBenchJson (flarelab bench response)
// ============================================================================
//
// Camera-response recovery (drivers/calibration_measure.h) against OpenCV's CalibrateDebevec
// (Debevec & Malik 1997) and CalibrateRobertson (Robertson et al. 2003), on the simulated camera
// (drivers/sim_camera.h) with a known curve applied: a gamma curve and a logarithmic one like the
// one Aravis's fake camera draws. The simulated camera looks at a lens's flare (a point light at
// angle_deg, its ghosts and a dim background: five decades of radiance in one frame), 12 bits,
// read noise, shot noise, hot pixels. Each case takes the dark frames and the exposure series
// flarelab calibrate would take (calibration_measure.h: planSeriesExposures, two frames per
// exposure), then recovers the curve with:
//   - flarelab          the series as captured (12 bits, both frames of each exposure);
//   - flarelab 8-bit    the first frame of each exposure reduced to 8 bits, the images OpenCV gets;
//   - OpenCV Debevec    those 8-bit images (replicated to three channels), 70 samples, lambda 10
//                       (OpenCV's defaults);
//   - OpenCV Robertson  the same images, 30 iterations, threshold 0.01 (defaults).
// OpenCV's calibrations take only 8-bit images, so the reduction (code = round(DN * 255 /
// (2^12 - 1))) is theirs to bear; the "flarelab 8-bit" row measures the method on the same bytes.
// Codes OpenCV leaves undefined (Robertson's NaN for a code no sample had) are filled in linearly
// from their neighbours, and OpenCV's curves are read linearly between codes.
//
// Error: at every DN z whose true relative exposure X(z) lies within `stops` stops below the
// clip level, e(z) = log2(X_recovered(z) / X_true(z)) minus its median (a curve is known only up
// to scale); reported as RMS and maximum |e| in stops, over the DN levels in that range.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <ostream>
#include <string>
#include <vector>

#include "common/result.h"

namespace flarelab::bench {

struct ResponseBenchOptions {
    std::string lens_file = "data/lenses/heliar-tronnier.csv";
    // "gamma:G" or "log:A" (sim_camera.h's curves), or "linear".
    std::vector<std::string> curves = {"gamma:2.2", "log:1000"};
    std::vector<uint64_t> seeds = {1};
    double angle_deg = 3.0;
    int64_t width = 320;
    int64_t height = 214;
    double stops = 10.0;  // evaluated range below the clip level
    bool opencv = true;
};

struct ResponseBenchRow {
    std::string curve;
    uint64_t seed = 0;
    std::string method;
    int bits = 12;
    bool linear_verdict = false;  // the method said linear (flarelab only)
    double rms_stops = 0.0;
    double max_stops = 0.0;
    int64_t levels = 0;  // DN levels evaluated
    double ms = 0.0;
    std::string note;
};

// InvalidArgument naming a bad option; other errors as the camera's or the lens file's.
Result<std::vector<ResponseBenchRow>> runResponseBench(const ResponseBenchOptions& options,
                                                       std::ostream& log);

void printResponseBench(const std::vector<ResponseBenchRow>& rows, std::ostream& out);
nlohmann::json responseBenchJson(const std::vector<ResponseBenchRow>& rows);

}  // namespace flarelab::bench
