#include "hdr/raw_io.h"

#include <fcntl.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>
#include <string_view>
#include <vector>

#include "common/file_descriptor.h"

namespace flarelab::hdr {
namespace {

constexpr std::string_view kMagicV1 = "P5\n# flarelab-raw 1\n";
constexpr std::string_view kMagic = "P5\n# flarelab-raw 2\n";

const std::array<std::pair<RawFormat, std::string_view>, 5> kFormats = {{
    {RawFormat::Mono, "mono"},
    {RawFormat::BayerRGGB, "bayer-rggb"},
    {RawFormat::BayerBGGR, "bayer-bggr"},
    {RawFormat::BayerGRBG, "bayer-grbg"},
    {RawFormat::BayerGBRG, "bayer-gbrg"},
}};

constexpr std::array<std::string_view, 12> kKeysV1 = {
    "format",         "exposure_s",     "gain",          "bit_depth",
    "black_level_dn", "white_level_dn", "read_noise_dn", "electrons_per_dn",
    "angle_deg",      "timestamp_ns",   "sequence",      "camera"};
// Version 2 adds these.
constexpr std::array<std::string_view, 2> kKeysV2 = {"timestamp_marks", "host_timestamp_ns"};

const std::array<std::pair<TimestampMark, std::string_view>, 4> kMarks = {{
    {TimestampMark::Unknown, "unknown"},
    {TimestampMark::ExposureStart, "exposure-start"},
    {TimestampMark::ExposureEnd, "exposure-end"},
    {TimestampMark::FrameArrival, "frame-arrival"},
}};

}  // namespace

std::string_view rawFormatName(RawFormat format) {
    for (const auto& [f, name] : kFormats)
        if (f == format) return name;
    return "mono";  // every enumerator is in the table
}

std::optional<RawFormat> parseRawFormat(std::string_view name) {
    for (const auto& [f, n] : kFormats)
        if (n == name) return f;
    return std::nullopt;
}

namespace {

Error invalid(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "raw frame: " + what);
}

std::string shortest(double v) {
    std::array<char, 64> buffer{};
    const auto result = std::to_chars(buffer.data(), buffer.data() + buffer.size(), v);
    return std::string(buffer.data(), result.ptr);
}

bool finite(double v) { return std::isfinite(v); }

}  // namespace

Status validateRawFrame(const RawFrame& f) {
    if (f.width < 1 || f.height < 1 || f.width > (int64_t{1} << 15) ||
        f.height > (int64_t{1} << 15))
        return invalid("width and height must lie in 1..32768");
    if (static_cast<int64_t>(f.samples.size()) != f.width * f.height)
        return invalid("samples holds " + std::to_string(f.samples.size()) +
                       " values, not width x height = " + std::to_string(f.width * f.height));
    if (!(f.exposure_s > 0.0) || !finite(f.exposure_s))
        return invalid("exposure_s must be finite and > 0");
    if (!(f.gain > 0.0) || !finite(f.gain)) return invalid("gain must be finite and > 0");
    if (f.bit_depth < 8 || f.bit_depth > 16) return invalid("bit_depth must lie in 8..16");
    const double max_dn = std::ldexp(1.0, f.bit_depth) - 1.0;
    if (!finite(f.black_level_dn) || f.black_level_dn < 0.0 || !finite(f.white_level_dn) ||
        !(f.black_level_dn < f.white_level_dn) || f.white_level_dn > max_dn)
        return invalid("black and white level must satisfy 0 <= black < white <= 2^bit_depth - 1");
    if (!finite(f.read_noise_dn) || f.read_noise_dn < 0.0)
        return invalid("read_noise_dn must be finite and >= 0");
    if (!finite(f.electrons_per_dn) || f.electrons_per_dn < 0.0)
        return invalid("electrons_per_dn must be finite and >= 0");
    if (!finite(f.angle_deg)) return invalid("angle_deg must be finite");
    if (f.camera.find_first_of("\r\n") != std::string::npos)
        return invalid("camera must be one line");
    for (size_t i = 0; i < f.samples.size(); ++i)
        if (f.samples[i] > max_dn)
            return invalid("sample " + std::to_string(i) + " is " + std::to_string(f.samples[i]) +
                           ", above 2^bit_depth - 1");
    return Ok{};
}

Status writeRaw(const std::string& path, const RawFrame& frame) {
    if (Status ok = validateRawFrame(frame); !ok)
        return makeError(ok.error().code, path + ": " + ok.error().message);
    std::string header(kMagic);
    header += "# format " + std::string(rawFormatName(frame.format)) + "\n";
    header += "# exposure_s " + shortest(frame.exposure_s) + "\n";
    header += "# gain " + shortest(frame.gain) + "\n";
    header += "# bit_depth " + std::to_string(frame.bit_depth) + "\n";
    header += "# black_level_dn " + shortest(frame.black_level_dn) + "\n";
    header += "# white_level_dn " + shortest(frame.white_level_dn) + "\n";
    header += "# read_noise_dn " + shortest(frame.read_noise_dn) + "\n";
    header += "# electrons_per_dn " + shortest(frame.electrons_per_dn) + "\n";
    header += "# angle_deg " + shortest(frame.angle_deg) + "\n";
    header += "# timestamp_ns " + std::to_string(frame.timestamp_ns) + "\n";
    for (const auto& [mark, name] : kMarks)
        if (mark == frame.timestamp_marks)
            header += "# timestamp_marks " + std::string(name) + "\n";
    header += "# host_timestamp_ns " + std::to_string(frame.host_timestamp_ns) + "\n";
    header += "# sequence " + std::to_string(frame.sequence) + "\n";
    header += "# camera " + frame.camera + "\n";
    header += std::to_string(frame.width) + " " + std::to_string(frame.height) + "\n";
    header += std::to_string((1 << frame.bit_depth) - 1) + "\n";
    std::vector<uint8_t> bytes(header.begin(), header.end());
    bytes.reserve(bytes.size() + frame.samples.size() * 2);
    for (const uint16_t v : frame.samples) {
        bytes.push_back(static_cast<uint8_t>(v >> 8));
        bytes.push_back(static_cast<uint8_t>(v & 0xff));
    }

    const std::string temporary = path + ".tmp-" + std::to_string(::getpid());
    const auto io_error = [&](const std::string& what, int error) {
        ::unlink(temporary.c_str());
        return makeError(ErrorCode::IoError, path + ": " + what + ": " + std::strerror(error));
    };
    FileDescriptor fd(
        ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0644));
    if (!fd.valid())
        return makeError(ErrorCode::IoError,
                         path + ": cannot create " + temporary + ": " + std::strerror(errno));
    if (const int error = writeAll(fd.get(), temporary, bytes.data(), bytes.size()); error != 0)
        return io_error("cannot write", error);
    if (const int error = syncFile(fd.get(), temporary); error != 0)
        return io_error("cannot flush to disk (fsync)", error);
    if (const int error = fd.close(); error != 0) return io_error("cannot close", error);
    if (::rename(temporary.c_str(), path.c_str()) != 0)
        return io_error("cannot rename into place", errno);
    // The frame's name must survive a crash too: a sweep lists the file once this returns.
    const std::string directory = std::filesystem::path(path).parent_path().string();
    if (Status synced = syncDirectory(directory); !synced)
        return makeError(ErrorCode::IoError,
                         path + ": renamed into place, but " + synced.error().message);
    return Ok{};
}

Result<RawFrame> readRawFromMemory(std::span<const uint8_t> bytes,
                                   const std::string& name,
                                   const RawReadOptions& options) {
    const auto parse_error = [&](const std::string& what) {
        return makeError(ErrorCode::ParseError, name + ": " + what);
    };
    const std::string_view text(reinterpret_cast<const char*>(bytes.data()), bytes.size());
    const bool v1 = text.substr(0, kMagicV1.size()) == kMagicV1;
    if (!v1 && text.substr(0, kMagic.size()) != kMagic)
        return parse_error(
            "not a flarelab raw frame (expected a PGM starting \"P5\" and "
            "\"# flarelab-raw 2\" or \"# flarelab-raw 1\")");
    size_t at = kMagic.size();  // both magics are as long
    const auto is_key = [&](std::string_view key) {
        for (const std::string_view k : kKeysV1)
            if (k == key) return true;
        if (!v1)
            for (const std::string_view k : kKeysV2)
                if (k == key) return true;
        return false;
    };
    // Header lines up to the size line; every one ends in '\n' and has no NUL.
    const auto next_line = [&]() -> std::optional<std::string_view> {
        const size_t end = text.find('\n', at);
        if (end == std::string_view::npos || end - at > 4096) return std::nullopt;
        const std::string_view line = text.substr(at, end - at);
        if (line.find('\0') != std::string_view::npos) return std::nullopt;
        at = end + 1;
        return line;
    };
    std::map<std::string, std::string, std::less<>> values;
    std::optional<std::string_view> line;
    while ((line = next_line()) && line->starts_with("# ")) {
        const std::string_view body = line->substr(2);
        const size_t space = body.find(' ');
        const std::string key(body.substr(0, space));
        const std::string value(space == std::string_view::npos ? "" : body.substr(space + 1));
        if (!is_key(key)) return parse_error("unknown header key \"" + key + "\"");
        if (!values.emplace(key, value).second)
            return parse_error("header key \"" + key + "\" appears twice");
    }
    if (!line) return parse_error("the header ends before the size line");
    for (const std::string_view k : kKeysV1)
        if (!values.contains(k))
            return parse_error("header key \"" + std::string(k) + "\" is missing");
    if (!v1)
        for (const std::string_view k : kKeysV2)
            if (!values.contains(k))
                return parse_error("header key \"" + std::string(k) + "\" is missing");

    RawFrame f;
    const auto number = [&](const char* key, double& out) -> Status {
        const std::string& v = values.find(key)->second;
        const auto result = std::from_chars(v.data(), v.data() + v.size(), out);
        if (result.ec != std::errc() || result.ptr != v.data() + v.size() || !std::isfinite(out))
            return parse_error(std::string(key) + " \"" + v + "\" is not a finite number");
        return Ok{};
    };
    const auto integer = [&](const char* key, int64_t& out) -> Status {
        const std::string& v = values.find(key)->second;
        const auto result = std::from_chars(v.data(), v.data() + v.size(), out);
        if (result.ec != std::errc() || result.ptr != v.data() + v.size())
            return parse_error(std::string(key) + " \"" + v + "\" is not an integer");
        return Ok{};
    };
    const std::string& format_name = values.find("format")->second;
    const std::optional<RawFormat> known = parseRawFormat(format_name);
    if (!known) return parse_error("format \"" + format_name + "\" is unknown");
    f.format = *known;
    int64_t bit_depth = 0;
    for (Status s :
         {number("exposure_s", f.exposure_s), number("gain", f.gain),
          integer("bit_depth", bit_depth), number("black_level_dn", f.black_level_dn),
          number("white_level_dn", f.white_level_dn), number("read_noise_dn", f.read_noise_dn),
          number("electrons_per_dn", f.electrons_per_dn), number("angle_deg", f.angle_deg),
          integer("timestamp_ns", f.timestamp_ns), integer("sequence", f.sequence)})
        if (!s) return s.error();
    if (bit_depth < 8 || bit_depth > 16) return parse_error("bit_depth must lie in 8..16");
    f.bit_depth = static_cast<int>(bit_depth);
    f.camera = values.find("camera")->second;
    if (!v1) {
        if (Status s = integer("host_timestamp_ns", f.host_timestamp_ns); !s) return s.error();
        const std::string& mark_name = values.find("timestamp_marks")->second;
        bool mark_known = false;
        for (const auto& [mark, mname] : kMarks)
            if (mname == mark_name) {
                f.timestamp_marks = mark;
                mark_known = true;
            }
        if (!mark_known) return parse_error("timestamp_marks \"" + mark_name + "\" is unknown");
    }

    // The size line (already read) and MAXVAL.
    int64_t width = 0, height = 0;
    {
        const std::string_view size = *line;
        const size_t space = size.find(' ');
        if (space == std::string_view::npos) return parse_error("the size line is not \"W H\"");
        const auto a = std::from_chars(size.data(), size.data() + space, width);
        const auto b = std::from_chars(size.data() + space + 1, size.data() + size.size(), height);
        if (a.ec != std::errc() || a.ptr != size.data() + space || b.ec != std::errc() ||
            b.ptr != size.data() + size.size())
            return parse_error("the size line is not \"W H\"");
    }
    if (width < 1 || height < 1 || width > options.max_side || height > options.max_side ||
        width * height > options.max_pixels)
        return parse_error("size " + std::to_string(width) + " x " + std::to_string(height) +
                           " is outside the limits");
    const auto maxval_line = next_line();
    int64_t maxval = 0;
    if (!maxval_line ||
        std::from_chars(maxval_line->data(), maxval_line->data() + maxval_line->size(), maxval)
                .ptr != maxval_line->data() + maxval_line->size())
        return parse_error("MAXVAL is missing or not an integer");
    if (maxval != (int64_t{1} << f.bit_depth) - 1)
        return parse_error("MAXVAL " + std::to_string(maxval) + " does not match bit_depth " +
                           std::to_string(f.bit_depth));
    const size_t expected = static_cast<size_t>(width * height) * 2;
    if (bytes.size() - at != expected)
        return parse_error("holds " + std::to_string(bytes.size() - at) +
                           " bytes of samples, not " + std::to_string(expected));
    f.width = width;
    f.height = height;
    f.samples.resize(static_cast<size_t>(width * height));
    for (size_t i = 0; i < f.samples.size(); ++i) {
        const uint16_t v = static_cast<uint16_t>((bytes[at + 2 * i] << 8) | bytes[at + 2 * i + 1]);
        if (v > maxval)
            return parse_error("sample " + std::to_string(i) + " (" + std::to_string(v) +
                               ") is above MAXVAL");
        f.samples[i] = v;
    }
    if (Status ok = validateRawFrame(f); !ok) return parse_error(ok.error().message);
    return f;
}

Result<RawFrame> readRaw(const std::string& path, const RawReadOptions& options) {
    // Not followed if a link, never waited on if a FIFO or device: see openRegularFile.
    auto file = openRegularFile(path);
    if (!file) return file.error();
    // The largest file the limits allow: a header of at most a few kilobytes plus the samples.
    if (file->size > options.max_pixels * 2 + (1 << 16))
        return makeError(ErrorCode::ParseError,
                         path + ": file is larger than any frame within the limits");
    std::vector<uint8_t> bytes(static_cast<size_t>(file->size));
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t got = ::read(file->fd.get(), bytes.data() + done, bytes.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": cannot read: " + std::strerror(errno));
        if (got == 0) break;  // shrank while being read: the parse reports it short
        done += static_cast<size_t>(got);
    }
    bytes.resize(done);
    return readRawFromMemory(bytes, path, options);
}

}  // namespace flarelab::hdr
