// ============================================================================
//  flarelab command line: addFitCommands (fit, score), sha256Hex
// ============================================================================
//
//   flarelab fit SWEEP -o MODEL [--lens FILE] [--sensor-mm WxH] [tuning flags]
//       fits every ghost of a sweep (fit/sweep_fit.h) and writes the model file; progress on
//       stderr. --lens records the prescription (file name and SHA-256) and gives the sensor size;
//       without it the sensor comes from the manifest's pixel pitch or --sensor-mm.
//   flarelab score MODEL --lens FILE [--angles A,B,...] [--json]
//       re-simulates what the sweep's simulated camera saw, ghosts only and without noise, and
//       scores the model against it (fit/score.h). The lens file must be the one recorded in the
//       model (its SHA-256 is checked when the model has one).
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>
#include <string>

#include "common/result.h"
#include "fit/model_file.h"

namespace flarelab::apps {

void addFitCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

// SHA-256 of a file's bytes as 64 lowercase hex digits (OpenSSL).
Result<std::string> sha256Hex(const std::string& path);

}  // namespace flarelab::apps
