// ============================================================================
//  flarelab drivers: CameraCalibration, ResponseCurve, readCalibration, parseCalibration,
//                    formatCalibration, writeCalibration, applyCalibration, checkMergeable,
//                    checkCalibrationFor
// ============================================================================
//
// What `flarelab calibrate` measured on one camera (calibration_measure.h measures it), kept in
// a file that capture and the merge use: the black level and the hot pixels from dark frames,
// the saturation level and linearity from an exposure series of a steady scene, read noise and
// conversion gain from frame pairs (photon transfer), and, for a camera whose response is not
// linear, its response curve, so that its frames can be made linear before the bracket merge
// (hdr/merge.h assumes DN - black proportional to exposure).
//
// File format "flarelab camera calibration", version 1: JSON (UTF-8), one object:
//
//   {
//     "format": "flarelab camera calibration",
//     "format_version": 1,
//     "camera": {"model": "...", "serial": "...", "width_px": 640, "height_px": 427,
//                "format": "mono" | "rggb" | "bggr" | "grbg" | "gbrg", "bit_depth": 12,
//                "gain": 1.0},
//     "created_utc": "2026-11-29T07:04:02Z",       (may be empty)
//     "software_version": "flarelab calibrate",    (may be empty)
//     "black_level_dn": 64.01,
//     "saturation_dn": 4095,
//     "linear": true,
//     "linearity_error": 0.002,
//     "noise": {"read_noise_dn": 0.75, "read_noise_e": 3.0, "electrons_per_dn": 4.0},
//     "response_curve": {"method": "...", "rms_error_stops": 0.01,
//                        "dn": [...], "relative_exposure": [...]},   (only when not linear)
//     "hot_pixels": [[x, y], ...],
//     "notes": ["...", ...]
//   }
//
// Rules (a file breaking one is refused with an Error naming the file and the field, as
// "camera.cal.json: noise.read_noise_dn: -1 is not a finite number >= 0"): every field above is
// present except response_curve, and no other field is (a writer that adds one raises the
// version: a misspelt field must not silently lose data); format_version 1 (another one is
// Unsupported); width_px and height_px in 1..32768; bit_depth 8..16; gain, saturation_dn finite
// and > 0; 0 <= black_level_dn < saturation_dn <= 2^bit_depth - 1; linearity_error finite >= 0;
// noise figures finite >= 0, 0 meaning "not measured"; response_curve present exactly when linear
// is false, with 2..65536 knots whose dn strictly increase within (black_level_dn,
// saturation_dn] and whose relative_exposure is finite, > 0 and strictly increases;
// rms_error_stops finite >= 0; hot pixels inside the frame, each listed once (in any order; the
// writer lists them by rows); strings hold no NUL and are valid UTF-8.
//
// The response curve maps a raw sample z (DN as read out, black level included) to its relative
// linear exposure X(z): piecewise linear between the knots; below the first knot linear down to
// 0 at black_level_dn (0 at or below it); above the last knot the sample is saturated. Knots are
// normalized so that X is 1 at the last knot, where the curve ends (saturation_dn).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"
#include "drivers/camera.h"
#include "hdr/raw_frame.h"

namespace flarelab::drivers {

inline constexpr int kCalibrationFormatVersion = 1;
inline constexpr char kCalibrationFormatName[] = "flarelab camera calibration";
inline constexpr int64_t kCalibrationMaxFileBytes = int64_t{64} << 20;
inline constexpr size_t kResponseCurveMaxKnots = 65536;

struct ResponseCurve {
    std::vector<double> dn;                 // knots: raw DN, strictly increasing
    std::vector<double> relative_exposure;  // X at each knot: > 0, strictly increasing
    std::string method;                     // what recovered it, with its settings
    double rms_error_stops = 0.0;  // how far the measured samples lie from the curve (log2)
    bool operator==(const ResponseCurve&) const = default;
};

// X(z) of the curve (see the top of this file); 0 at or below black_level_dn.
double relativeExposure(const ResponseCurve& curve, double black_level_dn, double z);

struct CameraCalibration {
    // The camera and the settings it was measured with.
    std::string camera_model;
    std::string camera_serial;
    int64_t width_px = 0;
    int64_t height_px = 0;
    hdr::RawFormat format = hdr::RawFormat::Mono;
    int bit_depth = 16;
    double gain = 1.0;  // linear, as the camera reported it

    std::string created_utc;  // RFC 3339; may be empty
    std::string software_version;

    double black_level_dn = 0.0;
    // The largest raw DN up to which the camera responds as measured (linear within
    // linearity_error when `linear`, else along response_curve): white level for the merge.
    double saturation_dn = 65535.0;
    bool linear = true;
    // Half the spread of the relative deviations from proportionality between 5 % and 95 % of
    // the range above black (EMVA 1288's linearity error, as a fraction).
    double linearity_error = 0.0;
    // Noise at `gain`: read noise in DN and electrons, conversion gain in electrons per DN; for a
    // camera that is not linear, in the 16-bit linear DN of applyCalibration's output. 0: not
    // measured (the camera gave no usable pairs).
    double read_noise_dn = 0.0;
    double read_noise_e = 0.0;
    double electrons_per_dn = 0.0;
    std::optional<ResponseCurve> response_curve;  // exactly when !linear
    std::vector<int64_t> hot_pixels;              // indices y * width_px + x, ascending, each once
    std::vector<std::string> notes;               // how each figure was measured, for people

    bool operator==(const CameraCalibration&) const = default;
};

// InvalidArgument naming the first field that breaks the file's rules (the top of this file).
Status validateCalibration(const CameraCalibration& calibration);

// Parses and validates calibration text; `name` stands for the file in messages. ParseError for
// malformed JSON, missing, unknown or mistyped fields and broken rules, naming the field;
// Unsupported for another format or format_version.
Result<CameraCalibration> parseCalibration(std::string_view text, const std::string& name);

// Reads `path` (NotFound, IoError; IoError beyond kCalibrationMaxFileBytes), then as
// parseCalibration.
Result<CameraCalibration> readCalibration(const std::string& path);

// The file's text; InvalidArgument (validateCalibration) when `calibration` breaks a rule, so
// that whatever this returns parses back to an equal calibration.
Result<std::string> formatCalibration(const CameraCalibration& calibration);

// Writes the file atomically: a temporary file beside `path`, flushed to disk, renamed over it.
// On failure whatever was at `path` is left as it was.
Status writeCalibration(const std::string& path, const CameraCalibration& calibration);

// "model serial", as DeviceIdentity::describe() and RawFrame::camera say it.
std::string calibrationCameraName(const CameraCalibration& calibration);

// The frame made ready for the merge with the calibration of its camera:
//   - checked: its camera (RawFrame::camera against calibrationCameraName), size, format and
//     bit depth must be the calibration's, its gain finite and > 0 (InvalidArgument naming what
//     differs, both values shown);
//   - hot pixels repaired: each takes the median of its nearest neighbours of the same colour
//     (8 in a mono frame; in a Bayer mosaic 4 or 8 at distance 2, green also the 4 diagonal
//     ones) that are not hot pixels themselves;
//   - a linear camera: samples otherwise unchanged; black_level_dn and white_level_dn (the
//     saturation level) from the calibration;
//   - a camera that is not linear: every sample through the response curve into 16-bit linear
//     DN, round(65535 * X(z)), so that black is 0 and the saturation level 65535 (bit_depth 16,
//     white_level_dn 65535: samples at or beyond it are the saturated ones);
//   - read_noise_dn and electrons_per_dn, when measured, scaled from the calibration's gain to
//     the frame's: electrons_per_dn * cal.gain / frame.gain, read noise in electrons kept (a
//     sensor's read noise in electrons changes little with gain; calibrate at the gain you
//     capture with for exact figures). Figures the calibration does not have stay as the camera
//     gave them.
Result<hdr::RawFrame> applyCalibration(const hdr::RawFrame& frame,
                                       const CameraCalibration& calibration);

// Whether the brackets of a camera with these capabilities may be merged: Unsupported, saying to
// run `flarelab calibrate`, when its response is NonLinear and no calibration with a response
// curve is given (a calibration that found the camera linear is not enough for a camera that says
// it is not); also when a given calibration was measured not linear but has no curve. Linear and
// Unknown cameras pass (Unknown: the backend cannot tell; calibrate measures it).
Status checkMergeable(const CameraCapabilities& capabilities, const CameraCalibration* calibration);

// checkMergeable for an open camera, and, when a calibration is given, that it was measured on
// this camera (its model and serial, as the camera names itself): InvalidArgument naming both
// otherwise, before a sweep has taken a frame.
Status checkCalibrationFor(const Camera& camera, const CameraCalibration* calibration);

}  // namespace flarelab::drivers
