// ============================================================================
//  flarelab drivers: V4l2Device, openV4l2Node
// ============================================================================
//
// The seam between the V4L2 camera (v4l2_camera.h) and the kernel: every ioctl, mmap and poll
// the camera makes goes through a V4l2Device, so that the camera's logic (format choice, control
// mapping, buffer handling, dropping stale frames) runs unchanged against a real device node
// (openV4l2Node) or against a recorded device played back (v4l2_playback.h). The interface is
// the kernel's own: ioctl requests and structures of linux/videodev2.h, so nothing of V4L2 is
// re-described here.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>

#include "common/result.h"

namespace flarelab::drivers {

class V4l2Device {
public:
    V4l2Device() = default;
    V4l2Device(const V4l2Device&) = delete;
    V4l2Device& operator=(const V4l2Device&) = delete;
    virtual ~V4l2Device() = default;

    // ioctl(2) on the open node with a videodev2.h request and its structure: 0, or the errno it
    // failed with (interrupted calls are repeated).
    virtual int ioctl(unsigned long request, void* argument) = 0;
    // Maps `length` bytes of a buffer at `offset` (VIDIOC_QUERYBUF's m.offset) for reading.
    // IoError naming the errno when it cannot.
    virtual Result<std::span<const uint8_t>> map(uint32_t length, uint32_t offset) = 0;
    virtual void unmap(std::span<const uint8_t> mapping) = 0;
    // Waits at most timeout_ms (>= 0) for a filled buffer: 1 when one can be dequeued, 0 when
    // none came in time, or -errno; -EPIPE when the node reports an error condition (POLLERR: no
    // buffer queued, or the device is gone: VIDIOC_DQBUF then says which).
    virtual int waitForFrame(int timeout_ms) = 0;
    // The clocks of buffer timestamps (CLOCK_MONOTONIC) and of the host's frame time
    // (CLOCK_REALTIME), in ns.
    virtual int64_t monotonicNs() const = 0;
    virtual int64_t realtimeNs() const = 0;
    // "/dev/video0", or what a playback device was made from.
    virtual const std::string& path() const = 0;
};

// Opens a device node for reading and writing, non-blocking. NotFound when it does not exist;
// IoError naming the path when it is not a character device or cannot be opened (EACCES: the
// message says to join the group that owns it, usually "video").
Result<std::unique_ptr<V4l2Device>> openV4l2Node(const std::string& path);

}  // namespace flarelab::drivers
