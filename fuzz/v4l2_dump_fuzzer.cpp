// Fuzz target: arbitrary text as a `v4l2-ctl --all --list-formats-ext` dump (drivers/v4l2_dump.h).
// What parses is played back as a device (drivers/v4l2_playback.h) and opened by the V4L2 camera,
// so odd ranges, flags, menus and sizes a device could report go through the control mapping
// and format choice too; small frames are captured and must respect their bit depth.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string_view>

#include "drivers/v4l2_camera.h"
#include "drivers/v4l2_dump.h"
#include "drivers/v4l2_playback.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace flarelab::drivers;
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    auto dump = parseV4l2Dump(text, "fuzz input");
    if (!dump) {
        if (dump.error().message.rfind("fuzz input:", 0) != 0) std::abort();  // names no line
        return 0;
    }
    auto device = makeV4l2Playback(*dump);
    if (!device) return 0;
    describeV4l2Device(**device, "v4l2:fuzz");
    auto camera = V4l2Camera::open(std::move(*device), V4l2CameraOptions{});
    if (!camera) return 0;
    V4l2Camera& c = **camera;
    const CameraCapabilities caps = c.capabilities();
    (void)c.setExposure(caps.max_exposure_s);
    (void)c.setGain(caps.max_gain);
    if (caps.width_px * caps.height_px > (int64_t{1} << 14)) return 0;
    auto frame = c.capture(0.5);
    if (!frame) return 0;
    if (frame->width != caps.width_px || frame->height != caps.height_px ||
        frame->samples.size() != static_cast<size_t>(frame->width * frame->height))
        std::abort();
    for (uint16_t v : frame->samples)
        if (v > frame->white_level_dn) std::abort();
    return 0;
}
