// ============================================================================
//  flarelab drivers: LibcameraCamera, listLibcameraCameras, addLibcameraCameraBackend
// ============================================================================
//
// Cameras through libcamera, against the 0.0.3 API that Debian 12 ships (libcamera-dev
// 0.0.3-6). Built only where pkg-config finds libcamera (drivers/CMakeLists.txt); this header
// includes no libcamera header, so that whatever includes it builds without libcamera's include
// path. The parts that need no camera (formats, unpacking, controls, metadata, URIs) are in
// libcamera_mapping.h and unit-tested there.
//
// NEVER RUN AGAINST A CAMERA. The machines flarelab is built on have no camera libcamera can
// open; what is tested is everything up to the camera (libcamera_camera_test.cpp) and that the
// backend lists no camera and refuses to open a missing one without crashing. docs/lab.md
// ("libcamera cameras") says how to test it on real hardware.
//
// One camera, "libcamera:NAME?width=W&height=H&format=F" (libcamera_mapping.h, LibcameraCamera-
// Options), opens as follows:
//   - the process's one CameraManager is started (libcamera allows one at a time: cameras and the
//     lister share it, and it stops when the last of them lets go);
//   - the camera named NAME is acquired (EBUSY: [busy], another program has it);
//   - a configuration for StreamRole::Raw is generated, its format and size chosen from what
//     the stream offers (chooseLibcameraFormat), validated (an adjusted one is taken if it is
//     still readable and keeps what the URI asked for: acceptValidatedFormat) and applied;
//   - ExposureTime and AnalogueGain ranges are read from the configured camera (an absent one
//     refuses the camera: it cannot be exposed by hand);
//   - a FrameBufferAllocator gives the stream's buffers; one is memory-mapped and carried by the
//     one Request the camera reuses; the camera is started with AE off and the initial settings.
// Each capture queues that request with AeEnable = false (where the camera has AeEnable),
// ExposureTime and AnalogueGain, and waits for requestCompleted until its timeout, never longer
// (a request still out when the timeout passes is waited for by the next capture). A completed
// frame whose metadata does not yet show the requested exposure and gain (sensors apply controls
// a few frames late) is dropped and the request queued again: LibcameraSettleTracker decides.
// The frame that does is unpacked to 16-bit samples and returned with the metadata's exposure,
// gain, black level and SensorTimestamp (the start of the exposure, as libcamera defines it;
// libcamera 0.0.3's pipelines copy it from the V4L2 buffer time, which on many CSI-2 receivers
// is the start of the frame's readout: check it on the lab's camera) and the host's clock.
//
// Faults: a camera that emits Camera::disconnected (unplugged) answers [disconnected] from then
// on; frames the pipeline marks FrameError are dropped and counted (statistics()).
//
// libcamera logs to stderr by default (a warning about missing IPA modules on every start on a
// machine without libcamera-ipa). Unless LIBCAMERA_LOG_FILE or LIBCAMERA_LOG_LEVELS is set (then
// libcamera logs as they say), its messages go to an in-memory sink instead; the last warnings
// and errors are appended to the errors of this backend, where they explain a failure.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "common/result.h"
#include "drivers/camera.h"
#include "drivers/device.h"
#include "drivers/libcamera_mapping.h"

namespace flarelab::drivers {

class LibcameraCamera final : public Camera {
public:
    // Opens the camera a "libcamera:" URI names (see above). InvalidArgument for a bad URI,
    // NotFound naming the camera when libcamera does not see it, [busy] when another program holds
    // it, Unsupported when it has no raw stream flarelab reads or no manual exposure, IoError when
    // libcamera refuses a step (the message says which and what libcamera logged).
    static Result<std::unique_ptr<LibcameraCamera>> open(const DeviceUri& uri);
    ~LibcameraCamera() override;

    DeviceIdentity identity() const override;
    CameraCapabilities capabilities() const override;
    Status setExposure(double exposure_s) override;
    double exposure_s() const override;
    Status setGain(double gain) override;
    double gain() const override;
    // Only the layout of the configured stream (its Bayer order, or Mono); another format is
    // chosen when opening (format= in the URI).
    Status setFormat(hdr::RawFormat format) override;
    hdr::RawFormat format() const override;
    Result<hdr::RawFrame> capture(double timeout_s) override;
    // Wakes the capture's wait for its request at once; the request stays queued and is never
    // read.
    void abort() override;
    // completed, failed (FrameError), discarded (not yet showing the settings), cancelled.
    std::vector<std::pair<std::string, int64_t>> statistics() const override;

    struct State;  // libcamera's objects; defined in libcamera_camera.cpp
    explicit LibcameraCamera(std::unique_ptr<State> state);

private:
    std::unique_ptr<State> state_;
};

// The cameras libcamera sees now: "libcamera:ID", the model, location and the raw formats and
// sizes of each. When libcamera cannot start, one listing for "libcamera:" whose details say why.
std::vector<DeviceListing> listLibcameraCameras();

// Adds the "libcamera" scheme (LibcameraCamera::open and listLibcameraCameras) to a registry.
Status addLibcameraCameraBackend(CameraRegistry& registry);

// libcamera's version string ("v0.0.3"), for messages and `flarelab rig devices`.
std::string libcameraVersion();

// The name libcamera gives a pixel format (PixelFormat::toString()), to hold the names of
// libcamera_mapping.h against it.
std::string libcameraFormatName(uint32_t fourcc, uint64_t modifier);

}  // namespace flarelab::drivers
