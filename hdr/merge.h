// ============================================================================
//  flarelab hdr: MergeOptions, MergedFrame, mergeBrackets, toImage
// ============================================================================
//
// The bracket merge (DESIGN.md, "Data flow"): the raw exposures a camera takes at one head angle
// become one linear HDR frame. The mosaic is kept: each sample of the result is the radiance of
// the same sample of the brackets, in DN per second at unity gain,
//
//     x_k = (DN_k - black_k) / (exposure_s_k * gain_k),
//
// so a frame is independent of the exposure times and gains it was taken with.
//
// Method: the noise-optimal weighted mean of Granados et al. 2010 ("Optimal HDR reconstruction
// with linear digital cameras", CVPR): each usable sample is weighted by the inverse of the
// variance of its x_k (Robertson et al. 2003 weight a linear sensor's samples by
// exposure_s^2, which is that only where every bracket has the same noise, i.e. without shot
// noise),
//
//     var(x_k) = (mu_k / e_k + r_k^2 + 1/12) / (exposure_s_k * gain_k)^2,
//
// with mu_k the expected signal in DN, e_k the conversion gain in electrons per DN (shot noise),
// r_k the read noise in DN and 1/12 DN^2 the quantization noise of the converter. mu_k is not
// taken from the sample itself (a sample that happens to read low would then weigh more, and the
// mean would be biased low): it is predicted from a pilot estimate of the pixel's radiance, the
// sum of the usable signals over the sum of their exposure_s * gain (the shot-noise-optimal
// estimate), as Granados et al. do. When a camera gives no noise figures (electrons_per_dn or
// read_noise_dn 0 in RawFrame), MergeOptions supplies a model: variance proportional to the signal
// (fallback_electrons_per_dn at unity gain, divided by the gain) plus a floor
// (fallback_read_noise_dn). With shot noise dominant the weights are proportional to
// exposure_s * gain whatever e_k is, so the fallback matters only where read noise competes.
//
// Which samples count:
//   - saturated: DN >= white_level_dn - saturation_margin_fraction * (white - black). Dropped:
//     near white the converter and the pixel well are no longer linear.
//   - dark: DN - black < min_signal_dn. Dropped as a value: at or below the black level a sample
//     holds no signal, and what lay below black may have been clipped by the converter. Kept as
//     an upper bound: the pixel's merged value is at most the least of its dark samples' ceilings,
//     (the usable threshold above black + 4 read-noise sigmas) / (exposure_s * gain). Without
//     it, where every long bracket is dark (outside a lens's image circle), a DN or two of read
//     noise in a very short bracket made the pixel 1e8 DN/s.
//   - every other sample is usable; MergedFrame::count holds how many each pixel had.
// A sample with no usable bracket (count 0) is
//   - a lower bound where at least one bracket saturated it: the largest (DN - black) /
//     (exposure_s * gain) over its saturated samples, which is the clipped value of its shortest
//     saturated exposure when the white levels agree (radiance > 0, count 0);
//   - 0 otherwise, dark in every bracket (radiance 0, count 0).
// MergedFrame counts both kinds (saturated_samples, dark_samples).
//
// The result does not depend on the order of the brackets, bit for bit: they are sorted by
// exposure_s * gain (then by their other fields) before anything is summed. It is never NaN or
// infinite: the inputs are checked so that no intermediate can overflow float.
//
// Threads: tbb::parallel_for over runs of samples; the arithmetic is single precision,
// vectorized over samples (AVX2 where the processor has it, chosen at run time).
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "hdr/raw_frame.h"

namespace flarelab::hdr {

// Most brackets one merge takes: MergedFrame::count is a uint8_t.
inline constexpr int kMaxBrackets = 255;
// Largest ratio of the brackets' exposure_s * gain (longest over shortest): beyond it the
// variance terms of the shortest bracket could overflow float.
inline constexpr double kMaxExposureRatio = 1e9;

struct MergeOptions {
    // A sample is saturated at DN >= white_level_dn - saturation_margin_fraction * (white_level_dn
    // - black_level_dn). In [0, 1); the default keeps clear of the last percent, where pixel wells
    // and converters go nonlinear before they clip.
    double saturation_margin_fraction = 0.01;
    // A sample is dark, and dropped, at DN - black_level_dn < min_signal_dn. Finite, >= 0; the
    // default drops samples at or below the black level (integer DN and black level).
    double min_signal_dn = 0.5;
    // Noise model for cameras that give no figures (RawFrame::electrons_per_dn or read_noise_dn
    // 0): electrons per DN at unity gain (divided by the gain of the bracket), and read noise in
    // DN. Finite, > 0. The defaults (Poisson in DN, 2 DN read noise) suit a 12-bit sensor.
    double fallback_electrons_per_dn = 1.0;
    double fallback_read_noise_dn = 2.0;
    // The brackets' angle_deg may differ by at most this much (the head does not move during a
    // bracket). Finite, >= 0.
    double max_angle_spread_deg = 1e-3;
    // Use the AVX2 kernel where the processor has it (else the SSE2 one, the x86-64 baseline).
    // Both give the same bits; false forces the baseline, for tests and comparisons.
    bool allow_avx2 = true;
};

struct MergedFrame {
    int64_t width = 0;
    int64_t height = 0;
    RawFormat format = RawFormat::Mono;  // the brackets' format: a Bayer mosaic stays a mosaic
    // Per sample, row-major like RawFrame::samples: (DN - black) / (exposure_s * gain), DN per
    // second at unity gain; finite and >= 0. Where count is 0 see the header comment.
    std::vector<float> radiance;
    // Per sample: how many brackets contributed (0 .. number of brackets).
    std::vector<uint8_t> count;

    double angle_deg = 0.0;                // the brackets' common head angle (their mean)
    std::vector<double> exposure_times_s;  // of the brackets, ascending by exposure_s * gain
    // The brackets' gain; when they differ, that of the bracket with the largest exposure_s * gain
    // (the one that weighs most in most pixels). The radiance is at unity gain either way.
    double gain = 1.0;
    std::string camera;  // the brackets' common camera description
    std::string method;  // how it was merged, for the EXR header ("flarelab.merge_method")

    int64_t saturated_samples = 0;  // count 0, saturated in some bracket: radiance a lower bound
    int64_t dark_samples = 0;       // count 0, dark in every bracket: radiance 0
};

// Merges a bracket of raw exposures of one scene into one linear HDR frame (see the header
// comment for the method). Errors (InvalidArgument), naming the bracket by its index in
// `brackets` and the field: no brackets or more than kMaxBrackets; a width or height < 1 or whose
// product overflows; samples.size() != width * height; a width, height, format, bit_depth or
// camera that differs from bracket 0's; an angle_deg farther than max_angle_spread_deg from
// bracket 0's; bit_depth outside 8..16; a non-finite or non-positive exposure_s or gain;
// black_level_dn < 0 or >= white_level_dn, white_level_dn > 2^bit_depth - 1; a negative or
// non-finite read_noise_dn or electrons_per_dn; exposure_s * gain whose
// ratio between brackets exceeds kMaxExposureRatio or that lets a radiance overflow float; and
// options out of their documented ranges (naming the option).
Result<MergedFrame> mergeBrackets(std::span<const RawFrame> brackets,
                                  const MergeOptions& options = {});

// How one raw exposure's samples fall under the merge's rules (MergeOptions' thresholds, as
// mergeBrackets applies them): usable, saturated (DN >= the saturation threshold) or dark. The
// capture records them per exposure in the sweep manifest, and a sweep whose shortest exposure
// clips much of the frame is warned of: there the merged radiance is only a lower bound.
struct ExposureCounts {
    int64_t usable = 0;
    int64_t saturated = 0;
    int64_t dark = 0;
};

// Errors (InvalidArgument): the options or the frame as mergeBrackets rejects them (one bracket).
Result<ExposureCounts> countExposure(const RawFrame& frame, const MergeOptions& options = {});

// The frame as an RGB image for EXR files and previews, values as in MergedFrame::radiance.
// Mono: R = G = B = the sample. Bayer: bilinear demosaic; each pixel keeps its own sample for its
// own colour, and each missing colour is the mean of the samples of that colour in its 3x3
// neighbourhood (the 2 or 4 edge or diagonal neighbours; fewer at the image border, where the
// neighbourhood is cut off, never mirrored). A colour with no sample in the 3x3 neighbourhood
// (only in images 1 pixel wide or high) is 0. Errors (InvalidArgument): a frame with width or
// height < 0, whose radiance size is not width * height, or with a non-finite or negative value
// (named by x and y).
Result<ImageRGB> toImage(const MergedFrame& frame);

// Bits of kLowerBoundRed, kLowerBoundGreen, kLowerBoundBlue: which channels of a pixel of
// toImage's image are only lower bounds.
inline constexpr uint8_t kLowerBoundRed = 1, kLowerBoundGreen = 2, kLowerBoundBlue = 4;
// Per pixel of toImage's image (row-major), the channels that are lower bounds: those whose value
// is, or averages in, a sample saturated in every bracket (count 0, radiance > 0). What a fit must
// not take at face value; the EXR keeps it (hdr/exr.h). Errors as toImage's.
Result<std::vector<uint8_t>> lowerBounds(const MergedFrame& frame);

}  // namespace flarelab::hdr
