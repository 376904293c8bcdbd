// flarelab merge: raw brackets on disk (hdr/raw_io.h) to one HDR EXR frame (hdr/merge.h).
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

void addMergeCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
