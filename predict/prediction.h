// ============================================================================
//  flarelab predict: PredictOptions, PredictedCamera, CameraTimelineSummary, TimelineSummary,
//                    PlannedShot, PlannedGap, SwitchingSummary, PredictedFrame,
//                    PredictionTimings, PredictionOutput, predictScene
// ============================================================================
//
// A whole prediction of a planner's scene file (issue 21), as `flarelab predict` and the daemon's
// Predict call both run it: the scene read (predict/scene.h), each camera's model read and tabled
// (predictor.h), the fixed lights' figures per camera, the sun's timeline and the switching plan
// when the scene has them, a frame per camera and instant, and the report folder:
//
//   report.html, report.json, figures.csv, timeline.csv (with a sun), plan.csv (with switching),
//   frames/N-CAMERA[_TIME].exr and .png
//
// docs/predict.md describes every file. The figures come back as values too, so that a caller
// need not parse the files it was handed; they are the very numbers report.json holds (NaN where
// report.json has null).
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "common/result.h"
#include "predict/figures.h"
#include "predict/lab_figures.h"
#include "predict/playback.h"
#include "predict/predictor.h"
#include "predict/switching.h"

namespace flarelab::predict {

struct PredictOptions {
    FigureTableOptions table = tableOptions(0.0, 10.0, 240);  // `flarelab predict`'s defaults
    double exposure_stops = 0.0;                  // the frames' PNGs, above the camera's white
    LabFigureOptions lab;                         // the models' lab figures
    // How the report and error messages name the scene; empty: by its path. With
    // paths_relative_to_scene, the files the scene names (models, glTF) are shown by their path
    // below the scene's folder, as the scene gives them: a caller that put the scene in a folder
    // of its own (the daemon) does not show that folder to its client.
    std::string scene_label;
    bool paths_relative_to_scene = false;
    // Bounds for callers that serve others (0: none). A scene whose sun timeline would hold
    // more than max_timeline_samples steps x cameras, or whose frames would hold more than
    // max_frame_pixels pixels together, is refused (InvalidArgument naming "sun" or "frames")
    // before the work they bound begins.
    int64_t max_timeline_samples = 0;
    int64_t max_frame_pixels = 0;
    // Asked between the steps of the work (each model's table, each camera's figures, the
    // timeline, each frame); true stops it there with an Unsupported error ("stopped"). A table
    // under way is finished first. With it, cameras are prepared a model at a time, so an error
    // among several is the first of the first model's cameras rather than of the scene's order.
    std::function<bool()> stop_requested;
    // Called with each note of the scene's glTF import once the cameras are prepared (the
    // command line prints them as they come); they are in PredictionOutput::notes too.
    std::function<void(const std::string&)> on_note;
};

struct PredictedCamera {
    std::string name;
    std::string model;  // the model file, as the report names it
    double model_valid_from_deg = 0.0;
    double model_valid_to_deg = 0.0;
    int64_t ghosts = 0;
    CameraExposure exposure;  // the f-number resolved
    int64_t width_px = 0;
    int64_t height_px = 0;
    std::vector<std::string> notes;
    CameraFigures fixed;  // the fixed lights, each and together
};

// One camera along the sun's span. The figures are NaN where no step is known.
struct CameraTimelineSummary {
    std::string camera;
    int64_t steps_sun_down = 0;
    int64_t steps_behind_camera = 0;
    int64_t steps_drawn = 0;
    int64_t steps_clamped = 0;
    int64_t steps_refused = 0;
    double flare_mean_median = 0.0;
    double flare_mean_max = 0.0;
    double flare_peak_max = 0.0;
    double contrast_loss_max = 0.0;
    double glare_indicator_max = 0.0;  // NaN without the scene's log-average
};

struct TimelineSummary {
    std::string from_utc;  // ISO 8601, as the report writes it
    std::string to_utc;
    double step_s = 0.0;
    int64_t steps = 0;
    std::vector<CameraTimelineSummary> cameras;  // in the scene's order
};

struct PlannedShot {
    std::string camera;
    int camera_index = 0;  // in the scene's order
    std::string from_utc;
    std::string to_utc;  // exclusive
    double seconds = 0.0;
    int64_t steps_over = 0;  // steps of the shot whose figure is over the threshold or unknown
};

struct PlannedGap {
    std::string from_utc;
    std::string to_utc;  // exclusive
    double seconds = 0.0;
};

struct SwitchingSummary {
    SwitchFigure figure = SwitchFigure::ContrastLoss;
    double threshold = 0.0;
    double min_dwell_s = 0.0;
    int64_t steps_over = 0;
    int64_t cuts = 0;
    std::vector<PlannedShot> shots;
    std::vector<PlannedGap> no_clean_camera;
};

struct PredictedFrame {
    std::string camera;
    std::string time_utc;  // empty for a frame of the fixed lights alone
    std::string png;       // relative to the report folder: "frames/1-main.png"
    std::string exr;
    FlareFigures figures;
    std::vector<LightState> light_states;  // the fixed lights', then the sun's when it is up
};

struct PredictionTimings {
    double tables_ms = 0.0;
    double timeline_ms = 0.0;
    double switching_ms = 0.0;
    double frames_ms = 0.0;
};

struct PredictionOutput {
    std::vector<PredictedCamera> cameras;  // in the scene's order
    std::optional<TimelineSummary> timeline;
    std::optional<SwitchingSummary> switching;
    std::vector<PredictedFrame> frames;
    std::vector<std::string> notes;  // the glTF import's
    int64_t fixed_lights = 0;
    bool sun = false;
    // Every file written, relative to the report folder, in the order written.
    std::vector<std::string> files;
    std::string report_json;  // report.json's text
    std::string summary;      // what `flarelab predict` prints: a line, then one per camera
    PredictionTimings timings;
};

// Reads the scene at `scene_path` and writes the report folder `out_dir` (created with its
// frames/ folder; files in it are replaced atomically, others are left alone). Errors: those of
// loadScene (NotFound, IoError, ParseError, Unsupported), of the models and tables
// (prepareCameras), InvalidArgument for a bound of `options` exceeded, IoError naming out_dir
// or a file when one cannot be written, Unsupported "stopped" when options.stop_requested said
// so. What was written before an error stays.
Result<PredictionOutput> predictScene(const std::string& scene_path,
                                      const std::string& out_dir,
                                      const PredictOptions& options = {});

}  // namespace flarelab::predict
