// flarelabd: the daemon that owns the rig and runs sweeps as jobs (daemon/, proto/daemon.proto).
//
//     flarelabd --state-dir DIR [--output-root DIR]
//               [--listen HOST:PORT --token-file FILE [--allow-remote --tls-cert F --tls-key F]]
//               [--no-resume] [--camera-retries N] [--min-free-mb N]
//               [--memory-budget-mb N] [--quarantine-after N]
//               [--keep-ended-jobs N] [--keep-ended-days D]
//               [--camera URI ...] [--head URI ...] [--calibration FILE ...]
//               | [--replay RECORDED_SWEEP]
//
// Without --camera and --head every job runs on the simulated rig its config describes; with
// them, jobs run on those devices (drivers/rig.h URIs: aravis:ID, v4l2:/dev/video0, zaber:...,
// apt:..., sim:...), each opened when a job starts and closed when it ends, so that a device
// that comes and goes between jobs needs no restart.
//
// It keeps its journal in DIR/jobs, listens on DIR/flarelabd.sock (mode 0660), holds
// DIR/flarelabd.lock so that one daemon owns a rig, and refuses a DIR that is not its own (owned
// by another user, or writable by group or others: created 0750 when missing). It stops cleanly
// on SIGTERM or SIGINT: the rig stops at once (head stopped, exposure aborted; the bracket under
// way is not a frame and is taken again), every frame already captured is written, and the job is
// resumed at the next start. A second SIGTERM drops the captured frames not yet written too (they
// are taken again; nothing on disk is lost) and stops a fit.
//
// Under systemd (flarelabd.service) it says READY=1 once it listens, WATCHDOG=1 at half the
// unit's WatchdogSec, STOPPING=1 when it stops (daemon/notify.h), and logs to the journal.
//
// Exit status: 0 after a clean stop, 1 when it cannot start (state directory, lock, socket,
// journal), 2 for flags that do not go together.
#include <fcntl.h>
#include <signal.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <sstream>
#include <thread>

#include "common/file_descriptor.h"
#include "daemon/access.h"
#include "daemon/job_manager.h"
#include "daemon/log.h"
#include "daemon/notify.h"
#include "daemon/service.h"
#include "daemon/sweep_runner.h"
#include "drivers/calibration.h"
#include "drivers/device.h"
#include "hdr/exr.h"
#include "hdr/sweep.h"

namespace {

namespace fs = std::filesystem;
using namespace flarelab;
using namespace flarelab::daemon;

timespec toTimespec(std::chrono::nanoseconds d) {
    return timespec{static_cast<time_t>(d.count() / 1'000'000'000),
                    static_cast<long>(d.count() % 1'000'000'000)};
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
    setLogTarget(detectLogTarget());
    CLI::App app{"flarelabd: the flarelab rig daemon (sweeps as jobs, over gRPC)"};
    std::string state_dir, output_root, listen, token_file, replay, log_level = "info";
    std::string tls_cert, tls_key;
    size_t keep_ended_jobs = 100;
    double keep_ended_days = 30.0;
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
                   "also listen on TCP at HOST:PORT (loopback unless --allow-remote; needs "
                   "--token-file)");
    app.add_flag("--allow-remote", allow_remote,
                 "let --listen bind an address beyond loopback (needs --tls-cert and --tls-key)");
    app.add_option("--tls-cert", tls_cert, "TLS certificate chain for --listen (PEM)");
    app.add_option("--tls-key", tls_key, "its private key (PEM, mode 600)");
    app.add_option("--token-file", token_file,
                   "ask every call for this shared token (metadata authorization: Bearer TOKEN); "
                   "first line of a file of mode 600");
    app.add_option("--keep-ended-jobs", keep_ended_jobs,
                   "ended jobs remembered (job list, the journal); their sweeps stay on disk")
        ->check(CLI::Range(size_t{0}, size_t{100000}))
        ->capture_default_str();
    app.add_option("--keep-ended-days", keep_ended_days,
                   "days an ended job is remembered after it ended")
        ->check(CLI::Range(0.0, 36500.0))
        ->capture_default_str();
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
    if (!listen.empty()) {
        if (allow_remote && (tls_cert.empty() || tls_key.empty())) {
            std::cerr << "flarelabd: --allow-remote needs TLS (--tls-cert and --tls-key): the "
                         "token would cross the network in clear\n";
            return 2;
        }
        if (!allow_remote)
            if (Status ok = checkLoopbackAddress(listen); !ok) {
                std::cerr << "flarelabd: --listen " << ok.error().message
                          << "; add --allow-remote (with --tls-cert and --tls-key) to expose "
                             "the rig\n";
                return 2;
            }
        if (token_file.empty()) {
            std::cerr << "flarelabd: --listen needs --token-file: every local user can reach a "
                         "TCP port\n";
            return 2;
        }
    } else if (allow_remote || !tls_cert.empty() || !tls_key.empty()) {
        std::cerr << "flarelabd: --allow-remote, --tls-cert and --tls-key go with --listen\n";
        return 2;
    }
    std::error_code ec;
    // Made private: the journal, the lock and the socket live here. The parents as the umask
    // says; the directory itself 0750 (the group reaches the socket through g+x).
    if (!fs::exists(state_dir, ec)) {
        fs::create_directories(fs::path(state_dir).lexically_normal().parent_path(), ec);
        if (::mkdir(state_dir.c_str(), 0750) != 0 && errno != EEXIST) {
            std::cerr << "flarelabd: --state-dir " << state_dir << ": " << osMessage(errno) << "\n";
            return 1;
        }
    }
    const fs::path state = fs::canonical(state_dir, ec);
    if (ec) {
        std::cerr << "flarelabd: --state-dir " << state_dir << ": " << ec.message() << "\n";
        return 1;
    }
    if (Status ok = checkPrivateDirectory(state.string(), "--state-dir"); !ok) {
        std::cerr << "flarelabd: " << ok.error().message << "\n";
        return 1;
    }
    if (output_root.empty()) output_root = (state / "output").string();
    fs::create_directories(output_root, ec);
    const fs::path root = fs::canonical(output_root, ec);
    if (ec) {
        std::cerr << "flarelabd: --output-root " << output_root << ": " << ec.message() << "\n";
        return 1;
    }
    std::string token;
    if (!token_file.empty()) {
        auto text = readSecretFile(token_file, "--token-file");
        if (!text) {
            std::cerr << "flarelabd: " << text.error().message << "\n";
            return 1;
        }
        token = text->substr(0, text->find('\n'));
        if (!token.empty() && token.back() == '\r') token.pop_back();
        if (token.size() < 16) {
            std::cerr << "flarelabd: --token-file " << token_file
                      << ": cannot read a token of at least 16 characters from its first line\n";
            return 1;
        }
    }

    // One daemon per state directory: the lock is held for the daemon's life. Never through a
    // link: it could point at a file of someone else's that the daemon would truncate.
    const std::string lock_path = (state / "flarelabd.lock").string();
    FileDescriptor lock(
        ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK, 0640));
    struct stat lock_info {};
    if (!lock.valid() || ::fstat(lock.get(), &lock_info) != 0 || !S_ISREG(lock_info.st_mode)) {
        std::cerr << "flarelabd: " << lock_path << ": "
                  << (!lock.valid() && errno == ELOOP ? std::string("a symbolic link; remove it")
                      : !lock.valid()                 ? osMessage(errno)
                                                      : std::string("not a regular file"))
                  << "\n";
        return 1;
    }
    if (::flock(lock.get(), LOCK_EX | LOCK_NB) != 0) {
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
    options.keep_ended = keep_ended_jobs;
    options.keep_ended_s = keep_ended_days * 86400.0;
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
    server_options.allow_remote = allow_remote;
    server_options.tls_cert_file = tls_cert;
    server_options.tls_key_file = tls_key;
    server_options.service.token = token;
    server_options.service.daemon_version = "flarelabd 0.1.0";
    auto server = DaemonServer::start(**manager, server_options);
    if (!server) {
        std::cerr << "flarelabd: " << server.error().message << "\n";
        return 1;
    }
    const auto watchdog = watchdogInterval();
    logEvent(LogLevel::Info, "daemon.ready",
             {{"pid", std::to_string(::getpid())},
              {"state_dir", state.string()},
              {"output_root", root.string()},
              {"resume", no_resume ? "off" : "on"},
              {"watchdog_s", std::to_string(watchdog.count() * 1e-6)}});
    notifyReady("listening on " + server_options.socket_path);

    // Signals, and the watchdog's pings at half its interval. A ping follows a look at the job
    // manager under its lock: a daemon stuck there (which must never be: no I/O happens under
    // it) stops pinging, and systemd restarts it.
    const auto slice = watchdog.count() > 0 ? std::chrono::nanoseconds(watchdog) / 2
                                            : std::chrono::nanoseconds(std::chrono::seconds(1));
    const auto waitSignal = [&](std::chrono::nanoseconds wait) {
        const timespec t = toTimespec(wait);
        return sigtimedwait(&signals, nullptr, &t);
    };
    int signal_number = -1;
    while (signal_number <= 0) {
        signal_number = waitSignal(slice);
        if (signal_number <= 0 && watchdog.count() > 0) {
            (void)(*manager)->runningJob();
            notifyWatchdog();
        }
    }
    logEvent(LogLevel::Info, "daemon.stopping", {{"signal", strsignal(signal_number)}});
    notifyStopping("stopping: the rig stops, captured frames are written");
    // The stop runs beside this thread, which stays on the signals: a second one hurries it.
    std::atomic<bool> stopped{false};
    std::thread stopper([&] {
        (*server)->shutdown();
        stopped = true;
    });
    bool hurried = false;
    auto next_ping = std::chrono::steady_clock::now();
    while (!stopped) {
        const int again = waitSignal(std::chrono::milliseconds(100));
        if (again > 0 && !hurried) {
            hurried = true;
            logEvent(LogLevel::Warn, "daemon.stopping_now",
                     {{"signal", strsignal(again)},
                      {"what",
                       "captured frames not yet written are dropped; the job takes them "
                       "again when it resumes"}});
            notifyStatus("stopping now: captured frames not yet written are dropped");
            (*manager)->stopNow();
        }
        if (watchdog.count() > 0 && std::chrono::steady_clock::now() >= next_ping) {
            notifyWatchdog();
            next_ping = std::chrono::steady_clock::now() + slice;
        }
    }
    stopper.join();
    server->reset();
    manager->reset();
    logEvent(LogLevel::Info, "daemon.stopped");
    flushLog(2.0);
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    try {
        // Frames are compressed and read on every core; the daemon never forks.
        flarelab::hdr::useExrThreads();
        return run(argc, argv);
    } catch (const std::exception& e) {
        std::cerr << "flarelabd: " << e.what() << "\n";
        return 2;
    }
}
