// ============================================================================
//  flarelab daemon: SweepLimits, PreparedSweep, prepareSweep, resolveOutputDir, sweepAngles,
//                   JobMemory, jobMemory, checkMemoryBudget
// ============================================================================
//
// A sweep request (flarelab.v1.SweepConfig, proto/daemon.proto) checked field by field and
// turned into what a job runs: the head angles, the bracket, the lens of the simulated camera,
// the sweep directory as an absolute path below the daemon's output root, and an estimate of the
// rig time. Everything a client sends passes through here before the daemon acts on it, so every
// refusal is an InvalidArgument whose message starts with the field at fault:
// "config.step_deg: must be a finite number > 0 (got -0.2)".
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/result.h"
#include "hdr/sweep.h"
#include "optics/lens.h"
#include "proto/daemon.pb.h"

namespace flarelab::daemon {

struct SweepLimits {
    int64_t max_frames = 100000;
    int max_exposures = 16;                  // per bracket
    int64_t max_pixels = int64_t{64} << 20;  // per frame
    int64_t max_prescription_bytes = 1 << 20;
    // What the daemon may hold in memory while it runs a job (flarelabd --memory-budget-mb): a
    // job whose frames could not fit (jobMemory) is refused, and the queue between capture and
    // processing holds what is left of it.
    int64_t memory_budget_bytes = int64_t{4} << 30;
    // The rig's ranges (the simulated rig's by default).
    double head_min_deg = -90.0;
    double head_max_deg = 90.0;
    double head_speed_deg_s = 20.0;
    double head_acceleration_deg_s2 = 100.0;
    double head_settle_s = 0.1;
    double min_exposure_s = 1e-9;  // the simulated camera's (sim_camera.h)
    double max_exposure_s = 60.0;
    double min_gain = 1.0;
    double max_gain = 16.0;
    double readout_s = 0.03;
    // The rig is a recorded sweep played back (flarelabd --replay) when set: then a config must
    // leave `sim` out, its angles must be recorded ones, and its frame size is the recording's.
    std::shared_ptr<const hdr::Sweep> replay;
    // The rig's devices (flarelabd --camera, --head): URIs or aliases a job may name; the first
    // is a job's default. Empty: that device is simulated per job from config.sim.
    std::vector<std::string> cameras;
    std::vector<std::string> heads;
};

struct PreparedSweep {
    flarelab::v1::SweepConfig config;  // as given, defaults filled in (brackets, size, gain, seed)
    std::vector<double> angles_deg;    // increasing, on the step grid, rounded to a nanodegree
    std::vector<double> exposure_times_s;
    std::string output_dir;            // absolute, normalised, below the output root
    std::optional<optics::Lens> lens;  // the simulated camera's (config.sim); none otherwise
    // The devices the job runs on: URIs of the daemon's, or empty for the one simulated from
    // config.sim (and none when replaying).
    std::string camera_uri;
    std::string head_uri;
    double rig_time_s = 0.0;  // exposures, readouts and moves, from angle 0
    std::vector<std::string> warnings;
};

// What a job holds in memory, by the size of its frames (pixels), its bracket (exposures) and
// whether its camera is simulated. The capture thread holds the bracket it is taking (and a
// simulated camera its rendered planes), the processing thread the bracket it merges with the
// merged radiance (5 bytes a pixel), the RGB image (12) and its preview (3), and the queue between
// them whole brackets; the rest of the daemon (gRPC, the journal, code) is the baseline, measured
// (README, "The daemon: measured").
struct JobMemory {
    int64_t bracket_bytes = 0;  // one bracket of raw frames, 2 bytes a sample
    int64_t fixed_bytes = 0;    // everything but the queue: baseline, two brackets, work buffers
    int64_t minimum_bytes = 0;  // fixed_bytes and a queue of one bracket
};
inline constexpr int64_t kDaemonBaselineBytes = int64_t{96} << 20;
JobMemory jobMemory(int64_t width_px, int64_t height_px, int64_t exposures, bool simulated_camera);
// InvalidArgument starting with `field` and giving the figures, when a job of this size could not
// run within limits.memory_budget_bytes.
Status checkMemoryBudget(int64_t width_px,
                         int64_t height_px,
                         int64_t exposures,
                         bool simulated_camera,
                         const SweepLimits& limits,
                         const std::string& field);

// Checks `config` and fills in its defaults; InvalidArgument naming the field otherwise.
// `output_root` is an absolute, canonical directory (the daemon's).
Result<PreparedSweep> prepareSweep(const flarelab::v1::SweepConfig& config,
                                   const std::string& output_root,
                                   const SweepLimits& limits = {});

// The sweep directory `requested` (absolute, or relative to `root`) as an absolute, normalised
// path strictly below `root` (absolute and canonical). InvalidArgument naming `field` when it is
// empty, has a ".." component, a NUL or control character, or leads (through a symbolic link of
// a part that exists) outside the root.
Result<std::string> resolveOutputDir(const std::string& requested,
                                     const std::string& root,
                                     const std::string& field);

// from + i step for i = 0 .. floor((to - from) / step), each rounded to a nanodegree and capped
// at `to`: the angles `flarelab capture` takes.
std::vector<double> sweepAngles(double from_deg, double to_deg, double step_deg);

}  // namespace flarelab::daemon
