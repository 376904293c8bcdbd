// `flarelab rig devices|head|camera`: the rig's devices by hand, without the daemon, so that a lab
// can identify its hardware and try one device at a time (drivers/rig.h opens them by URI).
//
//     flarelab rig devices [--json]
//     flarelab rig head URI home|position|stop|move DEG [--speed DEG_S] [--timeout S] [--json]
//     flarelab rig camera URI --exposure S [--gain G] -o frame.pgm [--png frame.png] [--json]
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

// Adds devices, head and camera under `rig` (the command daemon_commands.h makes).
void addRigDeviceCommands(CLI::App* rig, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
