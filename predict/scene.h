// ============================================================================
//  flarelab predict: SceneLight, SceneCamera, SceneSun, SceneSwitching, Scene, parseScene,
//                    loadScene, lightRatio
// ============================================================================
//
// A planner's scene file (item 2 of issue 21): cameras with their pose, flare model and exposure,
// lights by position or direction with their intensity and colour, and optionally the sun over a
// span of time at a site, a switching rule and the instants to draw frames at. JSON, format
// "flarelab-scene" version 1; docs/predict.md documents every field with an example, and
// data/scenes/ ships examples.
//
// {
//   "format": "flarelab-scene", "version": 1,
//   "out_of_range": "refuse",                   // or "clamp"; default "refuse"
//   "gltf": {"file": "venue.glb", "lights": true},  // optional: a venue from a 3D tool
//   "cameras": [{
//     "name": "main",                           // unique, 1..64 characters, no control characters
//     "model": "models/heliar.flm",             // relative to the scene file's folder
//     "position_m": [0, -40, 12],
//     "pan_deg": 0, "tilt_deg": -10, "roll_deg": 0,   // or "look_at_m": [x, y, z] (no roll);
//                                               // or neither with "gltf_camera": "node name"
//     "exposure_s": 0.01,                       // > 0
//     "f_number": 8,                            // > 0; default: the model's capture f-number
//     "gain": 1,                                // > 0, relative to the capture's; default 1
//     "width_px": 1920, "height_px": 1080,      // default: the model's capture size
//     "scene_min_dn": 40, "scene_max_dn": 3500, // the scene's darkest and brightest parts as the
//                                               // camera records them (both or neither), for the
//                                               // contrast ratio (eq. 9.3)
//     "scene_log_average_dn": 600,              // the scene's log-average as the camera records
//                                               // it (its key), for the glare indicator (§9.2)
//     "rig_illuminance_lux": 2000               // the rig light's illuminance at the lens during
//                                               // the capture: needed by photometric lights
//   }],
//   "lights": [{
//     "name": "flood 1",
//     "position_m": [30, 0, 25],                // or "direction": {"azimuth_deg": a,
//                                               //                  "elevation_deg": e}
//     "intensity_cd": 150000,                   // exactly one of: intensity_cd (with a
//                                               // position), illuminance_lux (at the camera),
//                                               // relative (to the rig's light at the lens)
//     "colour": [1, 0.9, 0.8]                   // linear RGB factors >= 0; default [1, 1, 1]
//   }],
//   "sun": {
//     "latitude_deg": 48.2, "longitude_deg": 16.37, "elevation_m": 170,
//     "pressure_mbar": 1013.25, "temperature_c": 12,   // optional, as predict/sun.h
//     "from": "2026-06-21T18:00:00+02:00", "to": "2026-06-21T21:00:00+02:00", "step_s": 1,
//     "illuminance_lux": 100000,                // or "relative"; as a light's
//     "colour": [1, 1, 1]
//   },
//   "switching": {"figure": "contrast-loss", "threshold": 0.05, "min_dwell_s": 10},
//   "frames": ["2026-06-21T20:30:00+02:00"]     // instants to draw, inside the sun's span (only
//                                               // with a sun; without one each camera is drawn
//                                               // once with the fixed lights)
// }
//
// Rules: every number finite; unknown fields are refused (a misspelt "exposure" must not fall back
// to a default); at most 64 cameras, 1024 lights, 64 frames; at least one camera, and at least one
// light or a sun; the sun's span from <= to, step_s in [0.001, 86400], at most 10 million steps;
// switching needs a sun (a timeline) and min_dwell_s >= 0; a light or sun given in candela or lux
// needs rig_illuminance_lux on every camera; keys may not repeat. Errors (ParseError; Unsupported
// for another version) name the scene and the field: "scene.json: cameras[1].exposure_s: must be
// > 0, got -1".
#pragma once

#include <array>
#include <chrono>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"
#include "predict/constellation.h"
#include "predict/playback.h"
#include "predict/sun.h"
#include "predict/switching.h"
#include "predict/utc_time.h"

namespace flarelab::predict {

inline constexpr int kSceneFormatVersion = 1;
inline constexpr size_t kSceneMaxCameras = 64;
inline constexpr size_t kSceneMaxLights = 1024;
inline constexpr size_t kSceneMaxFrames = 64;
inline constexpr int64_t kSceneMaxSteps = 10'000'000;
inline constexpr int64_t kSceneMaxFileBytes = int64_t{16} << 20;

// How bright a light is. Exactly one is set.
struct LightIntensity {
    std::optional<double> intensity_cd;     // > 0 (point lights only)
    std::optional<double> illuminance_lux;  // > 0, at the camera, perpendicular to the light
    std::optional<double> relative;         // >= 0, irradiance at the lens over the rig light's
};

struct SceneLight {
    std::string name;
    std::optional<Vec3> position_m;  // a point light; else `direction`
    std::optional<Vec3> direction;   // unit vector towards a light at infinity
    LightIntensity intensity;
    std::array<double, 3> colour = {1.0, 1.0, 1.0};
};

struct SceneCamera {
    std::string name;
    std::string model_path;  // resolved: the scene file's folder joined with the field's value
    // Not empty: the camera of the scene's glTF file whose node has this name gives the pose
    // (loadScene fills `pose` from it; parseScene leaves it at zero).
    std::string gltf_camera;
    CameraPose pose;
    double exposure_s = 0.0;
    std::optional<double> f_number;
    double gain = 1.0;
    std::optional<int64_t> width_px;
    std::optional<int64_t> height_px;
    std::optional<double> scene_min_dn;
    std::optional<double> scene_max_dn;
    std::optional<double> scene_log_average_dn;  // > 0: the glare indicator's reference
    std::optional<double> rig_illuminance_lux;
};

struct SceneSun {
    SunSite site;
    UtcInstant from;
    UtcInstant to;
    std::chrono::microseconds step{0};
    LightIntensity intensity;  // illuminance_lux or relative
    std::array<double, 3> colour = {1.0, 1.0, 1.0};
};

struct SceneSwitching {
    SwitchFigure figure = SwitchFigure::ContrastLoss;
    double threshold = 0.0;
    double min_dwell_s = 0.0;
};

// A venue from a 3D tool (predict/gltf_import.h): cameras by name, and its punctual lights.
struct SceneGltf {
    std::string path;    // resolved like a model's path
    bool lights = true;  // its lights join the scene's fixed lights (candela or lux)
};

struct Scene {
    RangePolicy out_of_range = RangePolicy::Refuse;
    std::optional<SceneGltf> gltf;
    std::vector<std::string> notes;  // what the glTF import skipped or approximated
    std::vector<SceneCamera> cameras;
    std::vector<SceneLight> lights;
    std::optional<SceneSun> sun;
    std::optional<SceneSwitching> switching;
    std::vector<UtcInstant> frames;
};

// Parses and validates a scene. `name` stands for the text in errors; model paths are joined to
// `base_dir` unless absolute. The models themselves are not read here, nor the glTF file.
Result<Scene> parseScene(std::string_view json,
                         const std::string& name,
                         const std::string& base_dir);

// Reads `path` (NotFound, IoError, or ParseError beyond kSceneMaxFileBytes) and parses it with
// the file's folder as base_dir; then reads the glTF file it names, if any: each camera with a
// gltf_camera takes the pose of the one camera of that name (ParseError naming the camera when
// there is none or more than one), and with "lights" every punctual light of the glTF is added
// (point and spot lights in candela at their position, directional ones in lux; a name the
// scene already has gets " (glTF)" added), which needs rig_illuminance_lux on every camera.
Result<Scene> loadScene(const std::string& path);

// Eq. 8.3's light term for one camera: the light's irradiance at the camera's lens over the rig
// light's. `distance_m` is the camera-to-light distance (point lights; ignored otherwise).
// InvalidArgument naming `what` when a photometric intensity meets a camera without
// rig_illuminance_lux, or a point light's distance is below 1 mm.
Result<double> lightRatio(const LightIntensity& intensity,
                          const SceneCamera& camera,
                          double distance_m,
                          const std::string& what);

}  // namespace flarelab::predict
