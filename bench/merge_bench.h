// ============================================================================
//  flarelab bench: MergeBenchOptions, runMergeBench (flarelab bench merge)
// ============================================================================
//
// The HDR bracket merge (hdr/merge.h) against OpenCV's MergeDebevec (Debevec & Malik 1997) and
// MergeRobertson (Robertson et al. 2003) and against the memory-bandwidth floor, in one run.
//
// Scene: a synthetic mono frame whose dynamic range exceeds 1e6, known without noise. Radiance in
// DN per second at unity gain:
//     L(x, y) = peak * (1 + (r / r_core)^2)^-q + background * (0.5 + x / width)
// with r the distance to the centre of pixel (width / 2, height / 2), r_core = min(width, height) /
// 1000 (at least 0.5 px), q such that the peak term falls by 1e7 from the centre to r = min(width,
// height) / 2, peak 5e6 and background 4 (so 2 .. 6 across the frame): a point-like light with a
// flare falloff over seven decades on a dim, sloped background. Camera: brackets of
// exposure_times_s (default 0.25 / 1 / 4 s) at gain 1 through a converter of bit_depth bits
// (default 12) with black level 2^(bit_depth - 5) DN, white level 2^bit_depth - 1, electrons_per_dn
// 2 and read noise 2.5 DN. Noise is seeded: shot noise Poisson in electrons (its normal
// approximation above 30 electrons), read noise Gaussian; then rounding to integer DN and clipping
// to 0 .. 2^bit_depth - 1.
//
// OpenCV gets the same brackets, black-subtracted and scaled linearly to 8 bits
// (code = round((DN - black) * 255 / (white - black)), clipped to 0..255: OpenCV's merges take
// only 8-bit images), the same samples, with a linear response passed explicitly (code z -> z;
// for Debevec z = 0 -> 1 as OpenCV's own default does, since it takes the log). MergeDebevec gets
// one channel. MergeRobertson's weights in OpenCV are 3-channel, so it gets the same bytes packed
// three samples to a pixel; it merges each channel on its own, so that is the same merge of the
// same samples. Their results, in codes per second, are scaled back by (white - black) / 255 to DN
// per second. The 8-bit conversion and packing are not timed.
//
// Accuracy: per pixel the relative error |est - true| / true. Evaluated are the pixels with
// true > 0 that do not saturate the shortest exposure (where every method can know no more than a
// lower bound; they are counted and left out). Reported: the median ("rel_err", the headline
// figure) and the mean per-pixel relative error, and the frame-level relative error of the sum
// |sum est - sum true| / sum true over the evaluated pixels, plus the median per decade of true
// radiance.
//
// Speed: the best of `repeat` runs of each. The floor is a plain copy of the same bytes on one
// thread: std::memcpy of the input samples into a fresh buffer plus writing the output's bytes
// (float radiance and uint8 count per sample) into fresh buffers, which is the least any merge
// that returns new images must do; the same on every core is reported beside it, and the same
// copies into buffers allocated and touched beforehand (no page faults: the pure bandwidth).
#pragma once

#include <cstdint>
#include <iosfwd>
#include <nlohmann/json.hpp>
#include <vector>

#include "common/result.h"

namespace flarelab::bench {

struct MergeBenchOptions {
    bool quick = false;    // 1200 x 800, at most 2 runs: a smoke test
    int repeat = 3;        // runs per time; the best is kept
    int64_t width = 6000;  // 24 megapixels
    int64_t height = 4000;
    int bit_depth = 12;  // of the simulated converter, 10..16
    std::vector<double> exposure_times_s = {0.25, 1.0, 4.0};
    uint64_t seed = 1;
    bool opencv = true;  // also run OpenCV's merges
};

// Runs the benchmark, prints Markdown tables to `out` as it goes (progress to `log`) and returns
// the JSON document: {"settings", "ours_ms", "ours_one_thread_ms", "debevec_ms", "robertson_ms",
// "copy_ms", "copy_parallel_ms", "copy_warm_ms", "ours_rel_err", "debevec_rel_err",
// "robertson_rel_err", "speedup_vs_debevec", "ours_over_copy", "accuracy": {method: {median, mean,
// frame, ...}}, "decades": [...]}. Times in milliseconds; errors are fractions (0.01 = 1 %).
// Invalid options (size, repeat, bit depth, exposure times) are an InvalidArgument error naming the
// option.
Result<nlohmann::json> runMergeBench(const MergeBenchOptions& options,
                                     std::ostream& out,
                                     std::ostream& log);

}  // namespace flarelab::bench
