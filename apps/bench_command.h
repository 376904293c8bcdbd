// flarelab bench: benchmarks run from the command line (bench/render_bench.h).
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

void addBenchCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
