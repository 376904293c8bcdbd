// The daemon's pipeline, measured (README, "The daemon: measured"):
//
//   daemon_bench overhead [--frames N] [--brackets T,T,..] [--width W] [--height H] [--runs R]
//       A sweep on the simulated rig in real time, twice per run: the rig alone (head moves and
//       exposures, nothing done with the frames: the baseline), then the daemon's job (capture,
//       merge, EXR and manifest, previews) through the same rig. Both are timed from the first
//       move after homing to the last frame: for the job, to the last frame safely on disk, so
//       its last frame's merge and write, which nothing can hide, count. Prints, per run and best
//       of R, both wall times, their ratio and the ratio to the rig's own time (exposures + head
//       moves, the simulated camera's readout set to 0 so that it is exactly that sum).
//   daemon_bench memory --frames N [--width W] [--height H]
//       A job of N frames from 0 to 20 degrees in simulated time (as fast as it renders); prints
//       the resident memory (VmRSS) after frame 10, N/8, N/4, N/2, 3N/4 and N, and the peak
//       (VmHWM).
//   daemon_bench rigmem --frames N [--width W] [--height H]
//       The same sweep through the simulated rig alone (no merge, no files), the baseline of
//       what the simulator and the allocator warm up to; the same samples.
//   daemon_bench idle --flarelabd PATH [--seconds S]
//       Starts flarelabd with no job, waits 2 s, then reads its CPU time (user + system, from
//       /proc) over S seconds.
// Each prints one JSON object on stdout (and a line for people on stderr).
#include <malloc.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "daemon/sweep_config.h"
#include "daemon/sweep_runner.h"

extern char** environ;

namespace {

namespace fs = std::filesystem;
using namespace flarelab;
using namespace flarelab::daemon;
using Clock = std::chrono::steady_clock;

double since(Clock::time_point t) {
    return std::chrono::duration<double>(Clock::now() - t).count();
}

// kB from /proc/self/status.
int64_t procStatus(const char* key) {
    std::ifstream in("/proc/self/status");
    std::string line;
    while (std::getline(in, line))
        if (line.rfind(key, 0) == 0) return std::stoll(line.substr(std::strlen(key) + 1));
    return -1;
}

std::string readText(const std::string& path) {
    std::ifstream in(path);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

// A job's owner that never pauses or stops it, and samples memory at chosen frames.
class BenchControl final : public JobControl {
public:
    std::map<uint32_t, int64_t> rss_kb_at;   // frames on disk -> VmRSS
    std::map<uint32_t, int64_t> heap_kb_at;  // frames on disk -> bytes malloc holds in use
    std::vector<uint32_t> sample_at;

    bool checkpoint() override { return true; }
    bool pauseForFault(const std::string& reason) override {
        std::cerr << "daemon_bench: the job paused: " << reason << "\n";
        return false;
    }
    const std::atomic<bool>& stopFlag() const override { return stop_; }
    void setStopHook(std::function<void()>) override {}
    void setPhase(v1::JobPhase) override {}
    void setFramesDone(uint32_t frames) override {
        for (const uint32_t at : sample_at)
            if (at == frames) {
                rss_kb_at[frames] = procStatus("VmRSS:");
                const struct mallinfo2 m = mallinfo2();
                heap_kb_at[frames] = static_cast<int64_t>((m.uordblks + m.hblkhd) / 1024);
            }
    }
    void warning(const std::string& message) override {
        std::cerr << "daemon_bench: warning: " << message << "\n";
    }
    void event(v1::JobEvent) override {}

private:
    std::atomic<bool> stop_{false};
};

struct Args {
    std::string mode;
    int frames = 20;
    std::string brackets = "0.25,1,4";
    int width = 640, height = 427, runs = 3;
    std::string flarelabd;
    double seconds = 30.0;
};

v1::SweepConfig config(const Args& a, const std::string& output, bool fast) {
    v1::SweepConfig c;
    c.mutable_sim()->set_fast(fast);
    c.mutable_sim()->set_seed(1);
    c.mutable_sim()->mutable_lens()->set_prescription_csv(
        readText(std::string(FLARELAB_SOURCE_DIR) + "/data/lenses/heliar-tronnier.csv"));
    c.mutable_sim()->mutable_lens()->set_name("heliar-tronnier.csv");
    c.set_from_deg(0.0);
    c.set_step_deg(0.2);
    c.set_to_deg(0.2 * (a.frames - 1));
    std::stringstream in(a.brackets);
    std::string t;
    while (std::getline(in, t, ',')) c.add_exposure_times_s(std::stod(t));
    c.set_width_px(a.width);
    c.set_height_px(a.height);
    c.set_output_dir(output);
    c.set_previews(true);
    return c;
}

// Memory runs cover 0 to 20 degrees whatever their length, so that a short and a long sweep see
// the same scenes (the renderer's buffers follow the ghosts in view) and differ only in length.
void spanTwentyDegrees(v1::SweepConfig& c, int frames) {
    c.set_from_deg(0.0);
    c.set_step_deg(20.0 / (frames - 1));
    c.set_to_deg(20.0);
}

struct Setup {
    std::string root;
    SweepLimits limits;
    RunnerOptions runner;
};

Setup setup() {
    Setup s;
    const fs::path dir =
        fs::temp_directory_path() / ("flarelab-daemon-bench-" + std::to_string(::getpid()));
    fs::create_directories(dir / "out");
    s.root = fs::canonical(dir / "out").string();
    s.limits.readout_s = 0.0;  // the rig's time is then exposures + moves exactly
    s.runner.output_root = s.root;
    s.runner.state_dir = dir.string();
    s.runner.limits = s.limits;
    s.runner.min_free_bytes = 0;
    s.runner.software_version = "daemon_bench";
    return s;
}

// The rig alone: home, then per frame a move and the bracket.
double rigOnly(const PreparedSweep& p, const SweepLimits& limits) {
    auto rig = openJobRig(p, limits);
    if (!rig) throw std::runtime_error(rig.error().message);
    if (Status ok = rig->head->home(600.0); !ok) throw std::runtime_error(ok.error().message);
    const auto start = Clock::now();
    for (const double angle : p.angles_deg) {
        if (auto at = rig->head->moveTo(angle, 600.0); !at)
            throw std::runtime_error(at.error().message);
        for (const double t : p.exposure_times_s) {
            if (Status ok = rig->camera->setExposure(t); !ok)
                throw std::runtime_error(ok.error().message);
            if (auto frame = rig->camera->capture(600.0); !frame)
                throw std::runtime_error(frame.error().message);
        }
    }
    return since(start);
}

double wholeJob(const Setup& s, const v1::SweepConfig& c, BenchControl& control, RunResult* out) {
    v1::Job job;
    job.set_id("job-000001");
    *job.mutable_config() = c;
    *out = runSweepJob(job, s.runner, control);
    if (out->outcome != RunOutcome::Succeeded)
        throw std::runtime_error("the job did not succeed: " + out->reason);
    return out->capture_wall_s;
}

int overhead(const Args& a) {
    const Setup s = setup();
    nlohmann::json runs = nlohmann::json::array();
    double best_rig = 1e300, best_job = 1e300, rig_time = 0.0, best_ratio = 1e300;
    for (int r = 0; r < a.runs; ++r) {
        const std::string dir = "run-" + std::to_string(r);
        auto prepared = prepareSweep(config(a, dir, false), s.root, s.limits);
        if (!prepared) throw std::runtime_error(prepared.error().message);
        rig_time = prepared->rig_time_s;
        const double rig = rigOnly(*prepared, s.limits);
        BenchControl control;
        RunResult result;
        const double job = wholeJob(s, config(a, dir, false), control, &result);
        best_rig = std::min(best_rig, rig);
        best_job = std::min(best_job, job);
        best_ratio = std::min(best_ratio, job / rig);
        runs.push_back({{"rig_only_s", rig},
                        {"job_s", job},
                        {"ratio", job / rig},
                        {"queue_high_water", result.queue_high_water}});
        std::cerr << "daemon_bench: run " << r + 1 << ": rig alone " << rig << " s, whole job "
                  << job << " s, ratio " << job / rig << "\n";
        fs::remove_all(s.root + "/" + dir);
    }
    nlohmann::json out = {{"mode", "overhead"},
                          {"frames", a.frames},
                          {"brackets", a.brackets},
                          {"width", a.width},
                          {"height", a.height},
                          {"rig_time_s", rig_time},
                          {"best_rig_only_s", best_rig},
                          {"best_job_s", best_job},
                          {"best_ratio_job_to_rig_only", best_ratio},
                          {"best_job_to_rig_time", best_job / rig_time},
                          {"runs", runs}};
    std::cout << out.dump() << "\n";
    std::cerr << "daemon_bench: " << a.frames << " frames, brackets " << a.brackets
              << " s: rig time (exposures + moves) " << rig_time << " s; best whole job "
              << best_job << " s = " << best_job / rig_time << " x rig time; best job / rig alone "
              << best_ratio << "\n";
    fs::remove_all(fs::path(s.root).parent_path());
    return 0;
}

// Frames at which memory is sampled: 10, then eighths, quarters and halves of the sweep.
std::vector<uint32_t> samplePoints(uint32_t n) {
    return {std::min<uint32_t>(10, n),        std::max<uint32_t>(1, n / 8),
            std::max<uint32_t>(1, n / 4),     std::max<uint32_t>(1, n / 2),
            std::max<uint32_t>(1, 3 * n / 4), n};
}

// The same sweep as `memory`, the simulated rig alone (no merge, no files): the baseline of what
// the simulator and the allocator warm up to.
int rigMemory(const Args& a) {
    const Setup s = setup();
    v1::SweepConfig c = config(a, "rigmem", true);
    spanTwentyDegrees(c, a.frames);
    auto p = prepareSweep(c, s.root, s.limits);
    if (!p) throw std::runtime_error(p.error().message);
    auto rig = openJobRig(*p, s.limits);
    if (!rig) throw std::runtime_error(rig.error().message);
    if (Status ok = rig->head->home(600.0); !ok) throw std::runtime_error(ok.error().message);
    const auto points = samplePoints(static_cast<uint32_t>(a.frames));
    nlohmann::json samples = nlohmann::json::object();
    uint32_t done = 0;
    for (const double angle : p->angles_deg) {
        if (auto at = rig->head->moveTo(angle, 600.0); !at)
            throw std::runtime_error(at.error().message);
        for (const double t : p->exposure_times_s) {
            if (Status ok = rig->camera->setExposure(t); !ok)
                throw std::runtime_error(ok.error().message);
            if (auto frame = rig->camera->capture(600.0); !frame)
                throw std::runtime_error(frame.error().message);
        }
        ++done;
        if (std::find(points.begin(), points.end(), done) != points.end())
            samples[std::to_string(done)] = procStatus("VmRSS:");
    }
    nlohmann::json out = {{"mode", "rig_memory"},
                          {"frames", a.frames},
                          {"width", a.width},
                          {"height", a.height},
                          {"rss_kb_after_frames", samples},
                          {"peak_rss_kb", procStatus("VmHWM:")}};
    std::cout << out.dump() << "\n";
    std::cerr << "daemon_bench: the rig alone, " << a.frames << " frames, peak RSS "
              << procStatus("VmHWM:") / 1024 << " MiB\n";
    fs::remove_all(fs::path(s.root).parent_path());
    return 0;
}

int memory(const Args& a) {
    const Setup s = setup();
    BenchControl control;
    const uint32_t n = static_cast<uint32_t>(a.frames);
    control.sample_at = samplePoints(n);
    v1::SweepConfig c = config(a, "memory", true);
    spanTwentyDegrees(c, a.frames);
    RunResult result;
    const double wall = wholeJob(s, c, control, &result);
    nlohmann::json samples = nlohmann::json::object(), heap = nlohmann::json::object();
    for (const auto& [frames, kb] : control.rss_kb_at) samples[std::to_string(frames)] = kb;
    for (const auto& [frames, kb] : control.heap_kb_at) heap[std::to_string(frames)] = kb;
    nlohmann::json out = {{"mode", "memory"},
                          {"frames", a.frames},
                          {"width", a.width},
                          {"height", a.height},
                          {"wall_s", wall},
                          {"rss_kb_after_frames", samples},
                          {"malloc_in_use_kb_after_frames", heap},
                          {"peak_rss_kb", procStatus("VmHWM:")},
                          {"queue_high_water", result.queue_high_water}};
    std::cout << out.dump() << "\n";
    std::cerr << "daemon_bench: " << a.frames << " frames in " << wall << " s, peak RSS "
              << procStatus("VmHWM:") / 1024 << " MiB\n";
    fs::remove_all(fs::path(s.root).parent_path());
    return 0;
}

// utime + stime of a process, in seconds.
double cpuSeconds(pid_t pid) {
    std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const auto close = text.rfind(')');
    std::istringstream fields(text.substr(close + 2));
    std::string f;
    double utime = 0, stime = 0;
    for (int i = 3; i <= 15 && fields >> f; ++i) {
        if (i == 14) utime = std::stod(f);
        if (i == 15) stime = std::stod(f);
    }
    return (utime + stime) / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

int idle(const Args& a) {
    if (a.flarelabd.empty()) throw std::runtime_error("idle needs --flarelabd PATH");
    char name[] = "/tmp/flarelabd-idle-XXXXXX";
    const std::string dir = ::mkdtemp(name);
    std::vector<std::string> argv = {a.flarelabd, "--state-dir", dir, "--log-level", "warn"};
    std::vector<char*> args;
    for (auto& s : argv) args.push_back(s.data());
    args.push_back(nullptr);
    pid_t pid = 0;
    if (posix_spawn(&pid, args[0], nullptr, nullptr, args.data(), environ) != 0)
        throw std::runtime_error("cannot start " + a.flarelabd);
    std::this_thread::sleep_for(std::chrono::seconds(2));
    const double before = cpuSeconds(pid);
    std::this_thread::sleep_for(std::chrono::duration<double>(a.seconds));
    const double after = cpuSeconds(pid);
    ::kill(pid, SIGTERM);
    int status = 0;
    ::waitpid(pid, &status, 0);
    fs::remove_all(dir);
    const double tick = 1.0 / static_cast<double>(::sysconf(_SC_CLK_TCK));
    nlohmann::json out = {{"mode", "idle"},
                          {"seconds", a.seconds},
                          {"cpu_s", after - before},
                          {"cpu_fraction", (after - before) / a.seconds},
                          {"clock_tick_s", tick}};
    std::cout << out.dump() << "\n";
    std::cerr << "daemon_bench: idle flarelabd used " << after - before << " s of CPU in "
              << a.seconds << " s (clock tick " << tick << " s)\n";
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    settleAllocator();  // as flarelabd runs
    try {
        Args a;
        if (argc < 2)
            throw std::runtime_error("usage: daemon_bench overhead|memory|idle [options]");
        a.mode = argv[1];
        for (int i = 2; i + 1 < argc; i += 2) {
            const std::string key = argv[i], value = argv[i + 1];
            if (key == "--frames")
                a.frames = std::stoi(value);
            else if (key == "--brackets")
                a.brackets = value;
            else if (key == "--width")
                a.width = std::stoi(value);
            else if (key == "--height")
                a.height = std::stoi(value);
            else if (key == "--runs")
                a.runs = std::stoi(value);
            else if (key == "--flarelabd")
                a.flarelabd = value;
            else if (key == "--seconds")
                a.seconds = std::stod(value);
            else
                throw std::runtime_error("unknown option " + key);
        }
        if (a.frames < 2 || a.runs < 1) throw std::runtime_error("--frames >= 2, --runs >= 1");
        if (a.mode == "overhead") return overhead(a);
        if (a.mode == "memory") return memory(a);
        if (a.mode == "rigmem") return rigMemory(a);
        if (a.mode == "idle") return idle(a);
        throw std::runtime_error("unknown mode " + a.mode);
    } catch (const std::exception& e) {
        std::cerr << "daemon_bench: " << e.what() << "\n";
        return 1;
    }
}
