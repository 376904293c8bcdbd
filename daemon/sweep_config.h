// ============================================================================
//  flarelab daemon: SweepLimits, PreparedSweep, prepareSweep, resolveOutputDir, sweepAngles
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
