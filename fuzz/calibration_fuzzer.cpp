// libFuzzer target for camera calibration files (drivers/calibration.h).
//
// Any byte string goes to parseCalibration, the code readCalibration runs on a file. A rejection
// must name the input and be a parse error or an unsupported format. An acceptance must keep the
// file's rules (rechecked here independently of the parser) and survive a round trip:
// formatCalibration accepts it, and its text parses back to the same calibration and formats to
// the same text. An accepted calibration of a small frame is then applied to a frame of its
// camera, which must succeed and keep the frame's size. Every violation is a trap, so libFuzzer
// records the input.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "drivers/calibration.h"

namespace {

using namespace flarelab;
using namespace flarelab::drivers;

constexpr char kSource[] = "fuzz-input";

void require(bool condition) {
    if (!condition) __builtin_trap();
}

void requireValid(const CameraCalibration& c) {
    require(c.width_px >= 1 && c.width_px <= 32768 && c.height_px >= 1 && c.height_px <= 32768);
    require(c.bit_depth >= 8 && c.bit_depth <= 16);
    require(std::isfinite(c.gain) && c.gain > 0.0);
    require(std::isfinite(c.saturation_dn) && c.saturation_dn > 0.0 &&
            c.saturation_dn <= std::ldexp(1.0, c.bit_depth) - 1.0);
    require(std::isfinite(c.black_level_dn) && c.black_level_dn >= 0.0 &&
            c.black_level_dn < c.saturation_dn);
    for (const double x : {c.linearity_error, c.read_noise_dn, c.read_noise_e, c.electrons_per_dn})
        require(std::isfinite(x) && x >= 0.0);
    require(c.linear == !c.response_curve.has_value());
    if (c.response_curve) {
        const ResponseCurve& r = *c.response_curve;
        require(r.dn.size() == r.relative_exposure.size() && r.dn.size() >= 2);
        for (size_t i = 0; i < r.dn.size(); ++i) {
            require(r.dn[i] > c.black_level_dn && r.dn[i] <= c.saturation_dn);
            require(std::isfinite(r.relative_exposure[i]) && r.relative_exposure[i] > 0.0);
            if (i > 0) require(r.dn[i] > r.dn[i - 1]);
            if (i > 0) require(r.relative_exposure[i] > r.relative_exposure[i - 1]);
        }
    }
    for (size_t i = 0; i < c.hot_pixels.size(); ++i) {
        require(c.hot_pixels[i] >= 0 && c.hot_pixels[i] < c.width_px * c.height_px);
        if (i > 0) require(c.hot_pixels[i] > c.hot_pixels[i - 1]);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size > static_cast<size_t>(kCalibrationMaxFileBytes)) return 0;  // the reader's limit
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    const Result<CameraCalibration> calibration = parseCalibration(text, kSource);
    if (!calibration) {
        require(calibration.error().message.rfind(std::string(kSource) + ": ", 0) == 0);
        require(calibration.error().code == ErrorCode::ParseError ||
                calibration.error().code == ErrorCode::Unsupported);
        return 0;
    }
    requireValid(*calibration);

    const Result<std::string> json = formatCalibration(*calibration);
    require(json.has_value());
    const Result<CameraCalibration> again = parseCalibration(*json, kSource);
    require(again.has_value());
    require(*again == *calibration);
    const Result<std::string> json_again = formatCalibration(*again);
    require(json_again.has_value() && *json_again == *json);

    const CameraCalibration& c = *calibration;
    if (c.width_px * c.height_px <= 4096) {
        hdr::RawFrame frame;
        frame.width = c.width_px;
        frame.height = c.height_px;
        frame.format = c.format;
        frame.bit_depth = c.bit_depth;
        frame.gain = 1.0;
        frame.exposure_s = 1.0;
        frame.camera = calibrationCameraName(c);
        const auto top = static_cast<uint32_t>(std::ldexp(1.0, c.bit_depth));
        for (int64_t i = 0; i < frame.width * frame.height; ++i)
            frame.samples.push_back(static_cast<uint16_t>((i * 2654435761u) % top));
        const Result<hdr::RawFrame> applied = applyCalibration(frame, c);
        require(applied.has_value());
        require(applied->samples.size() == frame.samples.size());
        require(std::isfinite(applied->read_noise_dn) && std::isfinite(applied->electrons_per_dn));
    }
    return 0;
}
