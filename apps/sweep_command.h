// ============================================================================
//  flarelab command line: `sweep info`
// ============================================================================
//
// `flarelab sweep info DIR [--check] [--strict] [--json]`: what a sweep directory (hdr/sweep.h)
// holds: lens, camera, capture settings, bracket and frame angles. By default only the manifest
// is read and validated; --check reads and checks every frame as well and lists files the
// manifest does not name as warnings, --strict (implies --check) makes unlisted EXR files errors.
// Exit code 0, or 1 with the reader's error (naming file and field) on stderr.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>

namespace flarelab::apps {

void addSweepCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
