// ============================================================================
//  flarelab command line: `model show`
// ============================================================================
//
// `flarelab model show MODEL [--json]`: what a flare model file (fit/model_file.h) holds: lens,
// capture settings, the valid angle range, and per ghost its parameters with the degree of each
// piece's Chebyshev series and its fit residuals. The file is read and validated first. --json
// prints the model in the protobuf JSON mapping instead (the model file's readable form, which
// fit::modelFromJson reads back). Exit code 0, or 1 with the reader's error (naming file and
// field) on stderr.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>

namespace flarelab::apps {

void addModelCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
