// ============================================================================
//  flarelab predict: CameraPose, LightDirection, Constellation, cameraFrame, constellationOf,
//                    sunDirection, CameraExposure, brightnessScale
// ============================================================================
//
// Where a light stands as a camera sees it, and how bright its flare is for that camera.
//
// World frame (scenes, the sun): right-handed, metres, x east, y north, z up. A camera's optical
// axis points along its pan (a compass heading: degrees clockwise from north, east = 90) and tilt
// (degrees above the horizon); its roll turns the camera clockwise about the axis as seen from
// behind it (the horizon then leans anticlockwise in the image).
//
// Constellation (DESIGN.md; eq. 8.1 and 8.2 of the thesis): theta is the angle between the optical
// axis and the direction from the camera to the light, phi the light's roll about the axis in
// image space (x right, y down: the direction from the image centre towards where the light is
// imaged, 0 to the right, 90 straight down). That is the convention of optics/lens.h and
// fit/model_eval.h, so a model is drawn at (theta, phi) directly.
//
// Brightness (eq. 8.3 of the thesis): a model holds DN per second at unity gain at the capture's
// f-number for the rig's light; the scene's camera reads that times its exposure time, its gain
// relative to the capture's, (f_capture / f_scene)^2 and the scene light's irradiance at the lens
// relative to the rig light's.
#pragma once

#include <array>
#include <optional>

#include "common/result.h"

namespace flarelab::predict {

using Vec3 = std::array<double, 3>;

struct CameraPose {
    Vec3 position_m = {0.0, 0.0, 0.0};
    double pan_deg = 0.0;   // heading of the optical axis, clockwise from north; any finite value
    double tilt_deg = 0.0;  // elevation of the axis above the horizon, [-90, 90]
    double roll_deg = 0.0;  // clockwise about the axis as seen from behind; any finite value
};

// The camera's axes in the world frame, each a unit vector: forward along the optical axis, right
// and up as the image shows them (up is the image's -y). At tilt +-90 the pan still turns the
// camera about the axis, so the frame is defined everywhere.
struct CameraFrame {
    Vec3 forward;
    Vec3 right;
    Vec3 up;
};
CameraFrame cameraFrame(const CameraPose& pose);

// The pose at `position_m` whose axis points at `target_m`, with no roll. InvalidArgument when
// the two points are closer than 1 mm or any coordinate is not finite.
Result<CameraPose> poseLookingAt(const Vec3& position_m, const Vec3& target_m);

// A direction in the world by its compass azimuth (clockwise from north) and elevation above the
// horizon, as a unit vector.
Vec3 directionFromAzimuthElevation(double azimuth_deg, double elevation_deg);

// The sun's direction from its topocentric zenith and azimuth (predict/sun.h: azimuth eastward from
// north), as a unit vector pointing at the sun.
Vec3 sunDirection(double zenith_deg, double azimuth_deg);

struct Constellation {
    double theta_deg = 0.0;  // [0, 180]; 90 and beyond: behind the camera
    double phi_deg = 0.0;    // (-180, 180]; 0 when theta is 0 (on the axis the roll is undefined)
};

// The constellation of a light in direction `to_light` (from the camera towards the light; any
// non-zero length) for a camera with `frame`. InvalidArgument when `to_light` is shorter than
// 1e-9 or not finite: a light at the camera's own position has no direction.
Result<Constellation> constellationOf(const CameraFrame& frame, const Vec3& to_light);

// A camera's exposure as eq. 8.3 needs it. `gain` is relative to the capture's (1: as captured).
struct CameraExposure {
    double f_number = 0.0;    // > 0
    double exposure_s = 1.0;  // > 0
    double gain = 1.0;        // > 0
};

// Eq. 8.3: what a model value (DN/s at unity gain, at f_capture, for the rig's light) becomes in
// the scene camera's image, for a light whose irradiance at the lens is `light_ratio` times the
// rig light's. InvalidArgument for a non-positive or non-finite f-number, exposure, gain or a
// negative light ratio.
Result<double> brightnessScale(double capture_f_number,
                               const CameraExposure& scene,
                               double light_ratio);

}  // namespace flarelab::predict
