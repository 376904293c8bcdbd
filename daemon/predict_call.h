// ============================================================================
//  flarelab daemon: PredictLimits, checkPredictRequest, runPredict, clearPredictWork
// ============================================================================
//
// The Predict call (proto/daemon.proto): a planner's scene predicted as `flarelab predict` does
// (predict/prediction.h), for a client that hands in the scene and every file it names.
//
// The daemon reads no file on a client's behalf: the scene may name only plain file names given
// in the request, which are written into a private folder (mode 0700) of their own below the
// daemon's state directory, `STATE/predict/p-XXXXXX/in/`, next to the scene; the report is
// written to `.../out/`, read back into the response, and the whole folder is removed before the
// call returns, whatever its outcome. A daemon killed during a prediction leaves the folder
// behind; clearPredictWork removes such leftovers when the next one starts (they are copies of
// what a client sent and a report it never got, nothing anyone else has).
//
// Everything a request can be refused for is checked before anything is written or computed
// (checkPredictRequest), except what needs the models read: the frames' pixels (their size may
// come from a model) and whatever the model and glTF readers refuse.
#pragma once

#include <grpcpp/support/status.h>

#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>

#include "proto/daemon.pb.h"

namespace flarelab::daemon {

struct PredictLimits {
    size_t max_files = 64;
    size_t max_name_bytes = 128;
    size_t max_scene_bytes = size_t{1} << 20;
    // The scene, the files' names and their contents together: what one call writes to disk.
    size_t max_input_bytes = size_t{2} << 20;
    // Steps of the sun's timeline times cameras: the timeline's memory and timeline.csv's size
    // grow with it (about 100 bytes a sample).
    int64_t max_timeline_samples = 2'000'000;
    // Pixels of every frame drawn together (each camera at each instant of "frames"): 12 bytes
    // a pixel in memory, an EXR and a PNG each on disk.
    int64_t max_frame_pixels = 64'000'000;
    // The files handed back (PredictOptions.return_report_files, return_frames) together.
    size_t max_output_bytes = size_t{64} << 20;
};

// OK, or INVALID_ARGUMENT naming the field at fault: the scene's name, the options' ranges, the
// files (names empty, longer than max_name_bytes, of characters other than [A-Za-z0-9._-],
// starting with '.', given twice; more than max_files), the sizes (the scene over
// max_scene_bytes, everything over max_input_bytes: RESOURCE_EXHAUSTED), the scene's text
// (predict::parseScene's errors, "scene.json: cameras[1].exposure_s: ..."), a timeline over
// max_timeline_samples, and every file the scene names: it must be a plain file name of the
// request, not an absolute path, nothing with a '/', not "..".
grpc::Status checkPredictRequest(const v1::PredictRequest& request, const PredictLimits& limits);

// Checks the request, then predicts it in a fresh private folder below `work_root` (created
// when missing) and fills `response`. `stop_requested` is asked between the steps of the work;
// when it says true the call ends CANCELLED. Errors of the prediction: INVALID_ARGUMENT for
// what the scene, a model or a glTF file is refused for (the message names the file or field by
// the request's names, never the daemon's folders); RESOURCE_EXHAUSTED for outputs over
// max_output_bytes; UNAVAILABLE when the folder cannot be made or written (a full disk);
// INTERNAL for a failure that should not happen.
grpc::Status runPredict(const v1::PredictRequest& request,
                        const PredictLimits& limits,
                        const std::string& work_root,
                        const std::function<bool()>& stop_requested,
                        v1::PredictResponse* response);

// Removes the folders predictions left in `work_root` (a daemon killed during one). Nothing is
// reported: what cannot be removed now is tried again at the next start.
void clearPredictWork(const std::string& work_root);

}  // namespace flarelab::daemon
