// ============================================================================
//  flarelab daemon: ManagerOptions, JobManager, WatchBatch
// ============================================================================
//
// The daemon's jobs: the one owner of the rig. Jobs capture one at a time, in the order they were
// started, on a worker thread (daemon/sweep_runner.h); the others wait QUEUED. A job that asks
// for a fit is fitted on a second thread once captured (phase FITTING, still RUNNING), while the
// rig goes on with the next job; a fitting job cannot pause (it holds no device) but can cancel.
// Every change of a job is written to the journal (daemon/journal.h) before it is announced, and
// announced as an event that any number of watchers can follow.
//
// States and what moves them:
//
//     QUEUED ──worker──► RUNNING ──► SUCCEEDED | FAILED
//       │  ▲               │  ▲
//     pause resume       pause resume (a client), or a fault the job could not ride out
//       ▼  │               ▼  │
//      PAUSED ◄────────── PAUSED
//     cancel: any unfinished state ──► CANCELLED (a running job at its next frame)
//     the daemon stops under a running job ──► INTERRUPTED; at the next start it is QUEUED again
//     (resumed where its sweep on disk ends) unless the daemon runs with resume off, when a
//     client's resume queues it.
//     FAILED ──resume──► QUEUED, for a failure that may pass (Job.resumable; sweep_runner.h).
//
// Quarantine. A job under which the daemon died (killed, crashed: its record still says RUNNING)
// quarantine_after times in a row without writing a frame in between is not resumed again: it
// becomes FAILED with a reason that says so, and only a client's resume runs it once more. A job
// that crashes the daemon would otherwise take it down at every start.
//
// The journal. Every change a client asks for (start, pause, resume, cancel) is written to the
// journal before it takes effect; when the record cannot be written (a full or read-only disk, a
// failed flush) the change is refused (UNAVAILABLE, naming the file and the error) and the job
// stays as it was, in memory and on disk. The client then knows its request did not take, and the
// daemon never holds a promise its disk does not: a cancelled job is recorded CANCELLED before
// it stops (and stays so in every later record), so no restart runs it again. Changes the daemon
// makes itself (a frame done, a job ended) cannot be refused: a failure is logged and the record
// is written again at the job's next change. Refusing the one request keeps a running sweep going
// through a transient fault (a disk another program filled and emptied) rather than stopping all
// work.
//
// Control: the client that starts a job controls it; another client's pause, resume or cancel
// is refused (PERMISSION_DENIED) unless it takes control. Errors are grpc::Status values whose
// messages name the field at fault.
#pragma once

#include <grpcpp/support/status.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "common/result.h"
#include "daemon/journal.h"
#include "daemon/sweep_runner.h"
#include "proto/daemon.pb.h"

namespace flarelab::daemon {

// The message of the STATE event a paused job sends once its rig has stopped (a pause takes
// effect after the frame under way).
inline constexpr char kHoldingMessage[] = "holding: the rig is stopped until the job is resumed";

struct ManagerOptions {
    RunnerOptions runner;
    bool resume = true;         // queue interrupted jobs again at start
    size_t max_queued = 64;     // jobs QUEUED or PAUSED at once
    size_t events_kept = 1024;  // per job, for watchers that fall behind
    int quarantine_after = 3;   // crashes in a row without progress; 0: never quarantine
};

// Events for a watcher, after the sequence number it has seen.
struct WatchBatch {
    std::vector<flarelab::v1::JobEvent> events;
    bool ended = false;  // the job has ended and these are its last events
};

class JobManager {
public:
    // Reads the journal of options.runner.state_dir, marks jobs that were running INTERRUPTED
    // and, with options.resume, queues them again; then starts the worker. Records that cannot be
    // read are set aside and reported in `warnings`.
    static Result<std::unique_ptr<JobManager>> open(ManagerOptions options,
                                                    std::vector<std::string>* warnings = nullptr);
    ~JobManager();
    JobManager(const JobManager&) = delete;
    JobManager& operator=(const JobManager&) = delete;

    // Stops the worker: a running job stops at its next frame (its captured frames written) and
    // becomes INTERRUPTED; watchers are told. Idempotent.
    void shutdown();

    grpc::Status check(const flarelab::v1::SweepConfig& config, flarelab::v1::SweepPlan* plan);
    grpc::Status start(const flarelab::v1::StartSweepRequest& request,
                       const std::string& client,
                       flarelab::v1::Job* job);
    grpc::Status pause(const flarelab::v1::JobControlRequest& request,
                       const std::string& client,
                       flarelab::v1::Job* job);
    grpc::Status resume(const flarelab::v1::JobControlRequest& request,
                        const std::string& client,
                        flarelab::v1::Job* job);
    grpc::Status cancel(const flarelab::v1::JobControlRequest& request,
                        const std::string& client,
                        flarelab::v1::Job* job);
    std::vector<flarelab::v1::Job> list() const;  // without their configs' lens text
    grpc::Status result(const std::string& job_id, flarelab::v1::JobResult* result) const;

    // The job's current state as a STATE event, and the sequence number to watch from.
    grpc::Status watchStart(const std::string& job_id,
                            flarelab::v1::JobEvent* first,
                            uint64_t* sequence) const;
    // Waits up to `wait` for events after `*sequence`, moves `*sequence` on. NOT_FOUND for an
    // unknown job, UNAVAILABLE once the manager shuts down.
    grpc::Status watchNext(const std::string& job_id,
                           uint64_t* sequence,
                           std::chrono::milliseconds wait,
                           WatchBatch* batch) const;

    std::string runningJob() const;
    // Model and serial of the device a job last opened by `uri`; empty before.
    std::pair<std::string, std::string> deviceIdentity(const std::string& uri) const;
    size_t queuedJobs() const;
    const ManagerOptions& options() const { return options_; }

private:
    class Control;
    friend class Control;
    struct Entry {
        flarelab::v1::Job job;
        std::deque<flarelab::v1::JobEvent> events;
        uint64_t next_sequence = 1;
        bool cancel_requested = false;
        std::unique_ptr<Control> control;  // while the job runs a stage
    };

    explicit JobManager(ManagerOptions options, Journal journal);
    void work();     // the capture worker: one job at a time owns the rig
    void fitWork();  // the fit worker: fits finished captures while the rig goes on
    void finish(Entry& entry, const RunResult& result);
    // With mutex_ held: persist and announce a change of `entry`. The journal's error, if it
    // could not be written (the change is announced all the same).
    flarelab::Status changed(Entry& entry, const std::string& log_note = "");
    // With mutex_ held: a change a client asked for, `before` the job as it was. Persisted and
    // announced, or, when the journal cannot be written, undone (the entry is `before` again) and
    // refused as UNAVAILABLE.
    grpc::Status commit(Entry& entry, const flarelab::v1::Job& before, const std::string& note);
    void announce(Entry& entry, const std::string& log_note);  // log line and STATE event
    void emit(Entry& entry, flarelab::v1::JobEvent event);
    grpc::Status find(const std::string& id, Entry** entry);
    grpc::Status findConst(const std::string& id, const Entry** entry) const;
    // The job named in `request`, when `client` may control it (taking control if asked).
    grpc::Status mayControl(const flarelab::v1::JobControlRequest& request,
                            const std::string& client,
                            const char* what,
                            Entry** entry);
    static bool ended(const flarelab::v1::Job& job);

    ManagerOptions options_;
    Journal journal_;
    mutable std::mutex mutex_;
    std::map<std::string, std::pair<std::string, std::string>> devices_seen_;  // uri: model, serial
    mutable std::condition_variable changed_cv_;  // job states and events
    std::map<uint64_t, Entry> jobs_;              // by job number
    std::map<std::string, uint64_t> by_request_;
    uint64_t next_number_ = 1;
    std::string running_;             // the job capturing, if any
    std::deque<uint64_t> fit_queue_;  // jobs captured and waiting for their fit
    bool shutting_down_ = false;
    std::thread worker_, fitter_;
};

}  // namespace flarelab::daemon
