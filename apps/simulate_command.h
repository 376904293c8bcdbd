// ============================================================================
//  flarelab command line: `simulate`
// ============================================================================
//
// `flarelab simulate --lens FILE --angle DEG [--roll DEG] [--light THETA,PHI[,R,G,B] ...]
//  --width W --height H -o out.exr [--png out.png]`: the flare image of a lens under point lights,
// drawn with the reference rasterizer and the aperture's starburst, written as float OpenEXR and
// optionally a tone-mapped PNG.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>

namespace flarelab::apps {

void addSimulateCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
