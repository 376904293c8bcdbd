// flarelab's client of flarelabd (proto/daemon.proto): `flarelab rig status`, `flarelab sweep
// start`, `flarelab job list|watch|pause|resume|cancel`.
//
// The daemon is found through --socket PATH, else the environment variable FLARELAB_SOCKET (a
// Unix socket path), else --address HOST:PORT / FLARELAB_ADDRESS (TCP). A token, when the daemon
// asks for one, comes from --token-file or FLARELAB_TOKEN_FILE. Calls carry the client's name,
// FLARELAB_CLIENT or USER@HOST, which is what the daemon's control rule goes by: jobs started under
// one name are controlled under it.
#pragma once

#include <CLI/CLI.hpp>
#include <iosfwd>

namespace flarelab::apps {

void addRigCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);
void addJobCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code);
// `start` under the existing `sweep` command.
void addSweepStartCommand(CLI::App& sweep, std::ostream& out, std::ostream& err, int& exit_code);

}  // namespace flarelab::apps
