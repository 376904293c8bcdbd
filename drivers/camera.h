// ============================================================================
//  flarelab drivers: Camera, CameraCapabilities, CameraResponse, CameraRegistry
// ============================================================================
//
// The interface every camera backend implements: the simulated camera (sim_camera.h), GigE
// Vision through Aravis (aravis_camera.h), V4L2 (v4l2_camera.h) and libcamera
// (libcamera_camera.h). A camera has one exposure time and one gain at a time; capture() takes
// one raw frame with them and returns it with everything the bracket merge needs
// (hdr/raw_frame.h): the exposure and gain the camera applied (read back from it where it can
// say), black and white level, bit depth, read noise and conversion gain when the camera knows
// them, the camera's and the host's timestamps and what the camera's marks, and the sequence
// number.
//
// Errors are device errors (device.h): a setting outside the camera's range is [out-of-range]
// naming the field (exposure_s, gain, format); a frame that does not arrive within the timeout
// is [timeout]; a camera that is gone is [disconnected]; a capture ended by abort() is [stopped].
// A failed call leaves the settings as they were. Cameras are not copied; a Camera object is used
// from one thread at a time, except abort(), which any thread may call at any time.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "common/result.h"
#include "drivers/device.h"
#include "hdr/raw_frame.h"

namespace flarelab::drivers {

// Whether a camera's samples are proportional to the light (after the black level), as the
// bracket merge assumes. A camera known to be NonLinear (a webcam's gamma curve, Aravis's fake
// camera, whose test pattern grows with the logarithm of the exposure) must have its response
// calibrated (calibration.h) before its brackets are merged; Unknown is a camera whose backend
// cannot tell (`flarelab calibrate` measures it).
enum class CameraResponse { Linear, NonLinear, Unknown };

struct CameraCapabilities {
    int64_t width_px = 0;  // of the frames capture() returns
    int64_t height_px = 0;
    std::vector<hdr::RawFormat> formats;  // setFormat accepts these
    int bit_depth = 16;                   // of the converter: samples lie in 0 .. 2^bit_depth - 1
    double min_exposure_s = 0.0;
    double max_exposure_s = 0.0;
    double min_gain = 1.0;  // linear; 1 is the sensor's unity setting
    double max_gain = 1.0;
    double black_level_dn = 0.0;
    double white_level_dn = 65535.0;  // the largest unclipped value
    // At gain 1; 0 where the camera does not say. Per frame, RawFrame carries them at its gain.
    double read_noise_e = 0.0;
    double electrons_per_dn = 0.0;
    CameraResponse response = CameraResponse::Linear;
    std::string response_note;  // why the backend says so, for messages; may be empty
};

class Camera {
public:
    Camera() = default;
    Camera(const Camera&) = delete;
    Camera& operator=(const Camera&) = delete;
    virtual ~Camera() = default;

    virtual DeviceIdentity identity() const = 0;
    virtual CameraCapabilities capabilities() const = 0;

    // [out-of-range] naming exposure_s outside [min_exposure_s, max_exposure_s] or not finite.
    virtual Status setExposure(double exposure_s) = 0;
    virtual double exposure_s() const = 0;
    // [out-of-range] naming gain outside [min_gain, max_gain] or not finite.
    virtual Status setGain(double gain) = 0;
    virtual double gain() const = 0;
    // [out-of-range] naming format when it is not in capabilities().formats.
    virtual Status setFormat(hdr::RawFormat format) = 0;
    virtual hdr::RawFormat format() const = 0;

    // Takes one frame with the current settings, waiting at most timeout_s (> 0) for it:
    // [timeout] when it does not come, [disconnected] when the camera is gone,
    // [out-of-range] naming timeout_s when it is not a positive finite number.
    virtual Result<hdr::RawFrame> capture(double timeout_s) = 0;

    // Stops the camera from another thread, so that a job stops within moments even during a
    // long exposure: a capture in progress returns [stopped] within about 0.1 s, and so does every
    // capture after it (an aborted camera takes no more frames; open it again for more). Sticky,
    // so that an abort that comes just before a capture begins is not lost. Safe to call from any
    // thread, at any time, more than once; it waits for nothing.
    virtual void abort() = 0;

    // Counters of the camera's transport since it was opened, for the log of a sweep (GigE
    // Vision: completed and failed buffers, underruns, resent and missing packets). Empty where
    // the backend keeps none.
    virtual std::vector<std::pair<std::string, int64_t>> statistics() const { return {}; }
    // What the backend chose on its own and a lab should know (an 8-bit format because the
    // camera has no deeper one, a gain unit it assumed): one sentence each; empty when nothing.
    virtual std::vector<std::string> notes() const { return {}; }
    // The power of the rig light's own image, summed over the sensor, in DN/s at unity gain, for
    // the sweep's record (hdr/sweep.h, camera.light_power_dn_s) and the lab figures of a model;
    // nullopt where the camera does not know it (a real camera: the light's core saturates a
    // bracket, so a lab measures it apart and gives it to `flarelab fit`).
    virtual std::optional<double> lightPowerDnPerS() const { return std::nullopt; }
};

// Cameras by URI: "sim:?lens=data/lenses/heliar-tronnier.csv" (sim_camera.h),
// "aravis:Fake_1", "v4l2:/dev/video0", "libcamera:NAME" (rig.h opens them all).
using CameraRegistry = DeviceRegistry<Camera>;

}  // namespace flarelab::drivers
