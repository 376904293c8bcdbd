// flarelab: the command-line tool. Each command parses its flags, fills an options struct and
// calls a library; see README.md for the commands.
#include <CLI/CLI.hpp>
#include <exception>
#include <iostream>

#include "apps/bench_command.h"
#include "apps/calibrate_command.h"
#include "apps/capture_command.h"
#include "apps/daemon_commands.h"
#include "apps/fit_command.h"
#include "apps/lens_commands.h"
#include "apps/merge_command.h"
#include "apps/model_command.h"
#include "apps/predict_command.h"
#include "apps/simulate_command.h"
#include "apps/sun_command.h"
#include "apps/sweep_command.h"
#include "hdr/exr.h"

int main(int argc, char** argv) {
    try {
        // EXR files are compressed and decompressed on every core; nothing here forks.
        flarelab::hdr::useExrThreads();
        CLI::App app{"flarelab: measure and predict camera lens flare"};
        app.require_subcommand(1);
        int exit_code = 0;
        flarelab::apps::addLensCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addSimulateCommand(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addMergeCommand(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addCaptureCommand(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addCalibrateCommand(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addSweepCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addModelCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addFitCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addBenchCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addRigCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addJobCommands(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addSunCommand(app, std::cout, std::cerr, exit_code);
        flarelab::apps::addPredictCommand(app, std::cout, std::cerr, exit_code);
        CLI11_PARSE(app, argc, argv);
        return exit_code;
    } catch (const std::exception& e) {
        std::cerr << "flarelab: " << e.what() << "\n";
        return 2;
    }
}
