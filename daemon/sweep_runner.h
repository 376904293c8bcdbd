// ============================================================================
//  flarelab daemon: JobControl, RunnerOptions, RunOutcome, RunResult, openJobRig, runSweepJob,
//                   fitSweepJob
// ============================================================================
//
// One sweep job from start to end: the rig is opened (the daemon's devices by URI, and whatever
// the daemon does not have simulated from the job's configuration; drivers/rig.h), the head
// homed, then a pipeline of two threads runs the capture:
//
//     capture thread:    move head ─► exposure 1 … n ─► queue (bounded) ─┐
//     processing thread: ◄──────────────────────────────────────────────┘
//                        count clipping ─► merge ─► raw files ─► EXR + manifest ─► preview
//
// so head moves and exposures never wait on merging or writing (only on a full queue, which
// bounds memory: the queue holds what the job's memory budget leaves, SweepLimits and jobMemory
// in daemon/sweep_config.h). When every frame is on disk and the job asks for
// it, fitSweepJob fits the sweep into `<sweep>/model.flm` (and `model.txt`, its description); the
// daemon runs it on a thread of its own, so the rig goes on with the next job meanwhile.
//
// Resuming. A job that finds a manifest in its directory continues it: frames the manifest lists
// are safely on disk and are not captured again; files it does not list (the frame a crash left
// half-recorded, temporary files) are moved to `<state dir>/recovered/<job id>/<time>/` (never
// deleted), and capture restarts at the first angle the manifest lacks. The simulated camera's
// frame sequence is set to where that angle's bracket starts, so a resumed sweep's frames equal
// those of an uninterrupted one with the same seed, bit for bit.
//
// Faults. A camera timeout is retried camera_retries times, then the job pauses with the reason
// (resume retries); a head that does not arrive likewise with head_retries; a head that lost
// position is homed again; a stalled head is stopped and the job paused ("the rig is stopped");
// a camera or head that is gone (or cannot be opened) pauses the job, and resuming it opens the
// device again; a setting the device refuses (out of range) fails the job. Too little free disk
// space (below min_free_bytes plus a frame), or a write that fails, ends the job as failed, with
// every frame written before it intact. Whatever was captured when a job stops (cancel, shutdown,
// a capture-side failure) is still merged and written before the job ends, unless the daemon
// must stop at once (JobControl::dropUnwritten); after a frame that could not be written nothing
// more is written (the sweep may have no gap). Running out of memory (std::bad_alloc anywhere in
// the job) fails the job, not the daemon.
//
// Stopping. A stop takes effect at once, not at the next frame: the head is stopped (again every
// 0.1 s until the capture ends, so that a move that begins just after is stopped too) and the
// exposure under way is aborted (Camera::abort); the bracket it belonged to is not a frame, and a
// resumed job takes that frame again from its first exposure.
//
// Which failures a client may resume (RunResult::resumable): a full disk or another write error,
// running out of memory, and a device error the driver could not classify; all of them may pass,
// and resuming continues where the sweep on disk ends. Not resumable: a failed flush to disk
// (fsync; the disk may have dropped data it had accepted, so the sweep needs a person's look and a
// new job with resume_existing), a setting the device refuses, a request the rig cannot serve, a
// sweep directory that holds another sweep, and a fit that failed on its data.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "daemon/sweep_config.h"
#include "drivers/calibration.h"
#include "drivers/rig.h"
#include "proto/daemon.pb.h"

namespace flarelab::daemon {

// What a running job tells its owner and asks of it. Called from the job's threads.
class JobControl {
public:
    virtual ~JobControl() = default;
    // Returns at once while the job runs; waits while it is paused; false when the job must stop
    // (cancelled, or the daemon is stopping).
    virtual bool checkpoint() = 0;
    // The job pauses itself for `reason` (a fault it could not ride out) and waits like
    // checkpoint() for a client to resume it.
    virtual bool pauseForFault(const std::string& reason) = 0;
    // True once the job must stop; the flag a fit watches.
    virtual const std::atomic<bool>& stopFlag() const = 0;
    // `hook` is called when the job must stop (at once when it must already), with the owner's
    // lock held: it must only signal, never wait or touch a device. An empty hook clears it; once
    // cleared, the old hook is never called again.
    virtual void setStopHook(std::function<void()> hook) = 0;
    // True once the daemon must stop at once (a second SIGTERM): frames captured and not yet
    // written are dropped (the next run takes them again).
    virtual bool dropUnwritten() const { return false; }
    virtual void setPhase(flarelab::v1::JobPhase phase) = 0;
    virtual void setFramesDone(uint32_t frames) = 0;
    virtual void warning(const std::string& message) = 0;
    // An EXPOSURE, FRAME or FIT_PROGRESS event; the owner numbers it and adds the job's state.
    virtual void event(flarelab::v1::JobEvent event) = 0;
    // The job opened a device of the daemon's (by the URI it was configured with), which names
    // itself so; for DescribeRig.
    virtual void deviceOpened(const std::string& uri,
                              const std::string& model,
                              const std::string& serial) {
        (void)uri, (void)model, (void)serial;
    }
};

struct RunnerOptions {
    std::string output_root;  // absolute, canonical
    std::string state_dir;    // absolute; recovered files go below it
    SweepLimits limits;
    int camera_retries = 3;  // per exposure, before the job pauses
    int head_retries = 2;    // per move
    int64_t min_free_bytes = int64_t{64} << 20;
    // Brackets between capture and processing at most; the memory budget (limits) bounds their
    // bytes, which is what matters.
    size_t queue_frames = 64;
    // Free bytes of the file system holding a path; statvfs when empty (a test seam).
    std::function<int64_t(const std::string&)> free_bytes;
    std::string software_version = "flarelabd";
    // Calibrations of the rig's cameras (flarelabd --calibration): a job's frames are merged
    // through the one measured on its camera; a camera whose response is not linear needs one.
    std::vector<drivers::CameraCalibration> calibrations;
    // Test seams: called on the capture thread before frame `index` is captured, and on the
    // processing thread before it is merged (a test throws std::bad_alloc from them, or sleeps).
    std::function<void(size_t index)> before_capture;
    std::function<void(size_t index)> before_merge;
};

// Captured: every frame is on disk and the job asks for a fit, which fitSweepJob does.
enum class RunOutcome { Succeeded, Captured, Failed, Stopped };

struct RunResult {
    RunOutcome outcome = RunOutcome::Failed;
    std::string reason;      // why it failed
    bool resumable = false;  // a failure a client may resume (see the top of this file)
    std::string model_file;  // when fitted
    uint32_t frames_on_disk = 0;
    double capture_wall_s = 0.0;  // from the first move to the last frame on disk
    double fit_wall_s = 0.0;
    size_t queue_high_water = 0;  // brackets
    size_t queue_high_water_bytes = 0;
};

// The rig a prepared sweep runs on: the daemon's devices it names (sweep.camera_uri, head_uri),
// and for each it leaves empty a simulated one: a head with the limits' motion and the config's
// injected faults, a camera with the lens, size, gain and seed, sharing one clock (simulated
// time when config.sim.fast, else real time). Errors carry "camera" or "head" and the URI.
Result<drivers::Rig> openJobRig(const PreparedSweep& sweep, const SweepLimits& limits);

// glibc's malloc, set for a process that runs sweeps for hours: buffers of 256 KiB and more (the
// brackets, merged frames, EXR and PNG encodings) are always mapped and returned to the system
// when freed. Left alone, glibc raises that threshold to the largest buffer freed so far, keeps
// such buffers in its heaps and lets them fragment, and a daemon's resident memory then grew by
// some 15 % over a 1000-frame sweep (README, "The daemon"). Call once at start, before threads.
void settleAllocator();

// Runs `job`'s capture (its config must have passed prepareSweep with the same root and
// limits): Succeeded, or Captured when the job asks for a fit.
RunResult runSweepJob(const flarelab::v1::Job& job,
                      const RunnerOptions& options,
                      JobControl& control);
// Fits a job's sweep, complete on disk, into `<sweep>/model.flm`. Stopped when control's stop
// flag is set during the fit.
RunResult fitSweepJob(const flarelab::v1::Job& job,
                      const RunnerOptions& options,
                      JobControl& control);

}  // namespace flarelab::daemon
