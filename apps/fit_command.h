// ============================================================================
//  flarelab command line: addFitCommands (fit, score), captureLens
// ============================================================================
//
//   flarelab fit SWEEP -o MODEL [--lens FILE] [--sensor-mm WxH] [tuning flags]
//       fits every ghost of a sweep (fit/sweep_fit.h) and writes the model file; progress on
//       stderr. --lens records the prescription (file name and SHA-256) and gives the sensor size;
//       without it the sensor comes from the manifest's pixel pitch or --sensor-mm.
//       With a sweep of format version 3 the sensor size is the one the sweep records (a
//       --sensor-mm that contradicts it is refused) and --lens must be the file the sweep records
//       (its SHA-256 is checked); the model copies the sweep's camera settings.
//   flarelab score MODEL --lens FILE [--angles A,B,...] [--json]
//       re-simulates what the sweep's simulated camera saw, ghosts only and without noise, and
//       scores the model against it (fit/score.h). The lens file must be the one recorded in the
//       model (its SHA-256 is checked when the model has one); the lens is built with the camera
//       settings the model records (captureLens).
#pragma once

#include <CLI/CLI.hpp>
#include <optional>
#include <ostream>
#include <string>

#include "common/result.h"
#include "fit/model_file.h"
#include "optics/lens.h"

namespace flarelab::apps {

void addFitCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

// The lens of the capture a model was fitted to, as `score` simulates it: the prescription at
// `lens_path` with the camera settings the model records (drivers::rebuildLens). When the model
// (format 1, or fitted to a sweep older than version 3) lacks some, one note on `err` names them
// and what was assumed; `model_path` names the model there. On failure the error goes to `err`.
std::optional<optics::Lens> captureLens(const std::string& lens_path,
                                        const fit::FlareModel& model,
                                        const std::string& model_path,
                                        std::ostream& err);

}  // namespace flarelab::apps
