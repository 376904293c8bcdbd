#include "hdr/sweep.h"

#include <fcntl.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <set>
#include <system_error>
#include <tuple>
#include <utility>

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
// The rules of format version 1 (sweep.h), on the plain structs. Parsing reports a broken rule as
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

Status checkHeader(const SweepHeader& h, const Checker& check) {
    if (h.format_version != kSweepFormatVersion)
        return check.fail("format_version", std::to_string(h.format_version) +
                                                " is not the version this writer writes (" +
                                                std::to_string(kSweepFormatVersion) + ")");
    if (auto ok = check.text("software_version", h.software_version); !ok) return ok;
    if (!h.created_utc.empty()) {
        pb::Timestamp stamp;
        if (!pb::util::TimeUtil::FromString(h.created_utc, &stamp))
            return check.fail("created", Checker::quoted(h.created_utc) +
                                             " is not an RFC 3339 time (2026-11-29T07:04:02Z)");
    }
    const SweepLens& lens = h.lens;
    if (auto ok = check.text("lens.description", lens.description); !ok) return ok;
    if (auto ok = check.text("lens.serial", lens.serial); !ok) return ok;
    if (auto ok = check.positive("lens.focal_length_mm", lens.focal_length_mm); !ok) return ok;
    if (auto ok = check.positive("lens.f_number", lens.f_number); !ok) return ok;
    const SweepCamera& camera = h.camera;
    if (auto ok = check.text("camera.description", camera.description); !ok) return ok;
    if (auto ok = check.text("camera.serial", camera.serial); !ok) return ok;
    if (auto ok = check.positive("camera.pixel_pitch_um", camera.pixel_pitch_um); !ok) return ok;
    if (camera.bit_depth && (*camera.bit_depth < 1 || *camera.bit_depth > kMaxBitDepth))
        return check.fail("camera.bit_depth", std::to_string(*camera.bit_depth) +
                                                  " is outside 1.." + std::to_string(kMaxBitDepth));
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
    for (const auto& f : m.frames()) {
        SweepFrame frame;
        frame.angle_deg = f.angle_deg();
        frame.exr_file = f.exr_file();
        frame.exposure_times_s = toVector(f.exposure_times_s());
        frame.raw_files.assign(f.raw_files().begin(), f.raw_files().end());
        frame.merge_method = f.merge_method();
        for (const auto& b : f.brackets())
            frame.brackets.push_back({b.exposure_s(), b.samples_used(), b.samples_clipped()});
        s.frames.push_back(std::move(frame));
    }
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
    auto* camera = m.mutable_camera();
    camera->set_description(h.camera.description);
    camera->set_serial(h.camera.serial);
    if (h.camera.pixel_pitch_um) camera->set_pixel_pitch_um(*h.camera.pixel_pitch_um);
    if (h.camera.bit_depth) camera->set_bit_depth(static_cast<uint32_t>(*h.camera.bit_depth));
    auto* capture = m.mutable_capture();
    capture->set_from_deg(h.capture.from_deg);
    capture->set_to_deg(h.capture.to_deg);
    capture->set_step_deg(h.capture.step_deg);
    capture->set_roll_deg(h.capture.roll_deg);
    for (const double t : h.capture.exposure_times_s) capture->add_exposure_times_s(t);
    if (h.capture.gain) capture->set_gain(*h.capture.gain);
    capture->set_width_px(static_cast<uint32_t>(h.capture.width_px));
    capture->set_height_px(static_cast<uint32_t>(h.capture.height_px));
    for (const SweepFrame& frame : s.frames) {
        auto* f = m.add_frames();
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
        if (relative == kSweepManifestFile || listed.count(relative)) continue;
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
    // Look at format_version before the strict parse: a later version may add fields, and its
    // reader should hear "unsupported version", not "unknown field".
    pb::Struct loose;
    pb::util::JsonParseOptions parse_options;
    parse_options.ignore_unknown_fields = false;
    const pb::StringPiece text(json.data(), json.size());
    if (auto status = pb::util::JsonStringToMessage(text, &loose, parse_options); !status.ok())
        return makeError(ErrorCode::ParseError,
                         name + ": not a valid JSON object: " + statusText(status));
    const auto& fields = loose.fields();
    auto version = fields.find("format_version");
    if (version == fields.end()) version = fields.find("formatVersion");
    if (version == fields.end())
        return makeError(ErrorCode::ParseError, name + ": format_version: missing");
    const pb::Value& value = version->second;
    // protobuf JSON allows integers as numbers or as strings ("1").
    const bool known = (value.kind_case() == pb::Value::kNumberValue &&
                        value.number_value() == kSweepFormatVersion) ||
                       (value.kind_case() == pb::Value::kStringValue &&
                        value.string_value() == std::to_string(kSweepFormatVersion));
    if (!known) {
        std::string shown = "a value that is not a number";
        if (value.kind_case() == pb::Value::kNumberValue)
            shown = formatDouble(value.number_value());
        if (value.kind_case() == pb::Value::kStringValue)
            shown = Checker::quoted(value.string_value());
        return makeError(ErrorCode::Unsupported, name + ": format_version: " + shown +
                                                     " is not a version this reader knows (" +
                                                     std::to_string(kSweepFormatVersion) + ")");
    }

    flarelab::v1::SweepManifest manifest;
    if (auto status = pb::util::JsonStringToMessage(text, &manifest, parse_options); !status.ok())
        return makeError(ErrorCode::ParseError, name + ": " + describeStrictFailure(status));
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
    pb::util::JsonPrintOptions print_options;
    print_options.add_whitespace = true;
    print_options.always_print_primitive_fields = true;
    print_options.preserve_proto_field_names = true;
    std::string json;
    if (auto status = pb::util::MessageToJsonString(toProto(sweep), &json, print_options);
        !status.ok())
        return makeError(ErrorCode::Internal,
                         "cannot print the sweep manifest: " + statusText(status));
    return json;
}

Result<Sweep> readSweepManifest(const std::string& directory) {
    const std::string path = manifestPath(directory);
    auto text = readWholeFile(path, kSweepMaxManifestBytes);
    if (!text) return text.error();
    auto sweep = parseSweepManifest(*text, path);
    if (!sweep) return sweep.error();
    sweep->directory = directory;
    return sweep;
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
    sweep->warnings = std::move(*warnings);
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
    auto exr = readExr(*path, options);
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

struct SweepWriter::DirectoryLock {
    explicit DirectoryLock(int descriptor) : fd(descriptor) {}
    ~DirectoryLock() { ::close(fd); }  // releases the flock
    DirectoryLock(const DirectoryLock&) = delete;
    DirectoryLock& operator=(const DirectoryLock&) = delete;
    int fd;
};

SweepWriter::SweepWriter(Sweep sweep,
                         SweepWriteOptions options,
                         std::unique_ptr<DirectoryLock> lock)
    : sweep_(std::move(sweep)), options_(std::move(options)), lock_(std::move(lock)) {}
SweepWriter::SweepWriter(SweepWriter&&) noexcept = default;
SweepWriter& SweepWriter::operator=(SweepWriter&&) noexcept = default;
SweepWriter::~SweepWriter() = default;

Result<SweepWriter> SweepWriter::create(const std::string& directory,
                                        SweepHeader header,
                                        SweepWriteOptions options) {
    const std::string manifest = manifestPath(directory);
    if (header.created_utc.empty())
        header.created_utc = pb::util::TimeUtil::ToString(pb::util::TimeUtil::GetCurrentTime());
    Sweep sweep;
    sweep.directory = directory;
    sweep.header = header;
    if (auto ok = checkHeader(header, Checker(ErrorCode::InvalidArgument, manifest)); !ok)
        return ok.error();

    std::error_code ec;
    fs::create_directories(directory, ec);
    if (ec) return makeError(ErrorCode::IoError, directory + ": cannot create: " + ec.message());
    const int fd = ::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0)
        return makeError(ErrorCode::IoError, directory + ": cannot open: " + osMessage(errno));
    auto lock = std::make_unique<DirectoryLock>(fd);
    if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
        const int error = errno;
        return makeError(error == EWOULDBLOCK ? ErrorCode::InvalidArgument : ErrorCode::IoError,
                         directory + ": " +
                             (error == EWOULDBLOCK ? std::string("another sweep writer is using it")
                                                   : "cannot lock: " + osMessage(error)));
    }

    const bool has_manifest = fs::exists(fs::symlink_status(manifest, ec));
    if (has_manifest && options.resume) {
        auto existing = readSweepManifest(directory);
        if (!existing) return existing.error();
        const SweepHeader& old = existing->header;
        const std::pair<const char*, bool> same[] = {{"lens", old.lens == header.lens},
                                                     {"camera", old.camera == header.camera},
                                                     {"capture", old.capture == header.capture}};
        for (const auto& [part, equal] : same)
            if (!equal)
                return makeError(ErrorCode::InvalidArgument,
                                 manifest + ": " + part +
                                     ": differs from the new sweep's; cannot resume this sweep");
        existing->warnings.clear();
        return SweepWriter(std::move(*existing), std::move(options), std::move(lock));
    }
    if (has_manifest)
        return makeError(ErrorCode::InvalidArgument,
                         manifest + ": the directory already holds a sweep; refusing to " +
                             "overwrite it (resume appends to it)");
    if (auto exr = findAnyExr(directory))
        return makeError(ErrorCode::InvalidArgument,
                         *exr + ": an EXR file without a sweep manifest; refusing to mix a new " +
                             "sweep with it");
    auto json = formatSweepManifest(sweep);
    if (!json) return json.error();
    if (auto ok = replaceFile(directory, fd, kSweepManifestFile, *json, {}); !ok) return ok.error();
    return SweepWriter(std::move(sweep), std::move(options), std::move(lock));
}

Result<SweepFrame> SweepWriter::addFrame(const render::ImageRGB& image,
                                         SweepFrame frame,
                                         const ExrStandardAttributes& standard) {
    const std::string& directory = sweep_.directory;
    const std::string manifest = manifestPath(directory);
    const size_t index = sweep_.frames.size();
    if (frame.exr_file.empty()) frame.exr_file = sweepFrameFileName(index, frame.angle_deg);

    const Checker check(ErrorCode::InvalidArgument, manifest);
    if (auto ok =
            checkFrame(sweep_.header, frame, index, index ? &sweep_.frames.back() : nullptr, check);
        !ok)
        return ok.error();
    std::set<std::string> files;
    for (size_t i = 0; i < index; ++i)
        if (auto ok = checkUnique(sweep_.frames[i], i, files, check); !ok) return ok.error();
    if (auto ok = checkUnique(frame, index, files, check); !ok) return ok.error();
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
                             " already exists; refusing to overwrite it (remove it by hand if it " +
                             "is the unlisted frame of an interrupted write)");
    // A folder of exr_file may be a link; the frame must still land inside the sweep, and no
    // folder is made outside it.
    const fs::path parent = fs::path(path).parent_path();
    const fs::path inside =
        fs::weakly_canonical(parent, ec).lexically_relative(canonical_directory);
    if (ec || (!inside.empty() && *inside.begin() == ".."))
        return makeError(ErrorCode::InvalidArgument,
                         context + ".exr_file: " + path + " lies outside the sweep directory");
    fs::create_directories(parent, ec);
    if (ec)
        return makeError(ErrorCode::IoError, parent.string() + ": cannot create: " + ec.message());

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
    if (auto written = writeExr(path, image, meta, options_.exr); !written)
        return written.error().withContext(context);
    if (options_.after_frame_written) options_.after_frame_written();

    Sweep next = sweep_;
    next.frames.push_back(frame);
    auto json = formatSweepManifest(next);
    Status replaced = json ? replaceFile(directory, lock_->fd, kSweepManifestFile, *json,
                                         options_.before_manifest_replaced)
                           : Status(json.error());
    if (!replaced) {
        ::unlink(path.c_str());  // ours, and not listed: the sweep stays as it was
        return replaced.error();
    }
    sweep_.frames.push_back(frame);
    return frame;
}

}  // namespace flarelab::hdr
