// flarelabd: the daemon that owns the rig and runs sweeps as jobs (daemon/, proto/daemon.proto).
//
//     flarelabd --state-dir DIR [--output-root DIR] [--listen HOST:PORT [--allow-remote]]
//               [--token-file FILE] [--no-resume] [--camera-retries N] [--min-free-mb N]
//               [--memory-budget-mb N] [--quarantine-after N]
//               [--camera URI ...] [--head URI ...] [--calibration FILE ...]
//               | [--replay RECORDED_SWEEP]
//
// Without --camera and --head every job runs on the simulated rig its config describes; with
// them, jobs run on those devices (drivers/rig.h URIs: aravis:ID, v4l2:/dev/video0, zaber:...,
// apt:..., sim:...), each opened when a job starts and closed when it ends, so that a device
// that comes and goes between jobs needs no restart.
//
// It keeps its journal in DIR/jobs, listens on DIR/flarelabd.sock (mode 0660), holds
// DIR/flarelabd.lock so that one daemon owns a rig, and stops cleanly on SIGTERM or SIGINT: a
// running job stops at its next frame, every captured frame is written, and the job is resumed at
// the next start.
#include <fcntl.h>
#include <signal.h>
#include <sys/file.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <sstream>

#include "common/file_descriptor.h"
#include "daemon/job_manager.h"
#include "daemon/log.h"
#include "daemon/service.h"
#include "daemon/sweep_runner.h"
#include "drivers/calibration.h"
#include "drivers/device.h"
#include "hdr/sweep.h"

namespace {

namespace fs = std::filesystem;
using namespace flarelab;
using namespace flarelab::daemon;

bool isLoopback(const std::string& address) {
    const auto colon = address.rfind(':');
    const std::string host = colon == std::string::npos ? address : address.substr(0, colon);
    return host == "localhost" || host == "127.0.0.1" || host == "[::1]" ||
           host.rfind("127.", 0) == 0;
}

// The default memory budget: half the machine's memory, at most 4 GiB. Half, because the fit of
// the last sweep runs beside the next capture and the page cache carries every EXR to the disk;
// 4 GiB holds the pipeline of a 24-Mpx camera with a three-exposure bracket (about 1.3 GiB, see
// daemon/sweep_config.h) with a queue of some twenty brackets, a minute of capture at most rates.
int64_t defaultMemoryBudgetMb() {
    const long pages = ::sysconf(_SC_PHYS_PAGES), page = ::sysconf(_SC_PAGESIZE);
    const int64_t half_mb = pages > 0 && page > 0 ? (int64_t{pages} * page >> 20) / 2 : 4096;
    return std::clamp<int64_t>(half_mb, 256, 4096);
}

int run(int argc, char** argv) {
    settleAllocator();
    CLI::App app{"flarelabd: the flarelab rig daemon (sweeps as jobs, over gRPC)"};
    std::string state_dir, output_root, listen, token_file, replay, log_level = "info";
    std::vector<std::string> cameras, heads, calibration_files;
    bool no_resume = false, allow_remote = false;
    int camera_retries = 3, head_retries = 2;
    int64_t min_free_mb = 64, memory_budget_mb = defaultMemoryBudgetMb();
    int quarantine_after = 3;
    app.add_option("--state-dir", state_dir,
                   "journal, lock and socket (DIR/flarelabd.sock) live here")
        ->required();
    app.add_option("--output-root", output_root,
                   "every sweep directory lies below it (default: STATE_DIR/output)");
    app.add_option("--listen", listen,
                   "also listen on TCP at HOST:PORT (loopback unless "
                   "--allow-remote)");
    app.add_flag("--allow-remote", allow_remote, "let --listen bind an address beyond loopback");
    app.add_option("--token-file", token_file,
                   "ask every call for this shared token (metadata authorization: Bearer TOKEN)");
    app.add_option("--replay", replay,
                   "drive a recorded sweep played back instead of the simulated rig");
    app.add_option("--camera", cameras,
                   "a camera jobs may use, by URI (repeat for several; the first is the "
                   "default; none: jobs simulate theirs)");
    app.add_option("--head", heads,
                   "a head jobs may use, by URI (repeat for several; the first is the default; "
                   "none: jobs simulate theirs)");
    app.add_option("--calibration", calibration_files,
                   "a camera's calibration (flarelab calibrate; repeat for several cameras): a "
                   "job's frames are merged through the one measured on its camera");
    app.add_flag("--no-resume", no_resume,
                 "do not resume interrupted jobs at start (they wait for a client's resume)");
    app.add_option("--camera-retries", camera_retries, "camera timeouts retried per exposure")
        ->check(CLI::Range(0, 100))
        ->capture_default_str();
    app.add_option("--head-retries", head_retries, "head timeouts retried per move")
        ->check(CLI::Range(0, 100))
        ->capture_default_str();
    app.add_option("--min-free-mb", min_free_mb, "free disk space a job leaves (MiB)")
        ->check(CLI::Range(int64_t{0}, int64_t{1} << 30))
        ->capture_default_str();
    app.add_option("--memory-budget-mb", memory_budget_mb,
                   "memory a job may hold (MiB): larger frames are refused, the queue between "
                   "capture and processing holds the rest (default: half the machine's, at most "
                   "4096)")
        ->check(CLI::Range(int64_t{128}, int64_t{1} << 30))
        ->capture_default_str();
    app.add_option("--quarantine-after", quarantine_after,
                   "a job under which the daemon died this many times in a row without getting "
                   "further is not resumed again but failed (0: never)")
        ->check(CLI::Range(0, 1000000))
        ->capture_default_str();
    app.add_option("--log-level", log_level, "debug, info, warn or error")->capture_default_str();
    CLI11_PARSE(app, argc, argv);

    if (log_level == "debug")
        setLogLevel(LogLevel::Debug);
    else if (log_level == "warn")
        setLogLevel(LogLevel::Warn);
    else if (log_level == "error")
        setLogLevel(LogLevel::Error);
    else if (log_level != "info") {
        std::cerr << "flarelabd: --log-level must be debug, info, warn or error\n";
        return 2;
    }
    if (!listen.empty() && !allow_remote && !isLoopback(listen)) {
        std::cerr << "flarelabd: --listen " << listen
                  << " is not a loopback address; add --allow-remote to expose the rig\n";
        return 2;
    }
    std::error_code ec;
    fs::create_directories(state_dir, ec);
    const fs::path state = fs::canonical(state_dir, ec);
    if (ec) {
        std::cerr << "flarelabd: --state-dir " << state_dir << ": " << ec.message() << "\n";
        return 1;
    }
    ::chmod(state.c_str(), 0770);
    if (output_root.empty()) output_root = (state / "output").string();
    fs::create_directories(output_root, ec);
    const fs::path root = fs::canonical(output_root, ec);
    if (ec) {
        std::cerr << "flarelabd: --output-root " << output_root << ": " << ec.message() << "\n";
        return 1;
    }
    std::string token;
    if (!token_file.empty()) {
        std::ifstream in(token_file);
        if (!in || !std::getline(in, token) || token.size() < 16) {
            std::cerr << "flarelabd: --token-file " << token_file
                      << ": cannot read a token of at least 16 characters from its first line\n";
            return 1;
        }
    }

    // One daemon per state directory: the lock is held for the daemon's life.
    const std::string lock_path = (state / "flarelabd.lock").string();
    FileDescriptor lock(::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0660));
    if (!lock.valid() || ::flock(lock.get(), LOCK_EX | LOCK_NB) != 0) {
        std::ifstream in(lock_path);
        std::string pid;
        std::getline(in, pid);
        std::cerr << "flarelabd: " << state.string() << " is owned by another flarelabd"
                  << (pid.empty() ? "" : " (pid " + pid + ")") << "\n";
        return 1;
    }
    const std::string pid = std::to_string(::getpid()) + "\n";
    if (::ftruncate(lock.get(), 0) != 0 || ::write(lock.get(), pid.data(), pid.size()) < 0)
        logEvent(LogLevel::Warn, "lock.pid_not_written", {{"path", lock_path}});

    // Signals are taken by sigwait below; every thread started from here on blocks them.
    sigset_t signals;
    sigemptyset(&signals);
    sigaddset(&signals, SIGTERM);
    sigaddset(&signals, SIGINT);
    sigaddset(&signals, SIGHUP);
    pthread_sigmask(SIG_BLOCK, &signals, nullptr);
    ::signal(SIGPIPE, SIG_IGN);

    ManagerOptions options;
    options.resume = !no_resume;
    options.runner.state_dir = state.string();
    options.runner.output_root = root.string();
    options.runner.camera_retries = camera_retries;
    options.runner.head_retries = head_retries;
    options.runner.min_free_bytes = min_free_mb << 20;
    options.runner.limits.memory_budget_bytes = memory_budget_mb << 20;
    options.quarantine_after = quarantine_after;
    options.runner.software_version = "flarelabd 0.1.0";
    ServerOptions server_options;
    if (!replay.empty() && (!cameras.empty() || !heads.empty())) {
        std::cerr
            << "flarelabd: --replay drives a recorded sweep: it takes no --camera or --head\n";
        return 2;
    }
    for (const auto& [flag, uris] :
         {std::pair<const char*, const std::vector<std::string>*>{"--camera", &cameras},
          {"--head", &heads}})
        for (const std::string& uri : *uris)
            if (auto parsed = drivers::parseDeviceUri(uri); !parsed || uri.empty()) {
                std::cerr << "flarelabd: " << flag << " '" << uri
                          << "': " << (parsed ? "empty" : parsed.error().message) << "\n";
                return 2;
            }
    for (const std::string& file : calibration_files) {
        auto calibration = drivers::readCalibration(file);
        if (!calibration) {
            std::cerr << "flarelabd: --calibration: " << calibration.error().message << "\n";
            return 1;
        }
        options.runner.calibrations.push_back(std::move(*calibration));
    }
    options.runner.limits.cameras = cameras;
    options.runner.limits.heads = heads;
    if (!cameras.empty() || !heads.empty()) {
        ServiceOptions& s = server_options.service;
        s.rig = "devices";
        s.cameras = cameras;
        s.heads = heads;
    }
    if (!replay.empty()) {
        auto recorded = hdr::readSweep(fs::absolute(replay).lexically_normal().string());
        if (!recorded) {
            std::cerr << "flarelabd: --replay: " << recorded.error().message << "\n";
            return 1;
        }
        if (recorded->frames.empty()) {
            std::cerr << "flarelabd: --replay " << replay << ": the sweep holds no frames\n";
            return 1;
        }
        auto sweep = std::make_shared<const hdr::Sweep>(std::move(*recorded));
        options.runner.limits.replay = sweep;
        options.runner.limits.head_min_deg = std::min(0.0, sweep->frames.front().angle_deg);
        options.runner.limits.head_max_deg = std::max(0.0, sweep->frames.back().angle_deg);
        options.runner.limits.min_exposure_s = 1e-6;
        options.runner.limits.max_exposure_s = 3600.0;
        options.runner.limits.max_gain = 64.0;
        ServiceOptions& s = server_options.service;
        s.rig = "replay";
        s.camera_model = "replay of " + sweep->header.camera.description;
        s.camera_serial = sweep->header.camera.serial;
        s.head_model = "replay head";
        s.head_serial = "REPLAY-0";
        s.device_uri = "replay:" + sweep->directory;
        s.bit_depth = 16;
    }
    auto manager = JobManager::open(options);
    if (!manager) {
        std::cerr << "flarelabd: " << manager.error().message << "\n";
        return 1;
    }
    server_options.socket_path = (state / "flarelabd.sock").string();
    server_options.tcp_address = listen;
    server_options.service.token = token;
    server_options.service.daemon_version = "flarelabd 0.1.0";
    auto server = DaemonServer::start(**manager, server_options);
    if (!server) {
        std::cerr << "flarelabd: " << server.error().message << "\n";
        return 1;
    }
    logEvent(LogLevel::Info, "daemon.ready",
             {{"pid", std::to_string(::getpid())},
              {"state_dir", state.string()},
              {"output_root", root.string()},
              {"resume", no_resume ? "off" : "on"}});
    int signal_number = 0;
    sigwait(&signals, &signal_number);
    logEvent(LogLevel::Info, "daemon.stopping", {{"signal", strsignal(signal_number)}});
    (*server)->shutdown();
    server->reset();
    manager->reset();
    logEvent(LogLevel::Info, "daemon.stopped");
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    try {
        return run(argc, argv);
    } catch (const std::exception& e) {
        std::cerr << "flarelabd: " << e.what() << "\n";
        return 2;
    }
}
