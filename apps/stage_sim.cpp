// flarelab-stage-sim: a simulated rotation stage on a pseudo-terminal (drivers/stage_sim.h), so
// that a lab or a test can drive the serial drivers without the device:
//
//     flarelab-stage-sim zaber|apt [--homed] [--speed-deg-s S] [--accel-deg-s2 A]
//                        [--device N] [--no-checksums] [--model NAME] [--stall-at-deg D]
//                        [--link PATH] [--tty PATH]
//
// It prints the slave's path (/dev/pts/N) on one line of stdout, then serves until SIGTERM or
// SIGINT. Open it as "zaber:/dev/pts/N" or "apt:/dev/pts/N", e.g.
//
//     sim=$(flarelab-stage-sim zaber --homed | head -1) ... flarelab rig head zaber:$sim move 10
//
// --link makes PATH a symbolic link to the slave, for scripts that want a fixed name. --tty serves
// on an existing terminal instead of a new pty (the gadget side of a USB serial gadget, so that
// the driver on the host side talks through the kernel's USB stack; scripts/vivid_test.sh); it
// then prints the terminal's path.
#include "drivers/stage_sim.h"

#include <signal.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>

namespace {

namespace drivers = flarelab::drivers;

int run(int argc, char** argv) {
    CLI::App app{"A simulated Zaber (ASCII) or Thorlabs APT rotation stage on a pseudo-terminal"};
    std::string protocol;
    app.add_option("protocol", protocol, "zaber or apt")
        ->required()
        ->check(CLI::IsMember({"zaber", "apt"}));
    bool homed = false;
    app.add_flag("--homed", homed, "start homed (default: needs homing, like after power-up)");
    std::optional<double> speed_deg_s;
    app.add_option("--speed-deg-s", speed_deg_s, "speed at power-up (default: zaber 30, apt 10)")
        ->check(CLI::PositiveNumber);
    std::optional<double> accel_deg_s2;
    app.add_option("--accel-deg-s2", accel_deg_s2, "acceleration (default: zaber 300, apt 10)")
        ->check(CLI::PositiveNumber);
    int device = 1;
    app.add_option("--device", device, "zaber: device address")->check(CLI::Range(1, 99));
    bool no_checksums = false;
    app.add_flag("--no-checksums", no_checksums, "zaber: replies without ':XX' checksums");
    std::string model = "K10CR1";
    app.add_option("--model", model, "apt: the model the controller reports (8 characters)");
    std::optional<double> stall_at_deg;
    app.add_option("--stall-at-deg", stall_at_deg, "an obstacle where moves stall");
    std::string link;
    app.add_option("--link", link, "make this path a symbolic link to the pty");
    std::string tty;
    app.add_option("--tty", tty, "serve on this terminal instead of a new pty");
    CLI11_PARSE(app, argc, argv);

    // Block the signals before the simulator's thread starts, so that it inherits the mask and
    // sigwait() below receives them.
    sigset_t stop_signals;
    sigemptyset(&stop_signals);
    sigaddset(&stop_signals, SIGTERM);
    sigaddset(&stop_signals, SIGINT);
    pthread_sigmask(SIG_BLOCK, &stop_signals, nullptr);

    std::unique_ptr<drivers::StageSim> sim;
    if (protocol == "zaber") {
        drivers::ZaberSimOptions o;
        const double units = drivers::kZaberDefaultUnitsPerDeg;
        o.device = device;
        o.homed = homed;
        o.checksums = !no_checksums;
        o.maxspeed =
            std::llround(speed_deg_s.value_or(30.0) * units * drivers::kZaberSpeedUnitsPerStepPerS);
        o.max_maxspeed = std::max(o.max_maxspeed, 4 * o.maxspeed);
        o.accel_steps_s2 = accel_deg_s2.value_or(300.0) * units;
        if (stall_at_deg) o.faults.stall_at = std::llround(*stall_at_deg * units);
        o.serve_tty = tty;
        auto started = drivers::ZaberSim::start(o);
        if (!started) {
            std::cerr << "flarelab-stage-sim: " << started.error().message << "\n";
            return 1;
        }
        sim = std::move(*started);
    } else {
        drivers::AptSimOptions o;
        o.homed = homed;
        o.model = model;
        o.speed_deg_s = speed_deg_s.value_or(10.0);
        o.accel_deg_s2 = accel_deg_s2.value_or(10.0);
        if (stall_at_deg) o.faults.stall_at = std::llround(*stall_at_deg * o.counts_per_deg);
        o.serve_tty = tty;
        auto started = drivers::AptSim::start(o);
        if (!started) {
            std::cerr << "flarelab-stage-sim: " << started.error().message << "\n";
            return 1;
        }
        sim = std::move(*started);
    }
    if (!link.empty() && !tty.empty()) {
        std::cerr << "flarelab-stage-sim: --link names a new pty; with --tty there is none\n";
        return 2;
    }
    if (!link.empty()) {
        std::error_code ec;
        std::filesystem::remove(link, ec);
        std::filesystem::create_symlink(sim->slavePath(), link, ec);
        if (ec) {
            std::cerr << "flarelab-stage-sim: cannot link " << link << ": " << ec.message() << "\n";
            return 1;
        }
    }
    std::cout << (tty.empty() ? sim->slavePath() : tty) << std::endl;
    int received = 0;
    sigwait(&stop_signals, &received);
    if (!link.empty()) {
        std::error_code ec;
        std::filesystem::remove(link, ec);
    }
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    try {
        return run(argc, argv);
    } catch (const std::exception& e) {
        std::cerr << "flarelab-stage-sim: " << e.what() << "\n";
        return 2;
    }
}
