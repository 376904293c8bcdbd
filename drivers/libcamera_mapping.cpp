#include "drivers/libcamera_mapping.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <sstream>

namespace flarelab::drivers {
namespace {

std::string fmt(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

int packingRank(RawPacking packing) {
    switch (packing) {
        case RawPacking::None:
            return 0;
        case RawPacking::Csi2:
            return 1;
        case RawPacking::Ipu3:
            return 2;
    }
    return 3;
}

std::string sizeText(const PixelSize& size) {
    return std::to_string(size.width) + "x" + std::to_string(size.height);
}

std::string offersText(std::span<const LibcameraFormatOffer> offers) {
    if (offers.empty()) return "nothing";
    std::string text;
    for (const LibcameraFormatOffer& offer : offers) {
        if (!text.empty()) text += ", ";
        text += offer.name.empty() ? "(unnamed)" : offer.name;
        std::string sizes;
        for (const PixelSize& size : offer.sizes) {
            if (!sizes.empty()) sizes += ' ';
            sizes += sizeText(size);
        }
        text += " (" + (sizes.empty() ? std::string("no size") : sizes) + ")";
    }
    return text;
}

std::string knownFormatsText() {
    std::string text;
    for (const LibcameraRawFormat& f : kLibcameraRawFormats)
        text += (text.empty() ? "" : ", ") + std::string(f.name);
    return text;
}

// As RawFrame allows (hdr/raw_io.h, validateRawFrame).
constexpr int64_t kMaxSide = 32768;

int64_t area(const PixelSize& size) { return size.width * size.height; }

}  // namespace

std::span<const LibcameraRawFormat> libcameraRawFormats() { return kLibcameraRawFormats; }

const LibcameraRawFormat* findLibcameraRawFormat(uint32_t code, uint64_t modifier) {
    for (const LibcameraRawFormat& f : kLibcameraRawFormats)
        if (f.fourcc == code && f.modifier == modifier) return &f;
    return nullptr;
}

const LibcameraRawFormat* findLibcameraRawFormat(std::string_view name) {
    for (const LibcameraRawFormat& f : kLibcameraRawFormats)
        if (f.name == name) return &f;
    return nullptr;
}

int64_t libcameraLineBytes(const LibcameraRawFormat& format, int64_t width) {
    if (width < 1) return 0;
    switch (format.packing) {
        case RawPacking::None:
            return width * (format.bit_depth == 8 ? 1 : 2);
        case RawPacking::Csi2:
            return format.bit_depth == 10 ? (width + 3) / 4 * 5 : (width + 1) / 2 * 3;
        case RawPacking::Ipu3:
            return (width + 24) / 25 * 32;
    }
    return 0;
}

Result<std::vector<uint16_t>> unpackLibcameraRaw(std::span<const uint8_t> data,
                                                 const LibcameraRawFormat& format,
                                                 int64_t width,
                                                 int64_t height,
                                                 int64_t stride_bytes) {
    const std::string what = std::string("raw buffer (") + std::string(format.name) + ")";
    if (width < 1 || width > kMaxSide)
        return makeError(ErrorCode::InvalidArgument, what + ": width = " + std::to_string(width) +
                                                         " outside 1.." + std::to_string(kMaxSide));
    if (height < 1 || height > kMaxSide)
        return makeError(ErrorCode::InvalidArgument, what + ": height = " + std::to_string(height) +
                                                         " outside 1.." + std::to_string(kMaxSide));
    const int64_t line = libcameraLineBytes(format, width);
    if (stride_bytes < line)
        return makeError(ErrorCode::InvalidArgument,
                         what + ": stride = " + std::to_string(stride_bytes) +
                             " bytes is shorter than a line of " + std::to_string(width) +
                             " samples (" + std::to_string(line) + " bytes)");
    // The last line needs only its own bytes, not a whole stride. Division keeps this free of
    // overflow for any stride.
    const auto size = static_cast<int64_t>(data.size());
    if (size < line || (height > 1 && (size - line) / (height - 1) < stride_bytes))
        return makeError(ErrorCode::ParseError,
                         what + ": the buffer's size = " + std::to_string(size) +
                             " bytes ends before line " + std::to_string(height) + " (stride " +
                             std::to_string(stride_bytes) + ", " + std::to_string(line) +
                             " bytes a line)");

    std::vector<uint16_t> out(static_cast<size_t>(width * height));
    for (int64_t y = 0; y < height; ++y) {
        const uint8_t* row = data.data() + y * stride_bytes;
        uint16_t* dst = out.data() + y * width;
        switch (format.packing) {
            case RawPacking::None:
                if (format.bit_depth == 8) {
                    for (int64_t x = 0; x < width; ++x) dst[x] = row[x];
                } else {
                    const int max = (1 << format.bit_depth) - 1;
                    for (int64_t x = 0; x < width; ++x) {
                        const int sample = row[2 * x] | row[2 * x + 1] << 8;
                        // Right-justified, as V4L2 and libcamera define these formats; anything
                        // above is a buffer that is not what it says (left-justified, garbage).
                        if (sample > max)
                            return makeError(ErrorCode::ParseError,
                                             what + ": sample (" + std::to_string(x) + ", " +
                                                 std::to_string(y) +
                                                 ") = " + std::to_string(sample) + " exceeds " +
                                                 std::to_string(format.bit_depth) + " bits");
                        dst[x] = static_cast<uint16_t>(sample);
                    }
                }
                break;
            case RawPacking::Csi2:
                if (format.bit_depth == 10) {
                    for (int64_t x = 0; x < width; ++x) {
                        const uint8_t* group = row + x / 4 * 5;
                        const int i = static_cast<int>(x % 4);
                        dst[x] = static_cast<uint16_t>(group[i] << 2 | (group[4] >> (2 * i) & 0x3));
                    }
                } else {
                    for (int64_t x = 0; x < width; ++x) {
                        const uint8_t* group = row + x / 2 * 3;
                        const int i = static_cast<int>(x % 2);
                        dst[x] = static_cast<uint16_t>(group[i] << 4 | (group[2] >> (4 * i) & 0xf));
                    }
                }
                break;
            case RawPacking::Ipu3:
                for (int64_t x = 0; x < width; ++x) {
                    // Sample i of a block starts at bit 10 i; bits 10 i .. 10 i + 9 lie in the
                    // two bytes from (10 i) / 8, both inside the block (the last ends at bit 249).
                    const int bit = 10 * static_cast<int>(x % 25);
                    const uint8_t* byte = row + x / 25 * 32 + bit / 8;
                    dst[x] = static_cast<uint16_t>((byte[0] | byte[1] << 8) >> (bit % 8) & 0x3ff);
                }
                break;
        }
    }
    return out;
}

Result<LibcameraFormatChoice> chooseLibcameraFormat(std::span<const LibcameraFormatOffer> offers,
                                                    const LibcameraFormatRequest& request,
                                                    std::string_view device) {
    // The readable offers that have a size, best first.
    std::vector<std::pair<const LibcameraRawFormat*, const LibcameraFormatOffer*>> readable;
    for (const LibcameraFormatOffer& offer : offers) {
        const LibcameraRawFormat* format = findLibcameraRawFormat(offer.fourcc, offer.modifier);
        const bool sized =
            std::any_of(offer.sizes.begin(), offer.sizes.end(), [](const PixelSize& s) {
                return s.width >= 1 && s.height >= 1 && s.width <= kMaxSide && s.height <= kMaxSide;
            });
        if (format && sized) readable.emplace_back(format, &offer);
    }
    if (readable.empty())
        return makeError(
            ErrorCode::Unsupported,
            std::string(device) +
                ": the camera's raw stream offers no format flarelab reads (it offers " +
                offersText(offers) + "; flarelab reads " + knownFormatsText() + ")");
    std::stable_sort(readable.begin(), readable.end(), [](const auto& a, const auto& b) {
        if (a.first->bit_depth != b.first->bit_depth)
            return a.first->bit_depth > b.first->bit_depth;
        return packingRank(a.first->packing) < packingRank(b.first->packing);
    });

    const LibcameraRawFormat* format = readable.front().first;
    const LibcameraFormatOffer* offer = readable.front().second;
    if (!request.format.empty()) {
        format = nullptr;
        for (const auto& [f, o] : readable)
            if (f->name == request.format) {
                format = f;
                offer = o;
                break;
            }
        if (!format)
            return deviceError(DeviceFault::OutOfRange, device,
                               "format = " + request.format +
                                   " is not offered (the camera offers " + offersText(offers) +
                                   ")");
    }

    std::optional<PixelSize> size;
    for (const PixelSize& s : offer->sizes) {
        if (s.width < 1 || s.height < 1 || s.width > kMaxSide || s.height > kMaxSide) continue;
        if (request.width != 0 && s.width != request.width) continue;
        if (request.height != 0 && s.height != request.height) continue;
        if (!size || area(s) > area(*size)) size = s;
    }
    if (!size) {
        const bool both = request.width != 0 && request.height != 0;
        const std::string field = request.width != 0 ? "width" : "height";
        const std::string asked =
            both ? "width x height = " + std::to_string(request.width) + "x" +
                       std::to_string(request.height)
                 : field + " = " +
                       std::to_string(request.width != 0 ? request.width : request.height);
        std::string sizes;
        for (const PixelSize& s : offer->sizes) sizes += (sizes.empty() ? "" : ", ") + sizeText(s);
        return deviceError(
            DeviceFault::OutOfRange, device,
            asked + " is not a size of " + std::string(format->name) + " (offered: " + sizes + ")");
    }
    return LibcameraFormatChoice{*format, *size};
}

Result<LibcameraFormatChoice> acceptValidatedFormat(uint32_t code,
                                                    uint64_t modifier,
                                                    std::string_view name,
                                                    const PixelSize& size,
                                                    const LibcameraFormatRequest& request,
                                                    std::string_view device) {
    const LibcameraRawFormat* format = findLibcameraRawFormat(code, modifier);
    const std::string made = std::string(name) + " " + sizeText(size);
    if (!format)
        return deviceError(DeviceFault::OutOfRange, device,
                           "format: the camera adjusted its raw stream to " + made +
                               ", a format flarelab does not read");
    if (!request.format.empty() && format->name != request.format)
        return deviceError(DeviceFault::OutOfRange, device,
                           "format = " + request.format + " was adjusted by the camera to " + made +
                               " (a flipped sensor changes its Bayer order; leave format= out to "
                               "take what it gives)");
    if (size.width < 1 || size.height < 1 || size.width > kMaxSide || size.height > kMaxSide)
        return makeError(ErrorCode::IoError, std::string(device) +
                                                 ": the camera adjusted its raw stream to " + made +
                                                 ", not a usable size");
    if (request.width != 0 && size.width != request.width)
        return deviceError(
            DeviceFault::OutOfRange, device,
            "width = " + std::to_string(request.width) + " was adjusted by the camera to " + made);
    if (request.height != 0 && size.height != request.height)
        return deviceError(DeviceFault::OutOfRange, device,
                           "height = " + std::to_string(request.height) +
                               " was adjusted by the camera to " + made);
    return LibcameraFormatChoice{*format, size};
}

Result<LibcameraLimits> libcameraLimits(const std::optional<LibcameraControlRange>& exposure_us,
                                        const std::optional<LibcameraControlRange>& gain,
                                        std::string_view device) {
    const std::string name(device);
    if (!exposure_us)
        return makeError(ErrorCode::Unsupported,
                         name +
                             ": the camera has no ExposureTime control, so its exposure cannot "
                             "be set (in libcamera 0.0.3 a pipeline without an image processing "
                             "algorithm module, such as 'simple', has none)");
    if (!gain)
        return makeError(ErrorCode::Unsupported,
                         name +
                             ": the camera has no AnalogueGain control, so its gain cannot be "
                             "set or known");
    const auto range = [](const LibcameraControlRange& r) {
        return std::string("[") + fmt(r.min) + ", " + fmt(r.max) + "]";
    };
    const LibcameraControlRange& e = *exposure_us;
    if (!std::isfinite(e.min) || !std::isfinite(e.max) || e.max < 1.0 || e.max < e.min)
        return makeError(ErrorCode::IoError, name + ": the camera's ExposureTime range " +
                                                 range(e) + " us holds no positive exposure");
    const LibcameraControlRange& g = *gain;
    if (!std::isfinite(g.min) || !std::isfinite(g.max) || !(g.min > 0.0) || g.max < g.min)
        return makeError(ErrorCode::IoError,
                         name + ": the camera's AnalogueGain range " + range(g) + " is not usable");
    constexpr double kInt32Max = std::numeric_limits<int32_t>::max();
    LibcameraLimits limits;
    limits.min_exposure_us = static_cast<int32_t>(std::clamp(std::ceil(e.min), 1.0, kInt32Max));
    limits.max_exposure_us = static_cast<int32_t>(std::clamp(std::floor(e.max), 1.0, kInt32Max));
    if (limits.max_exposure_us < limits.min_exposure_us)
        return makeError(ErrorCode::IoError, name + ": the camera's ExposureTime range " +
                                                 range(e) + " us holds no whole microsecond");
    limits.min_gain = g.min;
    limits.max_gain = g.max;
    return limits;
}

Result<int32_t> exposureToMicroseconds(double exposure_s,
                                       const LibcameraLimits& limits,
                                       std::string_view device) {
    const double us = std::round(exposure_s * 1e6);
    if (!(us >= limits.min_exposure_us && us <= limits.max_exposure_us))
        return deviceError(DeviceFault::OutOfRange, device,
                           "exposure_s = " + fmt(exposure_s) + " outside [" +
                               fmt(limits.min_exposure_us * 1e-6) + ", " +
                               fmt(limits.max_exposure_us * 1e-6) +
                               "] (ExposureTime takes whole microseconds)");
    return static_cast<int32_t>(us);
}

Result<float> gainToControl(double gain, const LibcameraLimits& limits, std::string_view device) {
    if (!(gain >= limits.min_gain && gain <= limits.max_gain))
        return deviceError(DeviceFault::OutOfRange, device,
                           "gain = " + fmt(gain) + " outside [" + fmt(limits.min_gain) + ", " +
                               fmt(limits.max_gain) + "]");
    return static_cast<float>(gain);
}

Result<hdr::RawFrame> rawFrameFromLibcamera(const LibcameraFrameMetadata& metadata,
                                            const LibcameraSettings& requested,
                                            const LibcameraFormatChoice& format,
                                            std::vector<uint16_t> samples,
                                            const std::string& camera) {
    const auto bad = [&](const std::string& what) {
        return makeError(ErrorCode::IoError,
                         camera + ": frame " + std::to_string(metadata.sequence) + ": " + what);
    };
    const int64_t w = format.size.width, h = format.size.height;
    if (w < 1 || h < 1 || static_cast<int64_t>(samples.size()) != w * h)
        return bad("samples: " + std::to_string(samples.size()) + " for a " +
                   sizeText(format.size) + " frame");
    hdr::RawFrame frame;
    frame.width = w;
    frame.height = h;
    frame.format = format.format.layout;
    frame.samples = std::move(samples);
    frame.bit_depth = format.format.bit_depth;
    frame.white_level_dn = std::ldexp(1.0, frame.bit_depth) - 1.0;

    if (metadata.exposure_us && *metadata.exposure_us <= 0)
        return bad("the metadata's ExposureTime = " + std::to_string(*metadata.exposure_us) +
                   " us is not positive");
    frame.exposure_s =
        static_cast<double>(metadata.exposure_us.value_or(requested.exposure_us)) * 1e-6;
    if (!(frame.exposure_s > 0.0))
        return bad("the requested ExposureTime = " + std::to_string(requested.exposure_us) +
                   " us is not positive");
    if (metadata.analogue_gain &&
        !(std::isfinite(*metadata.analogue_gain) && *metadata.analogue_gain > 0.0))
        return bad("the metadata's AnalogueGain = " + fmt(*metadata.analogue_gain) +
                   " is not a positive number");
    frame.gain = metadata.analogue_gain.value_or(static_cast<double>(requested.gain));

    if (metadata.black_levels) {
        double sum = 0.0;
        for (int64_t level : *metadata.black_levels) {
            if (level < 0 || level > 65535)
                return bad("the metadata's SensorBlackLevels hold " + std::to_string(level) +
                           ", outside 0..65535");
            sum += static_cast<double>(level);
        }
        // Given on a 16-bit scale: a b-bit converter's DN are 2^(16 - b) times smaller.
        frame.black_level_dn = sum / 4.0 / std::ldexp(1.0, 16 - frame.bit_depth);
        if (!(frame.black_level_dn < frame.white_level_dn))
            return bad("the metadata's SensorBlackLevels put black at " +
                       fmt(frame.black_level_dn) + " DN, not below white (" +
                       fmt(frame.white_level_dn) + ")");
    }

    if (metadata.sensor_timestamp_ns) {
        if (*metadata.sensor_timestamp_ns < 0)
            return bad("the metadata's SensorTimestamp = " +
                       std::to_string(*metadata.sensor_timestamp_ns) + " ns is negative");
        frame.timestamp_ns = *metadata.sensor_timestamp_ns;
        frame.timestamp_marks = hdr::TimestampMark::ExposureStart;
    }
    frame.host_timestamp_ns = metadata.host_timestamp_ns;
    frame.sequence = metadata.sequence;
    frame.camera = camera;
    return frame;
}

void LibcameraSettleTracker::request(const LibcameraSettings& settings) {
    if (settings_ && *settings_ == settings) return;
    settings_ = settings;
    frames_ = 0;
}

LibcameraSettleTracker::Decision LibcameraSettleTracker::judge(
    const LibcameraFrameMetadata& metadata, std::string_view device) {
    if (!settings_) return {Verdict::Accept, std::nullopt};  // nothing was asked for
    if (frames_ < std::numeric_limits<int>::max()) ++frames_;
    if (!metadata.exposure_us && !metadata.analogue_gain)
        return {frames_ > kBlindFrames ? Verdict::Accept : Verdict::Discard, std::nullopt};

    const double want_us = settings_->exposure_us;
    const double exposure_tolerance_us =
        std::max({2.0, 0.01 * want_us, static_cast<double>(min_exposure_us_)});
    const bool exposure_ok =
        !metadata.exposure_us ||
        std::abs(static_cast<double>(*metadata.exposure_us) - want_us) <= exposure_tolerance_us;
    const double want_gain = settings_->gain;
    const bool gain_ok = !metadata.analogue_gain ||
                         std::abs(*metadata.analogue_gain - want_gain) <= 0.05 * want_gain;
    if (exposure_ok && gain_ok) return {Verdict::Accept, std::nullopt};
    if (frames_ < kMaxFrames) return {Verdict::Discard, std::nullopt};

    const std::string after = " in " + std::to_string(frames_) + " frames after it was asked for";
    if (!exposure_ok)
        return {Verdict::Refuse,
                deviceError(DeviceFault::OutOfRange, device,
                            "exposure_s = " + fmt(want_us * 1e-6) +
                                " was not applied: the camera "
                                "reports " +
                                fmt(static_cast<double>(*metadata.exposure_us) * 1e-6) + " s" +
                                after + " (a frame duration limit?)")};
    return {Verdict::Refuse,
            deviceError(DeviceFault::OutOfRange, device,
                        "gain = " + fmt(want_gain) + " was not applied: the camera reports " +
                            fmt(*metadata.analogue_gain) + after)};
}

Result<LibcameraCameraOptions> libcameraOptionsFromUri(const DeviceUri& uri) {
    if (Status ok = uri.onlyParams({"width", "height", "format"}); !ok) return ok.error();
    LibcameraCameraOptions options;
    options.name = uri.path;
    for (auto [key, field] : {std::pair<const char*, int64_t*>{"width", &options.format.width},
                              {"height", &options.format.height}}) {
        auto value = uri.number(key, 0.0);
        if (!value) return value.error();
        if (uri.params.count(key) &&
            !(*value >= 1.0 && *value <= kMaxSide && *value == std::floor(*value)))
            return makeError(ErrorCode::InvalidArgument, "device uri '" + uri.text + "': " + key +
                                                             " must be an integer in 1.." +
                                                             std::to_string(kMaxSide));
        *field = static_cast<int64_t>(*value);
    }
    if (auto it = uri.params.find("format"); it != uri.params.end()) {
        if (!findLibcameraRawFormat(it->second))
            return makeError(ErrorCode::InvalidArgument,
                             "device uri '" + uri.text + "': format='" + it->second +
                                 "' is not a raw format flarelab reads (" + knownFormatsText() +
                                 ")");
        options.format.format = it->second;
    }
    return options;
}

Result<std::string> pickLibcameraCamera(std::span<const std::string> ids, std::string_view name) {
    std::string seen;
    for (const std::string& id : ids) seen += (seen.empty() ? "" : ", ") + id;
    if (seen.empty()) seen = "no camera";
    const std::string label = name.empty() ? "(any)" : std::string(name);
    for (const std::string& id : ids)
        if (id == name) return id;
    std::vector<std::string> matches;
    for (const std::string& id : ids)
        if (id.find(name) != std::string::npos) matches.push_back(id);
    if (matches.size() == 1) return matches.front();
    if (matches.empty())
        return makeError(ErrorCode::NotFound, "libcamera camera '" + label +
                                                  "': not found (libcamera sees " + seen + ")");
    return makeError(ErrorCode::InvalidArgument,
                     "libcamera camera '" + label + "': " + std::to_string(matches.size()) +
                         " cameras match (" + seen + "); name one by a longer part of its id");
}

}  // namespace flarelab::drivers
