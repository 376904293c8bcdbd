// Fuzz target: arbitrary bytes as a planner's scene file (predict/scene.h). A refusal must be a
// ParseError or Unsupported whose message names the scene, in valid UTF-8 (it may travel in a
// protobuf reply); never Internal, which would mean a reader converted a value it had not checked.
// What parses must keep every rule of the header's format, so that the planner can rely on them
// without checking again; and lightRatio must answer every light for every camera. Nothing may
// crash, hang, read out of bounds or overflow.
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <set>
#include <string>
#include <string_view>

#include "common/result.h"
#include "common/utf8.h"
#include "predict/scene.h"

namespace {

using namespace flarelab;
using namespace flarelab::predict;

void require(bool condition) {
    if (!condition) std::abort();
}

bool finite(const Vec3& v) {
    return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]);
}

bool positive(double x) { return std::isfinite(x) && x > 0.0; }
bool nonNegative(double x) { return std::isfinite(x) && x >= 0.0; }

void checkName(const std::string& name, std::set<std::string>& seen) {
    require(validUtf8(name));
    size_t characters = 0;
    for (size_t i = 0; i < name.size(); ++i) {
        const auto c = static_cast<unsigned char>(name[i]);
        require(c >= 0x20 && c != 0x7F);
        if (c == 0xC2 && i + 1 < name.size())
            require(static_cast<unsigned char>(name[i + 1]) > 0x9F);  // no C1 control
        if ((c & 0xC0) != 0x80) ++characters;
    }
    require(characters >= 1 && characters <= 64);
    require(seen.insert(name).second);
}

void checkColour(const std::array<double, 3>& colour) {
    for (const double c : colour) require(nonNegative(c));
    require(colour[0] > 0.0 || colour[1] > 0.0 || colour[2] > 0.0);
}

// Exactly one intensity, each in its range; intensity_cd only where `point`.
void checkIntensity(const LightIntensity& intensity, bool point) {
    const int given = int{intensity.intensity_cd.has_value()} +
                      int{intensity.illuminance_lux.has_value()} +
                      int{intensity.relative.has_value()};
    require(given == 1);
    if (intensity.intensity_cd) require(point && positive(*intensity.intensity_cd));
    if (intensity.illuminance_lux) require(positive(*intensity.illuminance_lux));
    if (intensity.relative) require(nonNegative(*intensity.relative));
}

void checkCamera(const SceneCamera& camera, std::set<std::string>& names) {
    checkName(camera.name, names);
    require(!camera.model_path.empty());
    require(std::string_view(camera.model_path).substr(0, 5) == "base/" ||
            camera.model_path.front() == '/');
    const CameraPose& pose = camera.pose;
    require(finite(pose.position_m));
    require(std::isfinite(pose.pan_deg) && std::isfinite(pose.roll_deg));
    require(pose.tilt_deg >= -90.0 && pose.tilt_deg <= 90.0);
    require(positive(camera.exposure_s));
    if (camera.f_number) require(positive(*camera.f_number));
    require(positive(camera.gain));
    require(camera.width_px.has_value() == camera.height_px.has_value());
    if (camera.width_px)
        require(*camera.width_px >= 1 && *camera.width_px <= 32768 && *camera.height_px >= 1 &&
                *camera.height_px <= 32768);
    require(camera.scene_min_dn.has_value() == camera.scene_max_dn.has_value());
    if (camera.scene_min_dn)
        require(nonNegative(*camera.scene_min_dn) && positive(*camera.scene_max_dn) &&
                *camera.scene_min_dn <= *camera.scene_max_dn);
    if (camera.rig_illuminance_lux) require(positive(*camera.rig_illuminance_lux));
}

void checkLight(const SceneLight& light, std::set<std::string>& names) {
    checkName(light.name, names);
    require(light.position_m.has_value() != light.direction.has_value());
    if (light.position_m) require(finite(*light.position_m));
    if (light.direction) {
        const Vec3& d = *light.direction;
        require(finite(d));
        require(std::abs(std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - 1.0) < 1e-9);
    }
    checkIntensity(light.intensity, light.position_m.has_value());
    checkColour(light.colour);
}

// lightRatio answers every light for every camera that the parser let through: photometric
// lights were refused unless each camera has its rig illuminance.
void checkRatio(const LightIntensity& intensity, const SceneCamera& camera, double distance_m) {
    auto ratio = lightRatio(intensity, camera, distance_m, "light");
    if (!ratio) {
        require(ratio.error().code == ErrorCode::InvalidArgument);
        require(!ratio.error().message.empty());
        require(camera.rig_illuminance_lux.has_value());
        // Only a point light nearer than 1 mm (or at a distance that overflows) may be refused.
        require(intensity.intensity_cd.has_value() &&
                !(std::isfinite(distance_m) && distance_m >= 1e-3 &&
                  std::isfinite(*intensity.intensity_cd / (distance_m * distance_m) /
                                *camera.rig_illuminance_lux)));
        return;
    }
    require(nonNegative(*ratio));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    const std::string name = "fuzz.json";
    auto parsed = parseScene(text, name, "base");
    if (!parsed) {
        const Error& error = parsed.error();
        require(error.code == ErrorCode::ParseError || error.code == ErrorCode::Unsupported);
        require(error.message.size() > name.size() + 2);
        require(error.message.compare(0, name.size() + 2, name + ": ") == 0);
        require(validUtf8(error.message));
        return 0;
    }
    const Scene& scene = *parsed;

    require(!scene.cameras.empty() && scene.cameras.size() <= kSceneMaxCameras);
    require(scene.lights.size() <= kSceneMaxLights);
    require(!scene.lights.empty() || scene.sun.has_value() || (scene.gltf && scene.gltf->lights));
    // A camera posed by the glTF file needs one; parseScene leaves its pose to loadScene.
    for (const SceneCamera& camera : scene.cameras)
        require(camera.gltf_camera.empty() || scene.gltf.has_value());
    require(!scene.gltf || !scene.gltf->path.empty());
    std::set<std::string> camera_names;
    for (const SceneCamera& camera : scene.cameras) checkCamera(camera, camera_names);
    std::set<std::string> light_names;
    for (const SceneLight& light : scene.lights) checkLight(light, light_names);

    if (scene.sun) {
        const SceneSun& sun = *scene.sun;
        require(checkSunSite(sun.site).has_value());
        require(sun.from <= sun.to);
        require(sun.step >= std::chrono::milliseconds(1) && sun.step <= std::chrono::hours(24));
        require((sun.to - sun.from) / sun.step + 1 <= kSceneMaxSteps);
        require(calendarYear(sun.from) >= kSunFirstYear && calendarYear(sun.to) <= kSunLastYear);
        checkIntensity(sun.intensity, false);
        checkColour(sun.colour);
    }
    if (scene.switching) {
        require(scene.sun.has_value());
        const SceneSwitching& s = *scene.switching;
        require(nonNegative(s.threshold) && nonNegative(s.min_dwell_s));
        if (s.figure == SwitchFigure::ContrastLoss) {
            require(s.threshold <= 1.0);
            for (const SceneCamera& camera : scene.cameras)
                require(camera.scene_min_dn.has_value());
        }
    }
    require(scene.frames.size() <= kSceneMaxFrames);
    if (!scene.frames.empty()) require(scene.sun.has_value());
    for (const UtcInstant frame : scene.frames)
        require(frame >= scene.sun->from && frame <= scene.sun->to);

    for (const SceneCamera& camera : scene.cameras) {
        for (const SceneLight& light : scene.lights) {
            double distance_m = 0.0;
            if (light.position_m) {
                const Vec3& p = *light.position_m;
                const Vec3& c = camera.pose.position_m;
                distance_m = std::hypot(p[0] - c[0], p[1] - c[1], p[2] - c[2]);
            }
            checkRatio(light.intensity, camera, distance_m);
        }
        if (scene.sun) checkRatio(scene.sun->intensity, camera, 0.0);
    }
    return 0;
}
