#include "hdr/sweep.h"

#include <fcntl.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <set>
#include <system_error>
#include <tuple>
#include <utility>
#include <vector>

#include "common/check.h"
#include "common/file_descriptor.h"
#include "common/utf8.h"
#include "proto/sweep.pb.h"

namespace flarelab::hdr {
namespace {

namespace fs = std::filesystem;
namespace pb = google::protobuf;

constexpr size_t kMaxPathBytes = 4096;
constexpr size_t kMaxComponentBytes = 255;
constexpr int kMaxBitDepth = 32;

// Shortest decimal that reads back to the same double, as the EXR attributes write them.
std::string formatDouble(double value) {
    std::array<char, 32> buffer{};
    const auto result = std::to_chars(buffer.data(), buffer.data() + buffer.size(), value);
    return std::string(buffer.data(), result.ptr);
}

std::string formatTimes(const std::vector<double>& times) {
    std::string text = "[";
    for (size_t i = 0; i < times.size(); ++i) {
        if (i) text += ' ';
        text += formatDouble(times[i]);
    }
    return text + "]";
}

std::string indexed(const char* field, size_t index) {
    return std::string(field) + "[" + std::to_string(index) + "]";
}

std::string manifestPath(const std::string& directory) {
    return (fs::path(directory) / kSweepManifestFile).string();
}

bool endsWith(std::string_view text, std::string_view suffix) {
    return text.size() >= suffix.size() && text.substr(text.size() - suffix.size()) == suffix;
}

bool isTemporaryName(std::string_view name) { return name.find(".tmp-") != std::string_view::npos; }

bool hasExrExtension(std::string_view name) {
    if (name.size() < 4) return false;
    std::string tail(name.substr(name.size() - 4));
    std::transform(tail.begin(), tail.end(), tail.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    return tail == ".exr";
}

// ---------------------------------------------------------------------------------------------
// The rules of the format (sweep.h), on the plain structs. Parsing reports a broken rule as
// ParseError, writing as InvalidArgument; `name` is the manifest (file or stand-in).

class Checker {
public:
    Checker(ErrorCode code, std::string name) : code_(code), name_(std::move(name)) {}

    Error fail(const std::string& field, const std::string& what) const {
        return makeError(code_, name_ + ": " + field + ": " + what);
    }

    Status finite(const std::string& field, double value) const {
        if (!std::isfinite(value)) return fail(field, formatDouble(value) + " is not finite");
        return Ok{};
    }
    Status positive(const std::string& field, double value) const {
        if (!(std::isfinite(value) && value > 0.0))
            return fail(field, formatDouble(value) + " is not a finite number > 0");
        return Ok{};
    }
    Status positive(const std::string& field, const std::optional<double>& value) const {
        return value ? positive(field, *value) : Status(Ok{});
    }
    Status times(const std::string& field, const std::vector<double>& values) const {
        for (size_t i = 0; i < values.size(); ++i)
            if (auto ok = positive(indexed(field.c_str(), i), values[i]); !ok) return ok;
        return Ok{};
    }
    // EXR string attributes end at the first NUL; protobuf JSON needs UTF-8.
    Status text(const std::string& field, const std::string& value) const {
        if (value.find('\0') != std::string::npos) return fail(field, "holds a NUL character");
        if (!validUtf8(value)) return fail(field, "is not valid UTF-8");
        return Ok{};
    }
    Status path(const std::string& field, const std::string& value) const {
        const std::string why = pathProblem(value);
        if (!why.empty()) return fail(field, quoted(value) + " " + why);
        return Ok{};
    }

    // Why `path` is not a relative path inside the sweep directory; empty when it is.
    static std::string pathProblem(std::string_view path) {
        if (path.empty()) return "is empty";
        if (path.size() > kMaxPathBytes)
            return "is longer than " + std::to_string(kMaxPathBytes) + " bytes";
        if (path.front() == '/') return "is absolute; files must lie inside the sweep directory";
        for (const char c : path) {
            const auto u = static_cast<unsigned char>(c);
            if (u < 0x20 || u == 0x7F) return "holds a control character";
            if (c == '\\') return "holds a backslash; separate folders with '/'";
        }
        size_t start = 0;
        while (true) {
            const size_t slash = path.find('/', start);
            const std::string_view part = path.substr(
                start, slash == std::string_view::npos ? std::string_view::npos : slash - start);
            if (part.empty()) return "has an empty component (a leading, doubled or final '/')";
            if (part == "." || part == "..")
                return "has a '" + std::string(part) +
                       "' component; files must lie inside the sweep directory";
            if (part.size() > kMaxComponentBytes)
                return "has a component longer than " + std::to_string(kMaxComponentBytes) +
                       " bytes";
            if (slash == std::string_view::npos) break;
            start = slash + 1;
        }
        if (!validUtf8(path)) return "is not valid UTF-8";
        return "";
    }

    // `text` in single quotes, printable.
    static std::string quoted(std::string_view text) {
        std::string out = "'";
        out += printable(text);
        out += '\'';
        return out;
    }

    // For messages: control characters escaped, long names shortened.
    static std::string printable(std::string_view text) {
        std::string out;
        for (const char c : text.substr(0, 200)) {
            const auto u = static_cast<unsigned char>(c);
            if (u < 0x20 || u == 0x7F) {
                char escape[8];
                std::snprintf(escape, sizeof(escape), "\\x%02x", u);
                out += escape;
            } else {
                out += c;
            }
        }
        if (text.size() > 200) out += "...";
        return out;
    }

private:
    ErrorCode code_;
    std::string name_;
};

bool isLowerHexDigest(std::string_view text) {
    return text.size() == 64 && std::all_of(text.begin(), text.end(), [](char c) {
               return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f');
           });
}

// What optics::CameraDescription accepts: 0 for a circle, else a polygon of 3 or more sides.
bool validBlades(int64_t blades) {
    return blades == 0 || (blades >= 3 && blades <= kSweepMaxApertureBlades);
}

std::string bladesProblem(int64_t blades) {
    return std::to_string(blades) + " is neither 0 (a circular stop) nor 3.." +
           std::to_string(kSweepMaxApertureBlades);
}

// The first lens field of version 3 that `lens` records, or nullptr: an older manifest has none.
const char* firstVersion3Field(const SweepLens& lens) {
    const std::pair<const char*, bool> fields[] = {
        {"lens.aperture_blades", lens.aperture_blades.has_value()},
        {"lens.blade_rotation_deg", lens.blade_rotation_deg.has_value()},
        {"lens.stop_semi_aperture_mm", lens.stop_semi_aperture_mm.has_value()},
        {"lens.coat_unspecified_surfaces", lens.coat_unspecified_surfaces.has_value()},
        {"lens.sensor_width_mm", lens.sensor_width_mm.has_value()},
        {"lens.sensor_height_mm", lens.sensor_height_mm.has_value()},
        {"lens.prescription_file", !lens.prescription_file.empty()},
        {"lens.prescription_sha256", !lens.prescription_sha256.empty()}};
    for (const auto& [field, present] : fields)
        if (present) return field;
    return nullptr;
}

Status checkLens(const SweepLens& lens, int format_version, const Checker& check) {
    if (auto ok = check.text("lens.description", lens.description); !ok) return ok;
    if (auto ok = check.text("lens.serial", lens.serial); !ok) return ok;
    if (auto ok = check.positive("lens.focal_length_mm", lens.focal_length_mm); !ok) return ok;
    if (auto ok = check.positive("lens.f_number", lens.f_number); !ok) return ok;
    if (format_version < 3)
        if (const char* field = firstVersion3Field(lens))
            return check.fail(field, "is a field of format version 3, not of version " +
                                         std::to_string(format_version));
    if (lens.aperture_blades && !validBlades(*lens.aperture_blades))
        return check.fail("lens.aperture_blades", bladesProblem(*lens.aperture_blades));
    if (lens.blade_rotation_deg)
        if (auto ok = check.finite("lens.blade_rotation_deg", *lens.blade_rotation_deg); !ok)
            return ok;
    if (auto ok = check.positive("lens.stop_semi_aperture_mm", lens.stop_semi_aperture_mm); !ok)
        return ok;
    if (auto ok = check.positive("lens.sensor_width_mm", lens.sensor_width_mm); !ok) return ok;
    if (auto ok = check.positive("lens.sensor_height_mm", lens.sensor_height_mm); !ok) return ok;
    if (auto ok = check.text("lens.prescription_file", lens.prescription_file); !ok) return ok;
    if (!lens.prescription_sha256.empty() && !isLowerHexDigest(lens.prescription_sha256))
        return check.fail("lens.prescription_sha256",
                          Checker::quoted(lens.prescription_sha256) +
                              " is not 64 lowercase hex digits (a SHA-256)");
    return Ok{};
}

Status checkHeader(const SweepHeader& h, const Checker& check) {
    if (h.format_version < kSweepOldestFormatVersion || h.format_version > kSweepFormatVersion)
        return check.fail("format_version", std::to_string(h.format_version) +
                                                " is not a version this module knows (" +
                                                std::to_string(kSweepOldestFormatVersion) + ".." +
                                                std::to_string(kSweepFormatVersion) + ")");
    if (auto ok = check.text("software_version", h.software_version); !ok) return ok;
    if (!h.created_utc.empty()) {
        pb::Timestamp stamp;
        if (!pb::util::TimeUtil::FromString(h.created_utc, &stamp))
            return check.fail("created", Checker::quoted(h.created_utc) +
                                             " is not an RFC 3339 time (2026-11-29T07:04:02Z)");
    }
    if (auto ok = checkLens(h.lens, h.format_version, check); !ok) return ok;
    const SweepCamera& camera = h.camera;
    if (auto ok = check.text("camera.description", camera.description); !ok) return ok;
    if (auto ok = check.text("camera.serial", camera.serial); !ok) return ok;
    if (auto ok = check.positive("camera.pixel_pitch_um", camera.pixel_pitch_um); !ok) return ok;
    if (camera.bit_depth && (*camera.bit_depth < 1 || *camera.bit_depth > kMaxBitDepth))
        return check.fail("camera.bit_depth", std::to_string(*camera.bit_depth) +
                                                  " is outside 1.." + std::to_string(kMaxBitDepth));
    if (camera.raw_format && h.format_version < 4)
        return check.fail("camera.raw_format", "is a field of format version 4, not of version " +
                                                   std::to_string(h.format_version));
    if (camera.light_power_dn_s) {
        if (h.format_version < 5)
            return check.fail("camera.light_power_dn_s",
                              "is a field of format version 5, not of version " +
                                  std::to_string(h.format_version));
        if (auto ok = check.positive("camera.light_power_dn_s", camera.light_power_dn_s); !ok)
            return ok;
    }
    const SweepCapture& capture = h.capture;
    if (auto ok = check.finite("capture.from_deg", capture.from_deg); !ok) return ok;
    if (auto ok = check.finite("capture.to_deg", capture.to_deg); !ok) return ok;
    if (auto ok = check.finite("capture.roll_deg", capture.roll_deg); !ok) return ok;
    if (auto ok = check.positive("capture.step_deg", capture.step_deg); !ok) return ok;
    if (capture.from_deg > capture.to_deg)
        return check.fail("capture.to_deg", formatDouble(capture.to_deg) +
                                                " is below capture.from_deg " +
                                                formatDouble(capture.from_deg));
    if (auto ok = check.times("capture.exposure_times_s", capture.exposure_times_s); !ok) return ok;
    if (auto ok = check.positive("capture.gain", capture.gain); !ok) return ok;
    const std::pair<const char*, int64_t> sides[] = {{"capture.width_px", capture.width_px},
                                                     {"capture.height_px", capture.height_px}};
    for (const auto& [field, side] : sides)
        if (side < 1 || side > kSweepMaxSide)
            return check.fail(field, std::to_string(side) + " is outside 1.." +
                                         std::to_string(kSweepMaxSide) + " pixels");
    return Ok{};
}

// Frame `index` alone and against the one before it.
Status checkFrame(const SweepHeader& h,
                  const SweepFrame& f,
                  size_t index,
                  const SweepFrame* previous,
                  const Checker& check) {
    const std::string at = indexed("frames", index) + ".";
    const SweepCapture& capture = h.capture;
    if (auto ok = check.finite(at + "angle_deg", f.angle_deg); !ok) return ok;
    if (f.angle_deg < capture.from_deg - kSweepAngleSlackDeg ||
        f.angle_deg > capture.to_deg + kSweepAngleSlackDeg)
        return check.fail(at + "angle_deg",
                          formatDouble(f.angle_deg) + " lies outside capture.from_deg.." +
                              "capture.to_deg (" + formatDouble(capture.from_deg) + ".." +
                              formatDouble(capture.to_deg) + ")");
    if (previous != nullptr && !(f.angle_deg > previous->angle_deg))
        return check.fail(at + "angle_deg",
                          formatDouble(f.angle_deg) +
                              (f.angle_deg == previous->angle_deg ? " repeats " : " is below ") +
                              indexed("frames", index - 1) + ".angle_deg " +
                              formatDouble(previous->angle_deg) + "; angles must increase");
    if (auto ok = check.path(at + "exr_file", f.exr_file); !ok) return ok;
    if (!endsWith(f.exr_file, ".exr"))
        return check.fail(at + "exr_file", Checker::quoted(f.exr_file) + " does not end in .exr");
    if (auto ok = check.times(at + "exposure_times_s", f.exposure_times_s); !ok) return ok;
    const size_t bracket = f.exposure_times_s.size();
    if (!f.raw_files.empty() && f.raw_files.size() != bracket)
        return check.fail(at + "raw_files", std::to_string(f.raw_files.size()) + " files for " +
                                                std::to_string(bracket) +
                                                " exposure times; give one per exposure or none");
    for (size_t i = 0; i < f.raw_files.size(); ++i)
        if (auto ok = check.path(at + indexed("raw_files", i), f.raw_files[i]); !ok) return ok;
    if (auto ok = check.text(at + "merge_method", f.merge_method); !ok) return ok;
    if (!f.brackets.empty() && f.brackets.size() != bracket)
        return check.fail(at + "brackets", std::to_string(f.brackets.size()) + " entries for " +
                                               std::to_string(bracket) +
                                               " exposure times; give one per exposure or none");
    for (size_t i = 0; i < f.brackets.size(); ++i)
        if (f.brackets[i].exposure_s != f.exposure_times_s[i])
            return check.fail(at + indexed("brackets", i) + ".exposure_s",
                              formatDouble(f.brackets[i].exposure_s) + " differs from " +
                                  indexed("exposure_times_s", i) + " " +
                                  formatDouble(f.exposure_times_s[i]));
    return Ok{};
}

// Every file named once, and none named manifest.json. `files` holds the names seen so far.
Status checkUnique(const SweepFrame& f,
                   size_t index,
                   std::set<std::string>& files,
                   const Checker& check) {
    const std::string at = indexed("frames", index) + ".";
    std::vector<std::pair<std::string, const std::string*>> named{{at + "exr_file", &f.exr_file}};
    for (size_t i = 0; i < f.raw_files.size(); ++i)
        named.emplace_back(at + indexed("raw_files", i), &f.raw_files[i]);
    for (const auto& [field, file] : named) {
        if (*file == kSweepManifestFile) return check.fail(field, "names the manifest file");
        if (!files.insert(*file).second)
            return check.fail(field, Checker::quoted(*file) + " is named twice in the manifest");
    }
    return Ok{};
}

Status checkSweep(const Sweep& s, const Checker& check) {
    if (auto ok = checkHeader(s.header, check); !ok) return ok;
    std::set<std::string> files;
    for (size_t i = 0; i < s.frames.size(); ++i) {
        if (auto ok = checkFrame(s.header, s.frames[i], i, i ? &s.frames[i - 1] : nullptr, check);
            !ok)
            return ok;
        if (auto ok = checkUnique(s.frames[i], i, files, check); !ok) return ok;
    }
    return Ok{};
}

// ---------------------------------------------------------------------------------------------
// Between the structs and flarelab.v1.SweepManifest.

template <typename T>
std::vector<T> toVector(const pb::RepeatedField<T>& values) {
    return std::vector<T>(values.begin(), values.end());
}

SweepFrame frameFromProto(const flarelab::v1::Frame& f) {
    SweepFrame frame;
    frame.angle_deg = f.angle_deg();
    frame.exr_file = f.exr_file();
    frame.exposure_times_s = toVector(f.exposure_times_s());
    frame.raw_files.assign(f.raw_files().begin(), f.raw_files().end());
    frame.merge_method = f.merge_method();
    for (const auto& b : f.brackets())
        frame.brackets.push_back({b.exposure_s(), b.samples_used(), b.samples_clipped()});
    return frame;
}

void frameToProto(const SweepFrame& frame, flarelab::v1::Frame* f) {
    f->set_angle_deg(frame.angle_deg);
    f->set_exr_file(frame.exr_file);
    for (const double t : frame.exposure_times_s) f->add_exposure_times_s(t);
    for (const std::string& raw : frame.raw_files) f->add_raw_files(raw);
    f->set_merge_method(frame.merge_method);
    for (const SweepBracketStats& b : frame.brackets) {
        auto* stats = f->add_brackets();
        stats->set_exposure_s(b.exposure_s);
        stats->set_samples_used(b.samples_used);
        stats->set_samples_clipped(b.samples_clipped);
    }
}

// Unvalidated, except for what does not fit the structs' types.
Result<Sweep> fromProto(const flarelab::v1::SweepManifest& m, const Checker& check) {
    Sweep s;
    SweepHeader& h = s.header;
    // format_version was checked before; keeps the uint32 from wrapping.
    h.format_version = static_cast<int>(std::min<uint32_t>(m.format_version(), 1u << 30));
    h.software_version = m.software_version();
    if (m.has_created()) h.created_utc = pb::util::TimeUtil::ToString(m.created());
    h.lens.description = m.lens().description();
    h.lens.serial = m.lens().serial();
    if (m.lens().has_focal_length_mm()) h.lens.focal_length_mm = m.lens().focal_length_mm();
    if (m.lens().has_f_number()) h.lens.f_number = m.lens().f_number();
    const auto& l = m.lens();
    if (l.has_aperture_blades()) {
        const uint32_t blades = l.aperture_blades();
        if (!validBlades(blades)) return check.fail("lens.aperture_blades", bladesProblem(blades));
        h.lens.aperture_blades = static_cast<int>(blades);
    }
    if (l.has_blade_rotation_deg()) h.lens.blade_rotation_deg = l.blade_rotation_deg();
    if (l.has_stop_semi_aperture_mm()) h.lens.stop_semi_aperture_mm = l.stop_semi_aperture_mm();
    if (l.has_coat_unspecified_surfaces())
        h.lens.coat_unspecified_surfaces = l.coat_unspecified_surfaces();
    if (l.has_sensor_width_mm()) h.lens.sensor_width_mm = l.sensor_width_mm();
    if (l.has_sensor_height_mm()) h.lens.sensor_height_mm = l.sensor_height_mm();
    h.lens.prescription_file = l.prescription_file();
    h.lens.prescription_sha256 = l.prescription_sha256();
    h.camera.description = m.camera().description();
    h.camera.serial = m.camera().serial();
    if (m.camera().has_pixel_pitch_um()) h.camera.pixel_pitch_um = m.camera().pixel_pitch_um();
    if (m.camera().has_bit_depth()) {
        const uint32_t depth = m.camera().bit_depth();
        if (depth < 1 || depth > kMaxBitDepth)
            return check.fail("camera.bit_depth", std::to_string(depth) + " is outside 1.." +
                                                      std::to_string(kMaxBitDepth));
        h.camera.bit_depth = static_cast<int>(depth);
    }
    if (m.camera().has_raw_format()) {
        const std::optional<RawFormat> format = parseRawFormat(m.camera().raw_format());
        if (!format)
            return check.fail("camera.raw_format",
                              Checker::quoted(m.camera().raw_format()) +
                                  " is not mono, bayer-rggb, bayer-bggr, bayer-grbg or bayer-gbrg");
        h.camera.raw_format = *format;
    }
    if (m.camera().has_light_power_dn_s())
        h.camera.light_power_dn_s = m.camera().light_power_dn_s();
    const auto& c = m.capture();
    h.capture.from_deg = c.from_deg();
    h.capture.to_deg = c.to_deg();
    h.capture.step_deg = c.step_deg();
    h.capture.roll_deg = c.roll_deg();
    h.capture.exposure_times_s = toVector(c.exposure_times_s());
    if (c.has_gain()) h.capture.gain = c.gain();
    h.capture.width_px = c.width_px();
    h.capture.height_px = c.height_px();
    s.frames.reserve(static_cast<size_t>(m.frames_size()));
    for (const auto& f : m.frames()) s.frames.push_back(frameFromProto(f));
    return s;
}

// `s` must have passed checkSweep.
flarelab::v1::SweepManifest toProto(const Sweep& s) {
    flarelab::v1::SweepManifest m;
    const SweepHeader& h = s.header;
    m.set_format_version(static_cast<uint32_t>(h.format_version));
    m.set_software_version(h.software_version);
    if (!h.created_utc.empty()) {
        const bool parsed = pb::util::TimeUtil::FromString(h.created_utc, m.mutable_created());
        FLARELAB_CHECK(parsed);
    }
    auto* lens = m.mutable_lens();
    lens->set_description(h.lens.description);
    lens->set_serial(h.lens.serial);
    if (h.lens.focal_length_mm) lens->set_focal_length_mm(*h.lens.focal_length_mm);
    if (h.lens.f_number) lens->set_f_number(*h.lens.f_number);
    if (h.lens.aperture_blades)
        lens->set_aperture_blades(static_cast<uint32_t>(*h.lens.aperture_blades));
    if (h.lens.blade_rotation_deg) lens->set_blade_rotation_deg(*h.lens.blade_rotation_deg);
    if (h.lens.stop_semi_aperture_mm)
        lens->set_stop_semi_aperture_mm(*h.lens.stop_semi_aperture_mm);
    if (h.lens.coat_unspecified_surfaces)
        lens->set_coat_unspecified_surfaces(*h.lens.coat_unspecified_surfaces);
    if (h.lens.sensor_width_mm) lens->set_sensor_width_mm(*h.lens.sensor_width_mm);
    if (h.lens.sensor_height_mm) lens->set_sensor_height_mm(*h.lens.sensor_height_mm);
    if (!h.lens.prescription_file.empty()) lens->set_prescription_file(h.lens.prescription_file);
    if (!h.lens.prescription_sha256.empty())
        lens->set_prescription_sha256(h.lens.prescription_sha256);
    auto* camera = m.mutable_camera();
    camera->set_description(h.camera.description);
    camera->set_serial(h.camera.serial);
    if (h.camera.pixel_pitch_um) camera->set_pixel_pitch_um(*h.camera.pixel_pitch_um);
    if (h.camera.bit_depth) camera->set_bit_depth(static_cast<uint32_t>(*h.camera.bit_depth));
    if (h.camera.raw_format)
        camera->set_raw_format(std::string(rawFormatName(*h.camera.raw_format)));
    if (h.camera.light_power_dn_s) camera->set_light_power_dn_s(*h.camera.light_power_dn_s);
    auto* capture = m.mutable_capture();
    capture->set_from_deg(h.capture.from_deg);
    capture->set_to_deg(h.capture.to_deg);
    capture->set_step_deg(h.capture.step_deg);
    capture->set_roll_deg(h.capture.roll_deg);
    for (const double t : h.capture.exposure_times_s) capture->add_exposure_times_s(t);
    if (h.capture.gain) capture->set_gain(*h.capture.gain);
    capture->set_width_px(static_cast<uint32_t>(h.capture.width_px));
    capture->set_height_px(static_cast<uint32_t>(h.capture.height_px));
    for (const SweepFrame& frame : s.frames) frameToProto(frame, m.add_frames());
    return m;
}

// protobuf's JSON syntax errors run over three lines: the complaint, an excerpt of the text and a
// caret under the offending character. One line here: the complaint and the text from the caret.
std::string statusText(const pb::util::Status& status) {
    const std::string text(status.message());
    const size_t first = text.find('\n');
    if (first == std::string::npos) return text;
    const size_t second = text.find('\n', first + 1);
    const std::string excerpt = text.substr(
        first + 1, second == std::string::npos ? std::string::npos : second - first - 1);
    const std::string caret_line = second == std::string::npos ? "" : text.substr(second + 1);
    const size_t caret = caret_line.find('^');
    std::string line = text.substr(0, first);
    if (caret == std::string::npos) return line;
    const std::string near = caret < excerpt.size() ? excerpt.substr(caret, 40) : "";
    line += near.empty() ? " (at the end of the text)" : " (at " + Checker::quoted(near) + ")";
    return line;
}

// protobuf says "(frames[1]) angle_degs: Cannot find field." for an unknown field; this says
// "frames[1].angle_degs: unknown field ...". Other complaints pass through statusText.
std::string describeStrictFailure(const pb::util::Status& status) {
    const std::string text = statusText(status);
    constexpr std::string_view kUnknown = ": Cannot find field.";
    if (!endsWith(text, kUnknown)) return text;
    std::string field = text.substr(0, text.size() - kUnknown.size());
    if (!field.empty() && field.front() == '(') {
        const size_t close = field.find(") ");
        if (close != std::string::npos)
            field = field.substr(1, close - 1) + "." + field.substr(close + 2);
    }
    return field + ": unknown field (a version " + std::to_string(kSweepFormatVersion) +
           " manifest has no such field; new fields come with a new format_version)";
}

// ---------------------------------------------------------------------------------------------
// Files.

Result<std::string> readWholeFile(const std::string& path, int64_t max_bytes) {
    auto file = openRegularFile(path);
    if (!file) return file.error();
    const FileDescriptor& fd = file->fd;
    if (file->size > max_bytes)
        return makeError(ErrorCode::IoError, path + ": " + std::to_string(file->size) +
                                                 " bytes, more than the limit of " +
                                                 std::to_string(max_bytes));
    std::string text(static_cast<size_t>(file->size), '\0');
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t got = ::read(fd.get(), text.data() + done, text.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": read failed: " + osMessage(errno));
        if (got == 0) break;  // shrank while being read
        done += static_cast<size_t>(got);
    }
    text.resize(done);
    return text;
}

// `directory`/`relative` as a path that exists, is a regular file and, symbolic links resolved,
// lies inside `canonical_directory`. `what` names the manifest field for messages.
Result<std::string> resolveFile(const std::string& directory,
                                const fs::path& canonical_directory,
                                const std::string& relative,
                                const std::string& what) {
    const fs::path path = fs::path(directory) / relative;
    const std::string shown = path.string();
    std::error_code ec;
    const fs::file_status status = fs::status(path, ec);
    if (!fs::exists(status))
        return makeError(ErrorCode::NotFound, what + ": " + shown + ": no such file");
    const fs::path resolved = fs::canonical(path, ec);
    if (ec) return makeError(ErrorCode::IoError, what + ": " + shown + ": " + ec.message());
    const fs::path inside = resolved.lexically_relative(canonical_directory);
    if (inside.empty() || *inside.begin() == "..")
        return makeError(ErrorCode::ParseError, what + ": " + shown + " resolves to " +
                                                    resolved.string() +
                                                    ", outside the sweep directory");
    if (!fs::is_regular_file(status))
        return makeError(ErrorCode::ParseError, what + ": " + shown + " is not a regular file");
    // Readers open sweep files without following links (a link may be swapped for anything
    // between this check and the open); the writer never makes one.
    if (fs::is_symlink(fs::symlink_status(path, ec)))
        return makeError(ErrorCode::ParseError,
                         what + ": " + shown + " is a symbolic link; sweep files must be regular " +
                             "files in the sweep directory");
    return shown;
}

// The frame image against frame `index` of the manifest (readSweep's rules).
Status checkFrameImage(const Sweep& s, size_t index, const ExrImage& exr, const std::string& what) {
    const SweepFrame& f = s.frames[index];
    const SweepCapture& capture = s.header.capture;
    const auto fail = [&](const std::string& text) -> Status {
        return makeError(ErrorCode::ParseError, what + ": " + text);
    };
    if (exr.image.width != capture.width_px || exr.image.height != capture.height_px)
        return fail("the image is " + std::to_string(exr.image.width) + "x" +
                    std::to_string(exr.image.height) + " pixels, but capture.width_px x " +
                    "capture.height_px is " + std::to_string(capture.width_px) + "x" +
                    std::to_string(capture.height_px));
    const ExrMetadata& meta = exr.meta;
    const auto number = [](const std::optional<double>& value) {
        return value ? formatDouble(*value) : std::string("absent");
    };
    if (meta.angle_deg != f.angle_deg)
        return fail(std::string("EXR attribute ") + kExrAttrAngle + " (" + number(meta.angle_deg) +
                    ") differs from angle_deg " + formatDouble(f.angle_deg));
    if (meta.roll_deg != capture.roll_deg)
        return fail(std::string("EXR attribute ") + kExrAttrRoll + " (" + number(meta.roll_deg) +
                    ") differs from capture.roll_deg " + formatDouble(capture.roll_deg));
    if (meta.gain != capture.gain)
        return fail(std::string("EXR attribute ") + kExrAttrGain + " (" + number(meta.gain) +
                    ") differs from capture.gain (" + number(capture.gain) + ")");
    if (meta.exposure_times_s != f.exposure_times_s)
        return fail(std::string("EXR attribute ") + kExrAttrExposureTimes + " " +
                    formatTimes(meta.exposure_times_s) + " differs from exposure_times_s " +
                    formatTimes(f.exposure_times_s));
    const std::tuple<const char*, const std::string*, const char*, const std::string*> texts[] = {
        {kExrAttrLens, &meta.lens, "lens.description", &s.header.lens.description},
        {kExrAttrCamera, &meta.camera, "camera.description", &s.header.camera.description},
        {kExrAttrMergeMethod, &meta.merge_method, "merge_method", &f.merge_method}};
    for (const auto& [attribute, value, field, expected] : texts)
        if (*value != *expected)
            return fail(std::string("EXR attribute ") + attribute + " " + Checker::quoted(*value) +
                        " differs from " + field + " " + Checker::quoted(*expected));
    return Ok{};
}

std::string frameContext(const Sweep& s, size_t index) {
    return manifestPath(s.directory) + ": " + indexed("frames", index);
}

// The writer's own files: not frames, not extra.
bool isSweepBookkeeping(std::string_view relative) {
    return relative == kSweepManifestFile || relative == kSweepFrameLogFile ||
           relative == kSweepLockFile;
}

// Looks through `directory` (recursively, without following links) for files the manifest does
// not list: warnings, or for EXR files errors when `exr_is_error`.
Result<std::vector<std::string>> findExtraFiles(const std::string& directory,
                                                const std::set<std::string>& listed,
                                                bool exr_is_error) {
    std::vector<std::string> extra;
    std::error_code ec;
    fs::recursive_directory_iterator it(directory, ec), end;
    for (; !ec && it != end; it.increment(ec)) {
        if (it->is_directory(ec) && !it->is_symlink(ec)) continue;
        const std::string relative = it->path().lexically_relative(directory).generic_string();
        if (isSweepBookkeeping(relative) || listed.count(relative)) continue;
        if (isSweepProduct(relative)) continue;
        extra.push_back(relative);
    }
    if (ec) return makeError(ErrorCode::IoError, directory + ": cannot list: " + ec.message());
    std::sort(extra.begin(), extra.end());
    std::vector<std::string> warnings;
    for (const std::string& relative : extra) {
        const std::string shown = (fs::path(directory) / relative).string();
        if (isTemporaryName(relative)) {
            warnings.push_back(shown + ": temporary file of an interrupted write, not listed in " +
                               kSweepManifestFile + "; safe to remove");
        } else if (hasExrExtension(relative)) {
            const std::string text = shown + ": EXR file not listed in " +
                                     std::string(kSweepManifestFile) +
                                     " (a frame of an interrupted write, or of another sweep)";
            if (exr_is_error) return makeError(ErrorCode::ParseError, text);
            warnings.push_back(text);
        } else {
            warnings.push_back(shown + ": not listed in " + std::string(kSweepManifestFile));
        }
    }
    return warnings;
}

// EXR files anywhere under `directory` (the writer refuses to mix sweeps).
std::optional<std::string> findAnyExr(const std::string& directory) {
    std::error_code ec;
    fs::recursive_directory_iterator it(directory, ec), end;
    for (; !ec && it != end; it.increment(ec))
        if (hasExrExtension(it->path().filename().string())) return it->path().string();
    return std::nullopt;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Manifest text.

Result<Sweep> parseSweepManifest(std::string_view json, const std::string& name) {
    pb::util::JsonParseOptions parse_options;
    parse_options.ignore_unknown_fields = false;
    const pb::StringPiece text(json.data(), json.size());
    flarelab::v1::SweepManifest manifest;
    const auto strict = pb::util::JsonStringToMessage(text, &manifest, parse_options);
    // The version decides which rules apply, so it is looked at first: a later version may add
    // fields, and its reader should hear "unsupported version", not "unknown field". The strict
    // parse comes first all the same, and the loose one (a whole JSON tree) only when it fails, so
    // that a large manifest is not held in memory twice.
    std::optional<pb::Value> version;
    if (strict.ok()) {
        pb::Value v;
        v.set_number_value(manifest.format_version());
        version = v;
    } else {
        pb::Struct loose;
        if (auto status = pb::util::JsonStringToMessage(text, &loose, parse_options); !status.ok())
            return makeError(ErrorCode::ParseError,
                             name + ": not a valid JSON object: " + statusText(status));
        const auto& fields = loose.fields();
        auto found = fields.find("format_version");
        if (found == fields.end()) found = fields.find("formatVersion");
        if (found != fields.end()) version = found->second;
    }
    if (!version || (strict.ok() && manifest.format_version() == 0))
        return makeError(ErrorCode::ParseError, name + ": format_version: missing");
    const pb::Value& value = *version;
    // protobuf JSON allows integers as numbers or as strings ("1").
    bool known = false;
    for (int v = kSweepOldestFormatVersion; v <= kSweepFormatVersion; ++v)
        known = known ||
                (value.kind_case() == pb::Value::kNumberValue && value.number_value() == v) ||
                (value.kind_case() == pb::Value::kStringValue &&
                 value.string_value() == std::to_string(v));
    if (!known) {
        std::string shown = "a value that is not a number";
        if (value.kind_case() == pb::Value::kNumberValue)
            shown = formatDouble(value.number_value());
        if (value.kind_case() == pb::Value::kStringValue)
            shown = Checker::quoted(value.string_value());
        return makeError(ErrorCode::Unsupported, name + ": format_version: " + shown +
                                                     " is not a version this reader knows (" +
                                                     std::to_string(kSweepOldestFormatVersion) +
                                                     ".." + std::to_string(kSweepFormatVersion) +
                                                     ")");
    }
    if (!strict.ok())
        return makeError(ErrorCode::ParseError, name + ": " + describeStrictFailure(strict));
    const Checker check(ErrorCode::ParseError, name);
    auto sweep = fromProto(manifest, check);
    if (!sweep) return sweep.error();
    if (auto ok = checkSweep(*sweep, check); !ok) return ok.error();
    return sweep;
}

Result<std::string> formatSweepManifest(const Sweep& sweep) {
    const Checker check(ErrorCode::InvalidArgument, sweep.directory.empty()
                                                        ? std::string("sweep manifest")
                                                        : manifestPath(sweep.directory));
    if (auto ok = checkSweep(sweep, check); !ok) return ok.error();
    // The header indented for people, then one frame per line: a frame indented field by field
    // takes three times the bytes, and a sweep may have 100000 of them.
    pb::util::JsonPrintOptions print_options;
    print_options.add_whitespace = true;
    print_options.always_print_primitive_fields = true;
    print_options.preserve_proto_field_names = true;
    Sweep header_only;
    header_only.header = sweep.header;
    std::string json;
    if (auto status = pb::util::MessageToJsonString(toProto(header_only), &json, print_options);
        !status.ok())
        return makeError(ErrorCode::Internal,
                         "cannot print the sweep manifest: " + statusText(status));
    // Strings are escaped in JSON, so the key with its empty list appears once, as the key.
    constexpr std::string_view kEmptyFrames = "\"frames\": []";
    const size_t at = json.find(kEmptyFrames);
    FLARELAB_CHECK(at != std::string::npos);
    std::string frames = "\"frames\": [";
    print_options.add_whitespace = false;
    for (size_t i = 0; i < sweep.frames.size(); ++i) {
        flarelab::v1::Frame f;
        frameToProto(sweep.frames[i], &f);
        std::string line;
        if (auto status = pb::util::MessageToJsonString(f, &line, print_options); !status.ok())
            return makeError(ErrorCode::Internal,
                             "cannot print frame " + std::to_string(i) + ": " + statusText(status));
        frames += (i ? ",\n  " : "\n  ") + line;
    }
    frames += sweep.frames.empty() ? "]" : "\n ]";
    json.replace(at, kEmptyFrames.size(), frames);
    return json;
}

// ---------------------------------------------------------------------------------------------
// The frame log.

namespace {

uint32_t crc32Of(std::string_view bytes) {
    uLong crc = ::crc32(0L, Z_NULL, 0);
    // zlib takes lengths as uInt; a record is at most kSweepMaxLogRecordBytes.
    crc =
        ::crc32(crc, reinterpret_cast<const Bytef*>(bytes.data()), static_cast<uInt>(bytes.size()));
    return static_cast<uint32_t>(crc);
}

void putLittle32(std::string& out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}

uint32_t getLittle32(std::string_view bytes, size_t at) {
    uint32_t v = 0;
    for (int i = 0; i < 4; ++i)
        v |= static_cast<uint32_t>(static_cast<unsigned char>(bytes[at + i])) << (8 * i);
    return v;
}

// The frames of the manifest `sweep` followed by those of `log` (rules at the top of sweep.h);
// `name` is the log's path. A torn tail becomes a warning.
Status applyFrameLog(Sweep& sweep, const SweepFrameLog& log, const std::string& name) {
    const Checker check(ErrorCode::ParseError, name);
    std::set<std::string> files;
    for (size_t i = 0; i < sweep.frames.size(); ++i)
        if (auto ok = checkUnique(sweep.frames[i], i, files, check); !ok) return ok;
    for (size_t r = 0; r < log.records.size(); ++r) {
        const auto& [index, frame] = log.records[r];
        const size_t have = sweep.frames.size();
        const std::string at =
            "record " + std::to_string(r) + " (frame " + std::to_string(index) + ")";
        if (index < have) {
            if (!(sweep.frames[index] == frame))
                return check.fail(
                    at, "differs from the manifest's frames[" + std::to_string(index) + "]");
            continue;
        }
        if (index > have)
            return check.fail(
                at, "leaves a gap: the sweep lists " + std::to_string(have) + " frames before it");
        if (auto ok =
                checkFrame(sweep.header, frame, have, have ? &sweep.frames.back() : nullptr, check);
            !ok)
            return ok;
        if (auto ok = checkUnique(frame, have, files, check); !ok) return ok;
        sweep.frames.push_back(frame);
    }
    if (log.torn_bytes > 0)
        sweep.warnings.push_back(name + ": the last " + std::to_string(log.torn_bytes) +
                                 " bytes (from byte " + std::to_string(log.valid_bytes) + ", " +
                                 log.torn +
                                 ") are a record cut short by an interrupted write; ignored");
    return Ok{};
}

}  // namespace

Result<SweepFrameLog> parseSweepFrameLog(std::string_view bytes, const std::string& name) {
    SweepFrameLog log;
    const std::string_view magic = kSweepFrameLogMagic;
    if (bytes.size() < magic.size()) {
        // A log cut short while it was created.
        if (bytes != magic.substr(0, bytes.size()))
            return makeError(ErrorCode::ParseError, name + ": not a flarelab frame log");
        log.torn_bytes = static_cast<int64_t>(bytes.size());
        if (!bytes.empty()) log.torn = "an unfinished header";
        return log;
    }
    if (bytes.substr(0, magic.size()) != magic)
        return makeError(ErrorCode::ParseError,
                         name + ": not a flarelab frame log (it does not start with \"" +
                             std::string(magic.substr(0, magic.size() - 1)) + "\")");
    size_t at = magic.size();
    const auto torn = [&](const std::string& why) {
        log.torn_bytes = static_cast<int64_t>(bytes.size() - at);
        log.torn = why;
    };
    while (at < bytes.size()) {
        if (bytes.size() - at < 8) {
            torn("a record header of " + std::to_string(bytes.size() - at) + " of 8 bytes");
            break;
        }
        const uint32_t length = getLittle32(bytes, at);
        const uint32_t crc = getLittle32(bytes, at + 4);
        if (length == 0 || length > kSweepMaxLogRecordBytes) {
            torn("a record declaring " + std::to_string(length) + " bytes, outside 1.." +
                 std::to_string(kSweepMaxLogRecordBytes));
            break;
        }
        if (length > bytes.size() - at - 8) {
            torn("a record of " + std::to_string(length) + " bytes with " +
                 std::to_string(bytes.size() - at - 8) + " left in the file");
            break;
        }
        const std::string_view payload = bytes.substr(at + 8, length);
        if (crc32Of(payload) != crc) {
            torn("a record whose checksum does not match");
            break;
        }
        flarelab::v1::FrameLogRecord record;
        if (!record.ParseFromArray(payload.data(), static_cast<int>(payload.size())))
            return makeError(ErrorCode::ParseError,
                             name + ": the record at byte " + std::to_string(at) +
                                 " passes its checksum but is not a frame record");
        log.records.push_back({record.index(), frameFromProto(record.frame())});
        at += 8 + length;
    }
    log.valid_bytes = static_cast<int64_t>(at);
    return log;
}

std::string formatSweepFrameLogRecord(uint64_t index, const SweepFrame& frame) {
    flarelab::v1::FrameLogRecord record;
    record.set_index(index);
    frameToProto(frame, record.mutable_frame());
    const std::string payload = record.SerializeAsString();
    std::string out;
    out.reserve(payload.size() + 8);
    putLittle32(out, static_cast<uint32_t>(payload.size()));
    putLittle32(out, crc32Of(payload));
    out += payload;
    return out;
}

namespace {

// The frame list of the sweep in `directory`, and what its log holds (nullopt without a log).
struct ListedSweep {
    Sweep sweep;
    std::optional<SweepFrameLog> log;
    size_t manifest_frames = 0;
};

Result<ListedSweep> readListing(const std::string& directory) {
    const std::string path = manifestPath(directory);
    auto text = readWholeFile(path, kSweepMaxManifestBytes);
    if (!text) return text.error();
    auto sweep = parseSweepManifest(*text, path);
    if (!sweep) return sweep.error();
    ListedSweep out;
    out.sweep = std::move(*sweep);
    out.sweep.directory = directory;
    out.manifest_frames = out.sweep.frames.size();
    // A version 1 manifest lists every frame; a log beside it is not its own (an extra file).
    if (out.sweep.header.format_version < 2) return out;
    const std::string log_path = (fs::path(directory) / kSweepFrameLogFile).string();
    auto bytes = readWholeFile(log_path, kSweepMaxManifestBytes);
    if (!bytes && bytes.error().code == ErrorCode::NotFound) return out;  // compacted
    if (!bytes) return bytes.error();
    auto log = parseSweepFrameLog(*bytes, log_path);
    if (!log) return log.error();
    if (auto ok = applyFrameLog(out.sweep, *log, log_path); !ok) return ok.error();
    out.log = std::move(*log);
    return out;
}

}  // namespace

Result<Sweep> readSweepManifest(const std::string& directory) {
    auto listed = readListing(directory);
    if (!listed) return listed.error();
    return std::move(listed->sweep);
}

Result<Sweep> readSweep(const std::string& directory, const ReadSweepOptions& options) {
    auto sweep = readSweepManifest(directory);
    if (!sweep) return sweep.error();
    std::error_code ec;
    const fs::path canonical_directory = fs::canonical(directory, ec);
    if (ec) return makeError(ErrorCode::IoError, directory + ": " + ec.message());

    std::set<std::string> listed;
    for (size_t i = 0; i < sweep->frames.size(); ++i) {
        const SweepFrame& f = sweep->frames[i];
        const std::string context = frameContext(*sweep, i);
        for (size_t r = 0; r < f.raw_files.size(); ++r) {
            auto raw = resolveFile(directory, canonical_directory, f.raw_files[r],
                                   context + "." + indexed("raw_files", r));
            if (!raw) return raw.error();
            listed.insert(f.raw_files[r]);
        }
        auto frame = loadFrame(*sweep, i, options.exr);
        if (!frame) return frame.error();
        listed.insert(f.exr_file);
    }
    auto warnings = findExtraFiles(directory, listed, options.extra_exr_files_are_errors);
    if (!warnings) return warnings.error();
    if (sweep->header.format_version < 2 &&
        fs::exists(fs::symlink_status(fs::path(directory) / kSweepFrameLogFile, ec)))
        warnings->push_back((fs::path(directory) / kSweepFrameLogFile).string() +
                            ": a frame log beside a version 1 manifest, which has none; ignored");
    sweep->warnings.insert(sweep->warnings.end(), warnings->begin(), warnings->end());
    return sweep;
}

Result<ExrImage> loadFrame(const Sweep& sweep, size_t index, const ExrReadOptions& options) {
    FLARELAB_CHECK_LT(index, sweep.frames.size());
    const std::string context = frameContext(sweep, index);
    std::error_code ec;
    const fs::path canonical_directory = fs::canonical(sweep.directory, ec);
    if (ec) return makeError(ErrorCode::IoError, sweep.directory + ": " + ec.message());
    auto path = resolveFile(sweep.directory, canonical_directory, sweep.frames[index].exr_file,
                            context + ".exr_file");
    if (!path) return path.error();
    // The manifest knows the frame's size: a header that declares another is refused before
    // anything is allocated for it.
    ExrReadOptions sized = options;
    sized.expected_width_px = sweep.header.capture.width_px;
    sized.expected_height_px = sweep.header.capture.height_px;
    auto exr = readExr(*path, sized);
    if (!exr) return exr.error().withContext(context + ".exr_file");
    if (auto ok = checkFrameImage(sweep, index, *exr, context + ".exr_file: " + *path); !ok)
        return ok.error();
    return exr;
}

bool isSweepProduct(std::string_view relative) {
    const std::string_view previews = kSweepPreviewsDir;
    if (relative.size() > previews.size() && relative.substr(0, previews.size()) == previews &&
        relative[previews.size()] == '/')
        return true;
    return relative == kSweepModelFile || relative == kSweepModelText;
}

std::string sweepFrameFileName(size_t index, double angle_deg) {
    char name[96];
    std::snprintf(name, sizeof(name), "frame_%05zu_%+.4fdeg.exr", index, angle_deg);
    return name;
}

ClippedFrames clippedFrames(const Sweep& sweep, double fraction) {
    ClippedFrames c;
    c.fraction = fraction;
    const double samples = static_cast<double>(sweep.header.capture.width_px) *
                           static_cast<double>(sweep.header.capture.height_px);
    if (!(samples > 0.0)) return c;
    for (const SweepFrame& f : sweep.frames) {
        if (f.brackets.empty()) continue;
        ++c.with_stats;
        const auto shortest = std::min_element(
            f.brackets.begin(), f.brackets.end(),
            [](const auto& a, const auto& b) { return a.exposure_s < b.exposure_s; });
        const double clipped = static_cast<double>(shortest->samples_clipped) / samples;
        if (clipped > fraction) ++c.frames;
        if (clipped > c.worst_fraction) {
            c.worst_fraction = clipped;
            c.worst_angle_deg = f.angle_deg;
            c.shortest_exposure_s = shortest->exposure_s;
        }
    }
    return c;
}

std::string clippingWarning(const ClippedFrames& clipped, size_t total_frames) {
    if (clipped.frames == 0) return {};
    char text[400];
    std::snprintf(text, sizeof(text),
                  "%zu of %zu frames have more than %.3g%% of their samples saturated in the "
                  "shortest exposure (worst %.1f%% at %.4g deg, %.4g s): there the merged "
                  "radiance is only a lower bound and ghosts under it cannot be fitted; capture "
                  "again with shorter --brackets",
                  clipped.frames, total_frames, 100.0 * clipped.fraction,
                  100.0 * clipped.worst_fraction, clipped.worst_angle_deg,
                  clipped.shortest_exposure_s);
    return text;
}

// ---------------------------------------------------------------------------------------------
// SweepWriter.

namespace {

// Creates `directory` and its missing parents, flushing each new name into its parent.
Status makeDirectoryDurably(const fs::path& directory) {
    std::vector<fs::path> missing;
    std::error_code ec;
    for (fs::path p = directory; !p.empty() && !fs::exists(fs::symlink_status(p, ec));
         p = p.parent_path()) {
        missing.push_back(p);
        if (p == p.parent_path()) break;
    }
    if (missing.empty()) return Ok{};
    fs::create_directories(directory, ec);
    if (ec)
        return makeError(ErrorCode::IoError,
                         directory.string() + ": cannot create: " + ec.message());
    for (auto it = missing.rbegin(); it != missing.rend(); ++it)
        if (Status ok = syncDirectory(it->parent_path().string()); !ok) return ok;
    return Ok{};
}

// Why no file of `frame` may be added to a sweep that lists `files`; Ok when none.
Status checkNewNames(const SweepFrame& frame,
                     size_t index,
                     const std::set<std::string>& files,
                     const Checker& check) {
    std::set<std::string> own;
    const std::string at = indexed("frames", index) + ".";
    std::vector<std::pair<std::string, const std::string*>> named{
        {at + "exr_file", &frame.exr_file}};
    for (size_t i = 0; i < frame.raw_files.size(); ++i)
        named.emplace_back(at + indexed("raw_files", i), &frame.raw_files[i]);
    for (const auto& [field, file] : named) {
        if (isSweepBookkeeping(*file))
            return check.fail(field, "names the sweep's own " + Checker::quoted(*file));
        if (files.count(*file) || !own.insert(*file).second)
            return check.fail(field, Checker::quoted(*file) + " is named twice in the manifest");
    }
    return Ok{};
}

// (device, inode) of `path`, following links; nullopt when it cannot be examined.
std::optional<std::pair<dev_t, ino_t>> identity(const fs::path& path) {
    struct stat info {};
    if (::stat(path.c_str(), &info) != 0) return std::nullopt;
    return std::pair{info.st_dev, info.st_ino};
}

// Moves the file `from` to `to` (which must not exist). One rename that never replaces on the
// same file system; across file systems a copy, flushed, then the original unlinked, so that a
// crash leaves the file in one place or both, never in neither. Both directories are flushed.
Status moveAside(const fs::path& from, const fs::path& to) {
    const auto fail = [&](const std::string& what, int error) -> Status {
        return makeError(ErrorCode::IoError, from.string() + ": cannot move it aside to " +
                                                 to.string() + ": " + what +
                                                 (error ? ": " + osMessage(error) : ""));
    };
    if (::renameat2(AT_FDCWD, from.c_str(), AT_FDCWD, to.c_str(), RENAME_NOREPLACE) == 0) {
        if (Status ok = syncDirectory(to.parent_path().string()); !ok) return ok;
        return syncDirectory(from.parent_path().string());
    }
    if (errno == EEXIST) return fail("the target exists (it is not overwritten)", 0);
    if (errno != EXDEV) return fail("rename failed", errno);
    struct stat info {};
    if (::lstat(from.c_str(), &info) != 0) return fail("cannot examine it", errno);
    if (S_ISLNK(info.st_mode)) {
        std::error_code ec;
        const fs::path target = fs::read_symlink(from, ec);
        if (ec) return fail("cannot read the link: " + ec.message(), 0);
        if (::symlink(target.c_str(), to.c_str()) != 0) return fail("cannot copy the link", errno);
    } else if (S_ISREG(info.st_mode)) {
        FileDescriptor in(::open(from.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK));
        if (!in.valid()) return fail("cannot open it", errno);
        FileDescriptor out(
            ::open(to.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0644));
        if (!out.valid()) return fail("cannot create the copy", errno);
        std::vector<char> buffer(size_t{1} << 20);
        for (;;) {
            const ssize_t got = ::read(in.get(), buffer.data(), buffer.size());
            if (got < 0 && errno == EINTR) continue;
            if (got < 0) return fail("cannot read it", errno);
            if (got == 0) break;
            if (const int e = writeAll(out.get(), to.string(), buffer.data(), size_t(got)); e)
                return fail("cannot write the copy", e);
        }
        if (const int e = syncFile(out.get(), to.string()); e != 0)
            return fail("cannot flush the copy to disk (fsync)", e);
        if (const int e = out.close(); e != 0) return fail("cannot close the copy", e);
    } else {
        return fail(std::string("it is ") + fileTypeName(info.st_mode) +
                        ", which cannot be copied to another file system; remove it by hand",
                    0);
    }
    if (Status ok = syncDirectory(to.parent_path().string()); !ok) return ok;
    if (::unlink(from.c_str()) != 0)
        return fail("copied, but the original cannot be removed", errno);
    return syncDirectory(from.parent_path().string());
}

}  // namespace

struct SweepWriter::State {
    FileDescriptor directory{-1};  // flock'ed too: writers of version 1 lock the directory itself
    FileDescriptor lock{-1};       // sweep.lock, flock'ed
    FileDescriptor log{-1};        // frames.log, opened to append
    std::string log_path;
    int64_t log_bytes = 0;        // what the log holds, all whole records
    size_t log_records = 0;       // records since the last compaction
    size_t compact_at = 0;        // log_records that start the next compaction
    std::set<std::string> files;  // every file the sweep lists
    std::string broken;           // why the writer refuses to write
    bool finished = false;
};

SweepWriter::SweepWriter(Sweep sweep, SweepWriteOptions options, std::unique_ptr<State> state)
    : sweep_(std::move(sweep)), options_(std::move(options)), state_(std::move(state)) {}
SweepWriter::SweepWriter(SweepWriter&&) noexcept = default;
SweepWriter& SweepWriter::operator=(SweepWriter&&) noexcept = default;
SweepWriter::~SweepWriter() = default;

const std::string& SweepWriter::broken() const { return state_->broken; }

Error SweepWriter::breakWith(const std::string& why) {
    state_->broken = why;
    return makeError(ErrorCode::IoError,
                     why + "; the sweep writer takes no more frames (a failed flush is never " +
                         "retried: the disk may have dropped what it failed to write)");
}

namespace {

// The sweep's lock file, opened and locked. Refused without being opened when something other
// than a regular file stands in its place.
Result<FileDescriptor> lockSweep(int directory_fd, const std::string& directory) {
    const std::string path = (fs::path(directory) / kSweepLockFile).string();
    struct stat info {};
    if (::fstatat(directory_fd, kSweepLockFile, &info, AT_SYMLINK_NOFOLLOW) == 0 &&
        !S_ISREG(info.st_mode))
        return makeError(ErrorCode::InvalidArgument,
                         path + ": is " + fileTypeName(info.st_mode) +
                             ", not the sweep's lock file; refusing to use the directory");
    FileDescriptor fd(::openat(directory_fd, kSweepLockFile,
                               O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK, 0644));
    if (!fd.valid())
        return makeError(errno == ELOOP ? ErrorCode::InvalidArgument : ErrorCode::IoError,
                         path + ": cannot open the sweep's lock file: " + osMessage(errno));
    if (::fstat(fd.get(), &info) != 0 || !S_ISREG(info.st_mode))
        return makeError(ErrorCode::InvalidArgument,
                         path + ": not a regular file; refusing to use the directory");
    if (::flock(fd.get(), LOCK_EX | LOCK_NB) != 0) {
        const int error = errno;
        return makeError(
            error == EWOULDBLOCK ? ErrorCode::InvalidArgument : ErrorCode::IoError,
            directory + ": " +
                (error == EWOULDBLOCK ? std::string("another sweep writer is using it")
                                      : "cannot lock " + path + ": " + osMessage(error)));
    }
    return fd;
}

// An empty frame log in `directory` (created or cut back to its magic), flushed with its name.
Status resetFrameLog(int directory_fd, const std::string& directory, FileDescriptor& log) {
    const std::string path = (fs::path(directory) / kSweepFrameLogFile).string();
    if (!log.valid()) {
        struct stat info {};
        if (::fstatat(directory_fd, kSweepFrameLogFile, &info, AT_SYMLINK_NOFOLLOW) == 0 &&
            !S_ISREG(info.st_mode))
            return makeError(ErrorCode::InvalidArgument,
                             path + ": is " + fileTypeName(info.st_mode) +
                                 ", not a frame log; refusing to use it");
        log = FileDescriptor(
            ::openat(directory_fd, kSweepFrameLogFile,
                     O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK, 0644));
        if (!log.valid())
            return makeError(ErrorCode::IoError, path + ": cannot open: " + osMessage(errno));
    }
    if (::ftruncate(log.get(), 0) != 0)
        return makeError(ErrorCode::IoError, path + ": cannot truncate: " + osMessage(errno));
    const std::string_view magic = kSweepFrameLogMagic;
    if (const int e = writeAll(log.get(), path, magic.data(), magic.size()); e != 0)
        return makeError(ErrorCode::IoError, path + ": cannot write: " + osMessage(e));
    if (const int e = syncFile(log.get(), path); e != 0)
        return makeError(ErrorCode::IoError,
                         path + ": cannot flush to disk (fsync): " + osMessage(e));
    return syncDirectory(directory);
}

std::string shown(const std::optional<double>& value) {
    return value ? formatDouble(*value) : "absent";
}
std::string shown(const std::optional<int>& value) {
    return value ? std::to_string(*value) : "absent";
}
std::string shown(const std::optional<bool>& value) {
    return value ? (*value ? "true" : "false") : "absent";
}
std::string shown(const std::string& value) { return Checker::quoted(value); }

template <typename T>
void noteDifference(std::string& why, const char* field, const T& was, const T& now) {
    if (why.empty() && !(was == now))
        why = std::string("lens.") + field + ": " + shown(was) + ", the new sweep's " + shown(now);
}

// Why the lens of a sweep being resumed is not the new header's: the first field that differs,
// with both values; empty when none does. A sweep older than version 3 recorded none of that
// version's fields: they are not compared (the new header's are not what its frames were taken
// with, nor known not to be) and the sweep keeps them absent.
std::string lensDifference(const SweepLens& was, const SweepLens& now, int was_version) {
    std::string why;
    noteDifference(why, "description", was.description, now.description);
    noteDifference(why, "serial", was.serial, now.serial);
    noteDifference(why, "focal_length_mm", was.focal_length_mm, now.focal_length_mm);
    noteDifference(why, "f_number", was.f_number, now.f_number);
    if (was_version < 3) return why;
    noteDifference(why, "aperture_blades", was.aperture_blades, now.aperture_blades);
    noteDifference(why, "blade_rotation_deg", was.blade_rotation_deg, now.blade_rotation_deg);
    noteDifference(why, "stop_semi_aperture_mm", was.stop_semi_aperture_mm,
                   now.stop_semi_aperture_mm);
    noteDifference(why, "coat_unspecified_surfaces", was.coat_unspecified_surfaces,
                   now.coat_unspecified_surfaces);
    noteDifference(why, "sensor_width_mm", was.sensor_width_mm, now.sensor_width_mm);
    noteDifference(why, "sensor_height_mm", was.sensor_height_mm, now.sensor_height_mm);
    // The file's bytes, not its name: the same file may be given by another path.
    noteDifference(why, "prescription_sha256", was.prescription_sha256, now.prescription_sha256);
    return why;
}

}  // namespace

Result<SweepWriter> SweepWriter::create(const std::string& directory,
                                        SweepHeader header,
                                        SweepWriteOptions options) {
    const std::string manifest = manifestPath(directory);
    if (header.created_utc.empty())
        header.created_utc = pb::util::TimeUtil::ToString(pb::util::TimeUtil::GetCurrentTime());
    header.format_version = kSweepFormatVersion;
    if (auto ok = checkHeader(header, Checker(ErrorCode::InvalidArgument, manifest)); !ok)
        return ok.error();

    if (Status made = makeDirectoryDurably(directory); !made) return made.error();
    auto state = std::make_unique<State>();
    state->directory =
        FileDescriptor(::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (!state->directory.valid())
        return makeError(ErrorCode::IoError, directory + ": cannot open: " + osMessage(errno));
    const int fd = state->directory.get();
    if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
        const int error = errno;
        return makeError(error == EWOULDBLOCK ? ErrorCode::InvalidArgument : ErrorCode::IoError,
                         directory + ": " +
                             (error == EWOULDBLOCK ? std::string("another sweep writer is using it")
                                                   : "cannot lock: " + osMessage(error)));
    }
    auto lock = lockSweep(fd, directory);
    if (!lock) return lock.error();
    state->lock = std::move(*lock);
    state->log_path = (fs::path(directory) / kSweepFrameLogFile).string();
    state->compact_at = std::max<size_t>(1, options.compact_after_frames);

    struct stat info {};
    const bool has_manifest = ::fstatat(fd, kSweepManifestFile, &info, AT_SYMLINK_NOFOLLOW) == 0;
    if (has_manifest && options.resume) {
        // Under the lock: nobody else writes here now. The header decides whether this is the
        // same sweep before anything is touched.
        auto existing = readListing(directory);
        if (!existing) return existing.error();
        const SweepHeader& old = existing->sweep.header;
        if (const std::string why = lensDifference(old.lens, header.lens, old.format_version);
            !why.empty())
            return makeError(
                ErrorCode::InvalidArgument,
                manifest + ": " + why + "; a different capture, cannot resume this sweep");
        // A sweep older than version 4 did not record the raw format: not compared, left absent.
        SweepCamera camera = header.camera;
        if (old.format_version < 4) camera.raw_format = old.camera.raw_format;
        // Nor, before version 5, the light's power.
        if (old.format_version < 5) camera.light_power_dn_s = old.camera.light_power_dn_s;
        const std::pair<const char*, bool> same[] = {{"camera", old.camera == camera},
                                                     {"capture", old.capture == header.capture}};
        for (const auto& [part, equal] : same)
            if (!equal)
                return makeError(ErrorCode::InvalidArgument,
                                 manifest + ": " + part +
                                     ": differs from the new sweep's; cannot resume this sweep");
        Sweep sweep = std::move(existing->sweep);
        sweep.warnings.clear();
        for (const SweepFrame& f : sweep.frames) {
            state->files.insert(f.exr_file);
            state->files.insert(f.raw_files.begin(), f.raw_files.end());
        }
        // Compacted once now: an older manifest becomes version 4 before any log exists, and
        // a record a crash tore at the end of the log is cut off before anything follows it.
        const bool clean =
            old.format_version == kSweepFormatVersion &&
            (!existing->log || (existing->log->records.empty() && existing->log->torn_bytes == 0));
        SweepWriter writer(std::move(sweep), std::move(options), std::move(state));
        writer.sweep_.header.format_version = kSweepFormatVersion;
        if (!clean) {
            if (Status ok = writer.compact(false); !ok) return ok.error();
        } else if (Status ok = resetFrameLog(fd, directory, writer.state_->log); !ok) {
            return ok.error();
        }
        writer.state_->log_bytes = static_cast<int64_t>(kSweepFrameLogMagic.size());
        return writer;
    }
    if (has_manifest)
        return makeError(ErrorCode::InvalidArgument,
                         manifest + ": the directory already holds a sweep; refusing to " +
                             "overwrite it (resume appends to it)");
    if (auto exr = findAnyExr(directory))
        return makeError(ErrorCode::InvalidArgument,
                         *exr + ": an EXR file without a sweep manifest; refusing to mix a new " +
                             "sweep with it");
    Sweep sweep;
    sweep.directory = directory;
    sweep.header = header;
    auto json = formatSweepManifest(sweep);
    if (!json) return json.error();
    if (auto ok = replaceFile(directory, fd, kSweepManifestFile, *json, {}); !ok) return ok.error();
    if (Status ok = resetFrameLog(fd, directory, state->log); !ok) return ok.error();
    state->log_bytes = static_cast<int64_t>(kSweepFrameLogMagic.size());
    return SweepWriter(std::move(sweep), std::move(options), std::move(state));
}

// Rewrites the manifest with every frame, then empties the frame log (or removes it): the order
// keeps every frame listed at every instant (records the manifest already holds are skipped by
// readers). A failed flush breaks the writer; a failed write (a full disk) leaves the log as it
// was, and the next compaction is tried when the log has doubled.
Status SweepWriter::compact(bool remove_log) {
    State& st = *state_;
    const std::string& directory = sweep_.directory;
    auto json = formatSweepManifest(sweep_);
    if (!json) return json.error();
    const uint64_t failed_flushes = syncFailureCount();
    Status replaced = replaceFile(directory, st.directory.get(), kSweepManifestFile, *json,
                                  options_.before_manifest_replaced);
    if (!replaced) {
        if (syncFailureCount() != failed_flushes) return breakWith(replaced.error().message);
        st.compact_at = std::max<size_t>(st.compact_at, 2 * st.log_records);
        return replaced;
    }
    if (remove_log) {
        st.log = FileDescriptor(-1);
        if (::unlink(st.log_path.c_str()) != 0 && errno != ENOENT)
            return breakWith(st.log_path +
                             ": cannot remove the compacted log: " + osMessage(errno));
        if (Status ok = syncDirectory(directory); !ok) return breakWith(ok.error().message);
    } else if (Status ok = resetFrameLog(st.directory.get(), directory, st.log); !ok) {
        return breakWith(ok.error().message);
    }
    st.log_bytes = static_cast<int64_t>(kSweepFrameLogMagic.size());
    st.log_records = 0;
    st.compact_at = std::max<size_t>(1, options_.compact_after_frames);
    return Ok{};
}

Result<SweepFrame> SweepWriter::addFrame(const ImageRGB& image,
                                         SweepFrame frame,
                                         const ExrStandardAttributes& standard,
                                         std::span<const uint8_t> lower_bound) {
    State& st = *state_;
    const std::string& directory = sweep_.directory;
    const std::string manifest = manifestPath(directory);
    const size_t index = sweep_.frames.size();
    if (!st.broken.empty())
        return makeError(ErrorCode::IoError,
                         directory + ": the sweep writer is closed: " + st.broken);
    if (st.finished)
        return makeError(ErrorCode::InvalidArgument,
                         directory + ": the sweep is finished; resume it to add frames");
    if (frame.exr_file.empty()) frame.exr_file = sweepFrameFileName(index, frame.angle_deg);

    const Checker check(ErrorCode::InvalidArgument, manifest);
    if (auto ok =
            checkFrame(sweep_.header, frame, index, index ? &sweep_.frames.back() : nullptr, check);
        !ok)
        return ok.error();
    if (auto ok = checkNewNames(frame, index, st.files, check); !ok) return ok.error();
    const SweepCapture& capture = sweep_.header.capture;
    if (image.width != capture.width_px || image.height != capture.height_px)
        return check.fail(indexed("frames", index),
                          "the image is " + std::to_string(image.width) + "x" +
                              std::to_string(image.height) + " pixels, but capture.width_px x " +
                              "capture.height_px is " + std::to_string(capture.width_px) + "x" +
                              std::to_string(capture.height_px));

    std::error_code ec;
    const fs::path canonical_directory = fs::canonical(directory, ec);
    if (ec) return makeError(ErrorCode::IoError, directory + ": " + ec.message());
    const std::string context = manifest + ": " + indexed("frames", index);
    for (size_t r = 0; r < frame.raw_files.size(); ++r)
        if (auto raw = resolveFile(directory, canonical_directory, frame.raw_files[r],
                                   context + "." + indexed("raw_files", r));
            !raw)
            return raw.error();
    const std::string path = (fs::path(directory) / frame.exr_file).string();
    struct stat info {};
    if (::lstat(path.c_str(), &info) == 0)
        return makeError(ErrorCode::InvalidArgument,
                         context + ".exr_file: " + path +
                             " already exists; refusing to overwrite it (move it aside if it " +
                             "is the unlisted frame of an interrupted write)");
    // A folder of exr_file may be a link; the frame must still land inside the sweep, and no
    // folder is made outside it.
    const fs::path parent = fs::path(path).parent_path();
    const fs::path inside =
        fs::weakly_canonical(parent, ec).lexically_relative(canonical_directory);
    if (ec || (!inside.empty() && *inside.begin() == ".."))
        return makeError(ErrorCode::InvalidArgument,
                         context + ".exr_file: " + path + " lies outside the sweep directory");
    const uint64_t failed_flushes = syncFailureCount();
    if (Status made = makeDirectoryDurably(parent); !made) {
        if (syncFailureCount() != failed_flushes) return breakWith(made.error().message);
        return made.error();
    }

    ExrMetadata meta;
    meta.angle_deg = frame.angle_deg;
    meta.roll_deg = capture.roll_deg;
    meta.exposure_times_s = frame.exposure_times_s;
    meta.gain = capture.gain;
    meta.camera = sweep_.header.camera.description;
    meta.lens = sweep_.header.lens.description;
    meta.merge_method = frame.merge_method;
    meta.software_version = sweep_.header.software_version;
    meta.standard = standard;
    if (!meta.standard.aperture && sweep_.header.lens.f_number)
        meta.standard.aperture = *sweep_.header.lens.f_number;
    if (!meta.standard.exp_time_s) meta.standard.exp_time_s = 1.0;
    if (auto written = writeExr(path, image, meta, options_.exr, lower_bound); !written) {
        // A failed flush is final; a failed write (a full disk) left nothing behind.
        if (syncFailureCount() != failed_flushes)
            return breakWith(context + ": " + written.error().message);
        return written.error().withContext(context);
    }
    if (options_.after_frame_written) options_.after_frame_written();

    // The EXR and its name are on disk: now the record that lists it.
    const std::string record = formatSweepFrameLogRecord(index, frame);
    if (const int e = writeAll(st.log.get(), st.log_path, record.data(), record.size()); e != 0) {
        // Part of the record may have reached the file: cut it off, or nothing may follow it.
        if (::ftruncate(st.log.get(), st.log_bytes) != 0)
            return breakWith(st.log_path + ": cannot append frame " + std::to_string(index) + " (" +
                             osMessage(e) +
                             ") nor cut the partial record off: " + osMessage(errno));
        ::unlink(path.c_str());  // ours, and not listed: the sweep stays as it was
        return makeError(ErrorCode::IoError,
                         st.log_path + ": cannot append frame " + std::to_string(index) + ": " +
                             osMessage(e) + "; the frame is not listed and its EXR was removed");
    }
    if (const int e = syncFile(st.log.get(), st.log_path); e != 0)
        return breakWith(st.log_path + ": cannot flush frame " + std::to_string(index) +
                         " to disk (fsync): " + osMessage(e) +
                         "; whether it is listed after a crash is unknown");
    st.log_bytes += static_cast<int64_t>(record.size());
    ++st.log_records;
    st.files.insert(frame.exr_file);
    st.files.insert(frame.raw_files.begin(), frame.raw_files.end());
    sweep_.frames.push_back(frame);

    // Compacted when the log is as long as the manifest: each compaction writes at most twice
    // what the log did since the last one, so bytes written stay linear in the frames.
    const size_t in_manifest = sweep_.frames.size() - st.log_records;
    if (st.log_records >= std::max(st.compact_at, in_manifest))
        if (Status ok = compact(false); !ok && !st.broken.empty())
            return makeError(ErrorCode::IoError,
                             context + ": the frame is written and listed in the frame log, " +
                                 "but compacting the manifest failed: " + ok.error().message);
    return frame;
}

Status SweepWriter::finish() {
    State& st = *state_;
    if (!st.broken.empty())
        return makeError(ErrorCode::IoError,
                         sweep_.directory + ": the sweep writer is closed: " + st.broken);
    if (st.finished) return Ok{};
    if (st.log_records > 0) {
        if (Status ok = compact(true); !ok) return ok;
    } else {
        // The manifest lists every frame already (an empty log follows a compaction).
        st.log = FileDescriptor(-1);
        if (::unlink(st.log_path.c_str()) != 0 && errno != ENOENT)
            return breakWith(st.log_path + ": cannot remove the empty log: " + osMessage(errno));
        if (Status ok = syncDirectory(sweep_.directory); !ok) return breakWith(ok.error().message);
    }
    st.finished = true;
    return Ok{};
}

Result<std::vector<std::string>> SweepWriter::setAsideUnlisted(const std::string& to) {
    State& st = *state_;
    const std::string& directory = sweep_.directory;
    if (!st.broken.empty())
        return makeError(ErrorCode::IoError,
                         directory + ": the sweep writer is closed: " + st.broken);
    // `to` may not lie inside the sweep: a path string can hide that (links, "//", bind mounts),
    // the identity of each folder on the way up cannot.
    const auto self = identity(directory);
    if (!self) return makeError(ErrorCode::IoError, directory + ": cannot examine it");
    std::error_code ec;
    for (fs::path p = fs::absolute(to, ec); !p.empty(); p = p.parent_path()) {
        if (identity(p) == self)
            return makeError(ErrorCode::InvalidArgument, to + ": lies inside the sweep directory " +
                                                             directory +
                                                             "; files are set aside outside it");
        if (p == p.parent_path()) break;
    }
    std::vector<std::string> extra;
    for (fs::recursive_directory_iterator it(directory, ec), end; !ec && it != end;
         it.increment(ec)) {
        if (it->is_directory(ec) && !it->is_symlink(ec)) continue;
        const std::string relative = it->path().lexically_relative(directory).generic_string();
        if (isSweepBookkeeping(relative) || st.files.count(relative) || isSweepProduct(relative))
            continue;
        extra.push_back(relative);
    }
    if (ec) return makeError(ErrorCode::IoError, directory + ": cannot list: " + ec.message());
    std::sort(extra.begin(), extra.end());
    std::vector<std::string> moved;
    for (const std::string& relative : extra) {
        const fs::path target = fs::path(to) / relative;
        if (Status made = makeDirectoryDurably(target.parent_path()); !made) return made.error();
        if (Status ok = moveAside(fs::path(directory) / relative, target); !ok) return ok.error();
        moved.push_back(relative);
    }
    return moved;
}

}  // namespace flarelab::hdr
