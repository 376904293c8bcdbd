// flarelab capture: a sweep on a rig (today the simulated one) into a sweep directory.
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>
#include <string>
#include <vector>

#include "common/result.h"

namespace flarelab::apps {

// "0.25,1,4": exposure times in seconds, each a positive finite number; InvalidArgument naming
// --brackets otherwise.
Result<std::vector<double>> parseBrackets(const std::string& text);
// Comma-separated exposure times in seconds, each finite and positive; `flag` names the option
// in the error. parseBrackets adds its own count rule, calibrate another.
Result<std::vector<double>> parseExposureTimes(const std::string& text, const std::string& flag);

void addCaptureCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
