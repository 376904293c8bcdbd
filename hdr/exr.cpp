#include "hdr/exr.h"

#include <Iex.h>
#include <ImfChannelList.h>
#include <ImfChromaticitiesAttribute.h>
#include <ImfCompression.h>
#include <ImfDoubleAttribute.h>
#include <ImfFloatAttribute.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfIO.h>
#include <ImfInputFile.h>
#include <ImfIntAttribute.h>
#include <ImfOutputFile.h>
#include <ImfStringAttribute.h>
#include <ImfThreading.h>
#include <fcntl.h>
#include <half.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <limits>
#include <new>
#include <set>
#include <sstream>
#include <string_view>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#include "common/file_descriptor.h"

namespace flarelab::hdr {
namespace {

constexpr int64_t kMaxWriteSide = int64_t{1} << 15;
// OpenEXR decodes a whole chunk (1 to 256 scan lines of every channel) at once; more than this
// for one chunk is a hostile header, not an image.
constexpr int64_t kMaxChunkBytes = int64_t{1} << 28;
constexpr size_t kWriteBufferBytes = size_t{1} << 20;
constexpr const char* kChannelNames[3] = {"R", "G", "B"};
constexpr const char* kLowerBoundChannel = "flarelab.lower_bound";

// ---------------------------------------------------------------------------------------------
// Streams. OpenEXR reports stream failures by exception; these throw Iex exceptions, which the
// callers below catch.

// An input of known size. readAt serves the header check, which must not throw on a short
// file; read() is what OpenEXR calls.
class SizedIStream : public Imf::IStream {
public:
    SizedIStream(const std::string& name, uint64_t size)
        : Imf::IStream(name.c_str()), size_(size) {}
    uint64_t size() const { return size_; }

    // Copies `n` bytes from `pos`; false when the input ends before them.
    bool readAt(uint64_t pos, char* destination, size_t n) {
        if (n > size_ || pos > size_ - n) return false;
        return copy(pos, destination, n);
    }

    bool read(char c[], int n) override {
        if (n < 0 || !readAt(position_, c, static_cast<size_t>(n)))
            throw Iex::InputExc("unexpected end of file");
        position_ += static_cast<uint64_t>(n);
        return true;
    }
    uint64_t tellg() override { return position_; }
    void seekg(uint64_t pos) override { position_ = pos; }

protected:
    // Copies bytes known to lie within the input.
    virtual bool copy(uint64_t pos, char* destination, size_t n) = 0;

private:
    uint64_t size_ = 0;
    uint64_t position_ = 0;
};

class MemoryIStream final : public SizedIStream {
public:
    MemoryIStream(const std::string& name, std::span<const uint8_t> bytes)
        : SizedIStream(name, bytes.size()), bytes_(bytes) {}

protected:
    bool copy(uint64_t pos, char* destination, size_t n) override {
        if (n > 0) std::memcpy(destination, bytes_.data() + pos, n);
        return true;
    }

private:
    std::span<const uint8_t> bytes_;
};

class FileIStream final : public SizedIStream {
public:
    FileIStream(const std::string& name, int fd, uint64_t size)
        : SizedIStream(name, size), fd_(fd) {}

protected:
    bool copy(uint64_t pos, char* destination, size_t n) override {
        size_t done = 0;
        while (done < n) {
            const ssize_t got =
                ::pread(fd_, destination + done, n - done, static_cast<off_t>(pos + done));
            if (got < 0) {
                if (errno == EINTR) continue;
                throw Iex::IoExc("read failed: " + osMessage(errno));
            }
            if (got == 0) return false;  // the file shrank while being read
            done += static_cast<size_t>(got);
        }
        return true;
    }

private:
    int fd_;
};

// Buffers OpenEXR's many small writes. The first failure is kept: OpenEXR writes the line offset
// table from OutputFile's destructor and drops any exception there, so the caller asks error().
class FileOStream final : public Imf::OStream {
public:
    FileOStream(const std::string& name, int fd)
        : Imf::OStream(name.c_str()), fd_(fd), name_(name) {
        buffer_.reserve(kWriteBufferBytes);
    }
    void write(const char c[], int n) override {
        if (n < 0) throw Iex::ArgExc("negative write size");
        buffer_.insert(buffer_.end(), c, c + n);
        if (buffer_.size() >= kWriteBufferBytes) flush();
    }
    uint64_t tellp() override { return offset_ + buffer_.size(); }
    void seekp(uint64_t pos) override {
        flush();
        offset_ = pos;
    }
    void flush() {
        if (!error_.empty()) throw Iex::IoExc(error_);
        if (const int injected = detail::injectedFault(false, name_); injected != 0) {
            error_ = "write failed: " + osMessage(injected);
            buffer_.clear();
            throw Iex::IoExc(error_);
        }
        size_t done = 0;
        while (done < buffer_.size()) {
            const ssize_t wrote = ::pwrite(fd_, buffer_.data() + done, buffer_.size() - done,
                                           static_cast<off_t>(offset_ + done));
            if (wrote < 0 && errno == EINTR) continue;
            if (wrote <= 0) {
                error_ = "write failed: " + (wrote < 0 ? osMessage(errno) : "no progress");
                buffer_.clear();
                throw Iex::IoExc(error_);
            }
            done += static_cast<size_t>(wrote);
        }
        offset_ += buffer_.size();
        buffer_.clear();
    }
    const std::string& error() const { return error_; }

private:
    int fd_;
    std::string name_;
    uint64_t offset_ = 0;
    std::vector<char> buffer_;
    std::string error_;
};

// ---------------------------------------------------------------------------------------------
// Header check. OpenEXR 3.1 trusts the header: it sizes tables by the data window, reads typed
// attributes by their type whatever size the file declares, and reads a channel list to its
// terminator. This walks the header first, with every size checked against the input, so that
// OpenEXR only ever sees a header it parses the same way, with bounded sizes.

struct HeaderFacts {
    Imath::Box2i data_window;
    int64_t width = 0;
    int64_t height = 0;
};

enum : int { kPixelUint = 0, kPixelHalf = 1, kPixelFloat = 2 };

// Serialized sizes of the fixed-size attribute types OpenEXR knows.
std::optional<int64_t> fixedAttributeSize(std::string_view type) {
    static const std::pair<std::string_view, int64_t> kSizes[] = {
        {"box2i", 16},
        {"box2f", 16},
        {"compression", 1},
        {"double", 8},
        {"float", 4},
        {"int", 4},
        {"lineOrder", 1},
        {"v2i", 8},
        {"v2f", 8},
        {"v2d", 16},
        {"v3i", 12},
        {"v3f", 12},
        {"v3d", 24},
        {"m33f", 36},
        {"m33d", 72},
        {"m44f", 64},
        {"m44d", 128},
        {"rational", 8},
        {"chromaticities", 32},
        {"envmap", 1},
        {"keycode", 28},
        {"timecode", 8},
        {"tiledesc", 9},
        {"deepImageState", 1},
    };
    for (const auto& [name, size] : kSizes)
        if (name == type) return size;
    return std::nullopt;
}

// Lines per chunk of each compression method (OpenEXR file layout); 0 for unknown ones.
int linesPerChunk(uint8_t compression) {
    constexpr std::array<int, 10> kLines = {1, 1, 1, 16, 32, 16, 32, 32, 32, 256};
    return compression < kLines.size() ? kLines[compression] : 0;
}

int32_t littleInt32(const char* p) {
    const auto* u = reinterpret_cast<const unsigned char*>(p);
    return static_cast<int32_t>(static_cast<uint32_t>(u[0]) | static_cast<uint32_t>(u[1]) << 8 |
                                static_cast<uint32_t>(u[2]) << 16 |
                                static_cast<uint32_t>(u[3]) << 24);
}

// The length of the NUL-terminated string at the start of `text` if its terminator comes within
// max_length + 1 bytes.
std::optional<size_t> terminatedLength(std::string_view text, size_t max_length) {
    const size_t nul = text.substr(0, max_length + 1).find('\0');
    if (nul == std::string_view::npos) return std::nullopt;
    return nul;
}

// Checks a chlist value: entries fill it exactly; pixel types known. Returns the channel count and
// the bytes one pixel takes over all channels.
Result<std::pair<int, int64_t>> checkChannelList(std::string_view value,
                                                 size_t max_name,
                                                 const std::string& where) {
    int count = 0;
    int64_t bytes = 0;
    size_t pos = 0;
    while (true) {
        const auto length = terminatedLength(value.substr(pos), max_name);
        if (!length) return makeError(ErrorCode::ParseError, where + ": malformed channel list");
        if (*length == 0) {
            ++pos;
            break;
        }
        pos += *length + 1;
        if (value.size() - pos < 16)
            return makeError(ErrorCode::ParseError, where + ": malformed channel list");
        const int32_t type = littleInt32(value.data() + pos);
        if (type != kPixelUint && type != kPixelHalf && type != kPixelFloat)
            return makeError(ErrorCode::ParseError,
                             where + ": channel of unknown pixel type " + std::to_string(type));
        bytes += type == kPixelHalf ? 2 : 4;
        ++count;
        pos += 16;
    }
    if (pos != value.size())
        return makeError(ErrorCode::ParseError, where + ": channel list size does not match");
    return std::pair{count, bytes};
}

// A stringvector value: int32 lengths, each followed by that many bytes, filling it exactly.
bool stringVectorFits(std::string_view value) {
    size_t pos = 0;
    while (pos < value.size()) {
        if (value.size() - pos < 4) return false;
        const int32_t length = littleInt32(value.data() + pos);
        pos += 4;
        if (length < 0 || static_cast<size_t>(length) > value.size() - pos) return false;
        pos += static_cast<size_t>(length);
    }
    return true;
}

Result<HeaderFacts> checkHeader(SizedIStream& in,
                                const std::string& name,
                                const ExrReadOptions& options) {
    const auto parseError = [&](const std::string& what) {
        return makeError(ErrorCode::ParseError, name + ": " + what);
    };
    const auto unsupported = [&](const std::string& what) {
        return makeError(ErrorCode::Unsupported, name + ": " + what);
    };

    std::array<char, 8> start{};
    if (!in.readAt(0, start.data(), start.size()))
        return parseError("not an OpenEXR file (shorter than its 8-byte preamble)");
    if (littleInt32(start.data()) != 20000630)
        return parseError("not an OpenEXR file (no OpenEXR magic number)");
    const auto version = static_cast<uint32_t>(littleInt32(start.data() + 4));
    if ((version & 0xffu) != 2)
        return unsupported("OpenEXR file format version " + std::to_string(version & 0xffu));
    constexpr uint32_t kTiled = 0x200, kLongNames = 0x400, kDeep = 0x800, kMultiPart = 0x1000;
    if (version & ~(0xffu | kTiled | kLongNames | kDeep | kMultiPart))
        return parseError("unknown flags in the version field");
    if (version & kMultiPart) return unsupported("multi-part files are not supported");
    if (version & kDeep) return unsupported("deep images are not supported");
    if (version & kTiled) return unsupported("tiled files are not supported (only scan lines)");
    const size_t max_name = (version & kLongNames) ? 255 : 31;

    std::optional<Imath::Box2i> data_window;
    int lines_per_chunk = 0;
    bool has_channels = false;
    int channel_count = 0;
    int64_t bytes_per_pixel = 0;
    std::optional<int32_t> chunk_count;
    std::set<std::string> seen;

    uint64_t pos = start.size();
    // Reads a name of at most max_name characters and its NUL.
    const auto readName = [&](std::string& out) -> bool {
        out.clear();
        char c = 0;
        while (true) {
            if (!in.readAt(pos, &c, 1)) return false;
            ++pos;
            if (c == '\0') return true;
            if (out.size() == max_name) return false;
            out.push_back(c);
        }
    };
    std::string attribute;
    std::string type;
    std::string value;
    while (true) {
        if (!readName(attribute)) return parseError("truncated or malformed header");
        if (attribute.empty()) break;
        if (!readName(type)) return parseError("truncated or malformed header");
        const std::string where = "header attribute '" + attribute + "'";
        std::array<char, 4> size_bytes{};
        if (!in.readAt(pos, size_bytes.data(), 4)) return parseError("truncated header");
        pos += 4;
        const int32_t size = littleInt32(size_bytes.data());
        if (size < 0) return parseError(where + " has a negative size");
        if (static_cast<uint64_t>(size) > in.size() - pos)
            return parseError(where + " extends past the end of the file (truncated?)");
        if (!seen.insert(attribute).second) return parseError(where + " appears twice");
        if (const auto fixed = fixedAttributeSize(type); fixed && *fixed != size)
            return parseError(where + " of type " + type + " has size " + std::to_string(size) +
                              ", not " + std::to_string(*fixed));
        // Too intricate to check here, and never in a flat scan-line image.
        if (type == "idmanifest" || type == "deepImageState")
            return unsupported(where + " has type " + type + ", which flarelab does not read");

        value.resize(static_cast<size_t>(size));
        if (size > 0 && !in.readAt(pos, value.data(), value.size()))
            return parseError("truncated header");
        pos += static_cast<uint64_t>(size);

        if (type == "chlist") {
            auto channels = checkChannelList(value, 255, name + ": " + where);
            if (!channels) return channels.error();
            if (attribute == "channels") {
                has_channels = true;
                channel_count = channels->first;
                bytes_per_pixel = channels->second;
            }
        } else if (type == "stringvector" && !stringVectorFits(value)) {
            return parseError(where + " is a malformed string vector");
        } else if (type == "floatvector" && size % 4 != 0) {
            return parseError(where + " is a malformed float vector");
        } else if (type == "preview") {
            // Width and height (unsigned), then 4 bytes per pixel; OpenEXR allocates them all.
            // Compared by division: the product of two 32-bit sizes and 4 overflows int64.
            bool fits = size >= 8 && (size - 8) % 4 == 0;
            if (fits) {
                const auto dimension = [&](size_t offset) {
                    return static_cast<int64_t>(
                        static_cast<uint32_t>(littleInt32(value.data() + offset)));
                };
                const int64_t pixels = (size - 8) / 4;
                const int64_t width = dimension(0);
                const int64_t height = dimension(4);
                fits = width == 0 || height == 0 ? pixels == 0
                                                 : pixels % width == 0 && pixels / width == height;
            }
            if (!fits) return parseError(where + " is a malformed preview image");
        }

        // The attributes OpenEXR reserves for itself must have their standard types.
        const auto requireType = [&](std::string_view expected) -> Status {
            if (type != expected)
                return parseError(where + " has type " + type + ", not " + std::string(expected));
            return Ok{};
        };
        if (attribute == "dataWindow") {
            if (auto ok = requireType("box2i"); !ok) return ok.error();
            const char* p = value.data();
            data_window = Imath::Box2i({littleInt32(p), littleInt32(p + 4)},
                                       {littleInt32(p + 8), littleInt32(p + 12)});
        } else if (attribute == "compression") {
            if (auto ok = requireType("compression"); !ok) return ok.error();
            const auto method = static_cast<uint8_t>(value[0]);
            lines_per_chunk = linesPerChunk(method);
            if (lines_per_chunk == 0)
                return parseError("unknown compression method " + std::to_string(method));
        } else if (attribute == "channels") {
            if (auto ok = requireType("chlist"); !ok) return ok.error();
        } else if (attribute == "type") {
            if (auto ok = requireType("string"); !ok) return ok.error();
            if (value != "scanlineimage")
                return unsupported("image type '" + value + "' is not supported");
        } else if (attribute == "tiles") {
            return parseError("scan-line file with a tile description");
        } else if (attribute == "chunkCount") {
            if (auto ok = requireType("int"); !ok) return ok.error();
            chunk_count = littleInt32(value.data());
        }
    }
    const uint64_t header_end = pos;

    if (!data_window) return parseError("header has no dataWindow");
    if (lines_per_chunk == 0) return parseError("header has no compression");
    if (!has_channels) return parseError("header has no channels");

    const Imath::Box2i& window = *data_window;
    const int64_t width = int64_t{window.max.x} - window.min.x + 1;
    const int64_t height = int64_t{window.max.y} - window.min.y + 1;
    if (width < 1 || height < 1) return parseError("empty data window");
    if (width > options.max_side || height > options.max_side ||
        width * height > options.max_pixels) {
        std::ostringstream out;
        out << "data window " << width << "x" << height << " exceeds the limit of "
            << options.max_side << " pixels per side and " << options.max_pixels << " pixels";
        return unsupported(out.str());
    }
    if ((options.expected_width_px > 0 && width != options.expected_width_px) ||
        (options.expected_height_px > 0 && height != options.expected_height_px))
        return parseError(
            "the header declares a " + std::to_string(width) + "x" + std::to_string(height) +
            " image, but " + std::to_string(options.expected_width_px) + "x" +
            std::to_string(options.expected_height_px) + " was expected; nothing was read");
    if (channel_count > options.max_channels)
        return unsupported(std::to_string(channel_count) + " channels, more than the limit of " +
                           std::to_string(options.max_channels));
    if (bytes_per_pixel * width * lines_per_chunk > kMaxChunkBytes)
        return unsupported("one chunk of this file decodes to more than " +
                           std::to_string(kMaxChunkBytes) + " bytes");
    const int64_t chunks = (height + lines_per_chunk - 1) / lines_per_chunk;
    if (chunk_count && *chunk_count != chunks)
        return parseError("chunkCount " + std::to_string(*chunk_count) + " does not match the " +
                          std::to_string(chunks) + " chunks of the data window");
    if (static_cast<uint64_t>(chunks) * 8 > in.size() - header_end)
        return parseError("truncated file (the line offset table ends past the end of the file)");
    return HeaderFacts{window, width, height};
}

// ---------------------------------------------------------------------------------------------
// Metadata.

bool startsWith(std::string_view text, std::string_view prefix) {
    return text.substr(0, prefix.size()) == prefix;
}

std::string formatDouble(double value) {
    std::array<char, 32> buffer{};
    const auto result = std::to_chars(buffer.data(), buffer.data() + buffer.size(), value);
    return std::string(buffer.data(), result.ptr);
}

std::string joinTimes(const std::vector<double>& times) {
    std::string text;
    for (const double t : times) {
        if (!text.empty()) text += ' ';
        text += formatDouble(t);
    }
    return text;
}

// "0.25 1 4": numbers separated by single spaces, each finite and positive.
std::optional<std::vector<double>> parseTimes(std::string_view text) {
    std::vector<double> times;
    size_t pos = 0;
    while (true) {
        const size_t space = text.find(' ', pos);
        const std::string_view token = text.substr(
            pos, space == std::string_view::npos ? std::string_view::npos : space - pos);
        double value = 0.0;
        const auto [end, ec] = std::from_chars(token.data(), token.data() + token.size(), value);
        if (token.empty() || ec != std::errc() || end != token.data() + token.size() ||
            !std::isfinite(value) || value <= 0.0)
            return std::nullopt;
        times.push_back(value);
        if (space == std::string_view::npos) return times;
        pos = space + 1;
    }
}

// Whether `text` is a capDate, "YYYY:MM:DD hh:mm:ss" with each field in its range.
bool validCapDate(std::string_view text) {
    if (text.size() != 19) return false;
    for (size_t i = 0; i < text.size(); ++i) {
        const char expected = i == 4 || i == 7 || i == 13 || i == 16 ? ':' : i == 10 ? ' ' : '0';
        if (expected == '0' ? !(text[i] >= '0' && text[i] <= '9') : text[i] != expected)
            return false;
    }
    const auto field = [&](size_t at, size_t n) {
        int v = 0;
        for (size_t i = at; i < at + n; ++i) v = 10 * v + (text[i] - '0');
        return v;
    };
    const int month = field(5, 2), day = field(8, 2), hour = field(11, 2), minute = field(14, 2),
              second = field(17, 2);
    return month >= 1 && month <= 12 && day >= 1 && day <= 31 && hour <= 23 && minute <= 59 &&
           second <= 60;
}

// Why a standard attribute's number cannot be written or was not acceptable; empty when fine.
// OpenEXR keeps them as floats, so the float must be finite (and positive where asked).
std::string standardNumberProblem(double value, bool positive, double limit) {
    const auto as_float = static_cast<float>(value);
    if (!std::isfinite(value) || !std::isfinite(as_float)) return "is not a finite float";
    if (positive && !(as_float > 0.0f)) return "is not positive";
    if (std::abs(value) > limit) return "lies beyond " + formatDouble(limit);
    return "";
}

constexpr double kMaxUtcOffset_s = 86400.0;

std::string chromaticitiesProblem(const ExrChromaticities& c) {
    for (const auto& xy : {c.red, c.green, c.blue, c.white})
        for (const double v : xy)
            if (!(std::isfinite(v) && v >= 0.0 && v <= 1.0))
                return "holds " + formatDouble(v) + ", not a chromaticity in [0, 1]";
    return "";
}

Status checkMetadata(const ExrMetadata& meta, const std::string& path) {
    const auto invalid = [&](const std::string& what) -> Status {
        return makeError(ErrorCode::InvalidArgument, path + ": " + what);
    };
    const std::pair<const char*, const std::optional<double>*> numbers[] = {
        {kExrAttrAngle, &meta.angle_deg},
        {kExrAttrRoll, &meta.roll_deg},
        {kExrAttrGain, &meta.gain}};
    for (const auto& [attribute, number] : numbers)
        if (number->has_value() && !std::isfinite(**number))
            return invalid(std::string(attribute) + " is not finite");
    for (const double t : meta.exposure_times_s)
        if (!std::isfinite(t) || t <= 0.0)
            return invalid(std::string(kExrAttrExposureTimes) + " holds " + formatDouble(t) +
                           "; exposure times are finite and positive");
    const ExrStandardAttributes& standard = meta.standard;
    if (!standard.cap_date.empty() && !validCapDate(standard.cap_date))
        return invalid(std::string(kExrStdCapDate) + " '" + standard.cap_date +
                       "' is not YYYY:MM:DD hh:mm:ss");
    const std::tuple<const char*, const std::optional<double>*, bool, double> numbers_std[] = {
        {kExrStdUtcOffset, &standard.utc_offset_s, false, kMaxUtcOffset_s},
        {kExrStdExpTime, &standard.exp_time_s, true, std::numeric_limits<double>::max()},
        {kExrStdAperture, &standard.aperture, true, std::numeric_limits<double>::max()},
        {kExrStdIsoSpeed, &standard.iso_speed, true, std::numeric_limits<double>::max()}};
    for (const auto& [attribute, number, positive, limit] : numbers_std)
        if (number->has_value())
            if (const std::string why = standardNumberProblem(**number, positive, limit);
                !why.empty())
                return invalid(std::string(attribute) + " = " + formatDouble(**number) + " " + why);
    if (standard.chromaticities)
        if (const std::string why = chromaticitiesProblem(*standard.chromaticities); !why.empty())
            return invalid(std::string(kExrStdChromaticities) + " " + why);
    for (const auto& [key, value] : meta.extra) {
        if (key.empty() || key.size() > kExrMaxExtraKeyLength ||
            key.find('\0') != std::string::npos)
            return invalid("extra metadata key '" + key +
                           "' is empty, has a NUL or is longer than " +
                           std::to_string(kExrMaxExtraKeyLength) + " characters");
    }
    return Ok{};
}

void addMetadata(Imf::Header& header, const ExrMetadata& meta) {
    header.insert(kExrAttrVersion, Imf::IntAttribute(kExrFormatVersion));
    if (meta.angle_deg) header.insert(kExrAttrAngle, Imf::DoubleAttribute(*meta.angle_deg));
    if (meta.roll_deg) header.insert(kExrAttrRoll, Imf::DoubleAttribute(*meta.roll_deg));
    if (!meta.exposure_times_s.empty())
        header.insert(kExrAttrExposureTimes,
                      Imf::StringAttribute(joinTimes(meta.exposure_times_s)));
    if (meta.gain) header.insert(kExrAttrGain, Imf::DoubleAttribute(*meta.gain));
    const std::pair<const char*, const std::string*> strings[] = {
        {kExrAttrCamera, &meta.camera},
        {kExrAttrLens, &meta.lens},
        {kExrAttrMergeMethod, &meta.merge_method},
        {kExrAttrSoftwareVersion, &meta.software_version}};
    for (const auto& [attribute, text] : strings)
        if (!text->empty()) header.insert(attribute, Imf::StringAttribute(*text));
    for (const auto& [key, value] : meta.extra)
        header.insert(kExrAttrExtraPrefix + key, Imf::StringAttribute(value));
    const ExrStandardAttributes& standard = meta.standard;
    if (!standard.cap_date.empty())
        header.insert(kExrStdCapDate, Imf::StringAttribute(standard.cap_date));
    const std::pair<const char*, const std::optional<double>*> numbers[] = {
        {kExrStdUtcOffset, &standard.utc_offset_s},
        {kExrStdExpTime, &standard.exp_time_s},
        {kExrStdAperture, &standard.aperture},
        {kExrStdIsoSpeed, &standard.iso_speed}};
    for (const auto& [attribute, number] : numbers)
        if (number->has_value())
            header.insert(attribute, Imf::FloatAttribute(static_cast<float>(**number)));
    if (standard.chromaticities) {
        const ExrChromaticities& c = *standard.chromaticities;
        const auto v = [](const std::array<double, 2>& xy) {
            return Imath::V2f(static_cast<float>(xy[0]), static_cast<float>(xy[1]));
        };
        header.insert(kExrStdChromaticities, Imf::ChromaticitiesAttribute(Imf::Chromaticities(
                                                 v(c.red), v(c.green), v(c.blue), v(c.white))));
    }
}

// OpenEXR's standard attributes of a header (exr.h); ParseError naming the one at fault.
Status readStandardAttributes(const Imf::Header& header,
                              const std::string& name,
                              ExrStandardAttributes& standard) {
    const auto fault = [&](const std::string& attribute, const std::string& what) -> Status {
        return makeError(ErrorCode::ParseError,
                         name + ": header attribute '" + attribute + "' " + what);
    };
    if (header.find(kExrStdCapDate) != header.end()) {
        const auto* text = header.findTypedAttribute<Imf::StringAttribute>(kExrStdCapDate);
        if (text == nullptr) return fault(kExrStdCapDate, "is not of type string");
        if (!validCapDate(text->value()))
            return fault(kExrStdCapDate, "is not YYYY:MM:DD hh:mm:ss");
        standard.cap_date = text->value();
    }
    const std::tuple<const char*, std::optional<double>*, bool, double> numbers[] = {
        {kExrStdUtcOffset, &standard.utc_offset_s, false, kMaxUtcOffset_s},
        {kExrStdExpTime, &standard.exp_time_s, true, std::numeric_limits<double>::max()},
        {kExrStdAperture, &standard.aperture, true, std::numeric_limits<double>::max()},
        {kExrStdIsoSpeed, &standard.iso_speed, true, std::numeric_limits<double>::max()}};
    for (const auto& [attribute, target, positive, limit] : numbers) {
        if (header.find(attribute) == header.end()) continue;
        const auto* number = header.findTypedAttribute<Imf::FloatAttribute>(attribute);
        if (number == nullptr) return fault(attribute, "is not of type float");
        const double value = number->value();
        if (const std::string why = standardNumberProblem(value, positive, limit); !why.empty())
            return fault(attribute, "= " + formatDouble(value) + " " + why);
        *target = value;
    }
    if (header.find(kExrStdChromaticities) != header.end()) {
        const auto* c =
            header.findTypedAttribute<Imf::ChromaticitiesAttribute>(kExrStdChromaticities);
        if (c == nullptr) return fault(kExrStdChromaticities, "is not of type chromaticities");
        const Imf::Chromaticities& v = c->value();
        const auto xy = [](const Imath::V2f& p) { return std::array<double, 2>{p.x, p.y}; };
        ExrChromaticities read{xy(v.red), xy(v.green), xy(v.blue), xy(v.white)};
        if (const std::string why = chromaticitiesProblem(read); !why.empty())
            return fault(kExrStdChromaticities, why);
        standard.chromaticities = read;
    }
    return Ok{};
}

Result<ExrMetadata> readMetadata(const Imf::Header& header, const std::string& name) {
    ExrMetadata meta;
    if (Status ok = readStandardAttributes(header, name, meta.standard); !ok) return ok.error();
    const auto fault = [&](const std::string& attribute, const std::string& what) {
        return makeError(ErrorCode::ParseError,
                         name + ": header attribute '" + attribute + "' " + what);
    };
    const auto* version = header.findTypedAttribute<Imf::IntAttribute>(kExrAttrVersion);
    if (header.find(kExrAttrVersion) != header.end() && version == nullptr)
        return fault(kExrAttrVersion, "is not of type int");

    for (auto it = header.begin(); it != header.end(); ++it) {
        const std::string attribute = it.name();
        if (!startsWith(attribute, "flarelab.")) continue;
        if (version == nullptr)
            return fault(attribute, std::string("is present but ") + kExrAttrVersion + " is not");
        if (attribute == kExrAttrVersion) continue;

        const auto* number = dynamic_cast<const Imf::DoubleAttribute*>(&it.attribute());
        const auto* text = dynamic_cast<const Imf::StringAttribute*>(&it.attribute());
        std::optional<double>* target = nullptr;
        if (attribute == kExrAttrAngle) target = &meta.angle_deg;
        if (attribute == kExrAttrRoll) target = &meta.roll_deg;
        if (attribute == kExrAttrGain) target = &meta.gain;
        if (target != nullptr) {
            if (number == nullptr) return fault(attribute, "is not of type double");
            if (!std::isfinite(number->value())) return fault(attribute, "is not finite");
            *target = number->value();
            continue;
        }

        std::string* string_target = nullptr;
        if (attribute == kExrAttrCamera) string_target = &meta.camera;
        if (attribute == kExrAttrLens) string_target = &meta.lens;
        if (attribute == kExrAttrMergeMethod) string_target = &meta.merge_method;
        if (attribute == kExrAttrSoftwareVersion) string_target = &meta.software_version;
        const bool extra = startsWith(attribute, kExrAttrExtraPrefix) &&
                           attribute.size() > sizeof(kExrAttrExtraPrefix) - 1;
        if (string_target == nullptr && !extra && attribute != kExrAttrExposureTimes)
            return fault(attribute, "is not a flarelab attribute of format version 1");
        if (text == nullptr) return fault(attribute, "is not of type string");
        if (string_target != nullptr) {
            *string_target = text->value();
        } else if (extra) {
            meta.extra[attribute.substr(sizeof(kExrAttrExtraPrefix) - 1)] = text->value();
        } else {
            auto times = parseTimes(text->value());
            if (!times)
                return fault(attribute, "is not a list of positive numbers separated by spaces");
            meta.exposure_times_s = std::move(*times);
        }
    }
    if (version != nullptr && version->value() != kExrFormatVersion)
        return makeError(ErrorCode::Unsupported,
                         name + ": " + kExrAttrVersion + " is " + std::to_string(version->value()) +
                             "; this reader knows version " + std::to_string(kExrFormatVersion));
    return meta;
}

// ---------------------------------------------------------------------------------------------
// Reading.

std::string describePixel(int64_t x, int64_t y, const char* channel, float value) {
    std::ostringstream out;
    out << "pixel (" << x << ", " << y << ") channel " << channel << " = " << value;
    return out.str();
}

Result<ExrImage> decode(SizedIStream& in, const std::string& name, const ExrReadOptions& options) {
    if (options.max_side < 1 || options.max_pixels < 1 || options.max_channels < 1)
        return makeError(ErrorCode::InvalidArgument, name + ": read limits must be positive");
    const char* stage = "cannot read the header";
    try {
        const auto facts = checkHeader(in, name, options);
        if (!facts) return facts.error();
        in.seekg(0);
        Imf::InputFile file(in);
        const Imf::Header& header = file.header();
        if (header.dataWindow() != facts->data_window)
            return makeError(ErrorCode::Internal,
                             name + ": OpenEXR read a different data window than was checked");

        auto meta = readMetadata(header, name);
        if (!meta) return meta.error();

        // Which file channel fills R, G and B.
        const Imf::ChannelList& channels = header.channels();
        const bool has_rgb =
            channels.findChannel("R") || channels.findChannel("G") || channels.findChannel("B");
        std::array<const char*, 3> sources = {"R", "G", "B"};
        int source_count = 3;
        if (!has_rgb && channels.findChannel("Y")) {
            if (channels.findChannel("RY") || channels.findChannel("BY"))
                return makeError(ErrorCode::Unsupported,
                                 name + ": luminance-chroma files (Y, RY, BY) are not supported");
            sources = {"Y", nullptr, nullptr};
            source_count = 1;
        }
        for (int c = 0; c < source_count; ++c) {
            const Imf::Channel* channel = channels.findChannel(sources[c]);
            if (channel == nullptr)
                return makeError(ErrorCode::ParseError,
                                 name + ": no channel " + sources[c] +
                                     (has_rgb ? "" : " (neither R, G, B nor Y)"));
            if (channel->type != Imf::HALF && channel->type != Imf::FLOAT)
                return makeError(ErrorCode::Unsupported, name + ": channel " + sources[c] +
                                                             " is UINT; only half and float "
                                                             "are read");
            if (channel->xSampling != 1 || channel->ySampling != 1)
                return makeError(ErrorCode::Unsupported,
                                 name + ": channel " + sources[c] + " is subsampled");
        }

        const Imf::Channel* bounds_channel = channels.findChannel(kLowerBoundChannel);
        if (bounds_channel &&
            ((bounds_channel->type != Imf::HALF && bounds_channel->type != Imf::FLOAT) ||
             bounds_channel->xSampling != 1 || bounds_channel->ySampling != 1))
            return makeError(ErrorCode::Unsupported,
                             name + ": channel " + kLowerBoundChannel +
                                 " is UINT or subsampled; only full half or float is read");

        stage = "cannot read the pixels";
        ExrImage result;
        result.meta = std::move(*meta);
        result.origin_x = facts->data_window.min.x;
        result.origin_y = facts->data_window.min.y;
        result.image = ImageRGB(facts->width, facts->height);
        ImageRGB& image = result.image;
        Imf::FrameBuffer frame;
        const size_t x_stride = 3 * sizeof(float);
        for (int c = 0; c < source_count; ++c)
            frame.insert(sources[c],
                         Imf::Slice::Make(Imf::FLOAT, image.pixels.data() + c, facts->data_window,
                                          x_stride, x_stride * static_cast<size_t>(image.width)));
        std::vector<float> bounds;
        if (bounds_channel) {
            bounds.assign(image.pixels.size() / 3, 0.0f);
            frame.insert(
                kLowerBoundChannel,
                Imf::Slice::Make(Imf::FLOAT, bounds.data(), facts->data_window, sizeof(float),
                                 sizeof(float) * static_cast<size_t>(image.width)));
        }
        file.setFrameBuffer(frame);
        file.readPixels(facts->data_window.min.y, facts->data_window.max.y);
        if (bounds_channel) {
            result.lower_bound.resize(bounds.size());
            for (size_t i = 0; i < bounds.size(); ++i) {
                const float v = bounds[i];
                if (!(v >= 0.0f && v <= 7.0f && v == std::floor(v)))
                    return makeError(
                        ErrorCode::ParseError,
                        name + ": " +
                            describePixel(
                                facts->data_window.min.x + static_cast<int64_t>(i) % image.width,
                                facts->data_window.min.y + static_cast<int64_t>(i) / image.width,
                                kLowerBoundChannel, v) +
                            " is not a whole number 0 to 7");
                result.lower_bound[i] = static_cast<uint8_t>(v);
            }
        }

        if (source_count == 1)
            for (size_t i = 0; i < image.pixels.size(); i += 3)
                image.pixels[i + 1] = image.pixels[i + 2] = image.pixels[i];
        for (int64_t y = 0; y < image.height; ++y)
            for (int64_t x = 0; x < image.width; ++x)
                for (int c = 0; c < 3; ++c)
                    if (!std::isfinite(image.at(x, y)[c]))
                        return makeError(
                            ErrorCode::ParseError,
                            name + ": " +
                                describePixel(result.origin_x + x, result.origin_y + y,
                                              source_count == 1 ? "Y" : kChannelNames[c],
                                              image.at(x, y)[c]) +
                                "; flarelab reads finite values only");
        return result;
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::Internal, name + ": " + stage + ": out of memory");
    } catch (const std::exception& e) {
        return makeError(ErrorCode::ParseError, name + ": " + stage + ": " + e.what());
    } catch (...) {
        return makeError(ErrorCode::ParseError, name + ": " + stage + ": unknown OpenEXR error");
    }
}

// ---------------------------------------------------------------------------------------------
// Writing.

Imf::Compression toImf(ExrCompression compression) {
    switch (compression) {
        case ExrCompression::None:
            return Imf::NO_COMPRESSION;
        case ExrCompression::Zip:
            return Imf::ZIP_COMPRESSION;
        case ExrCompression::Piz:
            return Imf::PIZ_COMPRESSION;
    }
    return Imf::ZIP_COMPRESSION;
}

// Why `value` does not fit half under `options`; empty when it does.
std::string halfMisfit(float value, double half_min_abs) {
    const double magnitude = std::abs(static_cast<double>(value));
    std::ostringstream out;
    if (magnitude > kHalfMax) {
        out << "exceeds half's largest value " << kHalfMax;
    } else if (magnitude != 0.0 && magnitude < half_min_abs) {
        out << "is below " << half_min_abs << ", where half would lose precision";
    }
    return out.str();
}

Status writeFile(const std::string& temporary,
                 const ImageRGB& image,
                 std::span<const uint8_t> lower_bound,
                 const Imf::Header& header) {
    FileDescriptor fd(
        ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0666));
    if (!fd.valid())
        return makeError(ErrorCode::IoError,
                         "cannot create " + temporary + ": " + osMessage(errno));
    FileOStream out(temporary, fd.get());
    try {
        {
            Imf::OutputFile file(out, header);
            // OpenEXR converts pixel types when reading but not when writing, so half channels
            // get a half copy (rounded to nearest, ties to even).
            const bool half = header.channels().findChannel("R")->type == Imf::HALF;
            std::vector<Imath::half> halves;
            if (half) halves.assign(image.pixels.begin(), image.pixels.end());
            const size_t value_bytes = half ? sizeof(Imath::half) : sizeof(float);
            const size_t x_stride = 3 * value_bytes;
            // OpenEXR only reads through the slices; the const_cast is for its API, not a write.
            char* base = half ? reinterpret_cast<char*>(halves.data())
                              : reinterpret_cast<char*>(const_cast<float*>(image.pixels.data()));
            Imf::FrameBuffer frame;
            for (int c = 0; c < 3; ++c)
                frame.insert(kChannelNames[c],
                             Imf::Slice(half ? Imf::HALF : Imf::FLOAT, base + c * value_bytes,
                                        x_stride, x_stride * static_cast<size_t>(image.width)));
            std::vector<Imath::half> bounds(lower_bound.begin(), lower_bound.end());
            if (!bounds.empty())
                frame.insert(kLowerBoundChannel,
                             Imf::Slice(Imf::HALF, reinterpret_cast<char*>(bounds.data()),
                                        sizeof(Imath::half),
                                        sizeof(Imath::half) * static_cast<size_t>(image.width)));
            file.setFrameBuffer(frame);
            file.writePixels(static_cast<int>(image.height));
        }
        out.flush();
    } catch (const std::exception& e) {
        const std::string what = out.error().empty() ? e.what() : out.error();
        return makeError(ErrorCode::IoError, "cannot write " + temporary + ": " + what);
    } catch (...) {
        return makeError(ErrorCode::IoError, "cannot write " + temporary + ": unknown error");
    }
    if (!out.error().empty())
        return makeError(ErrorCode::IoError, "cannot write " + temporary + ": " + out.error());
    if (const int error = syncFile(fd.get(), temporary); error != 0)
        return makeError(ErrorCode::IoError,
                         "cannot flush " + temporary + " to disk (fsync): " + osMessage(error));
    if (const int error = fd.close(); error != 0)
        return makeError(ErrorCode::IoError, "cannot close " + temporary + ": " + osMessage(error));
    return Ok{};
}

}  // namespace

Result<ExrStandardAttributes> exrCaptureTime(int64_t unix_time_ns) {
    if (unix_time_ns <= 0)
        return makeError(
            ErrorCode::InvalidArgument,
            "capture time " + std::to_string(unix_time_ns) + " ns is not after the Unix epoch");
    const auto seconds = static_cast<std::time_t>(unix_time_ns / 1000000000);
    std::tm local{};
    if (::localtime_r(&seconds, &local) == nullptr || local.tm_year + 1900 > 9999)
        return makeError(
            ErrorCode::InvalidArgument,
            "capture time " + std::to_string(unix_time_ns) + " ns has no four-digit year");
    std::array<char, 32> text{};
    const size_t n = std::strftime(text.data(), text.size(), "%Y:%m:%d %H:%M:%S", &local);
    ExrStandardAttributes standard;
    standard.cap_date.assign(text.data(), n);
    // tm_gmtoff is local time minus UTC; OpenEXR's utcOffset is UTC minus local time.
    standard.utc_offset_s = -static_cast<double>(local.tm_gmtoff);
    return standard;
}

Result<ExrWriteReport> writeExr(const std::string& path,
                                const ImageRGB& image,
                                const ExrMetadata& meta,
                                const ExrWriteOptions& options,
                                std::span<const uint8_t> lower_bound) {
    const auto invalid = [&](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, path + ": " + what);
    };
    if (image.width < 1 || image.height < 1 || image.width > kMaxWriteSide ||
        image.height > kMaxWriteSide)
        return invalid("image size " + std::to_string(image.width) + "x" +
                       std::to_string(image.height) + " is outside 1 to " +
                       std::to_string(kMaxWriteSide) + " pixels per side");
    if (image.pixels.size() != static_cast<size_t>(image.width * image.height * 3))
        return invalid("image holds " + std::to_string(image.pixels.size()) +
                       " values, not width * height * 3");
    if (!(options.half_min_abs >= 0.0 && options.half_min_abs <= kHalfMinNormal))
        return invalid("half_min_abs must lie in [0, 2^-14]");
    if (auto ok = checkMetadata(meta, path); !ok) return ok.error();
    if (!lower_bound.empty()) {
        if (lower_bound.size() != static_cast<size_t>(image.width * image.height))
            return invalid("lower_bound holds " + std::to_string(lower_bound.size()) +
                           " values, not width * height");
        for (size_t i = 0; i < lower_bound.size(); ++i)
            if (lower_bound[i] > 7)
                return invalid("lower_bound at x " + std::to_string(i % image.width) + ", y " +
                               std::to_string(i / image.width) + " is " +
                               std::to_string(lower_bound[i]) + " (bits 1, 2, 4 only)");
    }

    // No NaN passed on, and the first value half cannot hold, if half was asked for.
    const bool want_half = options.pixel_type != ExrPixelType::Float;
    std::string misfit;
    for (int64_t y = 0; y < image.height; ++y) {
        for (int64_t x = 0; x < image.width; ++x) {
            for (int c = 0; c < 3; ++c) {
                const float v = image.at(x, y)[c];
                if (!std::isfinite(v))
                    return invalid("refusing to write non-finite " +
                                   describePixel(x, y, kChannelNames[c], v));
                if (want_half && misfit.empty()) {
                    const std::string why = halfMisfit(v, options.half_min_abs);
                    if (!why.empty()) misfit = describePixel(x, y, kChannelNames[c], v) + " " + why;
                }
            }
        }
    }
    if (options.pixel_type == ExrPixelType::Half && !misfit.empty())
        return invalid("cannot write half: " + misfit);

    ExrWriteReport report;
    report.half = want_half && misfit.empty();
    if (want_half && !misfit.empty()) report.note = "wrote float32: " + misfit;

    try {
        Imf::Header header(static_cast<int>(image.width), static_cast<int>(image.height));
        header.compression() = toImf(options.compression);
        for (const char* channel : kChannelNames)
            header.channels().insert(channel, Imf::Channel(report.half ? Imf::HALF : Imf::FLOAT));
        if (!lower_bound.empty())
            header.channels().insert(kLowerBoundChannel, Imf::Channel(Imf::HALF));
        addMetadata(header, meta);

        const std::string temporary = path + ".tmp-" + std::to_string(::getpid());
        if (auto written = writeFile(temporary, image, lower_bound, header); !written) {
            ::unlink(temporary.c_str());
            return written.error().withContext(path);
        }
        if (::rename(temporary.c_str(), path.c_str()) != 0) {
            const int error = errno;
            ::unlink(temporary.c_str());
            return makeError(ErrorCode::IoError, path + ": cannot rename " + temporary +
                                                     " into place: " + osMessage(error));
        }
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, path + ": cannot build the EXR header: " + e.what());
    }

    // Make the rename itself durable. It has happened: the error says so, for a caller that
    // must know whether the frame will survive a crash (a sweep writer does).
    const std::string directory = std::filesystem::path(path).parent_path().string();
    if (Status synced = syncDirectory(directory); !synced)
        return makeError(ErrorCode::IoError, path + ": renamed into place, but " +
                                                 synced.error().message +
                                                 "; the file may not survive a crash");
    return report;
}

Result<ExrImage> readExr(const std::string& path, const ExrReadOptions& options) {
    auto file = openRegularFile(path);
    if (!file) return file.error();
    const FileDescriptor& fd = file->fd;
    FileIStream in(path, fd.get(), static_cast<uint64_t>(file->size));
    return decode(in, path, options);
}

Result<ExrImage> readExrFromMemory(std::span<const uint8_t> bytes,
                                   const std::string& name,
                                   const ExrReadOptions& options) {
    MemoryIStream in(name, bytes);
    return decode(in, name, options);
}

int useExrThreads(int threads) {
    const int count =
        threads > 0 ? threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
    Imf::setGlobalThreadCount(count);
    return Imf::globalThreadCount();
}

}  // namespace flarelab::hdr
