// ============================================================================
//  flarelab drivers: DarkFrames, DarkMeasurement, ExposureLevel, ResponseMeasurement,
//                    PhotonTransfer, CalibrationOptions, measureDark, measureResponse,
//                    recoverResponse, measurePhotonTransfer, buildCalibration, captureFrames,
//                    captureDarkFrames, planSeriesExposures, captureSeries
// ============================================================================
//
// How `flarelab calibrate` measures a camera (calibration.h keeps the result). Every measurement
// is a function of frames, so that it is tested on frames whose truth is known (the simulated
// camera, sim_camera.h); the capture functions at the bottom take them from any Camera.
//
//  1. Dark frames (lens capped). Bias frames, at the shortest exposure: the black level (their
//     mean within 4 sigmas of their most frequent value, sigma measured on the lower side, which
//     warm pixels and a gamma camera's upward trail cannot widen) and the read noise (pairs of
//     them: the variance of a difference is twice the noise's; the converter's 1/12 DN^2 of
//     rounding is taken out, as the merge adds it back). Long dark frames, at the longest
//     exposure a capture uses: hot pixels, those whose dark signal stands out of the frame's
//     (above its median by 8 robust sigmas and by 0.5 % of the converter's range), unless they
//     are not dark (too many, lying side by side as light does, or neighbouring pixels that
//     agree as in an image). The noise floor: the level noise alone reaches in a bias frame (its
//     99.9th percentile above black).
//  2. An exposure series of a steady scene (two or more frames at each exposure). Each pixel's
//     mean at each exposure is an observation of the response at a relative exposure
//     E_pixel * t. Whether the scene is steady is checked first: two frames at one exposure must
//     line up best unshifted (a pattern that moves between frames, like the test pattern of
//     Aravis's fake camera, lines up best shifted). For a scene that is not steady the pixels are
//     replaced by quantiles of each frame (a steady histogram is enough for them: for any rising
//     response the q-quantile of f(E t) is f(t times the q-quantile of E)).
//       - The clip level: where pixels stop responding to more exposure (the median level of
//         pixels in the upper half of the range whose signal grows by less than 0.5 % of the
//         range when the exposure doubles).
//       - Linearity (EMVA 1288's definition): each pixel's signal over black is fitted by a_i t
//         between 10 % and 70 % of the range up to the clip level; the relative deviations
//         s / (a_i t) - 1 are binned by predicted signal between 5 % and 95 %, and the linearity
//         error is half the spread of the bins' medians. Each observation is compared with the
//         pixel's other exposures (leave one out), the bin taken from its first frames and the
//         slope from the others: binned by a figure that shares its noise, the ratio would be
//         biased where pixels are few (more scatter into a bright bin from below than from
//         above). A camera is linear when the error is below linear_tolerance.
//       - The saturation level of a linear camera: the largest signal up to which the binned
//         ratio of measured to predicted signal stays above 1 - saturation_tolerance.
//       - A camera that is not linear gets its response curve (recoverResponse).
//  3. Photon transfer: in each pair of frames at one exposure, per pixel the mean signal and the
//     difference; binned by mean signal, half the difference's variance against the mean is the
//     photon transfer curve, var = read^2 + signal / K. A weighted straight-line fit over the
//     bins between 2 % and 70 % of the saturation level gives the conversion gain K (e-/DN) from
//     its slope. For a camera that is not linear the frames go through the recovered curve first
//     (the figures are then in 16-bit linear DN, as applyCalibration hands out frames, and its
//     read noise is the fit's intercept, a rough figure).
//
// The response curve (recoverResponse), in two stages.
//   a. The inverse response in logs, g(z) = log X(z), piecewise linear in z between knots placed
//      at quantiles of the samples (half of them) and evenly (the other half); each observation
//      says g(z_ij) = log E_i + log t_j. The per-pixel unknowns log E_i are eliminated in closed
//      form, which leaves a small dense system in the knot values with a smoothness term on
//      their second differences: Debevec & Malik's formulation ("Recovering High Dynamic Range
//      Radiance Maps from Photographs", SIGGRAPH 1997) at the converter's full bit depth, over
//      every sampled pixel, with samples beyond the clip level or below the noise floor left out
//      instead of weighted by a hat.
//   b. A maximum-likelihood refinement with the residuals where the noise is, in DN: the forward
//      response z = F(x) of log exposure, piecewise linear between knots evenly spaced in x, and
//      every pixel's log exposure, solved together by Levenberg-Marquardt with the pixels
//      eliminated through the Schur complement (as in bundle adjustment), each sample weighted by
//      the inverse of its variance (measured from the frames of one exposure), and the samples
//      chosen by stage a's prediction, not their own value, at the noise floor (chosen by value,
//      those that happened to read high would bend the foot down; chosen anew as the fit moves,
//      the choice would become a way to lower the cost). Stage a alone is biased wherever many
//      pixels share a level (the background at each exposure).
// The curve is made to rise (pool-adjacent-violators) where noise would bend it back, starts at
// the first knot with a fair share of the samples (at or above the noise floor), ends at the
// cut (1 % below the clip level) and goes on below its start as the power law it follows over
// its second octave above black. bench/response_bench.h compares it with OpenCV's CalibrateDebevec
// and CalibrateRobertson.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/result.h"
#include "drivers/calibration.h"
#include "drivers/camera.h"
#include "hdr/raw_frame.h"

namespace flarelab::drivers {

struct DarkFrames {
    std::vector<hdr::RawFrame> bias;       // >= 2, at one short exposure
    std::vector<hdr::RawFrame> long_dark;  // >= 1, at one long exposure
};

struct DarkMeasurement {
    double black_level_dn = 0.0;
    double read_noise_dn = 0.0;  // temporal, quantization removed
    std::vector<int64_t> hot_pixels;
    double hot_threshold_dn = 0.0;  // dark signal above black that makes a pixel hot
    double dark_signal_dn = 0.0;    // the median dark signal above black in the long frames
    // The level noise alone reaches above black (99.9th percentile of a bias frame): samples
    // below it say little about the response.
    double noise_floor_dn = 0.0;
    double bias_exposure_s = 0.0;
    double long_exposure_s = 0.0;
    std::vector<std::string> notes;
};

// InvalidArgument when there are too few frames, when they differ in size, format or exposure,
// or when they are not dark (more than 1 % of pixels above the hot-pixel threshold: "cap the
// lens").
Result<DarkMeasurement> measureDark(const DarkFrames& frames);

struct ExposureLevel {
    double exposure_s = 0.0;
    std::vector<hdr::RawFrame> frames;  // >= 1; >= 2 for photon transfer
};

struct CalibrationOptions {
    double linear_tolerance = 0.03;      // linearity error that still counts as linear
    double saturation_tolerance = 0.01;  // relative drop of the response that ends linearity
    int max_pixels = 40000;              // pixels sampled for linearity and the response curve
    int quantiles = 1024;                // virtual pixels of a scene that is not steady
    int knots = 32;                      // of the response curve's solve
    double smoothness = 1e-3;            // weight of the curve's second differences
    int refine_iterations = 15;          // of the maximum-likelihood refinement in DN; 0: none
};

struct LinearityBin {
    double signal_dn = 0.0;  // centre of the bin, above black
    double deviation = 0.0;  // median of s / (a t) - 1
    int64_t samples = 0;
};

struct ResponseMeasurement {
    bool steady = true;
    std::string steadiness;  // how the check went, in words
    double clip_dn = 0.0;    // where pixels stop responding (raw DN)
    bool linear = true;
    double linearity_error = 0.0;
    double saturation_dn = 0.0;  // raw DN
    std::vector<LinearityBin> bins;
    std::optional<ResponseCurve> curve;  // when !linear
    std::vector<std::string> notes;
};

// Steps 2 of the top of this file. InvalidArgument when the series has fewer than three
// exposures, frames that differ in size or format, a non-positive exposure, or never clips a
// pixel (no saturation level can be measured: lengthen the longest exposure); Unsupported when
// too few samples fall in the range the measures need (a scene without enough contrast).
Result<ResponseMeasurement> measureResponse(std::span<const ExposureLevel> series,
                                            double black_level_dn,
                                            double noise_floor_dn,
                                            const std::vector<int64_t>& hot_pixels,
                                            const CalibrationOptions& options = {});

// The response curve alone, from observations: obs[i][j] the mean sample of (virtual) pixel i at
// exposure j (NaN where it has none), used where black_level_dn + noise_floor_dn < z < cut_dn.
// variance_of(z), when given, is the variance (DN^2) of an observation at z: the samples are then
// weighted by the inverse of the variance it implies in log exposure (two passes after an
// unweighted one). Unsupported when fewer than two exposures or too few pixels with two usable
// observations.
Result<ResponseCurve> recoverResponse(const std::vector<std::vector<double>>& obs,
                                      std::span<const double> exposures_s,
                                      double black_level_dn,
                                      double noise_floor_dn,
                                      double cut_dn,
                                      const std::function<double(double)>& variance_of = {},
                                      const CalibrationOptions& options = {});

struct PhotonTransferPoint {
    double signal_dn = 0.0;     // mean over the bin, above black
    double variance_dn2 = 0.0;  // half the variance of the pair's difference
    int64_t pixels = 0;
};

struct PhotonTransfer {
    double electrons_per_dn = 0.0;  // 0 when it could not be measured
    double intercept_dn2 = 0.0;     // the fit's variance at zero signal
    std::vector<PhotonTransferPoint> points;
    int fitted_points = 0;
    std::string note;
};

// Step 3. Pairs are the frames 0-1, 2-3, ... of each level. With `curve` the samples go through
// it into 16-bit linear DN first (black 0). Never fails on data: a series without pairs or with
// too few usable bins gives electrons_per_dn 0 and a note saying why.
PhotonTransfer measurePhotonTransfer(std::span<const ExposureLevel> series,
                                     double black_level_dn,
                                     double saturation_dn,
                                     const std::vector<int64_t>& hot_pixels,
                                     const ResponseCurve* curve);

// Everything above, into a calibration of the camera `identity` whose frames these are (their
// size, format and bit depth; the gain of the series). Errors as the measures', and
// InvalidArgument when the dark frames and the series are not of the same camera settings.
Result<CameraCalibration> buildCalibration(const DeviceIdentity& identity,
                                           const DarkFrames& dark,
                                           std::span<const ExposureLevel> series,
                                           const CalibrationOptions& options = {});

// ---------------------------------------------------------------------------------------------
// Taking the frames from a camera. Errors are the camera's, with the exposure as context.

// `count` frames at `exposure_s` (the camera's gain and format as they are).
Result<std::vector<hdr::RawFrame>> captureFrames(Camera& camera,
                                                 double exposure_s,
                                                 int count,
                                                 double timeout_s);

struct CalibrationCapture {
    int bias_frames = 4;                // >= 2, at the camera's shortest exposure
    int long_dark_frames = 2;           // >= 1
    double long_dark_exposure_s = 4.0;  // clamped to the camera's range
    int frames_per_exposure = 2;        // >= 1 (2 per pair)
    int levels = 16;                    // most exposures of a planned series
    double budget_s = 300.0;  // most exposure time a planned series may take, frames included
    double timeout_margin_s = 10.0;  // added to each exposure for the capture timeout
};

// The dark frames (the lens must be capped).
Result<DarkFrames> captureDarkFrames(Camera& camera, const CalibrationCapture& options);

// A series for the scene in front of the camera, found by probes (one frame each, at most 32):
// t_top, where the brightest half percent of the scene (its 99.5th percentile) reaches half the
// converter's range; the foot, down from there in steps of 8 until that percentile lies within 5 %
// of black; the top, up in steps of 4 until it clips, then twice that. The series spans foot to
// top in even steps of at least a factor of 2, at most `levels` exposures, within the camera's
// range and budget_s (frames included). black_level_dn is the dark frames'. Unsupported when no
// exposure in the camera's range shows any signal.
Result<std::vector<double>> planSeriesExposures(Camera& camera,
                                                double black_level_dn,
                                                const CalibrationCapture& options);

Result<std::vector<ExposureLevel>> captureSeries(Camera& camera,
                                                 std::span<const double> exposures_s,
                                                 const CalibrationCapture& options);

}  // namespace flarelab::drivers
