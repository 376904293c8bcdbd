// ============================================================================
//  flarelab drivers: V4l2Playback, V4l2PlaybackOptions, V4l2PlaybackFrame, makeV4l2Playback
// ============================================================================
//
// A V4L2 device played back from a recorded `v4l2-ctl --all --list-formats-ext` dump
// (v4l2_dump.h), behind the same seam as a real node (v4l2_device.h), so that the camera's
// format choice, control mapping, buffer handling and frame dropping are tested against what
// real drivers report without the drivers. It is a model for tests, not a device: its answers
// follow the V4L2 specification as far as the camera uses it, and where a real driver may do
// otherwise (how it rounds a control, how it picks a size) it does what the V4L2 core and most
// drivers do, said below; nothing it does is evidence that a real device behaves so.
//
// What it answers: QUERYCAP, ENUM_FMT, ENUM_FRAMESIZES, G/S/TRY_FMT (an unknown fourcc becomes
// the first format; a size becomes the nearest listed one, or is clamped to a stepwise range and
// step), G/S_PARM (time per frame, snapped to a listed interval), QUERYCTRL, QUERY_EXT_CTRL
// (NEXT_CTRL included), QUERYMENU, G/S_CTRL, G/S/TRY_EXT_CTRLS (integers clamped to their range
// and rounded to their step as the V4L2 core does; read-only controls refuse with EACCES,
// menus refuse indices they do not list with EINVAL), REQBUFS (MMAP only), QUERYBUF, QBUF, DQBUF,
// STREAMON, STREAMOFF; anything else is ENOTTY.
//
// Time is simulated: the device's clock moves only when waitForFrame waits, so tests are
// instant and deterministic. After STREAMON frame k starts its exposure when frame k - 1's
// started plus max(time per frame, its exposure); it is done exposure + readout_s later and lands
// in the oldest queued buffer (with no buffer queued it is dropped, its sequence number skipped).
// Its timestamp marks the end of the frame (V4L2_BUF_FLAG_TSTAMP_SRC_EOF), or the start of its
// exposure with start_of_exposure. A control change at time t reaches the frames whose exposure
// starts at or after t + control_latency_frames frame periods (a pipelining sensor driver).
// Each sample is scene(x, y, frame) clipped to the format's bits, packed as the format lays it.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>

#include "common/result.h"
#include "drivers/v4l2_device.h"
#include "drivers/v4l2_dump.h"

namespace flarelab::drivers {

// What a frame was exposed with, for the scene.
struct V4l2PlaybackFrame {
    int64_t sequence = 0;
    int64_t exposure_start_ns = 0;
    std::map<uint32_t, int64_t> controls;  // control id -> value applied to this frame
    int bits = 8;                          // of the format being filled
};

struct V4l2PlaybackOptions {
    int64_t start_ns = 1'000'000'000;                        // the monotonic clock at creation
    int64_t realtime_offset_ns = 1'700'000'000'000'000'000;  // realtime = monotonic + this
    double readout_s = 0.002;
    // The exposure of a frame, in seconds, from its controls; by default exposure_time_absolute
    // in 100 us units when the device has it, else nothing (0).
    std::function<double(const V4l2PlaybackFrame&)> exposure_s;
    bool start_of_exposure = false;
    // V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC by default; UNKNOWN or COPY to test cameras that cannot
    // compare timestamps with the host's clock.
    uint32_t timestamp_type = 0x00002000;
    int control_latency_frames = 0;
    int64_t disconnect_after_frames = -1;  // then every call fails with ENODEV; < 0: never
    int64_t error_every = 0;               // every n-th frame has V4L2_BUF_FLAG_ERROR; 0: none
    // Sample values; by default (x + 2 y) modulo 2^bits.
    std::function<uint32_t(int64_t x, int64_t y, const V4l2PlaybackFrame&)> scene;
};

class V4l2Playback : public V4l2Device {
public:
    // Lets the simulated clock run on by `ns` (>= 0) as for a node nobody reads: frames fill the
    // queued buffers, then are dropped.
    virtual void advance(int64_t ns) = 0;
};

// NotFound naming the dump's source when it lacks "Driver Info" or the format list.
Result<std::unique_ptr<V4l2Playback>> makeV4l2Playback(V4l2DeviceDump dump,
                                                       V4l2PlaybackOptions options = {});

}  // namespace flarelab::drivers
