// ============================================================================
//  flarelab command line: the `lens` commands
// ============================================================================
//
// `flarelab lens show FILE [--json]` and `flarelab lens ghosts FILE --angle DEG [--json]`.
// Registration adds the subcommands to a CLI11 app; running one prints to the given streams and
// returns the process exit code (0 success, 1 bad input, with a message on `err`).
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>

namespace flarelab::apps {

// Adds `lens` with its subcommands to `app`. The callbacks write to `out` and `err` and store the
// exit code in `exit_code`.
void addLensCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
