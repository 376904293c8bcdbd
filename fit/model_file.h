// ============================================================================
//  flarelab fit: ModelLens, ModelCapture, ModelPiece, ModelParameter, ModelGhostFit, ModelGhost,
//                FlareModel, validateModel, writeModel, readModel, readModelFromMemory,
//                modelToJson, modelFromJson
// ============================================================================
//
// Flare model files (DESIGN.md, "Formats"): the message flarelab.v1.FlareModel
// (proto/model.proto), stored as binary protobuf, with the protobuf JSON mapping as its readable
// form. This module turns it into the plain structs below and back, and validates it; nothing
// else in fit/ sees protobuf. Each parameter of a ghost is a list of pieces, each a Chebyshev
// series on its normalized angle (the formula is at the top of model.proto).
//
// Format versions. Version 2 adds to the lens the camera settings the
// sweep recorded (version 3 of hdr/sweep.h): aperture blades and their rotation, the stop
// semi-aperture used and whether unspecified surfaces got the default coating, so that `flarelab
// score` simulates the capture's own lens again. Version 3, which the fit writes, adds the
// camera's raw format (capture.raw_format, version 4 of hdr/sweep.h), so that a score simulates
// a colour capture in colour. Version 4 adds the power of the rig light's own image
// (capture.light_power_dn_s), which the lab figures of predict/lab_figures.h need. Version 5
// adds the disc around the light that the fit left out of each frame it fitted
// (capture.light_discs), which `flarelab score` leaves out too. Every version is read.
//
// Rules of the format (every version). A model breaking any of them is refused with an Error
// naming the file (or stand-in) and the field path ("ghosts[2].parameters[5].pieces[0].
// coefficients"):
//   - format_version is 1..5 (another version: Unsupported). Fields the reader does not know
//     are refused (ParseError), in binary files as in JSON: a writer that adds a field raises the
//     version, so nothing is dropped silently; so are version 2's lens fields in a version 1
//     model and version 3's capture.raw_format, version 4's capture.light_power_dn_s or version 5's
//     capture.light_discs in an older one. JSON field names may be written as
//     in the .proto or in lowerCamelCase.
//   - every number is finite; strings hold no NUL, are valid UTF-8 and at most
//     kModelMaxStringBytes long; created is RFC 3339 or empty.
//   - lens: f_number, focal_length_mm, stop_semi_aperture_mm (when present), sensor_width_mm,
//     sensor_height_mm > 0; aperture_blades (when present) 0 or 3..kModelMaxApertureBlades;
//     prescription_sha256 empty or 64 lowercase hex digits.
//   - capture: from_deg <= to_deg, step_deg > 0, exposure times > 0, width_px and height_px
//     1..32768; raw_format empty or one of mono, bayer-rggb, bayer-bggr, bayer-grbg, bayer-gbrg;
//     light_power_dn_s, when present, > 0; light_discs: at most kModelMaxSamples, angles finite,
//     strictly increasing and inside from_deg..to_deg, radii finite, 0..the frame's diagonal.
//   - valid_range: from_deg < to_deg, inside capture.from_deg..capture.to_deg.
//   - 0..kModelMaxGhosts ghosts with unique ids; each has 1..kModelMaxParameters parameters with
//     unique, non-empty names; lower_bound <= upper_bound when both are present.
//   - a parameter has 1..kModelMaxPieces pieces; each piece has angle_from_deg < angle_to_deg
//     (or == for a parameter's only piece: a ghost fitted at one angle), 1..kModelMaxCoefficients
//     coefficients, residual_rms and residual_max >= 0, samples >= 1.
//     Pieces are contiguous: pieces[i].angle_from_deg == pieces[i-1].angle_to_deg exactly. (Gaps
//     are refused rather than allowed: an angle inside a parameter's span always has exactly one
//     piece, the one whose interval holds it, the later one at a shared end.) A parameter's span
//     (first from to last to) lies inside valid_range, and all parameters of a ghost share one
//     span, so a ghost is either fully defined at an angle or not at all.
//   - fit: frames_fitted >= 1, first_angle_deg <= last_angle_deg.
//   - a parameter's samples (version 4): sample_angles_deg and sample_values of one length,
//     0..kModelMaxSamples, finite, the angles strictly increasing inside the pieces' span.
// Errors: NotFound (no such file), IoError (unreadable, or larger than kModelMaxFileBytes),
// ParseError (malformed bytes or text, unknown fields, broken rules), Unsupported (another
// format_version).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"

namespace flarelab::fit {

inline constexpr int kModelFormatVersion = 5;        // what the fit writes
inline constexpr int kModelOldestFormatVersion = 1;  // the oldest version still read
inline constexpr int64_t kModelMaxFileBytes = int64_t{64} << 20;
inline constexpr size_t kModelMaxGhosts = 4096;
inline constexpr size_t kModelMaxParameters = 256;   // per ghost
inline constexpr size_t kModelMaxPieces = 256;       // per parameter
inline constexpr size_t kModelMaxCoefficients = 32;  // per piece; degree <= 31
inline constexpr size_t kModelMaxSamples = 100000;   // kept per-frame values, per parameter
inline constexpr size_t kModelMaxStringBytes = 4096;
inline constexpr int64_t kModelMaxSide = int64_t{1} << 15;  // capture width and height, pixels
inline constexpr int kModelMaxApertureBlades = 64;  // what optics::CameraDescription accepts

struct ModelLens {
    std::string description;
    std::string prescription_file;    // as given to the program; empty for a measured lens
    std::string prescription_sha256;  // 64 lowercase hex digits, or empty
    std::optional<double> f_number;
    std::optional<double> focal_length_mm;
    double sensor_width_mm = 0.0;
    double sensor_height_mm = 0.0;
    // Version 2; absent when the sweep did not record them (then a score assumes a circular stop
    // scaled for the f-number and bare unspecified surfaces).
    std::optional<int> aperture_blades;  // 0: a circular stop
    std::optional<double> blade_rotation_deg;
    std::optional<double> stop_semi_aperture_mm;
    std::optional<bool> coat_unspecified_surfaces;
    bool operator==(const ModelLens&) const = default;
};

// The light's disc in one fitted frame (version 5): radius 0 where the fit found no light.
struct ModelLightDisc {
    double angle_deg = 0.0;
    double radius_px = 0.0;
    bool operator==(const ModelLightDisc&) const = default;
};

struct ModelCapture {
    double from_deg = 0.0;
    double to_deg = 0.0;
    double step_deg = 0.2;
    double roll_deg = 0.0;
    std::vector<double> exposure_times_s;  // empty when not bracketed
    int64_t width_px = 0;
    int64_t height_px = 0;
    std::string camera;
    // Version 3: the sensor's raw format as hdr::rawFormatName writes it ("mono", "bayer-rggb",
    // ...); empty when the sweep did not record it.
    std::string raw_format;
    // Version 4: the rig light's own image, summed over the sensor, in DN/s at the capture's gain
    // (proto/model.proto); > 0, absent when not measured.
    std::optional<double> light_power_dn_s;
    // Version 5: the disc around the light's own image the fit left out, per fitted frame, by
    // increasing angle (proto/model.proto); empty when not recorded.
    std::vector<ModelLightDisc> light_discs;
    bool operator==(const ModelCapture&) const = default;
};

// value(θ) = Σ_k coefficients[k] T_k(x), x = 2 (θ - from) / (to - from) - 1 (0 when from == to),
// θ in degrees: the basis of fit/polyfit.h.
struct ModelPiece {
    double angle_from_deg = 0.0;
    double angle_to_deg = 0.0;
    std::vector<double> coefficients;
    double residual_rms = 0.0;  // in the parameter's unit
    double residual_max = 0.0;
    int64_t samples = 0;  // per-frame values fitted
    bool operator==(const ModelPiece&) const = default;
};

struct ModelParameter {
    std::string name;  // unique in the ghost
    std::string unit;  // "mm", "1"
    std::optional<double> lower_bound;
    std::optional<double> upper_bound;
    std::vector<ModelPiece> pieces;  // ordered, contiguous
    // Version 4, optional (SweepFitOptions::keep_samples): the per-frame values the pieces were
    // fitted to, at increasing angles inside the pieces' span; both empty or of one length.
    std::vector<double> sample_angles_deg;
    std::vector<double> sample_values;
    bool operator==(const ModelParameter&) const = default;
};

struct ModelGhostFit {
    int64_t frames_fitted = 0;
    double first_angle_deg = 0.0;
    double last_angle_deg = 0.0;
    bool operator==(const ModelGhostFit&) const = default;
};

struct ModelGhost {
    int64_t id = 0;  // unique in the model, 0..2^32-1
    std::string name;
    std::vector<ModelParameter> parameters;
    ModelGhostFit fit;
    bool operator==(const ModelGhost&) const = default;
};

struct FlareModel {
    int format_version = kModelFormatVersion;
    std::string software_version;
    // RFC 3339 ("2026-11-29T07:04:02Z"), or empty; readers return it in UTC ending in "Z", so a
    // time written with an offset reads back as the same instant, spelt differently.
    std::string created_utc;
    ModelLens lens;
    ModelCapture capture;
    double valid_from_deg = 0.0;
    double valid_to_deg = 0.0;
    std::vector<ModelGhost> ghosts;
    bool operator==(const FlareModel&) const = default;
};

// Checks `model` against the rules at the top of this file. InvalidArgument naming the field
// ("model: ghosts[2].parameters[5].pieces[0].coefficients: 0 coefficients ...") when one breaks.
Status validateModel(const FlareModel& model);

// Validates `model` (InvalidArgument) and writes it as binary protobuf to `path`, atomically: a
// temporary file beside it, flushed to disk, renamed over `path`, the directory flushed. On any
// failure (IoError) `path` keeps what it held before and the temporary file is removed.
Status writeModel(const std::string& path, const FlareModel& model);

// Reads and validates a binary model file. Errors as at the top of this file.
Result<FlareModel> readModel(const std::string& path);

// Parses and validates binary model bytes; `name` stands for them in error messages.
Result<FlareModel> readModelFromMemory(std::string_view bytes,
                                       const std::string& name = "<memory>");

// The JSON mapping of `model` (field names as in the .proto, indented, every field printed).
// InvalidArgument, naming the field, when `model` breaks a rule, so whatever this returns parses
// back to `model`.
Result<std::string> modelToJson(const FlareModel& model);

// A description for people, as `flarelab model show` prints it: lens, capture, valid range and
// per ghost its parameters' pieces, degrees and residuals. `path` names the file in the heading.
std::string describeModel(const FlareModel& model, const std::string& path);

// Parses and validates the JSON mapping; `name` stands for the text in error messages.
Result<FlareModel> modelFromJson(std::string_view json, const std::string& name = "<memory>");

}  // namespace flarelab::fit
