#include "predict/predictor.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <string>

#include "fit/model_eval.h"

namespace flarelab::predict {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

std::string number(double v) {
    char text[32];
    std::snprintf(text, sizeof text, "%.6g", v);
    return text;
}

double luminanceOf(const std::array<double, 3>& rgb) {
    return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2];
}

// Where a light is from the camera and how far (infinity for a direction).
struct Toward {
    Vec3 to_light;
    double distance_m;
};

Toward towardLight(const PreparedCamera& camera, const SceneLight& light) {
    if (light.position_m) {
        const Vec3& p = *light.position_m;
        const Vec3& c = camera.scene.pose.position_m;
        const Vec3 d = {p[0] - c[0], p[1] - c[1], p[2] - c[2]};
        return {d, std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])};
    }
    return {light.direction.value_or(Vec3{0.0, 0.0, 0.0}), std::numeric_limits<double>::infinity()};
}

}  // namespace

namespace {

// prepareCamera, taking the model and its table from `same_model` when given.
Result<PreparedCamera> prepare(const SceneCamera& camera,
                               const FigureTableOptions& table_options,
                               const PreparedCamera* same_model) {
    const std::string what = "camera '" + camera.name + "'";
    PreparedCamera p;
    p.scene = camera;
    if (same_model) {
        p.model = same_model->model;
    } else {
        auto model = fit::readModel(camera.model_path);
        if (!model) return model.error().withContext(what);
        p.model = std::move(*model);
    }
    p.frame = cameraFrame(camera.pose);
    if (!p.model.lens.f_number && !camera.f_number)
        return makeError(ErrorCode::InvalidArgument,
                         what + ": the model records no f-number, so the scene must give f_number");
    const double capture_f = p.model.lens.f_number.value_or(*camera.f_number);
    p.exposure.f_number = camera.f_number.value_or(capture_f);
    p.exposure.exposure_s = camera.exposure_s;
    p.exposure.gain = camera.gain;
    if (std::abs(p.exposure.f_number / capture_f - 1.0) > 1e-6)
        p.notes.push_back("f/" + number(p.exposure.f_number) + " differs from the capture's f/" +
                          number(capture_f) +
                          ": the brightness is scaled (eq. 8.3), the ghosts' shapes are the "
                          "capture's");
    p.width = camera.width_px.value_or(p.model.capture.width_px);
    p.height = camera.height_px.value_or(p.model.capture.height_px);
    // playback() checks the aspect; check it here once, before any timeline is computed.
    const auto probe = playback(p.model, p.frame, {}, PlaybackOptions{p.width, p.height});
    if (!probe) return probe.error().withContext(what);
    if (same_model) {
        p.table = same_model->table;
        return p;
    }
    auto table = FlareFigureTable::build(p.model, table_options);
    if (!table) return table.error().withContext(what);
    p.table = std::move(*table);
    return p;
}

}  // namespace

Result<PreparedCamera> prepareCamera(const SceneCamera& camera,
                                     const FigureTableOptions& table_options) {
    return prepare(camera, table_options, nullptr);
}

Result<std::vector<PreparedCamera>> prepareCameras(std::span<const SceneCamera> cameras,
                                                   const FigureTableOptions& table_options) {
    std::vector<PreparedCamera> out;
    out.reserve(cameras.size());
    for (const SceneCamera& camera : cameras) {
        const PreparedCamera* same = nullptr;
        for (const PreparedCamera& p : out)
            if (p.scene.model_path == camera.model_path) same = &p;
        auto p = prepare(camera, table_options, same);
        if (!p) return p.error();
        out.push_back(std::move(*p));
    }
    return out;
}

Result<std::array<double, 3>> lightScale(const PreparedCamera& camera,
                                         const LightIntensity& intensity,
                                         const std::array<double, 3>& colour,
                                         double distance_m,
                                         const std::string& what) {
    auto ratio = lightRatio(intensity, camera.scene, distance_m, what);
    if (!ratio) return ratio.error();
    const double capture_f = camera.model.lens.f_number.value_or(camera.exposure.f_number);
    auto scale = brightnessScale(capture_f, camera.exposure, *ratio);
    if (!scale) return scale.error().withContext(what);
    return std::array<double, 3>{*scale * colour[0], *scale * colour[1], *scale * colour[2]};
}

std::optional<double> cameraContrastRatio(const PreparedCamera& camera, double flare_mean) {
    if (!camera.scene.scene_min_dn || !camera.scene.scene_max_dn || !(flare_mean >= 0.0))
        return std::nullopt;
    return contrastRatio(*camera.scene.scene_min_dn, *camera.scene.scene_max_dn, flare_mean);
}

std::optional<double> cameraGlareIndicator(const PreparedCamera& camera, double flare_mean) {
    if (!camera.scene.scene_log_average_dn || !(flare_mean >= 0.0)) return std::nullopt;
    return glareIndicator(*camera.scene.scene_log_average_dn, flare_mean);
}

Result<CameraFigures> fixedLightFigures(const PreparedCamera& camera,
                                        std::span<const SceneLight> lights,
                                        RangePolicy policy) {
    CameraFigures out;
    bool first = true;
    for (size_t i = 0; i < lights.size(); ++i) {
        const SceneLight& light = lights[i];
        const Toward toward = towardLight(camera, light);
        LightFigures lf;
        lf.light = light.name;
        lf.placed = placeLight(camera.model, camera.frame, toward.to_light, policy);
        if (lf.placed.drawn()) {
            auto scale = lightScale(camera, light.intensity, light.colour, toward.distance_m,
                                    "lights[" + std::to_string(i) + "] '" + light.name + "'");
            if (!scale) return scale.error();
            const auto f =
                camera.table.at(lf.placed.model_theta_deg, lf.placed.constellation.phi_deg);
            if (!f)
                return makeError(ErrorCode::Internal,
                                 "figures: a placed light lies outside the camera's table");
            lf.figures = f->scaled(luminanceOf(*scale));
            lf.figures.total = lf.figures.mean * static_cast<double>(camera.width * camera.height);
        } else if (lf.placed.state == LightState::OutsideRange) {
            out.known = false;
        }
        // Images add: so do their means and totals; a minimum of a sum is at least the sum of the
        // minima, and a peak at most the sum of the peaks.
        out.sum.min += lf.figures.min;
        out.sum.max += lf.figures.max;
        out.sum.mean += lf.figures.mean;
        out.sum.total += lf.figures.total;
        out.sum.log_average =
            first ? lf.figures.log_average : std::max(out.sum.log_average, lf.figures.log_average);
        first = false;
        out.lights.push_back(lf);
    }
    if (out.known) {
        out.contrast_ratio = cameraContrastRatio(camera, out.sum.mean);
        out.glare_indicator = cameraGlareIndicator(camera, out.sum.mean);
    }
    return out;
}

Result<PlaybackResult> drawCameraFrame(const PreparedCamera& camera,
                                       std::span<const SceneLight> lights,
                                       const std::optional<SunLight>& sun,
                                       RangePolicy policy) {
    std::vector<PlaybackLight> drawn;
    for (size_t i = 0; i < lights.size(); ++i) {
        const Toward toward = towardLight(camera, lights[i]);
        auto scale = lightScale(camera, lights[i].intensity, lights[i].colour, toward.distance_m,
                                "lights[" + std::to_string(i) + "] '" + lights[i].name + "'");
        if (!scale) return scale.error();
        drawn.push_back(PlaybackLight{lights[i].name, toward.to_light, *scale});
    }
    if (sun) {
        auto scale = lightScale(camera, sun->intensity, sun->colour,
                                std::numeric_limits<double>::infinity(), "sun");
        if (!scale) return scale.error();
        drawn.push_back(PlaybackLight{"sun", sun->direction, *scale});
    }
    PlaybackOptions options;
    options.width = camera.width;
    options.height = camera.height;
    options.policy = policy;
    return playback(camera.model, camera.frame, drawn, options);
}

Result<Timeline> predictTimeline(const SceneSun& sun,
                                 std::span<const PreparedCamera> cameras,
                                 std::span<const SceneLight> lights,
                                 RangePolicy policy) {
    Timeline timeline;
    auto positions = sunTimeline(sun.site, sun.from, sun.to, sun.step);
    if (!positions) return positions.error().withContext("sun");
    timeline.sun = std::move(*positions);
    const size_t steps = timeline.sun.positions.size();
    std::vector<Vec3> directions(steps);
    std::vector<bool> up(steps);
    for (size_t t = 0; t < steps; ++t) {
        const SunPosition& s = timeline.sun.positions[t];
        directions[t] = sunDirection(s.zenith_deg, s.azimuth_deg);
        up[t] = s.elevation_deg > 0.0;
    }
    for (const PreparedCamera& camera : cameras) {
        auto fixed = fixedLightFigures(camera, lights, policy);
        if (!fixed) return fixed.error();
        auto scale = lightScale(camera, sun.intensity, sun.colour,
                                std::numeric_limits<double>::infinity(), "sun");
        if (!scale) return scale.error();
        const double k = luminanceOf(*scale);
        CameraTimeline ct;
        ct.flare_mean.assign(steps, kNaN);
        ct.flare_peak.assign(steps, kNaN);
        ct.contrast_loss.assign(steps, kNaN);
        ct.glare_indicator.assign(steps, kNaN);
        ct.sun_state.assign(steps, LightState::BehindCamera);
        for (size_t t = 0; t < steps; ++t) {
            double mean = fixed->sum.mean, peak = fixed->sum.max;
            bool known = fixed->known;
            if (!up[t]) {
                ++ct.steps_sun_down;
            } else {
                const LightAtCamera placed =
                    placeLight(camera.model, camera.frame, directions[t], policy);
                ct.sun_state[t] = placed.state;
                switch (placed.state) {
                    case LightState::Drawn:
                        ++ct.steps_drawn;
                        break;
                    case LightState::Clamped:
                        ++ct.steps_clamped;
                        break;
                    case LightState::OutsideRange:
                        ++ct.steps_refused;
                        known = false;
                        break;
                    default:
                        ++ct.steps_behind;
                        break;
                }
                if (placed.drawn()) {
                    const auto f =
                        camera.table.at(placed.model_theta_deg, placed.constellation.phi_deg);
                    if (!f)
                        return makeError(ErrorCode::Internal,
                                         "timeline: the sun lies outside the camera's table");
                    mean += k * f->mean;
                    peak += k * f->max;
                }
            }
            if (!known) continue;
            ct.flare_mean[t] = mean;
            ct.flare_peak[t] = peak;
            if (const auto ratio = cameraContrastRatio(camera, mean))
                ct.contrast_loss[t] = 1.0 - *ratio;
            if (const auto glare = cameraGlareIndicator(camera, mean)) ct.glare_indicator[t] = *glare;
        }
        timeline.cameras.push_back(std::move(ct));
    }
    return timeline;
}

std::vector<std::vector<double>> switchingFigures(const Timeline& timeline, SwitchFigure figure) {
    std::vector<std::vector<double>> out;
    for (const CameraTimeline& c : timeline.cameras) {
        switch (figure) {
            case SwitchFigure::ContrastLoss:
                out.push_back(c.contrast_loss);
                break;
            case SwitchFigure::FlareMean:
                out.push_back(c.flare_mean);
                break;
            case SwitchFigure::FlarePeak:
                out.push_back(c.flare_peak);
                break;
            case SwitchFigure::GlareIndicator:
                out.push_back(c.glare_indicator);
                break;
        }
    }
    return out;
}

}  // namespace flarelab::predict
