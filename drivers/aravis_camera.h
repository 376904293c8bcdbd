// ============================================================================
//  flarelab drivers: AravisCamera, AravisOptions, aravisOptions, addAravisCameraBackend
// ============================================================================
//
// GigE Vision (and USB3 Vision) cameras through Aravis 0.8's public C API (ArvCamera,
// ArvDevice, ArvStream, ArvBuffer). Built only where pkg-config finds aravis-0.8
// (drivers/CMakeLists.txt); rig.cpp then registers the "aravis" scheme.
//
// URI: "aravis:" DEVICE ["?" parameters], DEVICE an Aravis device id ("Aravis-Fake-GV01",
// "Basler-40012345"; `flarelab rig devices` or `arv-tool-0.8` lists them), a camera's IP address
// ("192.168.10.2"), or empty for the first camera Aravis finds. Parameters (any other is
// refused by name):
//   roi=X,Y,W,H        region of interest in sensor pixels (default: the whole sensor)
//   pixel_format=NAME  a PFNC name the camera offers (Mono12, BayerRG12p, ...; default: the
//                      best it offers, genicam_pixels.h)
//   packet_size=BYTES  GigE Vision stream packet size (9000 for jumbo frames; default: the
//                      camera's). The camera's value is read back and used.
//   socket_buffer=BYTES  receive buffer of the stream's UDP socket (default: as large as a
//                      frame). Above the kernel's limit net.core.rmem_max the open fails with
//                      the sysctl to run, because the kernel would silently give less. Where it
//                      may (root, CAP_NET_RAW), Aravis reads the stream through a packet-socket
//                      ring instead, which has no such buffer; giving socket_buffer keeps the
//                      UDP socket.
//   timeout_s=S        how long opening (and each reopening) looks for the camera (default 3)
//   retries=N          how often capture() retakes a damaged frame before failing (default 2)
//   trigger=software|single-frame  how one frame is taken per exposure (default: software
//                      trigger where the camera has it, else single-frame acquisition)
//   gain_db_per_raw=DB the gain step of a camera with only GainRaw, in dB per raw unit (its
//                      manual says; Basler's ace GigE: 0.0359). Without it such a camera is held
//                      at its lowest raw gain, reported as gain 1, and setGain accepts only 1.
//
// Features, with the fallbacks of older cameras (SFNC names first): ExposureTime or
// ExposureTimeAbs (microseconds); Gain (dB unless its unit says "x" or "times") or GainRaw;
// ExposureAuto and GainAuto are switched Off; AcquisitionMode; TriggerSelector=FrameStart,
// TriggerMode, TriggerSource=Software, TriggerSoftware.
//
// One frame per exposure. With a software trigger the acquisition runs continuously (Continuous
// mode, TriggerMode On) and each capture() fires TriggerSoftware and waits for its frame; in
// single-frame mode each capture() starts an acquisition of one frame and stops it. Frames come
// into a pool of buffers; capture() waits with arv_stream_timeout_pop_buffer in short slices up
// to its timeout and never longer. Frames whose leader arrived before the trigger (left from a
// failed capture) are put back and not returned.
//
// Every frame carries the exposure and gain read back from the camera after they were set (what
// it applied, rounded to its steps), the camera's timestamp (the GVSP leader's, converted to ns
// by Aravis from GevTimestampTickFrequency), the host's CLOCK_REALTIME when capture() had the
// frame, and the sequence: the camera's frame id (GVSP block id) unwrapped to 64 bits (GigE
// Vision 1.x ids wrap after 65535 and skip 0), continuing across reopens. What the timestamp
// marks: the GigE Vision standard leaves the latch point to the camera; the cameras whose
// manuals we read (Basler, Teledyne DALSA, FLIR) latch it at frame start, the start of the
// exposure of a triggered frame, so frames say TimestampMark::ExposureStart. Aravis's fake
// camera stamps a frame with its host's real-time clock when it fills it; it has no exposure,
// so that instant also stands for the start. A restarted camera restarts its clock.
//
// Failures (device.h tags):
//   [timeout]       no frame within the timeout while the camera still answers
//   [bad-frame]     a frame came damaged; the message names the Aravis buffer status
//                   (missing-packets, timeout: packets stopped before the frame was complete,
//                   size-mismatch, wrong-packet-id, ...). capture() retakes it up to `retries`
//                   times (retrying a size mismatch with buffers of the camera's payload size).
//   [disconnected]  the control channel no longer answers (a GVCP read or write timed out:
//                   Aravis tries 5 x 500 ms) or Aravis's heartbeat reported "control-lost".
//                   The call that finds it returns at once; the Aravis objects are released in
//                   the background. The next call reopens the camera (by the same id or address,
//                   refusing a different serial) and applies every setting again: pixel format,
//                   region, packet size, socket buffer, trigger, exposure, gain. Reopening is
//                   tried at most every 0.25, 0.5, 1, 2, then 4 s; calls in between answer
//                   [disconnected] at once.
//   [busy]          another application holds the camera's control channel.
//   [out-of-range]  a setting outside the camera's range, naming exposure_s, gain or format.
//
// Response. Aravis's fake camera (vendor "Aravis", model "Fake") draws a diagonal ramp that it
// scales by 1 + GainRaw + log10(ExposureTimeAbs / 10000 us) and clips (arv_fake_camera_
// diagonal_ramp in Aravis's src/arvfakecamera.c): its brightness grows with the logarithm of
// the exposure, is 0 at 1 ms and below with GainRaw 0, and the ramp moves one step per frame id.
// It is reported NonLinear with that note; every other camera Linear (raw GenICam output;
// `flarelab calibrate` measures it).
//
// statistics(): the stream's counters (Aravis's stream infos: completed_buffers, failures,
// underruns, timeouts, missing_frames, size_mismatch_errors, received_packets, missing_packets,
// resend_requests, resent_packets, ...) summed over every connection since open, plus the
// backend's own: retaken_frames, disconnects, reopens.
//
// Threads: Aravis runs a stream thread and a heartbeat thread per connection; this object is
// used from one thread at a time (camera.h). Aravis's device list is global, so opening and
// listing take one process-wide lock.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include "drivers/camera.h"
#include "drivers/device.h"
#include "drivers/genicam_pixels.h"

namespace flarelab::drivers {

enum class AravisTrigger { Auto, Software, SingleFrame };

struct AravisRoi {
    int64_t x = 0, y = 0, width = 0, height = 0;
    bool operator==(const AravisRoi&) const = default;
};

// What an "aravis:" URI asks for (parameters above).
struct AravisOptions {
    std::string device;  // id or address; empty: the first camera found
    std::optional<AravisRoi> roi;
    std::string pixel_format;   // PFNC name; empty: the best the camera offers
    int64_t packet_size = 0;    // bytes; 0: the camera's
    int64_t socket_buffer = 0;  // bytes; 0: as large as a frame
    double timeout_s = 3.0;     // > 0
    int retries = 2;            // >= 0
    AravisTrigger trigger = AravisTrigger::Auto;
    double gain_db_per_raw = 0;  // > 0 when given
    bool operator==(const AravisOptions&) const = default;
};

// InvalidArgument naming the parameter that is unknown or out of range (roi needs four
// integers, x, y >= 0 and w, h >= 1; packet_size 576..65535; socket_buffer 4096..2^31-1;
// timeout_s in (0, 600]; retries 0..100; gain_db_per_raw in (0, 10]).
Result<AravisOptions> aravisOptions(const DeviceUri& uri);

// The kernel's net.core.rmem_max in bytes (from /proc/sys/net/core/rmem_max); nullopt when it
// cannot be read.
std::optional<int64_t> kernelReceiveBufferLimit();
// The open error for a socket_buffer above `limit`: names the sysctl and the value to set.
Error socketBufferTooLarge(int64_t asked, int64_t limit);

class AravisCamera final : public Camera {
public:
    // Opens, configures (settings above) and starts the camera. NotFound naming the device when
    // it cannot be found within options.timeout_s; InvalidArgument naming the parameter the
    // camera cannot take (roi outside the sensor or off its steps, a pixel format it does not
    // offer, a socket buffer above net.core.rmem_max); [busy] when another application controls
    // it.
    static Result<std::unique_ptr<AravisCamera>> open(const AravisOptions& options,
                                                      const std::string& uri = "");
    static Result<std::unique_ptr<AravisCamera>> open(const DeviceUri& uri);
    ~AravisCamera() override;

    DeviceIdentity identity() const override;
    CameraCapabilities capabilities() const override;
    Status setExposure(double exposure_s) override;
    double exposure_s() const override;  // as read back from the camera
    Status setGain(double gain) override;
    double gain() const override;  // as read back from the camera
    // Chooses the best pixel format of the layout the camera offers (a pinned pixel_format
    // must have it); [out-of-range] naming format otherwise.
    Status setFormat(hdr::RawFormat format) override;
    hdr::RawFormat format() const override;
    // Waits up to timeout_s for each take; with retakes of damaged frames a call may last
    // (retries + 1) x timeout_s plus the control channel's own timeouts (2.5 s for a camera that
    // stopped answering).
    Result<hdr::RawFrame> capture(double timeout_s) override;
    // The frame wait runs in 50 ms slices and checks for it between them; a single-frame
    // acquisition under way is stopped. A reopen in progress (Aravis's search, ~1 s) ends first.
    void abort() override { aborted_ = true; }
    std::vector<std::pair<std::string, int64_t>> statistics() const override;

    const AravisOptions& options() const { return options_; }
    // The PFNC name of the pixel format in use ("Mono16").
    const std::string& pixelFormatName() const { return pixel_format_.name; }
    // The camera's formats as it lists them, taken or not.
    const std::vector<std::string>& offeredPixelFormats() const { return offered_formats_; }
    int64_t packetSize() const { return packet_size_; }  // read back; 0 for non-GigE cameras
    AravisTrigger trigger() const { return trigger_; }   // Software or SingleFrame
    bool connected() const;
    // What the backend chose and why, for the lab's log: the 8-bit warning, an assumed gain
    // unit, a socket buffer smaller than a frame, a packet size the camera changed.
    std::vector<std::string> notes() const override { return notes_; }

private:
    struct Key {
        explicit Key() = default;
    };

public:
    struct Connection;  // the Aravis objects of one connection (aravis_camera.cpp)
    AravisCamera(Key, AravisOptions options, std::string uri);

private:
    Status connect(double search_s);
    Status configure();
    Status startStream();
    Status ensureConnected();
    Error lose(const std::string& why);
    Error controlError(const std::string& doing, const std::string& detail);
    Result<hdr::RawFrame> takeOnce(double timeout_s);
    Status applyExposure(double exposure_s);
    Status applyGain(double gain);
    Status applyFormat(const GenicamPixelFormat& format);
    Status readRanges();
    void drainStream();
    void retire(std::unique_ptr<Connection> connection);
    std::string name() const;
    void note(std::string text);

    AravisOptions options_;
    std::string uri_;
    std::unique_ptr<Connection> connection_;  // null while disconnected
    std::vector<std::jthread> reapers_;       // release lost connections (GVCP timeouts: ~5 s)

    // Who the camera is (kept across reconnects).
    std::string vendor_, model_, serial_, device_id_;
    bool fake_ = false;
    bool gige_ = false;
    std::vector<std::string> offered_formats_;
    GenicamPixelFormat pixel_format_;

    // Settings wanted (re-applied on reconnect) and read back.
    double wanted_exposure_s_ = 0.0;
    double wanted_gain_ = 1.0;
    double exposure_s_ = 0.0;
    double gain_ = 1.0;
    AravisTrigger trigger_ = AravisTrigger::Software;
    int64_t packet_size_ = 0;
    int64_t width_ = 0, height_ = 0;

    // Ranges (read at connect).
    std::string exposure_feature_, gain_feature_;
    bool gain_in_db_ = true;
    double min_exposure_s_ = 0.0, max_exposure_s_ = 0.0;
    double min_gain_ = 1.0, max_gain_ = 1.0;
    double min_gain_raw_ = 0.0, max_gain_raw_ = 0.0;

    // Frame ids unwrapped to the sequence.
    int64_t sequence_base_ = 0;
    int64_t last_frame_id_ = -1;
    int64_t last_sequence_ = -1;

    // Reconnection.
    int reopen_failures_ = 0;
    bool reopening_ = false;
    std::chrono::steady_clock::time_point next_reopen_{};
    std::string lost_reason_;

    // Counters.
    std::map<std::string, int64_t> stream_totals_;  // of connections already released
    int64_t retaken_frames_ = 0, disconnects_ = 0, reopens_ = 0;
    std::vector<std::string> notes_;
    std::atomic<bool> aborted_{false};
};

// Adds the "aravis" scheme: opens AravisCamera by URI (above), and lists the cameras Aravis
// discovers (arv_update_device_list: a GigE Vision broadcast on every interface, ~1 s, and the
// USB3 Vision devices), each with vendor, model, serial, address, protocol and pixel formats
// (read by opening the camera briefly: a camera another application controls lists without
// them).
Status addAravisCameraBackend(CameraRegistry& registry);

// The listing of every camera Aravis sees now (as the lister above).
std::vector<DeviceListing> listAravisCameras();

}  // namespace flarelab::drivers
