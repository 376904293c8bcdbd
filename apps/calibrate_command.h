// flarelab calibrate: measures a camera (drivers/calibration_measure.h) and writes its
// calibration file (drivers/calibration.h), asking the operator to cap the lens for the dark
// frames and to uncover it for the exposure series.
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>
#include <iostream>

namespace flarelab::apps {

// `in` answers the operator's prompts (a line each); --yes skips them.
void addCalibrateCommand(CLI::App& app,
                         std::ostream& out,
                         std::ostream& err,
                         int& exit_code,
                         std::istream& in = std::cin);

}  // namespace flarelab::apps
