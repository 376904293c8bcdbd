// ============================================================================
//  flarelab drivers: V4l2Camera, V4l2CameraOptions, V4l2ExposureMode, v4l2CameraOptions,
//                    describeV4l2Device, listV4l2Devices, addV4l2CameraBackend
// ============================================================================
//
// A Video4Linux2 capture device as a Camera (camera.h), through the kernel's ioctls
// (linux/videodev2.h) on a V4l2Device (v4l2_device.h: a real node, or a recorded one played
// back for tests). URI:
//
//     v4l2:/dev/video0?format=Y16&width=1280&height=720&buffers=4
//
// with the parameters of V4l2CameraOptions below; an unknown parameter is refused by name.
//
// Format. The device's formats (VIDIOC_ENUM_FMT) are matched against v4l2_formats.h in its
// order of preference: 16, 14, 12 and 10-bit grey and raw Bayer first, 8-bit raw only when there
// is nothing deeper (with a warning), the luma of YUV last (its response is then Unknown: a
// webcam's gamma curve; `flarelab calibrate` measures it). Compressed-only and multi-planar
// devices are refused. format= picks one by its fourcc. The size is the largest the format lists
// (VIDIOC_ENUM_FRAMESIZES) unless width and height say; a size the driver changes is
// [out-of-range]. setFormat(RawFormat) chooses the preferred fourcc of that layout.
//
// Exposure. On V4L2_CID_EXPOSURE_ABSOLUTE (100 us units; UVC webcams and most USB cameras)
// after V4L2_CID_EXPOSURE_AUTO is set to manual (or shutter priority where manual is missing);
// else on V4L2_CID_EXPOSURE (sensor drivers, in lines: the line time is (width +
// V4L2_CID_HBLANK) / V4L2_CID_PIXEL_RATE when the node has both controls, else the URI's
// line_time_us, else the camera does not open). A device with neither (vivid, some capture
// cards) is exposed for its frame interval (VIDIOC_G_PARM), a fixed exposure that setExposure
// accepts alone. An exposure longer than the frame interval first asks for a longer interval
// (VIDIOC_S_PARM), and a shorter one returns to the interval of the start. Gain on
// V4L2_CID_ANALOGUE_GAIN, else V4L2_CID_GAIN, after V4L2_CID_AUTOGAIN is turned off. V4L2 gain
// has no unit: the gain is taken as proportional to the control's value, over gain_unity (the
// value meaning 1x: the URI's, else the control's minimum when positive; without either the
// gain control is left alone and the gain is 1). Sensors whose gain code is not proportional
// need their gain calibrated, or gain 1. After each setting the applied value is read back
// (VIDIOC_G_EXT_CTRLS), and every frame carries the values read back at its capture.
//
// Frames. mmap streaming (VIDIOC_REQBUFS, QUERYBUF, mmap, QBUF, STREAMON) starts at the first
// capture and runs until the camera is closed or its format changes. capture() returns the
// first frame whose exposure started after the later of (a) the call and (b) the last change of
// exposure or gain, so no frame exposed while the head moved or with old settings is returned
// (the first capture of a stream takes its first frame: settings precede STREAMON). With
// monotonic buffer timestamps the start of exposure is the timestamp where the driver marks the
// start of exposure (V4L2_BUF_FLAG_TSTAMP_SRC_SOE), else the timestamp (end of frame) less the
// exposure and the readout (height x line time where the line time is known, else one frame
// interval, which is conservative); with timestamps on another clock every frame done at the
// call and the one under way are dropped. A driver that applies a control some frames late
// (pipelined sensor registers) cannot be seen in timestamps: settle_frames more frames are
// dropped after a change (default 2 where exposure is in lines, as sensors latch exposure one or
// two frames late; 0 otherwise). So a capture may wait 3 frame periods, plus settle_frames
// after a change. The poll never waits past the timeout.
//
// Every frame: samples unpacked to 16 bits (v4l2_formats.h), bit_depth and white level of the
// format (or of bits= for 16-bit words), black level of the URI, the exposure and gain read
// back, the buffer timestamp (ns) and what it marks (SOE: ExposureStart; EOF: FrameArrival; a
// timestamp not on the monotonic clock: Unknown), the host's CLOCK_REALTIME when dequeued, and
// the buffer's sequence number. Buffers the driver flags V4L2_BUF_FLAG_ERROR are skipped and
// counted (statistics()).
//
// Errors: device errors (device.h) naming the device: [timeout] when no fresh frame comes in
// time, [disconnected] on ENODEV, [out-of-range] naming exposure_s, gain, format, width x
// height, fps, bits or timeout_s; other ioctl failures are IoError naming the ioctl and errno.
#pragma once

#include <atomic>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "common/result.h"
#include "drivers/camera.h"
#include "drivers/device.h"
#include "drivers/v4l2_device.h"
#include "drivers/v4l2_formats.h"

struct v4l2_buffer;  // linux/videodev2.h

namespace flarelab::drivers {

// URI parameters: format, width, height, buffers, line_time_us, settle_frames, fps, bits, align,
// gain_unity, black_level.
struct V4l2CameraOptions {
    std::string format;    // fourcc as v4l2-ctl prints it, trimmed: "Y16", "RG12", "pRAA"
    int64_t width_px = 0;  // 0 (with height 0): the largest size of the format
    int64_t height_px = 0;
    int buffers = 4;                   // 2..32 mmap buffers
    double line_time_us = 0.0;         // > 0: overrides the driver's line time
    std::optional<int> settle_frames;  // 0..16; default: 2 with exposure in lines, else 0
    double fps = 0.0;                  // > 0: ask for this frame rate (VIDIOC_S_PARM)
    int bits = 0;                      // 1..16: the sensor's depth in 16-bit words
    std::string align;                 // "msb" or "lsb": where those bits lie (needs bits)
    double gain_unity = 0.0;           // > 0: the gain control's value meaning 1x
    double black_level_dn = 0.0;       // >= 0, below white

    // InvalidArgument naming the first field out of range.
    Status validate() const;
};

// The options a "v4l2:" URI asks for: InvalidArgument naming an unknown parameter or one that
// is not a number where a number belongs.
Result<V4l2CameraOptions> v4l2CameraOptions(const DeviceUri& uri);

enum class V4l2ExposureMode {
    Absolute,       // V4L2_CID_EXPOSURE_ABSOLUTE, 100 us
    Lines,          // V4L2_CID_EXPOSURE, in lines of line_time_s
    FrameInterval,  // no exposure control: the frame interval
};

class V4l2Camera final : public Camera {
public:
    // Opens a camera on a device (a node from openV4l2Node, or a playback), with `uri` for its
    // identity. Unsupported when the device cannot capture by mmap streaming or offers no
    // format flarelab reads; [out-of-range] naming format, width or height when the options ask
    // for what the device does not offer; IoError naming the ioctl that failed.
    static Result<std::unique_ptr<V4l2Camera>> open(std::unique_ptr<V4l2Device> device,
                                                    const V4l2CameraOptions& options,
                                                    const std::string& uri = "");
    ~V4l2Camera() override;

    DeviceIdentity identity() const override;
    CameraCapabilities capabilities() const override;
    Status setExposure(double exposure_s) override;
    double exposure_s() const override { return exposure_s_; }
    Status setGain(double gain) override;
    double gain() const override { return gain_; }
    Status setFormat(hdr::RawFormat format) override;
    hdr::RawFormat format() const override { return format_->raw_format; }
    Result<hdr::RawFrame> capture(double timeout_s) override;
    // The capture polls in slices of at most 0.1 s and checks for it between them.
    void abort() override { aborted_ = true; }
    // frames, dropped-stale, dropped-settle, buffer-errors, sequence-gaps, clipped-samples.
    std::vector<std::pair<std::string, int64_t>> statistics() const override;

    // What was chosen, for listings, logs and tests.
    const V4l2FormatInfo& pixelFormat() const { return *format_; }
    V4l2ExposureMode exposureMode() const { return exposure_mode_; }
    double lineTime_s() const { return line_time_s_; }            // 0 unless Lines
    double frameInterval_s() const { return frame_interval_s_; }  // 0 when unknown
    int settleFrames() const { return settle_frames_; }
    uint32_t gainControl() const { return gain_id_; }  // 0: none used
    // Warnings of open (8-bit only, gain not mapped, ...), also logged.
    const std::vector<std::string>& warnings() const { return warnings_; }
    std::vector<std::string> notes() const override { return warnings_; }

private:
    struct Key {
        explicit Key() = default;
    };

public:
    V4l2Camera(Key, std::unique_ptr<V4l2Device> device, V4l2CameraOptions options, std::string uri);

private:
    struct ControlRange {
        uint32_t id = 0;
        int64_t minimum = 0;
        int64_t maximum = 0;
        int64_t step = 1;
        bool present = false;
        bool writable = false;
    };
    struct MappedBuffer {
        std::span<const uint8_t> memory;
    };

    Status initialize();
    Status chooseFormat(const std::vector<uint32_t>& offered, const V4l2FormatInfo* wanted);
    Status applyFormat(const V4l2FormatInfo& info, int64_t width, int64_t height);
    Status setupControls();
    Status setupExposure();
    Status setupGain();
    Status readFrameInterval();
    Status startStreaming();
    void stopStreaming();
    Result<ControlRange> queryRange(uint32_t id);
    Result<int64_t> readControl(uint32_t id);
    Status writeControl(uint32_t id, int64_t value, const char* field);
    Result<int64_t> roundedRaw(const ControlRange& range,
                               double raw,
                               const char* field,
                               double unit,
                               const char* unit_name) const;
    Error ioctlError(const char* name, int error) const;
    Error deviceErr(DeviceFault fault, const std::string& detail) const;
    std::string describe() const;
    int64_t exposureStartNs(const ::v4l2_buffer& buffer) const;

    std::unique_ptr<V4l2Device> device_;
    V4l2CameraOptions options_;
    std::string uri_;
    std::string card_, driver_, bus_;
    std::vector<uint32_t> offered_;  // supported fourccs the device lists, in its order
    const V4l2FormatInfo* format_ = nullptr;
    int64_t width_ = 0, height_ = 0, bytes_per_line_ = 0;
    int bit_depth_ = 16;
    bool msb_aligned_ = false;

    V4l2ExposureMode exposure_mode_ = V4l2ExposureMode::FrameInterval;
    ControlRange exposure_;
    double exposure_unit_s_ = 0.0;
    double line_time_s_ = 0.0;
    double frame_interval_s_ = 0.0;
    double base_interval_s_ = 0.0;  // at open; longer only while an exposure needs it
    ControlRange gain_range_;
    uint32_t gain_id_ = 0;
    double gain_unity_ = 0.0;
    double exposure_s_ = 0.0;
    double gain_ = 1.0;
    double previous_exposure_s_ = 0.0;  // before the last change, for the staleness rule
    int settle_frames_ = 0;

    std::map<uint32_t, bool> wide_;  // control id -> 64-bit, as queried
    std::vector<MappedBuffer> buffers_;
    bool streaming_ = false;
    bool timestamps_monotonic_ = true;  // as the last buffer said
    int64_t change_ns_ = 0;             // monotonic time of the last control change
    int pending_settle_ = 0;
    int64_t last_sequence_ = -1;
    std::vector<std::string> warnings_;
    int64_t frames_ = 0, dropped_stale_ = 0, dropped_settle_ = 0, buffer_errors_ = 0;
    int64_t sequence_gaps_ = 0, clipped_samples_ = 0;
    std::atomic<bool> aborted_{false};
};

// One listing (device.h) of a device: card, driver, bus, capabilities and each format flarelab
// reads with its sizes and layout, the formats it does not, and its exposure and gain controls.
// kind "camera"; a node that cannot capture says so in its details.
DeviceListing describeV4l2Device(V4l2Device& device, const std::string& uri);

// Every /dev/video* node under `dev_dir` that can capture video (others, such as metadata nodes
// of UVC cameras, are left out), in number order; nodes that cannot be opened are listed with
// the reason in their details.
std::vector<DeviceListing> listV4l2Devices(const std::string& dev_dir = "/dev");

// Adds the "v4l2" scheme: opens "v4l2:/dev/videoN?..." (NotFound naming the node when it does
// not exist), lists with listV4l2Devices.
Status addV4l2CameraBackend(CameraRegistry& registry);

}  // namespace flarelab::drivers
