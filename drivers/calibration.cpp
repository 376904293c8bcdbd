#include "drivers/calibration.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <limits>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "common/file_descriptor.h"
#include "common/utf8.h"

namespace flarelab::drivers {
namespace {

using nlohmann::json;

constexpr int64_t kMaxSide = 32768;

std::string fmt(double x) {
    std::array<char, 32> buffer{};
    const auto result = std::to_chars(buffer.data(), buffer.data() + buffer.size(), x);
    return std::string(buffer.data(), result.ptr);
}

const char* formatName(hdr::RawFormat format) {
    switch (format) {
        case hdr::RawFormat::Mono:
            return "mono";
        case hdr::RawFormat::BayerRGGB:
            return "rggb";
        case hdr::RawFormat::BayerBGGR:
            return "bggr";
        case hdr::RawFormat::BayerGRBG:
            return "grbg";
        case hdr::RawFormat::BayerGBRG:
            return "gbrg";
    }
    return "?";
}

std::optional<hdr::RawFormat> formatFromName(std::string_view name) {
    for (const hdr::RawFormat f :
         {hdr::RawFormat::Mono, hdr::RawFormat::BayerRGGB, hdr::RawFormat::BayerBGGR,
          hdr::RawFormat::BayerGRBG, hdr::RawFormat::BayerGBRG})
        if (name == formatName(f)) return f;
    return std::nullopt;
}

std::string quoted(const std::string& text) {
    std::string out;
    out.reserve(text.size() + 2);
    out.push_back('\'');
    out.append(text);
    out.push_back('\'');
    return out;
}

std::string indexed(const std::string& field, size_t i) {
    return field + "[" + std::to_string(i) + "]";
}

// The rules of the file (the top of calibration.h) on the value, errors of `code` prefixed with
// `name`.
Status check(const CameraCalibration& c, ErrorCode code, const std::string& name) {
    const auto fail = [&](const std::string& field, const std::string& what) -> Status {
        return makeError(code, name + ": " + field + ": " + what);
    };
    const auto text = [&](const std::string& field, const std::string& value) -> Status {
        if (value.find('\0') != std::string::npos) return fail(field, "holds a NUL character");
        if (!validUtf8(value)) return fail(field, "is not valid UTF-8");
        return Ok{};
    };
    const auto nonNegative = [&](const std::string& field, double value) -> Status {
        if (!(std::isfinite(value) && value >= 0.0))
            return fail(field, fmt(value) + " is not a finite number >= 0");
        return Ok{};
    };
    for (const auto& [field, value] :
         {std::pair<const char*, const std::string*>{"camera.model", &c.camera_model},
          {"camera.serial", &c.camera_serial},
          {"created_utc", &c.created_utc},
          {"software_version", &c.software_version}})
        if (Status ok = text(field, *value); !ok) return ok;
    for (size_t i = 0; i < c.notes.size(); ++i)
        if (Status ok = text(indexed("notes", i), c.notes[i]); !ok) return ok;
    if (c.width_px < 1 || c.width_px > kMaxSide)
        return fail("camera.width_px", std::to_string(c.width_px) + " is outside 1..32768");
    if (c.height_px < 1 || c.height_px > kMaxSide)
        return fail("camera.height_px", std::to_string(c.height_px) + " is outside 1..32768");
    if (!formatFromName(formatName(c.format))) return fail("camera.format", "unknown format");
    if (c.bit_depth < 8 || c.bit_depth > 16)
        return fail("camera.bit_depth", std::to_string(c.bit_depth) + " is outside 8..16");
    if (!(std::isfinite(c.gain) && c.gain > 0.0))
        return fail("camera.gain", fmt(c.gain) + " is not a finite number > 0");
    const double full = std::ldexp(1.0, c.bit_depth) - 1.0;
    if (!(std::isfinite(c.saturation_dn) && c.saturation_dn > 0.0 && c.saturation_dn <= full))
        return fail("saturation_dn", fmt(c.saturation_dn) + " is not in (0, " + fmt(full) +
                                         "], the range of a " + std::to_string(c.bit_depth) +
                                         "-bit converter");
    if (!(std::isfinite(c.black_level_dn) && c.black_level_dn >= 0.0 &&
          c.black_level_dn < c.saturation_dn))
        return fail("black_level_dn", fmt(c.black_level_dn) + " is not in [0, saturation_dn = " +
                                          fmt(c.saturation_dn) + ")");
    if (Status ok = nonNegative("linearity_error", c.linearity_error); !ok) return ok;
    if (Status ok = nonNegative("noise.read_noise_dn", c.read_noise_dn); !ok) return ok;
    if (Status ok = nonNegative("noise.read_noise_e", c.read_noise_e); !ok) return ok;
    if (Status ok = nonNegative("noise.electrons_per_dn", c.electrons_per_dn); !ok) return ok;
    if (c.linear && c.response_curve)
        return fail("response_curve", "is present but linear is true");
    if (!c.linear && !c.response_curve)
        return fail("response_curve",
                    "is missing but linear is false (a camera that is not "
                    "linear needs its curve)");
    if (c.response_curve) {
        const ResponseCurve& r = *c.response_curve;
        if (Status ok = text("response_curve.method", r.method); !ok) return ok;
        if (Status ok = nonNegative("response_curve.rms_error_stops", r.rms_error_stops); !ok)
            return ok;
        if (r.dn.size() != r.relative_exposure.size())
            return fail("response_curve", "dn has " + std::to_string(r.dn.size()) +
                                              " knots but relative_exposure " +
                                              std::to_string(r.relative_exposure.size()));
        if (r.dn.size() < 2 || r.dn.size() > kResponseCurveMaxKnots)
            return fail("response_curve.dn", std::to_string(r.dn.size()) +
                                                 " knots; a curve has 2 to " +
                                                 std::to_string(kResponseCurveMaxKnots));
        for (size_t i = 0; i < r.dn.size(); ++i) {
            const double z = r.dn[i], x = r.relative_exposure[i];
            if (!(std::isfinite(z) && z > c.black_level_dn && z <= c.saturation_dn))
                return fail(indexed("response_curve.dn", i),
                            fmt(z) + " is not in (black_level_dn, saturation_dn] = (" +
                                fmt(c.black_level_dn) + ", " + fmt(c.saturation_dn) + "]");
            if (i > 0 && !(z > r.dn[i - 1]))
                return fail(indexed("response_curve.dn", i),
                            fmt(z) + " does not exceed the knot before it");
            if (!(std::isfinite(x) && x > 0.0))
                return fail(indexed("response_curve.relative_exposure", i),
                            fmt(x) + " is not a finite number > 0");
            if (i > 0 && !(x > r.relative_exposure[i - 1]))
                return fail(indexed("response_curve.relative_exposure", i),
                            fmt(x) + " does not exceed the knot before it (the curve must rise)");
        }
    }
    const int64_t pixels = c.width_px * c.height_px;
    for (size_t i = 0; i < c.hot_pixels.size(); ++i) {
        const int64_t p = c.hot_pixels[i];
        if (p < 0 || p >= pixels)
            return fail(indexed("hot_pixels", i), "lies outside the " + std::to_string(c.width_px) +
                                                      "x" + std::to_string(c.height_px) + " frame");
        if (i > 0 && p <= c.hot_pixels[i - 1])
            return fail(indexed("hot_pixels", i), p == c.hot_pixels[i - 1]
                                                      ? "is listed twice"
                                                      : "is out of order (rows, then columns)");
    }
    return Ok{};
}

// Reads the JSON value into the calibration, field by field, naming each that is missing, of
// the wrong type or unknown.
class Reader {
public:
    explicit Reader(std::string name) : name_(std::move(name)) {}

    Error fail(const std::string& field, const std::string& what) const {
        return makeError(ErrorCode::ParseError, name_ + ": " + field + ": " + what);
    }

    // The members of `object` must be exactly `known` (all of them unless optional).
    Status members(const json& object,
                   const std::string& where,
                   const std::vector<std::string>& required,
                   const std::vector<std::string>& optional = {}) const {
        const std::string prefix = where.empty() ? "" : where + ".";
        if (!object.is_object())
            return fail(where.empty() ? "(top level)" : where, "is not a JSON object");
        for (const auto& [key, value] : object.items()) {
            if (std::find(required.begin(), required.end(), key) == required.end() &&
                std::find(optional.begin(), optional.end(), key) == optional.end())
                return fail(prefix + key, "is not a field of format version 1");
        }
        for (const std::string& key : required)
            if (!object.contains(key)) return fail(prefix + key, "is missing");
        return Ok{};
    }

    Result<double> number(const json& value, const std::string& field) const {
        if (!value.is_number()) return fail(field, "is not a number");
        const double x = value.get<double>();
        if (!std::isfinite(x)) return fail(field, "is not finite");
        return x;
    }
    Result<int64_t> integer(const json& value, const std::string& field) const {
        if (value.is_number_integer()) {
            if (value.is_number_unsigned() &&
                value.get<uint64_t>() > static_cast<uint64_t>(std::numeric_limits<int64_t>::max()))
                return fail(field, "is too large");
            return value.get<int64_t>();
        }
        if (value.is_number_float()) {
            const double x = value.get<double>();
            if (std::isfinite(x) && x == std::floor(x) && std::abs(x) < 9.007199254740992e15)
                return static_cast<int64_t>(x);
        }
        return fail(field, "is not an integer");
    }
    Result<std::string> string(const json& value, const std::string& field) const {
        if (!value.is_string()) return fail(field, "is not a string");
        return value.get<std::string>();
    }
    Result<bool> boolean(const json& value, const std::string& field) const {
        if (!value.is_boolean()) return fail(field, "is not true or false");
        return value.get<bool>();
    }
    Result<std::vector<double>> numbers(const json& value, const std::string& field) const {
        if (!value.is_array()) return fail(field, "is not an array");
        if (value.size() > kResponseCurveMaxKnots)
            return fail(field,
                        "has more than " + std::to_string(kResponseCurveMaxKnots) + " entries");
        std::vector<double> out;
        out.reserve(value.size());
        for (size_t i = 0; i < value.size(); ++i) {
            auto x = number(value[i], indexed(field, i));
            if (!x) return x.error();
            out.push_back(*x);
        }
        return out;
    }

private:
    std::string name_;
};

Result<CameraCalibration> fromJson(const json& doc, const std::string& name) {
    const Reader r(name);
    if (!doc.is_object()) return r.fail("(top level)", "is not a JSON object");
    // The format and version first, so that a newer file says so rather than "unknown field".
    if (!doc.contains("format")) return r.fail("format", "is missing");
    auto format_name = r.string(doc["format"], "format");
    if (!format_name) return format_name.error();
    if (*format_name != kCalibrationFormatName)
        return makeError(ErrorCode::Unsupported, name + ": format: '" + *format_name +
                                                     "' is not '" + kCalibrationFormatName + "'");
    if (!doc.contains("format_version")) return r.fail("format_version", "is missing");
    auto version = r.integer(doc["format_version"], "format_version");
    if (!version) return version.error();
    if (*version != kCalibrationFormatVersion)
        return makeError(ErrorCode::Unsupported,
                         name + ": format_version: " + std::to_string(*version) +
                             "; this reader knows version " +
                             std::to_string(kCalibrationFormatVersion));
    if (Status ok = r.members(doc, "",
                              {"format", "format_version", "camera", "created_utc",
                               "software_version", "black_level_dn", "saturation_dn", "linear",
                               "linearity_error", "noise", "hot_pixels", "notes"},
                              {"response_curve"});
        !ok)
        return ok.error();

    CameraCalibration c;
    const json& camera = doc["camera"];
    if (Status ok =
            r.members(camera, "camera",
                      {"model", "serial", "width_px", "height_px", "format", "bit_depth", "gain"});
        !ok)
        return ok.error();
    auto model = r.string(camera["model"], "camera.model");
    if (!model) return model.error();
    c.camera_model = std::move(*model);
    auto serial = r.string(camera["serial"], "camera.serial");
    if (!serial) return serial.error();
    c.camera_serial = std::move(*serial);
    auto width = r.integer(camera["width_px"], "camera.width_px");
    if (!width) return width.error();
    c.width_px = *width;
    auto height = r.integer(camera["height_px"], "camera.height_px");
    if (!height) return height.error();
    c.height_px = *height;
    for (const auto& [field, value] :
         {std::pair<const char*, int64_t>{"camera.width_px", c.width_px},
          {"camera.height_px", c.height_px}})
        if (value < 1 || value > kMaxSide)
            return r.fail(field, std::to_string(value) + " is outside 1..32768");
    auto raw_format = r.string(camera["format"], "camera.format");
    if (!raw_format) return raw_format.error();
    const auto parsed_format = formatFromName(*raw_format);
    if (!parsed_format)
        return r.fail("camera.format",
                      "'" + *raw_format + "' is not mono, rggb, bggr, grbg or gbrg");
    c.format = *parsed_format;
    auto bits = r.integer(camera["bit_depth"], "camera.bit_depth");
    if (!bits) return bits.error();
    if (*bits < 8 || *bits > 16)
        return r.fail("camera.bit_depth", std::to_string(*bits) + " is outside 8..16");
    c.bit_depth = static_cast<int>(*bits);
    auto gain = r.number(camera["gain"], "camera.gain");
    if (!gain) return gain.error();
    c.gain = *gain;

    auto created = r.string(doc["created_utc"], "created_utc");
    if (!created) return created.error();
    c.created_utc = std::move(*created);
    auto software = r.string(doc["software_version"], "software_version");
    if (!software) return software.error();
    c.software_version = std::move(*software);
    auto black = r.number(doc["black_level_dn"], "black_level_dn");
    if (!black) return black.error();
    c.black_level_dn = *black;
    auto saturation = r.number(doc["saturation_dn"], "saturation_dn");
    if (!saturation) return saturation.error();
    c.saturation_dn = *saturation;
    auto linear = r.boolean(doc["linear"], "linear");
    if (!linear) return linear.error();
    c.linear = *linear;
    auto linearity = r.number(doc["linearity_error"], "linearity_error");
    if (!linearity) return linearity.error();
    c.linearity_error = *linearity;

    const json& noise = doc["noise"];
    if (Status ok =
            r.members(noise, "noise", {"read_noise_dn", "read_noise_e", "electrons_per_dn"});
        !ok)
        return ok.error();
    for (const auto& [key, target] :
         {std::pair<const char*, double*>{"read_noise_dn", &c.read_noise_dn},
          {"read_noise_e", &c.read_noise_e},
          {"electrons_per_dn", &c.electrons_per_dn}}) {
        auto value = r.number(noise[key], std::string("noise.") + key);
        if (!value) return value.error();
        *target = *value;
    }

    if (doc.contains("response_curve")) {
        const json& curve = doc["response_curve"];
        if (Status ok = r.members(curve, "response_curve",
                                  {"method", "rms_error_stops", "dn", "relative_exposure"});
            !ok)
            return ok.error();
        ResponseCurve rc;
        auto method = r.string(curve["method"], "response_curve.method");
        if (!method) return method.error();
        rc.method = std::move(*method);
        auto rms = r.number(curve["rms_error_stops"], "response_curve.rms_error_stops");
        if (!rms) return rms.error();
        rc.rms_error_stops = *rms;
        auto dn = r.numbers(curve["dn"], "response_curve.dn");
        if (!dn) return dn.error();
        rc.dn = std::move(*dn);
        auto x = r.numbers(curve["relative_exposure"], "response_curve.relative_exposure");
        if (!x) return x.error();
        rc.relative_exposure = std::move(*x);
        c.response_curve = std::move(rc);
    }

    const json& hot = doc["hot_pixels"];
    if (!hot.is_array()) return r.fail("hot_pixels", "is not an array");
    if (static_cast<int64_t>(hot.size()) > c.width_px * c.height_px)
        return r.fail("hot_pixels", "lists more pixels than the frame has");
    c.hot_pixels.reserve(hot.size());
    std::set<int64_t> seen;
    for (size_t i = 0; i < hot.size(); ++i) {
        const std::string field = indexed("hot_pixels", i);
        if (!hot[i].is_array() || hot[i].size() != 2) return r.fail(field, "is not a pair [x, y]");
        auto x = r.integer(hot[i][0], field + "[0]");
        if (!x) return x.error();
        auto y = r.integer(hot[i][1], field + "[1]");
        if (!y) return y.error();
        if (*x < 0 || *x >= c.width_px || *y < 0 || *y >= c.height_px)
            return r.fail(field, "[" + std::to_string(*x) + ", " + std::to_string(*y) +
                                     "] lies outside the " + std::to_string(c.width_px) + "x" +
                                     std::to_string(c.height_px) + " frame");
        const int64_t index = *y * c.width_px + *x;
        if (!seen.insert(index).second)
            return r.fail(
                field, "[" + std::to_string(*x) + ", " + std::to_string(*y) + "] is listed twice");
        c.hot_pixels.push_back(index);
    }
    std::sort(c.hot_pixels.begin(), c.hot_pixels.end());

    const json& notes = doc["notes"];
    if (!notes.is_array()) return r.fail("notes", "is not an array");
    for (size_t i = 0; i < notes.size(); ++i) {
        auto note = r.string(notes[i], indexed("notes", i));
        if (!note) return note.error();
        c.notes.push_back(std::move(*note));
    }

    if (Status ok = check(c, ErrorCode::ParseError, name); !ok) return ok.error();
    return c;
}

// The sample at (x, y) of a Bayer mosaic: its colour, 0 red, 1 green, 2 blue; -1 for mono.
int colourAt(hdr::RawFormat format, int64_t x, int64_t y) {
    const int i = static_cast<int>((y & 1) * 2 + (x & 1));  // position in the 2x2 tile
    switch (format) {
        case hdr::RawFormat::Mono:
            return -1;
        case hdr::RawFormat::BayerRGGB:
            return std::array{0, 1, 1, 2}[i];
        case hdr::RawFormat::BayerBGGR:
            return std::array{2, 1, 1, 0}[i];
        case hdr::RawFormat::BayerGRBG:
            return std::array{1, 0, 2, 1}[i];
        case hdr::RawFormat::BayerGBRG:
            return std::array{1, 2, 0, 1}[i];
    }
    return -1;
}

// The median of the nearest same-colour neighbours of pixel (x, y) that are not hot; nullopt when
// every one is hot or outside the frame.
std::optional<uint16_t> repairedValue(const hdr::RawFrame& frame,
                                      const std::vector<bool>& hot,
                                      int64_t x,
                                      int64_t y) {
    std::vector<std::pair<int, int>> offsets;
    const int colour = colourAt(frame.format, x, y);
    if (colour < 0) {
        offsets = {{-1, -1}, {0, -1}, {1, -1}, {-1, 0}, {1, 0}, {-1, 1}, {0, 1}, {1, 1}};
    } else {
        offsets = {{-2, 0}, {2, 0}, {0, -2}, {0, 2}, {-2, -2}, {2, -2}, {-2, 2}, {2, 2}};
        if (colour == 1)  // green sits on both diagonals of its tile
            offsets.insert(offsets.end(), {{-1, -1}, {1, -1}, {-1, 1}, {1, 1}});
    }
    std::vector<uint16_t> values;
    for (const auto& [dx, dy] : offsets) {
        const int64_t nx = x + dx, ny = y + dy;
        if (nx < 0 || ny < 0 || nx >= frame.width || ny >= frame.height) continue;
        const size_t i = static_cast<size_t>(ny * frame.width + nx);
        if (hot[i]) continue;
        values.push_back(frame.samples[i]);
    }
    if (values.empty()) return std::nullopt;
    std::sort(values.begin(), values.end());
    const size_t n = values.size();
    if (n % 2 == 1) return values[n / 2];
    return static_cast<uint16_t>((static_cast<uint32_t>(values[n / 2 - 1]) + values[n / 2] + 1) /
                                 2);
}

}  // namespace

double relativeExposure(const ResponseCurve& curve, double black_level_dn, double z) {
    if (curve.dn.empty() || !(z > black_level_dn)) return 0.0;
    const auto& dn = curve.dn;
    const auto& x = curve.relative_exposure;
    if (z <= dn.front()) {
        const double span = dn.front() - black_level_dn;
        return span > 0.0 ? x.front() * (z - black_level_dn) / span : x.front();
    }
    if (z >= dn.back()) return x.back();
    const size_t hi = static_cast<size_t>(std::upper_bound(dn.begin(), dn.end(), z) - dn.begin());
    const size_t lo = hi - 1;
    const double f = (z - dn[lo]) / (dn[hi] - dn[lo]);
    return x[lo] + f * (x[hi] - x[lo]);
}

Status validateCalibration(const CameraCalibration& calibration) {
    return check(calibration, ErrorCode::InvalidArgument, "camera calibration");
}

Result<CameraCalibration> parseCalibration(std::string_view text, const std::string& name) {
    json doc;
    try {
        doc = json::parse(text.begin(), text.end());
    } catch (const json::exception& e) {
        return makeError(ErrorCode::ParseError, name + ": not valid JSON: " + e.what());
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::ParseError, name + ": too large to parse");
    }
    try {
        return fromJson(doc, name);
    } catch (const json::exception& e) {
        // The reader checks every type before it converts; this is a bug, not bad input.
        return makeError(ErrorCode::Internal, name + ": " + e.what());
    }
}

Result<CameraCalibration> readCalibration(const std::string& path) {
    auto file = openRegularFile(path);
    if (!file) return file.error();
    if (file->size > kCalibrationMaxFileBytes)
        return makeError(ErrorCode::IoError, path + ": " + std::to_string(file->size) +
                                                 " bytes, more than a calibration file may hold (" +
                                                 std::to_string(kCalibrationMaxFileBytes) + ")");
    std::string text(static_cast<size_t>(file->size), '\0');
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t got = ::read(file->fd.get(), text.data() + done, text.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": cannot read: " + osMessage(errno));
        if (got == 0) break;  // the file shrank while being read
        done += static_cast<size_t>(got);
    }
    text.resize(done);
    return parseCalibration(text, path);
}

Result<std::string> formatCalibration(const CameraCalibration& c) {
    if (Status ok = validateCalibration(c); !ok) return ok.error();
    json doc = json::object();
    doc["format"] = kCalibrationFormatName;
    doc["format_version"] = kCalibrationFormatVersion;
    doc["camera"] = {{"model", c.camera_model},
                     {"serial", c.camera_serial},
                     {"width_px", c.width_px},
                     {"height_px", c.height_px},
                     {"format", formatName(c.format)},
                     {"bit_depth", c.bit_depth},
                     {"gain", c.gain}};
    doc["created_utc"] = c.created_utc;
    doc["software_version"] = c.software_version;
    doc["black_level_dn"] = c.black_level_dn;
    doc["saturation_dn"] = c.saturation_dn;
    doc["linear"] = c.linear;
    doc["linearity_error"] = c.linearity_error;
    doc["noise"] = {{"read_noise_dn", c.read_noise_dn},
                    {"read_noise_e", c.read_noise_e},
                    {"electrons_per_dn", c.electrons_per_dn}};
    if (c.response_curve)
        doc["response_curve"] = {{"method", c.response_curve->method},
                                 {"rms_error_stops", c.response_curve->rms_error_stops},
                                 {"dn", c.response_curve->dn},
                                 {"relative_exposure", c.response_curve->relative_exposure}};
    json hot = json::array();
    for (const int64_t p : c.hot_pixels) hot.push_back({p % c.width_px, p / c.width_px});
    doc["hot_pixels"] = std::move(hot);
    doc["notes"] = c.notes;
    // nlohmann writes doubles with 17 significant digits, which read back to the same double.
    return doc.dump(2) + "\n";
}

Status writeCalibration(const std::string& path, const CameraCalibration& calibration) {
    auto text = formatCalibration(calibration);
    if (!text) return text.error().withContext(path);
    const std::filesystem::path target(path);
    if (target.filename().empty())
        return makeError(ErrorCode::InvalidArgument, path + ": names no file");
    const std::string directory =
        target.parent_path().empty() ? std::string(".") : target.parent_path().string();
    FileDescriptor dir(::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (!dir.valid())
        return makeError(errno == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                         path + ": cannot open its directory: " + osMessage(errno));
    return replaceFile(directory, dir.get(), target.filename().string(), *text, {});
}

std::string calibrationCameraName(const CameraCalibration& calibration) {
    return calibration.camera_model + " " + calibration.camera_serial;
}

Result<hdr::RawFrame> applyCalibration(const hdr::RawFrame& frame, const CameraCalibration& cal) {
    const auto differs = [&](const std::string& what, const std::string& frame_value,
                             const std::string& cal_value) -> Error {
        return makeError(ErrorCode::InvalidArgument,
                         "calibration of " + calibrationCameraName(cal) + ": the frame's " + what +
                             " is " + frame_value + ", the calibration's " + cal_value);
    };
    if (frame.camera != calibrationCameraName(cal))
        return differs("camera", quoted(frame.camera), quoted(calibrationCameraName(cal)));
    if (frame.width != cal.width_px || frame.height != cal.height_px)
        return differs("size", std::to_string(frame.width) + "x" + std::to_string(frame.height),
                       std::to_string(cal.width_px) + "x" + std::to_string(cal.height_px));
    if (frame.format != cal.format)
        return differs("format", formatName(frame.format), formatName(cal.format));
    if (frame.bit_depth != cal.bit_depth)
        return differs("bit depth", std::to_string(frame.bit_depth), std::to_string(cal.bit_depth));
    if (frame.samples.size() != static_cast<size_t>(frame.width * frame.height))
        return makeError(ErrorCode::InvalidArgument,
                         "calibration of " + calibrationCameraName(cal) + ": the frame holds " +
                             std::to_string(frame.samples.size()) + " samples, not width * height");
    if (!(std::isfinite(frame.gain) && frame.gain > 0.0))
        return makeError(ErrorCode::InvalidArgument,
                         "calibration of " + calibrationCameraName(cal) + ": the frame's gain " +
                             fmt(frame.gain) + " is not a finite number > 0");

    hdr::RawFrame out = frame;
    // Hot pixels: from the original samples, so that a repaired pixel never feeds another.
    if (!cal.hot_pixels.empty()) {
        std::vector<bool> hot(frame.samples.size(), false);
        for (const int64_t p : cal.hot_pixels) hot[static_cast<size_t>(p)] = true;
        for (const int64_t p : cal.hot_pixels) {
            const auto value = repairedValue(frame, hot, p % frame.width, p / frame.width);
            if (value) out.samples[static_cast<size_t>(p)] = *value;
        }
    }

    if (cal.linear) {
        out.black_level_dn = cal.black_level_dn;
        out.white_level_dn = cal.saturation_dn;
    } else {
        // One table entry per possible sample: the converter has at most 2^16 codes.
        const size_t codes = size_t{1} << cal.bit_depth;
        std::vector<uint16_t> table(codes);
        const ResponseCurve& curve = *cal.response_curve;
        const double top = curve.relative_exposure.back();
        for (size_t z = 0; z < codes; ++z) {
            const double x = relativeExposure(curve, cal.black_level_dn, static_cast<double>(z));
            table[z] =
                static_cast<uint16_t>(std::clamp(std::round(65535.0 * x / top), 0.0, 65535.0));
        }
        for (uint16_t& s : out.samples) s = table[std::min<size_t>(s, codes - 1)];
        out.bit_depth = 16;
        out.black_level_dn = 0.0;
        out.white_level_dn = 65535.0;
    }
    if (cal.electrons_per_dn > 0.0) {
        out.electrons_per_dn = cal.electrons_per_dn * cal.gain / frame.gain;
        const double read_e =
            cal.read_noise_e > 0.0 ? cal.read_noise_e : cal.read_noise_dn * cal.electrons_per_dn;
        out.read_noise_dn = read_e / out.electrons_per_dn;
    } else if (cal.read_noise_dn > 0.0) {
        // No conversion gain: the read noise in DN, which holds at the calibration's gain only.
        out.read_noise_dn = cal.read_noise_dn * frame.gain / cal.gain;
    }
    return out;
}

Status checkMergeable(const CameraCapabilities& capabilities,
                      const CameraCalibration* calibration) {
    const std::string how =
        "run `flarelab calibrate --camera URI -o camera.cal.json` with the camera on a steady "
        "light and pass the file it writes";
    if (calibration != nullptr) {
        if (capabilities.width_px != calibration->width_px ||
            capabilities.height_px != calibration->height_px)
            return makeError(ErrorCode::InvalidArgument,
                             "the calibration of " + calibrationCameraName(*calibration) +
                                 " is for " + std::to_string(calibration->width_px) + "x" +
                                 std::to_string(calibration->height_px) +
                                 " frames, the camera gives " +
                                 std::to_string(capabilities.width_px) + "x" +
                                 std::to_string(capabilities.height_px));
        if (!calibration->linear && !calibration->response_curve)
            return makeError(ErrorCode::Unsupported,
                             "the calibration of " + calibrationCameraName(*calibration) +
                                 " found its response not linear but holds no response curve; " +
                                 how);
    }
    if (capabilities.response != CameraResponse::NonLinear) return Ok{};
    if (calibration != nullptr && calibration->response_curve) return Ok{};
    const std::string why =
        capabilities.response_note.empty() ? "" : " (" + capabilities.response_note + ")";
    if (calibration != nullptr)
        return makeError(ErrorCode::Unsupported,
                         "the camera's response is not linear" + why +
                             ", but its calibration holds no response curve, so its brackets "
                             "cannot be merged; " +
                             how);
    return makeError(ErrorCode::Unsupported,
                     "the camera's response is not linear" + why +
                         ": its brackets cannot be merged until its response is calibrated; " +
                         how);
}

Status checkCalibrationFor(const Camera& camera, const CameraCalibration* calibration) {
    if (calibration != nullptr &&
        calibrationCameraName(*calibration) != camera.identity().describe())
        return makeError(ErrorCode::InvalidArgument,
                         "the calibration was measured on " + calibrationCameraName(*calibration) +
                             ", not on this camera, " + camera.identity().describe());
    return checkMergeable(camera.capabilities(), calibration);
}

}  // namespace flarelab::drivers
