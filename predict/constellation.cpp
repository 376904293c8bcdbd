#include "predict/constellation.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <string>

namespace flarelab::predict {
namespace {

constexpr double kDegree = std::numbers::pi / 180.0;

double dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

bool finite(const Vec3& v) {
    return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]);
}

std::string number(double v) {
    char text[32];
    std::snprintf(text, sizeof text, "%.9g", v);
    return text;
}

}  // namespace

CameraFrame cameraFrame(const CameraPose& pose) {
    const double pan = pose.pan_deg * kDegree;
    const double tilt = pose.tilt_deg * kDegree;
    const double roll = pose.roll_deg * kDegree;
    const double cp = std::cos(pan), sp = std::sin(pan), ct = std::cos(tilt), st = std::sin(tilt);
    // Unrolled: right is horizontal, up = right x forward. At tilt +-90 forward is vertical and
    // the pan still names the direction the image's right points to.
    const Vec3 forward = {ct * sp, ct * cp, st};
    const Vec3 right0 = {cp, -sp, 0.0};
    const Vec3 up0 = {-st * sp, -st * cp, ct};
    // Clockwise as seen from behind: the image's right edge goes down.
    const double cr = std::cos(roll), sr = std::sin(roll);
    CameraFrame frame;
    frame.forward = forward;
    for (int k = 0; k < 3; ++k) {
        frame.right[k] = cr * right0[k] - sr * up0[k];
        frame.up[k] = sr * right0[k] + cr * up0[k];
    }
    return frame;
}

Result<CameraPose> poseLookingAt(const Vec3& position_m, const Vec3& target_m) {
    if (!finite(position_m) || !finite(target_m))
        return makeError(ErrorCode::InvalidArgument, "look-at: a coordinate is not finite");
    const Vec3 d = {target_m[0] - position_m[0], target_m[1] - position_m[1],
                    target_m[2] - position_m[2]};
    const double length = std::sqrt(dot(d, d));
    if (!(length >= 1e-3))
        return makeError(ErrorCode::InvalidArgument,
                         "look-at: the target is " + number(length) +
                             " m from the camera; it must be at least 1 mm away");
    CameraPose pose;
    pose.position_m = position_m;
    const double horizontal = std::hypot(d[0], d[1]);
    pose.tilt_deg = std::atan2(d[2], horizontal) / kDegree;
    pose.pan_deg = horizontal > 0.0 ? std::atan2(d[0], d[1]) / kDegree : 0.0;
    return pose;
}

Vec3 directionFromAzimuthElevation(double azimuth_deg, double elevation_deg) {
    const double az = azimuth_deg * kDegree, el = elevation_deg * kDegree;
    return {std::cos(el) * std::sin(az), std::cos(el) * std::cos(az), std::sin(el)};
}

Vec3 sunDirection(double zenith_deg, double azimuth_deg) {
    return directionFromAzimuthElevation(azimuth_deg, 90.0 - zenith_deg);
}

Result<Constellation> constellationOf(const CameraFrame& frame, const Vec3& to_light) {
    if (!finite(to_light))
        return makeError(ErrorCode::InvalidArgument, "light direction: not finite");
    const double length = std::sqrt(dot(to_light, to_light));
    if (!(length >= 1e-9))
        return makeError(ErrorCode::InvalidArgument,
                         "light direction: the light is at the camera's position");
    const double f = dot(frame.forward, to_light) / length;
    const double x = dot(frame.right, to_light) / length;
    const double y = -dot(frame.up, to_light) / length;  // image y points down
    Constellation c;
    // atan2 of the sideways and forward parts: accurate near 0 and 180, where acos is not.
    c.theta_deg = std::atan2(std::hypot(x, y), f) / kDegree;
    c.phi_deg = (x == 0.0 && y == 0.0) ? 0.0 : std::atan2(y, x) / kDegree;
    if (c.phi_deg <= -180.0) c.phi_deg = 180.0;
    return c;
}

Result<double> brightnessScale(double capture_f_number,
                               const CameraExposure& scene,
                               double light_ratio) {
    const auto positive = [](double v) { return std::isfinite(v) && v > 0.0; };
    if (!positive(capture_f_number))
        return makeError(
            ErrorCode::InvalidArgument,
            "brightness: the capture's f-number must be > 0, got " + number(capture_f_number));
    if (!positive(scene.f_number))
        return makeError(ErrorCode::InvalidArgument,
                         "brightness: f_number must be > 0, got " + number(scene.f_number));
    if (!positive(scene.exposure_s))
        return makeError(ErrorCode::InvalidArgument,
                         "brightness: exposure_s must be > 0, got " + number(scene.exposure_s));
    if (!positive(scene.gain))
        return makeError(ErrorCode::InvalidArgument,
                         "brightness: gain must be > 0, got " + number(scene.gain));
    if (!(std::isfinite(light_ratio) && light_ratio >= 0.0))
        return makeError(ErrorCode::InvalidArgument,
                         "brightness: the light ratio must be >= 0, got " + number(light_ratio));
    const double aperture = capture_f_number / scene.f_number;
    return aperture * aperture * scene.exposure_s * scene.gain * light_ratio;
}

}  // namespace flarelab::predict
