// flarelab capture: a sweep on a rig (today the simulated one) into a sweep directory.
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

void addCaptureCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
