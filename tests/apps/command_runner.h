// Runs one flarelab command in-process, as `main` would, capturing its output and exit code.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>
#include <sstream>
#include <string>
#include <vector>

namespace flarelab::apps::testing {

struct CommandRun {
    int code = -1;
    std::string out, err;
};

// `add` registers the command on the app, as flarelab.cpp does (addLensCommands, ...); `args`
// follow the program name.
template <typename AddCommand>
CommandRun runCommand(AddCommand add, const std::vector<std::string>& args) {
    CLI::App app;
    app.require_subcommand(1);
    std::ostringstream out, err;
    int code = 0;
    add(app, out, err, code);
    std::vector<const char*> argv{"flarelab"};
    for (const auto& a : args) argv.push_back(a.c_str());
    try {
        app.parse(static_cast<int>(argv.size()), argv.data());
    } catch (const CLI::ParseError& e) {
        return {app.exit(e, out, err), out.str(), err.str()};
    }
    return {code, out.str(), err.str()};
}

}  // namespace flarelab::apps::testing
