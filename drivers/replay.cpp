#include "drivers/replay.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

#include "hdr/raw_io.h"

namespace flarelab::drivers {
namespace {

const char* const kHeadName = "replay head";
const char* const kCameraName = "replay camera";

std::string degrees(double v) {
    std::ostringstream s;
    s << v << " deg";
    return s.str();
}

}  // namespace

ReplayHead::ReplayHead(std::shared_ptr<const hdr::Sweep> sweep) : sweep_(std::move(sweep)) {}

DeviceIdentity ReplayHead::identity() const {
    return {"replay", "replay head", sweep_->directory, "replay:" + sweep_->directory};
}

HeadLimits ReplayHead::limits() const {
    HeadLimits l;
    l.min_deg = 0.0;
    l.max_deg = 0.0;
    for (const hdr::SweepFrame& f : sweep_->frames) {
        l.min_deg = std::min(l.min_deg, f.angle_deg);
        l.max_deg = std::max(l.max_deg, f.angle_deg);
    }
    l.max_speed_deg_s = 1e6;
    return l;
}

Status ReplayHead::home(double timeout_s) {
    if (!(timeout_s > 0.0) || !std::isfinite(timeout_s))
        return deviceError(DeviceFault::OutOfRange, kHeadName, "timeout_s must be positive");
    position_deg_ = 0.0;
    homed_ = true;
    return Ok{};
}

Result<double> ReplayHead::moveTo(double angle_deg, double timeout_s) {
    if (!(timeout_s > 0.0) || !std::isfinite(timeout_s))
        return deviceError(DeviceFault::OutOfRange, kHeadName, "timeout_s must be positive");
    if (!homed_) return deviceError(DeviceFault::NotHomed, kHeadName, "home the head first");
    const HeadLimits l = limits();
    if (!std::isfinite(angle_deg) || angle_deg < l.min_deg || angle_deg > l.max_deg)
        return deviceError(DeviceFault::OutOfRange, kHeadName,
                           "angle_deg " + degrees(angle_deg) + " is outside the sweep's " +
                               degrees(l.min_deg) + " .. " + degrees(l.max_deg));
    position_deg_ = angle_deg;
    return position_deg_;
}

Result<double> ReplayHead::position() {
    if (!homed_) return deviceError(DeviceFault::NotHomed, kHeadName, "home the head first");
    return position_deg_;
}

Status ReplayHead::setSpeed(double speed_deg_s) {
    if (!(speed_deg_s > 0.0) || !(speed_deg_s <= limits().max_speed_deg_s))
        return deviceError(DeviceFault::OutOfRange, kHeadName, "speed_deg_s out of range");
    speed_deg_s_ = speed_deg_s;
    return Ok{};
}

ReplayCamera::ReplayCamera(std::shared_ptr<const hdr::Sweep> sweep,
                           std::shared_ptr<Head> head,
                           ReplayOptions options)
    : sweep_(std::move(sweep)),
      head_(std::move(head)),
      options_(options),
      exposure_s_(options.initial_exposure_s) {}

DeviceIdentity ReplayCamera::identity() const {
    return {"replay", sweep_->header.camera.description, sweep_->header.camera.serial,
            "replay:" + sweep_->directory};
}

CameraCapabilities ReplayCamera::capabilities() const {
    CameraCapabilities c;
    c.width_px = sweep_->header.capture.width_px;
    c.height_px = sweep_->header.capture.height_px;
    c.formats = {hdr::RawFormat::Mono};
    c.bit_depth = options_.bit_depth;
    c.min_exposure_s = 1e-6;
    c.max_exposure_s = 3600.0;
    c.min_gain = 1.0;
    c.max_gain = 64.0;
    c.black_level_dn = options_.black_level_dn;
    c.white_level_dn = std::ldexp(1.0, options_.bit_depth) - 1.0;
    return c;
}

Status ReplayCamera::setExposure(double exposure_s) {
    const CameraCapabilities c = capabilities();
    if (!std::isfinite(exposure_s) || exposure_s < c.min_exposure_s ||
        exposure_s > c.max_exposure_s)
        return deviceError(DeviceFault::OutOfRange, kCameraName, "exposure_s out of range");
    exposure_s_ = exposure_s;
    return Ok{};
}

Status ReplayCamera::setGain(double gain) {
    const CameraCapabilities c = capabilities();
    if (!std::isfinite(gain) || gain < c.min_gain || gain > c.max_gain)
        return deviceError(DeviceFault::OutOfRange, kCameraName, "gain out of range");
    gain_ = gain;
    return Ok{};
}

Status ReplayCamera::setFormat(hdr::RawFormat format) {
    if (format != hdr::RawFormat::Mono)
        return deviceError(DeviceFault::OutOfRange, kCameraName, "format: only mono is replayed");
    format_ = format;
    return Ok{};
}

Result<hdr::RawFrame> ReplayCamera::capture(double timeout_s) {
    if (!(timeout_s > 0.0) || !std::isfinite(timeout_s))
        return deviceError(DeviceFault::OutOfRange, kCameraName, "timeout_s must be positive");
    if (aborted_) return deviceError(DeviceFault::Stopped, kCameraName, "the capture was aborted");
    const auto angle = head_->position();
    if (!angle) return angle.error();
    // The recorded frame nearest the head.
    size_t best = sweep_->frames.size();
    double best_distance = std::numeric_limits<double>::infinity();
    for (size_t i = 0; i < sweep_->frames.size(); ++i) {
        const double d = std::abs(sweep_->frames[i].angle_deg - *angle);
        if (d < best_distance) {
            best_distance = d;
            best = i;
        }
    }
    if (best == sweep_->frames.size() || best_distance > options_.angle_tolerance_deg)
        return deviceError(DeviceFault::OutOfRange, kCameraName,
                           "nothing was recorded at " + degrees(*angle));
    const hdr::SweepFrame& frame = sweep_->frames[best];
    ++sequence_;
    clock_ns_ += static_cast<int64_t>(std::llround(exposure_s_ * 1e9));
    // The recorded bracket of this exposure, when there is one.
    for (size_t k = 0; k < frame.raw_files.size() && k < frame.exposure_times_s.size(); ++k) {
        if (std::abs(frame.exposure_times_s[k] - exposure_s_) > 1e-9 * exposure_s_) continue;
        auto raw = hdr::readRaw(sweep_->directory + "/" + frame.raw_files[k]);
        if (!raw) return raw.error();
        if (std::abs(raw->gain - gain_) > 1e-9 * gain_)
            return deviceError(
                DeviceFault::OutOfRange, kCameraName,
                "gain: the recorded bracket was taken at gain " + std::to_string(raw->gain));
        raw->sequence = sequence_;
        raw->timestamp_ns = clock_ns_;
        return std::move(*raw);
    }
    // Otherwise the HDR frame exposed again.
    auto image = hdr::loadFrame(*sweep_, best);
    if (!image) return image.error();
    hdr::RawFrame raw;
    raw.width = image->image.width;
    raw.height = image->image.height;
    raw.format = hdr::RawFormat::Mono;
    raw.exposure_s = exposure_s_;
    raw.gain = gain_;
    raw.bit_depth = options_.bit_depth;
    raw.black_level_dn = options_.black_level_dn;
    raw.white_level_dn = std::ldexp(1.0, options_.bit_depth) - 1.0;
    raw.angle_deg = frame.angle_deg;
    raw.timestamp_ns = clock_ns_;
    raw.sequence = sequence_;
    raw.camera = sweep_->header.camera.description;
    raw.samples.resize(static_cast<size_t>(raw.width * raw.height));
    for (int64_t y = 0; y < raw.height; ++y)
        for (int64_t x = 0; x < raw.width; ++x) {
            const double dn = static_cast<double>(image->image.at(x, y)[1]) * exposure_s_ * gain_ +
                              raw.black_level_dn;
            raw.samples[static_cast<size_t>(y * raw.width + x)] =
                static_cast<uint16_t>(std::clamp(std::round(dn), 0.0, raw.white_level_dn));
        }
    return raw;
}

Result<ReplayRig> openReplay(const std::string& directory, const ReplayOptions& options) {
    if (options.bit_depth < 8 || options.bit_depth > 16)
        return makeError(ErrorCode::InvalidArgument, "replay: bit_depth must lie in 8..16");
    if (!(options.black_level_dn >= 0.0) ||
        !(options.black_level_dn < std::ldexp(1.0, options.bit_depth) - 1.0))
        return makeError(ErrorCode::InvalidArgument, "replay: black_level_dn out of range");
    if (!(options.angle_tolerance_deg >= 0.0) || !std::isfinite(options.angle_tolerance_deg))
        return makeError(ErrorCode::InvalidArgument, "replay: angle_tolerance_deg out of range");
    auto sweep = hdr::readSweep(directory);
    if (!sweep) return sweep.error();
    if (sweep->frames.empty())
        return makeError(ErrorCode::InvalidArgument, "replay: " + directory + " holds no frames");
    ReplayRig rig;
    rig.sweep = std::make_shared<const hdr::Sweep>(std::move(*sweep));
    rig.head = std::make_shared<ReplayHead>(rig.sweep);
    rig.camera = std::make_shared<ReplayCamera>(rig.sweep, rig.head, options);
    return rig;
}

}  // namespace flarelab::drivers
