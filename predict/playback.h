// ============================================================================
//  flarelab predict: RangePolicy, LightState, LightAtCamera, placeLight, PlaybackLight,
//                    playback
// ============================================================================
//
// A flare model played back for one camera and any number of lights (item 1 of issue 21): each
// light's constellation (predict/constellation.h) picks the model's angle and roll, eq. 8.3 its
// brightness, and the lights' flare images add.
//
// A light the model cannot answer for is never extrapolated silently. Behind the camera (theta
// >= 90) it is skipped: no light enters the lens. Outside the model's valid angles (but in front)
// the scene chooses: Refuse leaves it out and reports it, Clamp draws it at the nearest valid angle
// and reports that. A light at the camera's own position is reported and skipped.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "fit/model_file.h"
#include "predict/constellation.h"

namespace flarelab::predict {

enum class RangePolicy { Refuse, Clamp };
const char* rangePolicyName(RangePolicy policy);  // "refuse", "clamp"

enum class LightState {
    Drawn,         // inside the model's range, drawn at its own angle
    Clamped,       // outside the range, drawn at the nearest valid angle (RangePolicy::Clamp)
    OutsideRange,  // outside the range and refused: not drawn, its flare is unknown
    BehindCamera,  // theta >= 90 deg: no light enters the lens, no flare
    AtCamera,      // no direction (the light at the camera's position): not drawn
};
const char* lightStateName(LightState state);  // "drawn", "clamped", "outside-range", ...

// Where one light falls for one camera and at which angle the model is evaluated for it.
struct LightAtCamera {
    LightState state = LightState::Drawn;
    Constellation constellation;   // meaningful unless AtCamera
    double model_theta_deg = 0.0;  // the angle drawn (Drawn, Clamped); else 0
    // Whether the light draws anything: Drawn or Clamped.
    bool drawn() const { return state == LightState::Drawn || state == LightState::Clamped; }
};

// Classifies a light in direction `to_light` (from the camera) against `model`'s valid range.
// Model angles are head angles; theta is >= 0, so a model valid from a negative angle is used
// from 0. Total: every finite input gives a state.
LightAtCamera placeLight(const fit::FlareModel& model,
                         const CameraFrame& frame,
                         const Vec3& to_light,
                         RangePolicy policy);

struct PlaybackLight {
    std::string name;
    Vec3 to_light = {0.0, 0.0, 1.0};  // from the camera towards the light, any non-zero length
    // Per channel: eq. 8.3's brightness scale times the light's colour (>= 0, finite).
    std::array<double, 3> rgb_scale = {1.0, 1.0, 1.0};
};

struct PlaybackOptions {
    int64_t width = 0;  // 0: the model's capture size; else 1..32768, same aspect as the capture
    int64_t height = 0;
    RangePolicy policy = RangePolicy::Refuse;
};

struct PlaybackResult {
    ImageRGB image;                     // the scene camera's flare, its DN (see constellation.h)
    std::vector<LightAtCamera> lights;  // one per light, in order
};

// The flare of `lights` for a camera with `frame`. InvalidArgument for a size out of range, an
// aspect more than 1 % off the capture's (the model covers the capture's sensor area only), or a
// scale that is negative or not finite.
Result<PlaybackResult> playback(const fit::FlareModel& model,
                                const CameraFrame& frame,
                                std::span<const PlaybackLight> lights,
                                const PlaybackOptions& options = {});

}  // namespace flarelab::predict
