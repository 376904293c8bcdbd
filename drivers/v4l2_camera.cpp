#include "drivers/v4l2_camera.h"

#include <dirent.h>
#include <linux/videodev2.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <climits>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>

#include "common/file_descriptor.h"

namespace flarelab::drivers {
namespace {

constexpr int64_t kNsPerS = 1'000'000'000;
constexpr double kAbsoluteUnit_s = 100e-6;  // V4L2_CID_EXPOSURE_ABSOLUTE counts 100 us
// Readout assumed when neither the line time nor the frame interval is known (EOF timestamps).
constexpr double kUnknownReadout_s = 0.1;
constexpr int kMaxFormats = 256;
constexpr int kMaxSizes = 4096;

spdlog::logger& logger() {
    static const std::shared_ptr<spdlog::logger> instance = [] {
        auto made = std::make_shared<spdlog::logger>(
            "flarelab.v4l2", std::make_shared<spdlog::sinks::stderr_sink_mt>());
        made->set_level(spdlog::level::info);
        return made;
    }();
    return *instance;
}

std::string num(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

// A fixed-size, maybe unterminated, kernel string.
template <size_t N>
std::string text(const uint8_t (&s)[N]) {
    const auto* begin = reinterpret_cast<const char*>(s);
    return std::string(begin, strnlen(begin, N));
}
template <size_t N>
std::string text(const char (&s)[N]) {
    return std::string(s, strnlen(s, N));
}

const char* controlName(uint32_t id) {
    switch (id) {
        case V4L2_CID_EXPOSURE_ABSOLUTE:
            return "exposure_time_absolute";
        case V4L2_CID_EXPOSURE_AUTO:
            return "auto_exposure";
        case V4L2_CID_EXPOSURE:
            return "exposure";
        case V4L2_CID_GAIN:
            return "gain";
        case V4L2_CID_ANALOGUE_GAIN:
            return "analogue_gain";
        case V4L2_CID_AUTOGAIN:
            return "gain_automatic";
        case V4L2_CID_HBLANK:
            return "horizontal_blanking";
        case V4L2_CID_PIXEL_RATE:
            return "pixel_rate";
        default:
            return "control";
    }
}

uint32_t effectiveCaps(const v4l2_capability& cap) {
    return (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
}

struct OfferedFormat {
    uint32_t fourcc = 0;
    uint32_t flags = 0;
    std::string description;
};

std::vector<OfferedFormat> enumerateFormats(V4l2Device& device) {
    std::vector<OfferedFormat> out;
    for (int i = 0; i < kMaxFormats; ++i) {
        v4l2_fmtdesc d{};
        d.index = static_cast<uint32_t>(i);
        d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        if (device.ioctl(VIDIOC_ENUM_FMT, &d) != 0) break;
        out.push_back({d.pixelformat, d.flags, text(d.description)});
    }
    return out;
}

// The format's sizes: discrete ones, or one stepwise/continuous range.
std::vector<v4l2_frmsizeenum> enumerateSizes(V4l2Device& device, uint32_t fourcc) {
    std::vector<v4l2_frmsizeenum> out;
    for (int i = 0; i < kMaxSizes; ++i) {
        v4l2_frmsizeenum e{};
        e.index = static_cast<uint32_t>(i);
        e.pixel_format = fourcc;
        if (device.ioctl(VIDIOC_ENUM_FRAMESIZES, &e) != 0) break;
        out.push_back(e);
        if (e.type != V4L2_FRMSIZE_TYPE_DISCRETE) break;
    }
    return out;
}

std::string sizesText(const std::vector<v4l2_frmsizeenum>& sizes) {
    if (sizes.empty()) return "not listed by the driver";
    if (sizes.front().type != V4L2_FRMSIZE_TYPE_DISCRETE) {
        const v4l2_frmsize_stepwise& s = sizes.front().stepwise;
        return std::to_string(s.min_width) + "x" + std::to_string(s.min_height) + " to " +
               std::to_string(s.max_width) + "x" + std::to_string(s.max_height) + " in steps of " +
               std::to_string(s.step_width) + "x" + std::to_string(s.step_height);
    }
    std::string out;
    for (const v4l2_frmsizeenum& e : sizes) {
        if (!out.empty()) out += ' ';
        out += std::to_string(e.discrete.width) + "x" + std::to_string(e.discrete.height);
    }
    return out;
}

// The largest size a format lists (by area), or nullopt when it lists none.
std::optional<std::pair<int64_t, int64_t>> largestSize(const std::vector<v4l2_frmsizeenum>& sizes) {
    std::optional<std::pair<int64_t, int64_t>> best;
    for (const v4l2_frmsizeenum& e : sizes) {
        const int64_t w =
            e.type == V4L2_FRMSIZE_TYPE_DISCRETE ? e.discrete.width : e.stepwise.max_width;
        const int64_t h =
            e.type == V4L2_FRMSIZE_TYPE_DISCRETE ? e.discrete.height : e.stepwise.max_height;
        if (!best || w * h > best->first * best->second) best = std::make_pair(w, h);
    }
    return best;
}

// The preferred supported format among those offered, of `layout` when given.
const V4l2FormatInfo* preferred(const std::vector<uint32_t>& offered,
                                std::optional<hdr::RawFormat> layout) {
    for (const V4l2FormatInfo& f : v4l2Formats()) {
        if (layout && f.raw_format != *layout) continue;
        if (std::find(offered.begin(), offered.end(), f.fourcc) != offered.end()) return &f;
    }
    return nullptr;
}

std::vector<uint32_t> supportedOf(const std::vector<OfferedFormat>& formats) {
    std::vector<uint32_t> out;
    for (const OfferedFormat& f : formats)
        if (!(f.flags & V4L2_FMT_FLAG_COMPRESSED) && findV4l2Format(f.fourcc))
            out.push_back(f.fourcc);
    return out;
}

std::string formatList(const std::vector<OfferedFormat>& formats) {
    std::string out;
    for (const OfferedFormat& f : formats) {
        if (!out.empty()) out += ", ";
        out += fourccText(f.fourcc);
    }
    return out.empty() ? "none" : out;
}

std::string formatDisplayName(hdr::RawFormat f) {
    switch (f) {
        case hdr::RawFormat::Mono:
            return "grey";
        case hdr::RawFormat::BayerRGGB:
            return "Bayer RGGB";
        case hdr::RawFormat::BayerBGGR:
            return "Bayer BGGR";
        case hdr::RawFormat::BayerGRBG:
            return "Bayer GRBG";
        case hdr::RawFormat::BayerGBRG:
            return "Bayer GBRG";
    }
    return "?";
}

Result<int> wholeNumber(const DeviceUri& uri, const std::string& key, int fallback) {
    auto x = uri.number(key, fallback);
    if (!x) return x.error();
    if (*x != std::floor(*x) || std::abs(*x) > 1e9)
        return makeError(ErrorCode::InvalidArgument, "device uri '" + uri.text + "': " + key +
                                                         "='" + uri.params.at(key) +
                                                         "' is not a whole number");
    return static_cast<int>(*x);
}

}  // namespace

// ---- options ---------------------------------------------------------------------------------

Status V4l2CameraOptions::validate() const {
    const auto bad = [](const std::string& what) -> Status {
        return makeError(ErrorCode::InvalidArgument, "v4l2 camera options: " + what);
    };
    if (!format.empty() && !fourccFromText(format))
        return bad("format '" + format + "' is not a fourcc such as Y16, RG12 or pRAA");
    if (width_px < 0 || height_px < 0 || width_px > 32768 || height_px > 32768 ||
        (width_px == 0) != (height_px == 0))
        return bad("width and height must both be given, each in 1..32768");
    if (buffers < 2 || buffers > 32) return bad("buffers must lie in 2..32");
    if (!std::isfinite(line_time_us) || line_time_us < 0.0 || line_time_us > 1e6)
        return bad("line_time_us must lie in (0, 1e6]");
    if (settle_frames && (*settle_frames < 0 || *settle_frames > 16))
        return bad("settle_frames must lie in 0..16");
    if (!std::isfinite(fps) || fps < 0.0 || fps > 10000.0) return bad("fps must lie in (0, 10000]");
    if (bits < 0 || bits > 16) return bad("bits must lie in 1..16");
    if (!align.empty() && align != "msb" && align != "lsb") return bad("align must be msb or lsb");
    if (bits > 0 && bits < 16 && align.empty())
        return bad("bits=" + std::to_string(bits) +
                   " needs align=msb (samples in the high bits) or align=lsb (in the low bits)");
    if (!align.empty() && bits == 0) return bad("align needs bits");
    if (!std::isfinite(gain_unity) || gain_unity < 0.0) return bad("gain_unity must be positive");
    if (!std::isfinite(black_level_dn) || black_level_dn < 0.0 || black_level_dn >= 65535.0)
        return bad("black_level must lie in [0, 65535)");
    return Ok{};
}

Result<V4l2CameraOptions> v4l2CameraOptions(const DeviceUri& uri) {
    if (Status ok =
            uri.onlyParams({"format", "width", "height", "buffers", "line_time_us", "settle_frames",
                            "fps", "bits", "align", "gain_unity", "black_level"});
        !ok)
        return ok.error();
    V4l2CameraOptions o;
    if (auto it = uri.params.find("format"); it != uri.params.end()) o.format = it->second;
    if (auto it = uri.params.find("align"); it != uri.params.end()) o.align = it->second;
    auto width = wholeNumber(uri, "width", 0);
    auto height = wholeNumber(uri, "height", 0);
    auto buffers = wholeNumber(uri, "buffers", o.buffers);
    auto bits = wholeNumber(uri, "bits", 0);
    auto settle = wholeNumber(uri, "settle_frames", -1);
    auto line = uri.number("line_time_us", 0.0);
    auto fps = uri.number("fps", 0.0);
    auto unity = uri.number("gain_unity", 0.0);
    auto black = uri.number("black_level", 0.0);
    for (const Error* e : {width ? nullptr : &width.error(), height ? nullptr : &height.error(),
                           buffers ? nullptr : &buffers.error(), bits ? nullptr : &bits.error(),
                           settle ? nullptr : &settle.error(), line ? nullptr : &line.error(),
                           fps ? nullptr : &fps.error(), unity ? nullptr : &unity.error(),
                           black ? nullptr : &black.error()})
        if (e) return *e;
    o.width_px = *width;
    o.height_px = *height;
    o.buffers = *buffers;
    o.bits = *bits;
    if (uri.params.count("settle_frames")) o.settle_frames = *settle;
    o.line_time_us = *line;
    o.fps = *fps;
    o.gain_unity = *unity;
    o.black_level_dn = *black;
    if (Status ok = o.validate(); !ok)
        return ok.error().withContext("device uri '" + uri.text + "'");
    return o;
}

// ---- camera ----------------------------------------------------------------------------------

V4l2Camera::V4l2Camera(Key,
                       std::unique_ptr<V4l2Device> device,
                       V4l2CameraOptions options,
                       std::string uri)
    : device_(std::move(device)), options_(std::move(options)), uri_(std::move(uri)) {}

V4l2Camera::~V4l2Camera() { stopStreaming(); }

Result<std::unique_ptr<V4l2Camera>> V4l2Camera::open(std::unique_ptr<V4l2Device> device,
                                                     const V4l2CameraOptions& options,
                                                     const std::string& uri) {
    if (Status ok = options.validate(); !ok) return ok.error();
    if (!device) return makeError(ErrorCode::InvalidArgument, "v4l2 camera: no device");
    auto camera = std::make_unique<V4l2Camera>(Key{}, std::move(device), options, uri);
    if (Status ok = camera->initialize(); !ok) return ok.error();
    return camera;
}

std::string V4l2Camera::describe() const {
    return "v4l2 " + device_->path() + (card_.empty() ? "" : " (" + card_ + ")");
}

Error V4l2Camera::ioctlError(const char* name, int error) const {
    if (error == ENODEV)
        return deviceError(DeviceFault::Disconnected, describe(),
                           std::string(name) + ": the device is gone (" + osMessage(error) + ")");
    return makeError(ErrorCode::IoError, describe() + ": " + name + " failed: " + osMessage(error));
}

Error V4l2Camera::deviceErr(DeviceFault fault, const std::string& detail) const {
    return deviceError(fault, describe(), detail);
}

Status V4l2Camera::initialize() {
    v4l2_capability cap{};
    if (const int e = device_->ioctl(VIDIOC_QUERYCAP, &cap); e != 0)
        return ioctlError("VIDIOC_QUERYCAP", e);
    card_ = text(cap.card);
    driver_ = text(cap.driver);
    bus_ = text(cap.bus_info);
    const uint32_t caps = effectiveCaps(cap);
    if (!(caps & V4L2_CAP_VIDEO_CAPTURE)) {
        if (caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE)
            return makeError(ErrorCode::Unsupported,
                             describe() +
                                 ": multi-planar capture (V4L2_CAP_VIDEO_CAPTURE_MPLANE) "
                                 "is not supported by flarelab's V4L2 backend");
        return makeError(ErrorCode::Unsupported, describe() + ": not a video capture node");
    }
    if (!(caps & V4L2_CAP_STREAMING))
        return makeError(ErrorCode::Unsupported,
                         describe() +
                             ": cannot stream (no V4L2_CAP_STREAMING); flarelab captures "
                             "by mmap streaming only");

    const std::vector<OfferedFormat> formats = enumerateFormats(*device_);
    offered_ = supportedOf(formats);
    const V4l2FormatInfo* info = nullptr;
    if (!options_.format.empty()) {
        const uint32_t fourcc = *fourccFromText(options_.format);
        const bool listed = std::any_of(formats.begin(), formats.end(),
                                        [&](const OfferedFormat& f) { return f.fourcc == fourcc; });
        info = findV4l2Format(fourcc);
        if (!listed || !info ||
            std::find(offered_.begin(), offered_.end(), fourcc) == offered_.end())
            return deviceErr(DeviceFault::OutOfRange,
                             "format '" + options_.format + "' is " +
                                 (listed ? "not one flarelab reads" : "not offered") +
                                 " (the device offers " + formatList(formats) + ")");
    } else {
        info = preferred(offered_, std::nullopt);
        if (!info)
            return makeError(ErrorCode::Unsupported,
                             describe() + ": offers no format flarelab reads (it offers " +
                                 formatList(formats) +
                                 "; compressed and RGB formats are not read)");
    }
    if (Status ok = applyFormat(*info, options_.width_px, options_.height_px); !ok) return ok;
    if (Status ok = setupControls(); !ok) return ok;
    return Ok{};
}

Status V4l2Camera::applyFormat(const V4l2FormatInfo& info, int64_t width, int64_t height) {
    const bool asked = width > 0;
    if (!asked) {
        const auto largest = largestSize(enumerateSizes(*device_, info.fourcc));
        if (largest) {
            width = largest->first;
            height = largest->second;
        } else {
            v4l2_format current{};
            current.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            if (const int e = device_->ioctl(VIDIOC_G_FMT, &current); e != 0)
                return ioctlError("VIDIOC_G_FMT", e);
            width = current.fmt.pix.width;
            height = current.fmt.pix.height;
        }
    }
    v4l2_format f{};
    f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    f.fmt.pix.width = static_cast<uint32_t>(std::clamp<int64_t>(width, 1, 1 << 15));
    f.fmt.pix.height = static_cast<uint32_t>(std::clamp<int64_t>(height, 1, 1 << 15));
    f.fmt.pix.pixelformat = info.fourcc;
    f.fmt.pix.field = V4L2_FIELD_NONE;
    if (const int e = device_->ioctl(VIDIOC_S_FMT, &f); e != 0)
        return ioctlError("VIDIOC_S_FMT", e);
    const v4l2_pix_format& got = f.fmt.pix;
    if (got.pixelformat != info.fourcc)
        return deviceErr(DeviceFault::OutOfRange, std::string("format ") + info.name +
                                                      " was refused: the driver set " +
                                                      fourccText(got.pixelformat));
    if (asked && (got.width != width || got.height != height))
        return deviceErr(DeviceFault::OutOfRange,
                         "width x height " + std::to_string(width) + "x" + std::to_string(height) +
                             " is not offered in " + info.name + " (the driver set " +
                             std::to_string(got.width) + "x" + std::to_string(got.height) +
                             "; offered: " + sizesText(enumerateSizes(*device_, info.fourcc)) +
                             ")");
    if (got.width < 1 || got.height < 1 || got.width > (1u << 15) || got.height > (1u << 15))
        return makeError(ErrorCode::IoError, describe() + ": the driver set a frame of " +
                                                 std::to_string(got.width) + "x" +
                                                 std::to_string(got.height));
    if (got.field != V4L2_FIELD_NONE && got.field != V4L2_FIELD_ANY)
        return makeError(ErrorCode::Unsupported,
                         describe() + ": the driver delivers interlaced fields (field " +
                             std::to_string(got.field) + "); flarelab reads progressive frames");
    const bool words = info.layout == V4l2Layout::Full16 || info.layout == V4l2Layout::Full16Be;
    if (options_.bits > 0 && !words)
        return deviceErr(DeviceFault::OutOfRange,
                         std::string("bits applies to 16-bit word formats (Y16, RG16, ...), not ") +
                             info.name + ", whose depth is " + std::to_string(info.bits));
    format_ = &info;
    width_ = got.width;
    height_ = got.height;
    bytes_per_line_ = std::max<int64_t>(got.bytesperline, minBytesPerLine(info, width_));
    bit_depth_ = words && options_.bits > 0 ? options_.bits : info.bits;
    msb_aligned_ = words && options_.align == "msb";
    const bool deeper = std::any_of(offered_.begin(), offered_.end(), [&](uint32_t f) {
        const V4l2FormatInfo* other = findV4l2Format(f);
        return other->raw && other->bits > info.bits;
    });
    std::string warning;
    if (!info.raw)
        warning = std::string("no raw format: using the luma of ") + info.name +
                  ", gamma-encoded by the camera (response unknown; calibrate it)";
    else if (info.bits == 8)
        warning = deeper ? std::string("8-bit ") + info.name +
                               " as asked, though the device offers deeper raw formats"
                         : std::string("only 8-bit raw formats are offered: using ") + info.name;
    if (!warning.empty()) {
        logger().warn("{}: {}", describe(), warning);
        warnings_.push_back(std::move(warning));
    }
    return Ok{};
}

Result<V4l2Camera::ControlRange> V4l2Camera::queryRange(uint32_t id) {
    ControlRange range;
    range.id = id;
    v4l2_query_ext_ctrl q{};
    q.id = id;
    int e = device_->ioctl(VIDIOC_QUERY_EXT_CTRL, &q);
    if (e == ENOTTY) {
        // Drivers before Linux 3.17 know only the 32-bit query.
        v4l2_queryctrl old{};
        old.id = id;
        e = device_->ioctl(VIDIOC_QUERYCTRL, &old);
        if (e == 0) {
            q.id = old.id;
            q.minimum = old.minimum;
            q.maximum = old.maximum;
            q.step = static_cast<uint64_t>(std::max(old.step, 0));
            q.flags = old.flags;
        }
    }
    if (e == EINVAL) return range;  // no such control
    if (e != 0) return ioctlError("VIDIOC_QUERY_EXT_CTRL", e);
    if (q.id != id || (q.flags & V4L2_CTRL_FLAG_DISABLED)) return range;
    range.present = true;
    // 64-bit controls (pixel_rate) travel in value64, the others in 32 bits.
    const bool wide = q.type == V4L2_CTRL_TYPE_INTEGER64;
    wide_[id] = wide;
    const int64_t lo = wide ? std::numeric_limits<int64_t>::min() : INT32_MIN;
    const int64_t hi = wide ? std::numeric_limits<int64_t>::max() : INT32_MAX;
    const auto minimum = static_cast<int64_t>(q.minimum);
    const auto maximum = std::max(minimum, static_cast<int64_t>(q.maximum));
    range.minimum = std::clamp(minimum, lo, hi);
    range.maximum = std::clamp(maximum, lo, hi);
    range.step = q.step > 0 && q.step < static_cast<uint64_t>(std::numeric_limits<int64_t>::max())
                     ? static_cast<int64_t>(q.step)
                     : 1;
    range.writable = !(q.flags & V4L2_CTRL_FLAG_READ_ONLY);
    return range;
}

Result<int64_t> V4l2Camera::readControl(uint32_t id) {
    v4l2_ext_control c{};
    c.id = id;
    v4l2_ext_controls list{};
    list.which = V4L2_CTRL_WHICH_CUR_VAL;
    list.count = 1;
    list.controls = &c;
    const bool wide = wide_.count(id) && wide_.at(id);
    int e = device_->ioctl(VIDIOC_G_EXT_CTRLS, &list);
    if (e == 0) return wide ? c.value64 : int64_t{c.value};
    if (e == ENOTTY && !wide) {
        v4l2_control old{};
        old.id = id;
        e = device_->ioctl(VIDIOC_G_CTRL, &old);
        if (e == 0) return int64_t{old.value};
    }
    return ioctlError((std::string("VIDIOC_G_EXT_CTRLS of ") + controlName(id)).c_str(), e);
}

Status V4l2Camera::writeControl(uint32_t id, int64_t value, const char* field) {
    v4l2_ext_control c{};
    c.id = id;
    if (wide_.count(id) && wide_.at(id))
        c.value64 = value;
    else
        c.value = static_cast<int32_t>(std::clamp<int64_t>(value, INT32_MIN, INT32_MAX));
    v4l2_ext_controls list{};
    list.which = V4L2_CTRL_WHICH_CUR_VAL;
    list.count = 1;
    list.controls = &c;
    int e = device_->ioctl(VIDIOC_S_EXT_CTRLS, &list);
    if (e == ENOTTY) {
        v4l2_control old{};
        old.id = id;
        old.value = c.value;
        e = device_->ioctl(VIDIOC_S_CTRL, &old);
    }
    if (e == ERANGE || e == EINVAL)
        return deviceErr(DeviceFault::OutOfRange,
                         std::string(field) + ": the driver refused " + controlName(id) + " = " +
                             std::to_string(value) + " (" + osMessage(e) + ")");
    if (e != 0)
        return ioctlError((std::string("VIDIOC_S_EXT_CTRLS of ") + controlName(id)).c_str(), e);
    return Ok{};
}

Result<int64_t> V4l2Camera::roundedRaw(const ControlRange& range,
                                       double raw,
                                       const char* field,
                                       double unit,
                                       const char* unit_name) const {
    const double lo = static_cast<double>(range.minimum), hi = static_cast<double>(range.maximum);
    const double step = static_cast<double>(range.step);
    const double steps = std::round((raw - lo) / step);
    const double value = lo + steps * step;
    if (!std::isfinite(raw) || !std::isfinite(value) || value < lo || value > hi)
        return deviceErr(DeviceFault::OutOfRange,
                         std::string(field) + " = " + num(raw * unit) + " is outside " +
                             num(std::max(lo, step) * unit) + " .. " + num(hi * unit) + " " +
                             unit_name + " (" + controlName(range.id) + " " +
                             std::to_string(range.minimum) + ".." + std::to_string(range.maximum) +
                             ")");
    // The ends exactly: a double next to int64's limits does not convert back.
    if (value >= hi) return range.maximum;
    if (value <= lo) return range.minimum;
    return static_cast<int64_t>(value);
}

Status V4l2Camera::readFrameInterval() {
    v4l2_streamparm p{};
    p.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    const int e = device_->ioctl(VIDIOC_G_PARM, &p);
    const bool settable = e == 0 && (p.parm.capture.capability & V4L2_CAP_TIMEPERFRAME);
    if (options_.fps > 0.0) {
        if (!settable)
            return deviceErr(
                DeviceFault::OutOfRange,
                "fps: the driver cannot set its frame rate (no V4L2_CAP_TIMEPERFRAME)");
        v4l2_streamparm s{};
        s.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        s.parm.capture.timeperframe = {1000,
                                       static_cast<uint32_t>(std::llround(options_.fps * 1000))};
        if (const int se = device_->ioctl(VIDIOC_S_PARM, &s); se != 0)
            return ioctlError("VIDIOC_S_PARM", se);
        p = s;
    }
    const v4l2_fract t = p.parm.capture.timeperframe;
    frame_interval_s_ = e == 0 && t.numerator > 0 && t.denominator > 0
                            ? static_cast<double>(t.numerator) / t.denominator
                            : 0.0;
    return Ok{};
}

Status V4l2Camera::setupExposure() {
    auto absolute = queryRange(V4L2_CID_EXPOSURE_ABSOLUTE);
    if (!absolute) return absolute.error();
    auto lines = queryRange(V4L2_CID_EXPOSURE);
    if (!lines) return lines.error();
    auto automatic = queryRange(V4L2_CID_EXPOSURE_AUTO);
    if (!automatic) return automatic.error();
    // Controls the camera sets must be writable; a read-only exposure is no use.
    absolute->present = absolute->present && absolute->writable;
    lines->present = lines->present && lines->writable;
    if (automatic->present && automatic->writable && (absolute->present || lines->present)) {
        // Manual mode; shutter priority also lets the exposure be set where manual is missing.
        std::optional<int64_t> manual;
        for (int64_t mode :
             {int64_t{V4L2_EXPOSURE_MANUAL}, int64_t{V4L2_EXPOSURE_SHUTTER_PRIORITY}}) {
            v4l2_querymenu m{};
            m.id = V4L2_CID_EXPOSURE_AUTO;
            m.index = static_cast<uint32_t>(mode);
            if (mode >= automatic->minimum && mode <= automatic->maximum &&
                device_->ioctl(VIDIOC_QUERYMENU, &m) == 0) {
                manual = mode;
                break;
            }
        }
        if (!manual)
            return makeError(ErrorCode::Unsupported,
                             describe() + ": auto_exposure has no manual or shutter-priority mode");
        if (Status ok = writeControl(V4L2_CID_EXPOSURE_AUTO, *manual, "exposure_s"); !ok) return ok;
    }
    if (absolute->present) {
        exposure_mode_ = V4l2ExposureMode::Absolute;
        exposure_ = *absolute;
        exposure_unit_s_ = kAbsoluteUnit_s;
    } else if (lines->present) {
        exposure_mode_ = V4l2ExposureMode::Lines;
        exposure_ = *lines;
        if (options_.line_time_us > 0.0) {
            line_time_s_ = options_.line_time_us * 1e-6;
        } else {
            auto hblank = queryRange(V4L2_CID_HBLANK);
            auto rate = queryRange(V4L2_CID_PIXEL_RATE);
            if (!hblank) return hblank.error();
            if (!rate) return rate.error();
            line_time_s_ = 0.0;
            if (hblank->present && rate->present) {
                auto h = readControl(V4L2_CID_HBLANK);
                auto r = readControl(V4L2_CID_PIXEL_RATE);
                if (h && r && *r > 0 && *h >= 0)
                    line_time_s_ = (static_cast<double>(width_) + static_cast<double>(*h)) /
                                   static_cast<double>(*r);
            }
            if (!(line_time_s_ > 0.0))
                return makeError(ErrorCode::Unsupported,
                                 describe() +
                                     ": its exposure control counts lines, and the node reports "
                                     "no horizontal_blanking and pixel_rate to time them: give "
                                     "the sensor's line time in the URI (line_time_us=)");
        }
        exposure_unit_s_ = line_time_s_;
    } else {
        exposure_mode_ = V4l2ExposureMode::FrameInterval;
        exposure_ = ControlRange{};
        exposure_unit_s_ = 0.0;
        if (!(frame_interval_s_ > 0.0))
            return makeError(ErrorCode::Unsupported,
                             describe() +
                                 ": has no exposure control and reports no frame "
                                 "interval, so its exposure is unknown");
        exposure_s_ = previous_exposure_s_ = frame_interval_s_;
        settle_frames_ = options_.settle_frames.value_or(0);
        return Ok{};
    }
    auto raw = readControl(exposure_.id);
    if (!raw) return raw.error();
    exposure_s_ = previous_exposure_s_ = static_cast<double>(*raw) * exposure_unit_s_;
    settle_frames_ =
        options_.settle_frames.value_or(exposure_mode_ == V4l2ExposureMode::Lines ? 2 : 0);
    return Ok{};
}

Status V4l2Camera::setupGain() {
    gain_id_ = 0;
    gain_ = 1.0;
    for (uint32_t id : {uint32_t{V4L2_CID_ANALOGUE_GAIN}, uint32_t{V4L2_CID_GAIN}}) {
        auto range = queryRange(id);
        if (!range) return range.error();
        if (!range->present || !range->writable) continue;
        gain_range_ = *range;
        gain_unity_ = options_.gain_unity > 0.0 ? options_.gain_unity
                      : range->minimum > 0      ? static_cast<double>(range->minimum)
                                                : 0.0;
        if (!(gain_unity_ > 0.0)) {
            warnings_.push_back(std::string(controlName(id)) + " starts at " +
                                std::to_string(range->minimum) +
                                ", so its unity is unknown: left as the driver has it, frames say "
                                "gain 1 (give gain_unity= to use it)");
            logger().warn("{}: {}", describe(), warnings_.back());
            return Ok{};
        }
        auto automatic = queryRange(V4L2_CID_AUTOGAIN);
        if (!automatic) return automatic.error();
        if (automatic->present && automatic->writable)
            if (Status ok = writeControl(V4L2_CID_AUTOGAIN, 0, "gain"); !ok) return ok;
        gain_id_ = id;
        auto raw = readControl(id);
        if (!raw) return raw.error();
        gain_ = static_cast<double>(*raw) / gain_unity_;
        return Ok{};
    }
    return Ok{};
}

Status V4l2Camera::setupControls() {
    if (Status ok = readFrameInterval(); !ok) return ok;
    base_interval_s_ = frame_interval_s_;
    if (Status ok = setupExposure(); !ok) return ok;
    if (Status ok = setupGain(); !ok) return ok;
    return Ok{};
}

DeviceIdentity V4l2Camera::identity() const {
    return DeviceIdentity{"v4l2", card_.empty() ? driver_ : card_, bus_,
                          uri_.empty() ? "v4l2:" + device_->path() : uri_};
}

CameraCapabilities V4l2Camera::capabilities() const {
    CameraCapabilities c;
    c.width_px = width_;
    c.height_px = height_;
    const bool any_raw = std::any_of(offered_.begin(), offered_.end(),
                                     [](uint32_t f) { return findV4l2Format(f)->raw; });
    for (uint32_t fourcc : offered_) {
        const V4l2FormatInfo* f = findV4l2Format(fourcc);
        if ((f->raw || !any_raw) &&
            std::find(c.formats.begin(), c.formats.end(), f->raw_format) == c.formats.end())
            c.formats.push_back(f->raw_format);
    }
    c.bit_depth = bit_depth_;
    if (exposure_mode_ == V4l2ExposureMode::FrameInterval) {
        c.min_exposure_s = c.max_exposure_s = frame_interval_s_;
    } else {
        c.min_exposure_s =
            static_cast<double>(std::max(exposure_.minimum, exposure_.step)) * exposure_unit_s_;
        c.max_exposure_s = static_cast<double>(exposure_.maximum) * exposure_unit_s_;
    }
    if (gain_id_) {
        c.min_gain =
            static_cast<double>(std::max(gain_range_.minimum, gain_range_.step)) / gain_unity_;
        c.max_gain = static_cast<double>(gain_range_.maximum) / gain_unity_;
    }
    c.black_level_dn = options_.black_level_dn;
    c.white_level_dn = std::ldexp(1.0, bit_depth_) - 1.0;
    if (format_->raw) {
        c.response = CameraResponse::Linear;
        c.response_note = std::string("raw ") + format_->name +
                          " samples, linear in the light after the black level";
    } else {
        c.response = CameraResponse::Unknown;
        c.response_note = std::string("luma of ") + format_->name +
                          ", gamma-encoded by the camera's processor: its response is unknown "
                          "until calibrated";
    }
    return c;
}

Status V4l2Camera::setExposure(double exposure_s) {
    const CameraCapabilities caps = capabilities();
    if (exposure_mode_ == V4l2ExposureMode::FrameInterval) {
        if (!std::isfinite(exposure_s) ||
            std::abs(exposure_s - frame_interval_s_) > 1e-6 * frame_interval_s_)
            return deviceErr(DeviceFault::OutOfRange,
                             "exposure_s = " + num(exposure_s) +
                                 ": the device has no exposure control; its frames are exposed "
                                 "for at most its frame interval, " +
                                 num(frame_interval_s_) + " s, the only exposure it takes");
        return Ok{};
    }
    if (!std::isfinite(exposure_s) || !(exposure_s > 0.0))
        return deviceErr(DeviceFault::OutOfRange,
                         "exposure_s = " + num(exposure_s) + " is not a positive number");
    auto raw =
        roundedRaw(exposure_, exposure_s / exposure_unit_s_, "exposure_s", exposure_unit_s_, "s");
    if (!raw) return raw.error();
    if (*raw < std::max<int64_t>(exposure_.minimum, 1))
        return deviceErr(DeviceFault::OutOfRange, "exposure_s = " + num(exposure_s) +
                                                      " is below the shortest, " +
                                                      num(caps.min_exposure_s) + " s");
    auto current = readControl(exposure_.id);
    if (!current) return current.error();
    if (*current == *raw) {
        exposure_s_ = static_cast<double>(*raw) * exposure_unit_s_;
        return Ok{};
    }
    // A frame interval shorter than the exposure would cut it (or stretch the frame without
    // saying): ask for a longer one first, and go back to the original for short exposures.
    const double wanted_interval = std::max(base_interval_s_, exposure_s);
    if (base_interval_s_ > 0.0 && std::abs(wanted_interval - frame_interval_s_) > 1e-9) {
        v4l2_streamparm p{};
        p.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        if (device_->ioctl(VIDIOC_G_PARM, &p) == 0 &&
            (p.parm.capture.capability & V4L2_CAP_TIMEPERFRAME)) {
            p.parm.capture.timeperframe = {
                static_cast<uint32_t>(std::llround(std::min(wanted_interval, 4000.0) * 1e6)),
                1'000'000};
            if (device_->ioctl(VIDIOC_S_PARM, &p) == 0 && p.parm.capture.timeperframe.denominator)
                frame_interval_s_ = static_cast<double>(p.parm.capture.timeperframe.numerator) /
                                    p.parm.capture.timeperframe.denominator;
        }
    }
    if (Status ok = writeControl(exposure_.id, *raw, "exposure_s"); !ok) return ok;
    auto applied = readControl(exposure_.id);
    if (!applied) return applied.error();
    previous_exposure_s_ = exposure_s_;
    exposure_s_ = static_cast<double>(*applied) * exposure_unit_s_;
    change_ns_ = device_->monotonicNs();
    pending_settle_ = settle_frames_;
    return Ok{};
}

Status V4l2Camera::setGain(double gain) {
    if (!gain_id_) {
        if (!std::isfinite(gain) || std::abs(gain - 1.0) > 1e-9)
            return deviceErr(DeviceFault::OutOfRange,
                             "gain = " + num(gain) +
                                 ": no gain control is mapped (none, or its unity is unknown: "
                                 "gain_unity=), so only 1 is taken");
        return Ok{};
    }
    if (!std::isfinite(gain) || !(gain > 0.0))
        return deviceErr(DeviceFault::OutOfRange, "gain = " + num(gain) + " is not positive");
    auto raw = roundedRaw(gain_range_, gain * gain_unity_, "gain", 1.0 / gain_unity_, "x");
    if (!raw) return raw.error();
    if (*raw <= 0)
        return deviceErr(DeviceFault::OutOfRange, "gain = " + num(gain) + " rounds to 0");
    auto current = readControl(gain_id_);
    if (!current) return current.error();
    if (*current == *raw) {
        gain_ = static_cast<double>(*raw) / gain_unity_;
        return Ok{};
    }
    if (Status ok = writeControl(gain_id_, *raw, "gain"); !ok) return ok;
    auto applied = readControl(gain_id_);
    if (!applied) return applied.error();
    gain_ = static_cast<double>(*applied) / gain_unity_;
    change_ns_ = device_->monotonicNs();
    pending_settle_ = settle_frames_;
    return Ok{};
}

Status V4l2Camera::setFormat(hdr::RawFormat layout) {
    if (format_->raw_format == layout) return Ok{};
    const bool any_raw = std::any_of(offered_.begin(), offered_.end(),
                                     [](uint32_t f) { return findV4l2Format(f)->raw; });
    const V4l2FormatInfo* wanted = nullptr;
    for (const V4l2FormatInfo& f : v4l2Formats())
        if (f.raw_format == layout && (f.raw || !any_raw) &&
            std::find(offered_.begin(), offered_.end(), f.fourcc) != offered_.end()) {
            wanted = &f;
            break;
        }
    if (!wanted)
        return deviceErr(DeviceFault::OutOfRange,
                         "format " + formatDisplayName(layout) + " is not offered");
    const V4l2FormatInfo* old = format_;
    const int64_t old_width = width_, old_height = height_;
    stopStreaming();
    if (Status ok = applyFormat(*wanted, options_.width_px, options_.height_px); !ok) {
        if (Status back = applyFormat(*old, old_width, old_height); !back)
            logger().error("{}: could not restore format {}: {}", describe(), old->name,
                           back.error().message);
        return ok;
    }
    // A new mode may change the line time and the exposure range.
    return setupControls();
}

Status V4l2Camera::startStreaming() {
    v4l2_requestbuffers r{};
    r.count = static_cast<uint32_t>(options_.buffers);
    r.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    r.memory = V4L2_MEMORY_MMAP;
    if (const int e = device_->ioctl(VIDIOC_REQBUFS, &r); e != 0)
        return ioctlError("VIDIOC_REQBUFS", e);
    if (r.count < 2) {
        stopStreaming();
        return makeError(ErrorCode::IoError, describe() + ": the driver granted " +
                                                 std::to_string(r.count) +
                                                 " buffers, fewer than 2");
    }
    for (uint32_t i = 0; i < r.count; ++i) {
        v4l2_buffer b{};
        b.index = i;
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        if (const int e = device_->ioctl(VIDIOC_QUERYBUF, &b); e != 0) {
            stopStreaming();
            return ioctlError("VIDIOC_QUERYBUF", e);
        }
        auto mapped = device_->map(b.length, b.m.offset);
        if (!mapped) {
            stopStreaming();
            return mapped.error();
        }
        buffers_.push_back({*mapped});
    }
    for (uint32_t i = 0; i < r.count; ++i) {
        v4l2_buffer b{};
        b.index = i;
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        if (const int e = device_->ioctl(VIDIOC_QBUF, &b); e != 0) {
            stopStreaming();
            return ioctlError("VIDIOC_QBUF", e);
        }
    }
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (const int e = device_->ioctl(VIDIOC_STREAMON, &type); e != 0) {
        stopStreaming();
        return ioctlError("VIDIOC_STREAMON", e);
    }
    streaming_ = true;
    last_sequence_ = -1;
    return Ok{};
}

void V4l2Camera::stopStreaming() {
    if (!device_) return;
    if (streaming_) {
        int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        device_->ioctl(VIDIOC_STREAMOFF, &type);
        streaming_ = false;
    }
    for (const MappedBuffer& b : buffers_) device_->unmap(b.memory);
    if (!buffers_.empty()) {
        buffers_.clear();
        v4l2_requestbuffers r{};
        r.count = 0;
        r.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        r.memory = V4L2_MEMORY_MMAP;
        device_->ioctl(VIDIOC_REQBUFS, &r);
    }
}

int64_t V4l2Camera::exposureStartNs(const v4l2_buffer& b) const {
    const int64_t stamp = static_cast<int64_t>(b.timestamp.tv_sec) * kNsPerS +
                          static_cast<int64_t>(b.timestamp.tv_usec) * 1000;
    if ((b.flags & V4L2_BUF_FLAG_TSTAMP_SRC_MASK) == V4L2_BUF_FLAG_TSTAMP_SRC_SOE) return stamp;
    // End of frame: back by the longest exposure the frame may have had and its readout.
    const double exposure = std::max(exposure_s_, previous_exposure_s_);
    const double readout = exposure_mode_ == V4l2ExposureMode::Lines
                               ? static_cast<double>(height_) * line_time_s_
                           : frame_interval_s_ > 0.0 ? frame_interval_s_
                                                     : kUnknownReadout_s;
    // At most a million seconds back, whatever the controls claim, so the ns stay in range.
    return stamp -
           static_cast<int64_t>(std::llround(std::clamp(exposure + readout, 0.0, 1e6) * 1e9));
}

Result<hdr::RawFrame> V4l2Camera::capture(double timeout_s) {
    if (!std::isfinite(timeout_s) || !(timeout_s > 0.0) || timeout_s > 1e6)
        return deviceErr(DeviceFault::OutOfRange,
                         "timeout_s = " + num(timeout_s) + " is not a positive number of seconds");
    const auto stopped = [&] { return deviceErr(DeviceFault::Stopped, "the capture was aborted"); };
    if (aborted_) return stopped();
    const int64_t called_ns = device_->monotonicNs();
    const int64_t deadline_ns = called_ns + static_cast<int64_t>(std::llround(timeout_s * 1e9));
    // Frames of a stream started now are all exposed after the call.
    const bool fresh_stream = !streaming_;
    if (fresh_stream)
        if (Status ok = startStreaming(); !ok) return ok.error();
    // Settings are applied before a stream starts, so its first frames are fresh; after that a
    // frame must have started its exposure after the call and after the last change.
    const int64_t not_before_ns =
        fresh_stream ? std::numeric_limits<int64_t>::min() : std::max(called_ns, change_ns_);
    int64_t errors_here = 0, stale_here = 0;
    // Timestamps off the host's monotonic clock cannot date a frame against the call: then
    // every frame done now and the one under way are stale, and settle_frames after them.
    int unknown_clock_drops = pending_settle_;
    if (!fresh_stream && !timestamps_monotonic_) {
        for (;;) {
            v4l2_buffer b{};
            b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            b.memory = V4L2_MEMORY_MMAP;
            const int e = device_->ioctl(VIDIOC_DQBUF, &b);
            if (e == EAGAIN) break;
            if (e != 0) return ioctlError("VIDIOC_DQBUF", e);
            v4l2_buffer requeue{};
            requeue.index = b.index;
            requeue.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            requeue.memory = V4L2_MEMORY_MMAP;
            if (const int qe = device_->ioctl(VIDIOC_QBUF, &requeue); qe != 0)
                return ioctlError("VIDIOC_QBUF", qe);
            ++dropped_stale_;
            ++stale_here;
        }
        unknown_clock_drops += 1;
    }

    for (;;) {
        if (aborted_) return stopped();
        const int64_t now = device_->monotonicNs();
        if (now >= deadline_ns)
            return deviceErr(DeviceFault::Timeout,
                             "no fresh frame within " + num(timeout_s) + " s (" +
                                 std::to_string(stale_here) + " stale frames dropped, " +
                                 std::to_string(errors_here) + " buffers flagged as errors)");
        // In slices, so that abort() ends a long exposure's wait within one.
        const int64_t wait_ms = std::min<int64_t>((deadline_ns - now + 999'999) / 1'000'000, 100);
        const int ready = device_->waitForFrame(
            static_cast<int>(std::min<int64_t>(wait_ms, std::numeric_limits<int>::max())));
        if (ready == 0) continue;
        v4l2_buffer b{};
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        const int e = device_->ioctl(VIDIOC_DQBUF, &b);
        if (e == EAGAIN) {
            if (ready < 0)
                return makeError(ErrorCode::IoError, describe() + ": poll reports an error (" +
                                                         osMessage(-ready) +
                                                         ") and no buffer is done");
            continue;
        }
        if (e != 0) return ioctlError("VIDIOC_DQBUF", e);
        const int64_t host_ns = device_->realtimeNs();
        if (b.index >= buffers_.size())
            return makeError(ErrorCode::IoError, describe() + ": VIDIOC_DQBUF returned buffer " +
                                                     std::to_string(b.index) + " of " +
                                                     std::to_string(buffers_.size()));
        if (last_sequence_ >= 0) {
            const uint32_t gap = b.sequence - static_cast<uint32_t>(last_sequence_) - 1u;
            if (gap > 0 && gap < (1u << 31)) sequence_gaps_ += gap;
        }
        last_sequence_ = b.sequence;
        timestamps_monotonic_ =
            (b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;

        bool keep = !(b.flags & V4L2_BUF_FLAG_ERROR);
        if (!keep) {
            ++buffer_errors_;
            ++errors_here;
        } else if (!timestamps_monotonic_) {
            if (unknown_clock_drops > 0) {
                --unknown_clock_drops;
                ++dropped_stale_;
                ++stale_here;
                keep = false;
            }
        } else if (exposureStartNs(b) < not_before_ns) {
            ++dropped_stale_;
            ++stale_here;
            keep = false;
        } else if (pending_settle_ > 0) {
            --pending_settle_;
            ++dropped_settle_;
            keep = false;
        }

        Result<V4l2Samples> samples = V4l2Samples{};
        if (keep) {
            const std::span<const uint8_t> memory = buffers_[b.index].memory;
            const size_t used = b.bytesused == 0 ? memory.size() : b.bytesused;
            if (used > memory.size())
                samples = makeError(ErrorCode::IoError,
                                    describe() + ": bytesused " + std::to_string(used) +
                                        " exceeds the buffer's " + std::to_string(memory.size()));
            else
                samples =
                    unpackV4l2Samples(*format_, memory.first(used),
                                      V4l2Unpacking{width_, height_, bytes_per_line_,
                                                    format_->layout == V4l2Layout::Full16 ||
                                                            format_->layout == V4l2Layout::Full16Be
                                                        ? bit_depth_
                                                        : 0,
                                                    msb_aligned_});
        }
        // The buffer goes back to the driver before anything else can fail. VIDIOC_QBUF
        // writes the buffer's new state into the structure it is given, so it gets its own.
        v4l2_buffer requeue{};
        requeue.index = b.index;
        requeue.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        requeue.memory = V4L2_MEMORY_MMAP;
        if (const int qe = device_->ioctl(VIDIOC_QBUF, &requeue); qe != 0)
            return ioctlError("VIDIOC_QBUF", qe);
        if (!keep) continue;
        if (!samples) return samples.error().withContext(describe());

        // What the device applied, read back for this frame.
        double exposure = exposure_s_, gain = gain_;
        if (exposure_mode_ != V4l2ExposureMode::FrameInterval) {
            auto raw = readControl(exposure_.id);
            if (!raw) return raw.error();
            exposure = static_cast<double>(*raw) * exposure_unit_s_;
        } else {
            exposure = frame_interval_s_;
        }
        if (gain_id_) {
            auto raw = readControl(gain_id_);
            if (!raw) return raw.error();
            gain = static_cast<double>(*raw) / gain_unity_;
        }
        ++frames_;
        clipped_samples_ += samples->clipped;
        pending_settle_ = 0;

        hdr::RawFrame frame;
        frame.width = width_;
        frame.height = height_;
        frame.format = format_->raw_format;
        frame.samples = std::move(samples->samples);
        frame.exposure_s = exposure;
        frame.gain = gain;
        frame.bit_depth = samples->bit_depth;
        frame.black_level_dn = options_.black_level_dn;
        frame.white_level_dn = std::ldexp(1.0, samples->bit_depth) - 1.0;
        frame.timestamp_ns = static_cast<int64_t>(b.timestamp.tv_sec) * kNsPerS +
                             static_cast<int64_t>(b.timestamp.tv_usec) * 1000;
        if ((b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) != V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC)
            frame.timestamp_marks = hdr::TimestampMark::Unknown;
        else if ((b.flags & V4L2_BUF_FLAG_TSTAMP_SRC_MASK) == V4L2_BUF_FLAG_TSTAMP_SRC_SOE)
            frame.timestamp_marks = hdr::TimestampMark::ExposureStart;
        else
            frame.timestamp_marks = hdr::TimestampMark::FrameArrival;
        frame.host_timestamp_ns = host_ns;
        frame.sequence = b.sequence;
        frame.camera = card_ + " " + bus_;
        return frame;
    }
}

std::vector<std::pair<std::string, int64_t>> V4l2Camera::statistics() const {
    return {{"frames", frames_},
            {"dropped-stale", dropped_stale_},
            {"dropped-settle", dropped_settle_},
            {"buffer-errors", buffer_errors_},
            {"sequence-gaps", sequence_gaps_},
            {"clipped-samples", clipped_samples_}};
}

// ---- listing ---------------------------------------------------------------------------------

namespace {

// A control's name as v4l2-ctl writes it (and takes it in --set-ctrl): "Exposure Time, Absolute"
// is exposure_time_absolute.
std::string ctlName(const std::string& name) {
    std::string out;
    for (const char c : name) {
        if (std::isalnum(static_cast<unsigned char>(c)))
            out += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
        else if (!out.empty() && out.back() != '_')
            out += '_';
    }
    while (!out.empty() && out.back() == '_') out.pop_back();
    return out;
}

std::string readSysfs(const std::string& path) {
    std::ifstream in(path);
    std::string line;
    if (in) std::getline(in, line);
    return line;
}

}  // namespace

DeviceListing describeV4l2Device(V4l2Device& device, const std::string& uri) {
    DeviceListing d;
    d.uri = uri;
    d.kind = "camera";
    d.backend = "v4l2";
    v4l2_capability cap{};
    if (const int e = device.ioctl(VIDIOC_QUERYCAP, &cap); e != 0) {
        d.details.push_back("error: VIDIOC_QUERYCAP failed: " + osMessage(e));
        return d;
    }
    d.model = text(cap.card);
    d.serial = text(cap.bus_info);
    d.details.push_back("card: " + text(cap.card));
    d.details.push_back("driver: " + text(cap.driver) + " " + std::to_string(cap.version >> 16) +
                        "." + std::to_string((cap.version >> 8) & 0xff) + "." +
                        std::to_string(cap.version & 0xff));
    d.details.push_back("bus: " + text(cap.bus_info));
    const uint32_t caps = effectiveCaps(cap);
    if (!(caps & V4L2_CAP_VIDEO_CAPTURE)) {
        d.details.push_back(caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE
                                ? "not usable: multi-planar capture, which flarelab does not read"
                                : "not usable: not a video capture node");
        return d;
    }
    if (!(caps & V4L2_CAP_STREAMING)) d.details.push_back("not usable: cannot stream");
    const std::vector<OfferedFormat> formats = enumerateFormats(device);
    std::string others;
    for (const OfferedFormat& f : formats) {
        const V4l2FormatInfo* info = findV4l2Format(f.fourcc);
        if (!info || (f.flags & V4L2_FMT_FLAG_COMPRESSED)) {
            if (!others.empty()) others += ' ';
            others += fourccText(f.fourcc);
            continue;
        }
        d.details.push_back("format: " + std::string(info->name) + " (" + f.description + "), " +
                            formatDisplayName(info->raw_format) + " " + std::to_string(info->bits) +
                            " bit, " + info->layout_note + (info->raw ? "" : ", not raw") +
                            "; sizes " + sizesText(enumerateSizes(device, f.fourcc)));
    }
    if (!others.empty()) d.details.push_back("formats flarelab does not read: " + others);
    const V4l2FormatInfo* best = preferred(supportedOf(formats), std::nullopt);
    d.details.push_back(best ? std::string("opens as: ") + best->name + " (" + uri +
                                   "?format=FCC picks another)"
                             : std::string("not usable: no format flarelab reads"));
    const auto describeControl = [&](uint32_t id, const std::string& role,
                                     const std::string& unit) {
        v4l2_query_ext_ctrl q{};
        q.id = id;
        if (device.ioctl(VIDIOC_QUERY_EXT_CTRL, &q) != 0 || q.id != id ||
            (q.flags & V4L2_CTRL_FLAG_DISABLED))
            return false;
        d.details.push_back(role + ": " + ctlName(text(q.name)) + " " + std::to_string(q.minimum) +
                            ".." + std::to_string(q.maximum) + unit);
        return true;
    };
    if (!describeControl(V4L2_CID_EXPOSURE_ABSOLUTE, "exposure", " x 100 us") &&
        !describeControl(V4L2_CID_EXPOSURE, "exposure", " lines"))
        d.details.push_back("exposure: no control (frames are exposed for the frame interval)");
    if (!describeControl(V4L2_CID_ANALOGUE_GAIN, "gain", "") &&
        !describeControl(V4L2_CID_GAIN, "gain", ""))
        d.details.push_back("gain: no control");
    return d;
}

std::vector<DeviceListing> listV4l2Devices(const std::string& dev_dir) {
    std::vector<std::pair<int, std::string>> nodes;
    if (DIR* dir = ::opendir(dev_dir.c_str())) {
        while (const dirent* entry = ::readdir(dir)) {
            const std::string name = entry->d_name;
            if (name.size() <= 5 || name.compare(0, 5, "video") != 0) continue;
            const std::string digits = name.substr(5);
            if (digits.size() > 6 || !std::all_of(digits.begin(), digits.end(), ::isdigit))
                continue;
            nodes.emplace_back(std::stoi(digits), name);
        }
        ::closedir(dir);
    }
    std::sort(nodes.begin(), nodes.end());
    std::vector<DeviceListing> out;
    for (const auto& [number, name] : nodes) {
        const std::string path = dev_dir + "/" + name;
        const std::string uri = "v4l2:" + path;
        auto device = openV4l2Node(path);
        if (!device) {
            DeviceListing d;
            d.uri = uri;
            d.kind = "camera";
            d.backend = "v4l2";
            d.details.push_back("error: " + device.error().message);
            out.push_back(std::move(d));
            continue;
        }
        v4l2_capability cap{};
        if ((*device)->ioctl(VIDIOC_QUERYCAP, &cap) != 0) continue;
        if (!(effectiveCaps(cap) & (V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_VIDEO_CAPTURE_MPLANE)))
            continue;  // output, metadata, radio, ... nodes
        DeviceListing d = describeV4l2Device(**device, uri);
        // USB cameras: the USB device above the interface the node belongs to.
        const std::string usb = "/sys/class/video4linux/" + name + "/device/../";
        const std::string vendor = readSysfs(usb + "idVendor");
        if (!vendor.empty()) {
            d.details.push_back("usb: " + vendor + ":" + readSysfs(usb + "idProduct") + " " +
                                readSysfs(usb + "manufacturer") + " " + readSysfs(usb + "product"));
            const std::string serial = readSysfs(usb + "serial");
            if (!serial.empty()) {
                d.details.push_back("usb serial: " + serial);
                d.serial = serial;
            }
        }
        out.push_back(std::move(d));
    }
    return out;
}

Status addV4l2CameraBackend(CameraRegistry& registry) {
    auto open = [](const DeviceUri& uri) -> Result<std::unique_ptr<Camera>> {
        if (uri.path.empty())
            return makeError(
                ErrorCode::InvalidArgument,
                "device uri '" + uri.text + "': name the device node, as in v4l2:/dev/video0");
        auto options = v4l2CameraOptions(uri);
        if (!options) return options.error();
        auto device = openV4l2Node(uri.path);
        if (!device) return device.error().withContext("device uri '" + uri.text + "'");
        auto camera = V4l2Camera::open(std::move(*device), *options, uri.text);
        if (!camera) return camera.error();
        return std::unique_ptr<Camera>(std::move(*camera));
    };
    return registry.addBackend("v4l2", "Video4Linux2 cameras (kernel ioctls, mmap streaming)",
                               std::move(open), [] { return listV4l2Devices(); });
}

}  // namespace flarelab::drivers
