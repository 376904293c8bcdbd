// flarelab predict: a planner's scene (predict/scene.h) turned into flare figures per camera and
// light, a timeline of the sun with a camera switching plan, frames, and a report folder (HTML,
// JSON, CSV).
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

void addPredictCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
