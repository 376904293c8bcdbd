// flarelab sun: the sun's zenith and azimuth at a site and a UTC instant (predict/sun.h).
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

void addSunCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
