#include "predict/playback.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "fit/model_eval.h"

namespace flarelab::predict {
namespace {

std::string number(double v) {
    char text[32];
    std::snprintf(text, sizeof text, "%.6g", v);
    return text;
}

// The head angle and roll at which `model` shows a light at (theta, phi), if it covers theta:
// a head angle a at roll r is the light at |a| with roll r, or r + 180 for a < 0 (model_eval.h).
struct ModelAngle {
    double angle_deg = 0.0;
    double roll_deg = 0.0;
};

std::optional<ModelAngle> modelAngleFor(const fit::FlareModel& model, double theta, double phi) {
    if (theta >= model.valid_from_deg && theta <= model.valid_to_deg) return ModelAngle{theta, phi};
    if (-theta >= model.valid_from_deg && -theta <= model.valid_to_deg)
        return ModelAngle{-theta, phi + 180.0};
    return std::nullopt;
}

}  // namespace

const char* rangePolicyName(RangePolicy policy) {
    return policy == RangePolicy::Clamp ? "clamp" : "refuse";
}

const char* lightStateName(LightState state) {
    switch (state) {
        case LightState::Drawn:
            return "drawn";
        case LightState::Clamped:
            return "clamped";
        case LightState::OutsideRange:
            return "outside-range";
        case LightState::BehindCamera:
            return "behind-camera";
        case LightState::AtCamera:
            return "at-camera";
    }
    return "unknown";
}

LightAtCamera placeLight(const fit::FlareModel& model,
                         const CameraFrame& frame,
                         const Vec3& to_light,
                         RangePolicy policy) {
    LightAtCamera out;
    const auto c = constellationOf(frame, to_light);
    if (!c) {
        out.state = LightState::AtCamera;
        return out;
    }
    out.constellation = *c;
    if (c->theta_deg >= 90.0) {
        out.state = LightState::BehindCamera;
        return out;
    }
    if (modelAngleFor(model, c->theta_deg, c->phi_deg)) {
        out.state = LightState::Drawn;
        out.model_theta_deg = c->theta_deg;
        return out;
    }
    if (policy == RangePolicy::Refuse) {
        out.state = LightState::OutsideRange;
        return out;
    }
    // The valid angle nearest theta among the model's |head angles|.
    const double lo = model.valid_from_deg, hi = model.valid_to_deg;
    double nearest;
    if (lo >= 0.0)
        nearest = c->theta_deg < lo ? lo : hi;
    else if (hi <= 0.0)
        nearest = c->theta_deg < -hi ? -hi : -lo;
    else
        nearest = std::max(-lo, hi);  // the range holds 0, so theta lies beyond both ends
    out.state = LightState::Clamped;
    out.model_theta_deg = nearest;
    return out;
}

Result<PlaybackResult> playback(const fit::FlareModel& model,
                                const CameraFrame& frame,
                                std::span<const PlaybackLight> lights,
                                const PlaybackOptions& options) {
    const int64_t width = options.width > 0 ? options.width : model.capture.width_px;
    const int64_t height = options.height > 0 ? options.height : model.capture.height_px;
    if (options.width < 0 || options.height < 0 || width < 1 || height < 1 ||
        width > fit::kModelMaxSide || height > fit::kModelMaxSide)
        return makeError(ErrorCode::InvalidArgument,
                         "playback: the image size must be 1..32768 pixels per side, got " +
                             std::to_string(width) + "x" + std::to_string(height));
    const double model_aspect = model.lens.sensor_width_mm / model.lens.sensor_height_mm;
    const double aspect = static_cast<double>(width) / static_cast<double>(height);
    // One pixel of rounding either way is not a different sensor.
    const double slack = std::max(0.01, 1.0 / static_cast<double>(std::min(width, height)));
    if (!(std::abs(aspect / model_aspect - 1.0) <= slack))
        return makeError(ErrorCode::InvalidArgument,
                         "playback: a " + std::to_string(width) + "x" + std::to_string(height) +
                             " image has aspect " + number(aspect) + ", the model's sensor " +
                             number(model_aspect) +
                             ": the model covers its capture's sensor area only");
    PlaybackResult result;
    result.image = ImageRGB(width, height);
    for (const PlaybackLight& light : lights) {
        for (double s : light.rgb_scale)
            if (!(std::isfinite(s) && s >= 0.0))
                return makeError(ErrorCode::InvalidArgument,
                                 "playback: light '" + light.name +
                                     "': its scale must be finite and >= 0, got " + number(s));
        const LightAtCamera placed = placeLight(model, frame, light.to_light, options.policy);
        result.lights.push_back(placed);
        if (!placed.drawn()) continue;
        if (light.rgb_scale[0] == 0.0 && light.rgb_scale[1] == 0.0 && light.rgb_scale[2] == 0.0)
            continue;
        const auto angle =
            modelAngleFor(model, placed.model_theta_deg, placed.constellation.phi_deg);
        if (!angle)
            return makeError(ErrorCode::Internal, "playback: a placed light left the model");
        fit::ModelRenderOptions render;
        render.frame_tolerance = true;  // the frame's error budget, not each ghost's
        auto image =
            fit::renderModel(model, angle->angle_deg, angle->roll_deg, width, height, render);
        if (!image) return image.error().withContext("playback: light '" + light.name + "'");
        float* dst = result.image.pixels.data();
        const float* src = image->pixels.data();
        const size_t n = result.image.pixels.size();
        for (size_t i = 0; i < n; i += 3)
            for (int c = 0; c < 3; ++c)
                dst[i + c] += static_cast<float>(light.rgb_scale[c] * src[i + c]);
    }
    return result;
}

}  // namespace flarelab::predict
