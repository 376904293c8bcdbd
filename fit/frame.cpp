#include "fit/frame.h"

#include <cmath>
#include <iomanip>
#include <sstream>
#include <utility>

namespace flarelab::fit {

Result<std::array<double, 2>> sweepSensorSize(const hdr::Sweep& sweep,
                                              const std::array<double, 2>* sensor_mm) {
    const auto& lens = sweep.header.lens;
    if (lens.sensor_width_mm && lens.sensor_height_mm) {
        const std::array<double, 2> recorded{*lens.sensor_width_mm, *lens.sensor_height_mm};
        // Equal but for the rounding of a decimal round trip ("36x24" typed again).
        const auto same = [](double a, double b) { return std::abs(a - b) <= 1e-9 * std::abs(b); };
        if (sensor_mm &&
            !(same((*sensor_mm)[0], recorded[0]) && same((*sensor_mm)[1], recorded[1]))) {
            std::ostringstream why;
            why << std::setprecision(17) << "sensor size: " << (*sensor_mm)[0] << " x "
                << (*sensor_mm)[1] << " mm contradicts the " << recorded[0] << " x " << recorded[1]
                << " mm that sweep " << sweep.directory
                << " records (lens.sensor_width_mm, lens.sensor_height_mm), the size its frames "
                   "were taken with; leave the sensor size out";
            return makeError(ErrorCode::InvalidArgument, why.str());
        }
        return recorded;
    }
    if (sensor_mm) {
        if (!((*sensor_mm)[0] > 0.0) || !((*sensor_mm)[1] > 0.0) ||
            !std::isfinite((*sensor_mm)[0]) || !std::isfinite((*sensor_mm)[1]))
            return makeError(ErrorCode::InvalidArgument,
                             "sensor size: width and height must be finite and > 0 mm");
        return *sensor_mm;
    }
    const auto& pitch = sweep.header.camera.pixel_pitch_um;
    if (pitch && *pitch > 0.0 && std::isfinite(*pitch)) {
        const double w = static_cast<double>(sweep.header.capture.width_px) * *pitch * 1e-3;
        const double h = static_cast<double>(sweep.header.capture.height_px) * *pitch * 1e-3;
        if (w > 0.0 && h > 0.0) return std::array<double, 2>{w, h};
    }
    return makeError(ErrorCode::InvalidArgument,
                     "sweep " + sweep.directory +
                         ": the manifest records no camera.pixel_pitch_um, so the sensor size is "
                         "unknown; give it (--sensor-mm WxH)");
}

Result<FitFrame> frameFromImage(ImageRGB image,
                                double angle_deg,
                                double sensor_width_mm,
                                double sensor_height_mm) {
    if (image.empty()) return makeError(ErrorCode::InvalidArgument, "frame: the image is empty");
    if (!std::isfinite(angle_deg))
        return makeError(ErrorCode::InvalidArgument, "frame: the angle is not finite");
    if (!(sensor_width_mm > 0.0) || !(sensor_height_mm > 0.0) || !std::isfinite(sensor_width_mm) ||
        !std::isfinite(sensor_height_mm))
        return makeError(ErrorCode::InvalidArgument, "frame: the sensor size must be > 0 mm");
    bool mono = true;
    for (int64_t y = 0; y < image.height; ++y) {
        for (int64_t x = 0; x < image.width; ++x) {
            const float* p = image.at(x, y);
            for (int c = 0; c < 3; ++c) {
                if (!std::isfinite(p[c]) || p[c] < 0.0f) {
                    std::ostringstream message;
                    message << "frame: pixel (" << x << ", " << y << ") channel " << c << " holds "
                            << p[c] << "; a linear image is finite and >= 0";
                    return makeError(ErrorCode::InvalidArgument, message.str());
                }
            }
            mono = mono && p[0] == p[1] && p[1] == p[2];
        }
    }
    FitFrame frame;
    frame.angle_deg = angle_deg;
    frame.mapping.px_per_mm_x = static_cast<double>(image.width) / sensor_width_mm;
    frame.mapping.px_per_mm_y = static_cast<double>(image.height) / sensor_height_mm;
    frame.mapping.centre_x_px = 0.5 * static_cast<double>(image.width);
    frame.mapping.centre_y_px = 0.5 * static_cast<double>(image.height);
    frame.channels = mono ? 1 : 3;
    frame.image = std::move(image);
    return frame;
}

Result<FitFrame> loadFitFrame(const hdr::Sweep& sweep,
                              size_t index,
                              double sensor_width_mm,
                              double sensor_height_mm) {
    if (index >= sweep.frames.size())
        return makeError(ErrorCode::InvalidArgument,
                         "sweep " + sweep.directory + ": no frame " + std::to_string(index));
    auto exr = hdr::loadFrame(sweep, index);
    if (!exr) return exr.error();
    auto frame = frameFromImage(std::move(exr->image), sweep.frames[index].angle_deg,
                                sensor_width_mm, sensor_height_mm);
    if (!frame)
        return makeError(frame.error().code,
                         sweep.frames[index].exr_file + ": " + frame.error().message);
    frame->lower_bound = std::move(exr->lower_bound);  // the reader gives one per pixel or none
    return frame;
}

}  // namespace flarelab::fit
