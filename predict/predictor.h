// ============================================================================
//  flarelab predict: PreparedCamera, prepareCamera, LightFigures, CameraFigures, lightScale,
//                    fixedLightFigures, FrameRequest, drawCameraFrame, CameraTimeline, Timeline,
//                    predictTimeline, switchingFigures
// ============================================================================
//
// A scene's figures (predict/scene.h): each camera's model read once and its figure table built
// once (predict/figures.h); the fixed lights' figures per camera, the sun's along its span of
// time, the sum of both per step, and frames drawn at chosen instants (predict/playback.h).
//
// Units: every figure is in the scene camera's DN (constellation.h, eq. 8.3). Figures of several
// lights add exactly for the mean and the total (the images add); the peak of a sum is at most the
// sum of the peaks, which is what is reported (an upper bound, tight when one light dominates).
// A light's colour scales the table's figures by its luminance, 0.2126 r + 0.7152 g + 0.0722 b:
// exact for a grey model, and within the colour's own spread for a tinted one. Frames are drawn
// per channel exactly.
#pragma once

#include <array>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/result.h"
#include "fit/model_file.h"
#include "predict/figures.h"
#include "predict/playback.h"
#include "predict/scene.h"
#include "predict/sun.h"

namespace flarelab::predict {

struct PreparedCamera {
    SceneCamera scene;
    fit::FlareModel model;
    CameraFrame frame;
    CameraExposure exposure;  // the f-number resolved (the model's when the scene gives none)
    int64_t width = 0;        // the camera's image, resolved
    int64_t height = 0;
    FlareFigureTable table;
    std::vector<std::string> notes;  // what a planner should know (another f-number, ...)
};

// Reads the camera's model and builds its table. Errors name the camera: a model that cannot be
// read, one without an f-number when the scene gives none, an image of another aspect.
Result<PreparedCamera> prepareCamera(const SceneCamera& camera,
                                     const FigureTableOptions& table_options = {});
// The same for every camera of a scene, each model file read and tabled once however many
// cameras share it.
Result<std::vector<PreparedCamera>> prepareCameras(std::span<const SceneCamera> cameras,
                                                   const FigureTableOptions& table_options = {});

// Eq. 8.3 per channel for one light at one camera: brightness times colour. `what` names the light
// in errors ("lights[2]", "sun").
Result<std::array<double, 3>> lightScale(const PreparedCamera& camera,
                                         const LightIntensity& intensity,
                                         const std::array<double, 3>& colour,
                                         double distance_m,
                                         const std::string& what);

struct LightFigures {
    std::string light;
    LightAtCamera placed;
    FlareFigures figures;  // zero unless drawn
};

struct CameraFigures {
    std::vector<LightFigures> lights;
    // The lights together: mean and total exact (images add), min a lower and max an upper bound
    // (sums of the lights'), log-average the largest light's (a lower bound).
    FlareFigures sum;
    bool known = true;  // false when a light was refused (outside the model's range)
    std::optional<double> contrast_ratio;  // eq. 9.3 when the scene gives the camera's range
    std::optional<double> glare_indicator;  // when the scene gives the camera's log-average
};

// The fixed lights' figures for one camera, from its table.
Result<CameraFigures> fixedLightFigures(const PreparedCamera& camera,
                                        std::span<const SceneLight> lights,
                                        RangePolicy policy);

// The eq. 9.3 ratio of a camera for a flare mean, when the scene gives its range.
std::optional<double> cameraContrastRatio(const PreparedCamera& camera, double flare_mean);
// glareIndicator against the camera's scene_log_average_dn; nullopt without one.
std::optional<double> cameraGlareIndicator(const PreparedCamera& camera, double flare_mean);

// One frame of a camera: the fixed lights and, when given, the sun in `sun_direction`.
struct SunLight {
    Vec3 direction;  // towards the sun
    LightIntensity intensity;
    std::array<double, 3> colour = {1.0, 1.0, 1.0};
};
Result<PlaybackResult> drawCameraFrame(const PreparedCamera& camera,
                                       std::span<const SceneLight> lights,
                                       const std::optional<SunLight>& sun,
                                       RangePolicy policy);

// Per camera along the sun's span: the fixed lights' and the sun's figures added per step. NaN
// where the model cannot say (a light refused). The sun below the horizon adds nothing.
struct CameraTimeline {
    std::vector<double> flare_mean;
    std::vector<double> flare_peak;
    std::vector<double> contrast_loss;  // 1 - eq. 9.3's ratio; NaN without the scene's range
    std::vector<double> glare_indicator;  // NaN without the scene's log-average
    std::vector<LightState> sun_state;  // BehindCamera also below the horizon
    int64_t steps_sun_down = 0;
    int64_t steps_drawn = 0;  // the sun in the model's range, drawn
    int64_t steps_clamped = 0;
    int64_t steps_refused = 0;
    int64_t steps_behind = 0;
};

struct Timeline {
    SunTimeline sun;
    std::vector<CameraTimeline> cameras;  // in the scene's order
};

Result<Timeline> predictTimeline(const SceneSun& sun,
                                 std::span<const PreparedCamera> cameras,
                                 std::span<const SceneLight> lights,
                                 RangePolicy policy);

// The series the switching plan compares for `figure`, one per camera.
std::vector<std::vector<double>> switchingFigures(const Timeline& timeline, SwitchFigure figure);

}  // namespace flarelab::predict
