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
// No thread waits on a disk while it holds the manager's lock, so that a slow disk (or a stalled
// log reader) never freezes the rig, the watchers or the other calls: the journal is written by
// a thread of its own. A change is made in memory under the lock and queued, in order, with the
// events that follow it; the journal's thread writes the record and only then publishes its STATE
// event and everything queued behind it. Events that follow no pending record are published at
// once.
//
// The journal's refusals. A change a client asks for (start, pause, resume, cancel) is answered
// once its record is on disk. When the record cannot be written (a full or read-only disk, a
// failed flush) the change is refused (UNAVAILABLE, naming the file and the error) and undone:
// the job is as it was, in memory, for watchers, and on disk (its record is written again). The
// client then knows its request did not take, and the daemon never holds a promise its disk does
// not: the worker does not take a queued job while a client's change to it waits for the disk,
// and a cancel stops the rig only once the journal holds the job CANCELLED (as does every later
// record of it), so no restart runs it again. A job whose record could grow past what the journal
// reads back (kJournalMaxRecordBytes: a lens text full of characters JSON escapes) is refused at
// start (RESOURCE_EXHAUSTED, naming the field). Changes the daemon makes itself (a frame done, a
// job ended) cannot be refused: a failure is logged and the record is written again at the job's
// next change. Refusing the one request keeps a running sweep going through a transient fault (a
// disk another program filled and emptied) rather than stopping all work.
//
// Ended jobs are forgotten, in memory and in the journal (their sweeps stay on disk), beyond the
// newest keep_ended of them and keep_ended_s after they ended.
//
// States and what moves them:
//
//     QUEUED ──worker──► RUNNING ──► SUCCEEDED | FAILED
//       │  ▲               │  ▲
//     pause resume       pause resume (a client), or a fault the job could not ride out
//       ▼  │               ▼  │
//      PAUSED ◄────────── PAUSED
//     cancel: any unfinished state ──► CANCELLED (a running job once its rig has stopped, at once)
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
// Control: the client that starts a job controls it; another client's pause, resume or cancel
// is refused (PERMISSION_DENIED) unless it takes control. A client is its name together with its
// peer, the identity the service vouches for (Unix socket credentials, or the TCP address): the
// same name from another user is another client. Errors are grpc::Status values whose messages
// name the field at fault.
#pragma once

#include <grpcpp/support/status.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
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

// Who calls: the name the client gives (metadata flarelab-client) and the peer the service
// vouches for ("uid 1000" on the Unix socket, "ipv4:10.0.0.7" on TCP; empty in-process).
struct Caller {
    std::string name;
    std::string peer;
};

struct ManagerOptions {
    RunnerOptions runner;
    bool resume = true;         // queue interrupted jobs again at start
    size_t max_queued = 64;     // jobs QUEUED or PAUSED at once
    size_t events_kept = 1024;  // per job, for watchers that fall behind
    int quarantine_after = 3;   // crashes in a row without progress; 0: never quarantine
    // Ended jobs kept: `job list` shows the last ones, and a retried start finds its job. Each
    // costs its record in memory (a lens text is up to 1 MiB; most are a few KiB) and is read at
    // every start, so the count is bounded; a month covers the questions a lab asks of its jobs.
    size_t keep_ended = 100;
    double keep_ended_s = 30 * 86400.0;
    size_t ended_events_kept = 64;  // per ended job, for the watchers still reading it
    // Test seam: called on the journal's thread before it writes each record (the job's id).
    std::function<void(const std::string&)> before_journal_write;
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

    // Stops the worker: a running job stops now (its head stopped, its exposure aborted, the
    // bracket under way dropped: it is not a frame yet), the frames it captured are written, and
    // it becomes INTERRUPTED; watchers are told. Idempotent.
    void shutdown();
    // Makes a shutdown under way quicker (a second SIGTERM): the running job drops the frames it
    // captured and has not written (its next run takes them again; nothing on disk is lost) and a
    // fit stops. Any thread, at any time.
    void stopNow();

    grpc::Status check(const flarelab::v1::SweepConfig& config, flarelab::v1::SweepPlan* plan);
    grpc::Status start(const flarelab::v1::StartSweepRequest& request,
                       const Caller& client,
                       flarelab::v1::Job* job);
    grpc::Status pause(const flarelab::v1::JobControlRequest& request,
                       const Caller& client,
                       flarelab::v1::Job* job);
    grpc::Status resume(const flarelab::v1::JobControlRequest& request,
                        const Caller& client,
                        flarelab::v1::Job* job);
    grpc::Status cancel(const flarelab::v1::JobControlRequest& request,
                        const Caller& client,
                        flarelab::v1::Job* job);
    std::vector<flarelab::v1::Job> list() const;  // without their configs' lens text
    // The job's products. model.txt is read only when it is a regular file (not followed through
    // a link, never a FIFO or a device) of at most 1 MiB; what is refused is said in warnings.
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
        // Client changes queued and not yet written (the worker leaves such a job alone).
        int proposals = 0;
        // The output directory resolved (links followed) when the job was made, so that two
        // spellings of one directory are found the same without touching the disk under the lock.
        std::string directory_key;
        // Versions of the job's record: of the last change, the last one the journal's thread
        // tried to write, and the last one on disk (0: none yet; such a job is not yet known to
        // clients). record_error: why the last write failed.
        uint64_t version = 0, attempted = 0, recorded = 0;
        std::string record_error;
        // What clients are told: the job as its latest record written says, or as the daemon's
        // own change the disk refused would have said (with frames_done, which the sweep's
        // manifest vouches for, from `job`; and a cancelled job still stopping as it is, where
        // its record says CANCELLED already).
        flarelab::v1::Job told;
    };
    // What the journal's thread does next, in order: write a record (or forget one), then
    // publish an event.
    struct Outgoing {
        uint64_t number = 0;
        std::optional<flarelab::v1::Job> record;
        uint64_t version = 0;
        bool forget = false;
        bool cancelled = false;  // a cancel was requested: the record says CANCELLED (asWritten)
        bool refusable = false;  // a client's change: its event is dropped when the write fails
        std::optional<flarelab::v1::JobEvent> event;
    };

    explicit JobManager(ManagerOptions options, Journal journal);
    void work();     // the capture worker: one job at a time owns the rig
    void fitWork();  // the fit worker: fits finished captures while the rig goes on
    void record();   // the journal's thread: writes records, then publishes what follows them
    void finish(Entry& entry, const RunResult& result);
    // With mutex_ held: queue a change of `entry` to be written and then announced; its version.
    // A change the daemon makes itself: its STATE event is published even when the write fails
    // (unless `refusable`, as propose() queues a client's).
    uint64_t changed(Entry& entry, const std::string& log_note = "", bool refusable = false);
    // With mutex_ held: queue a change a client asked for, `before` the job as it was; its STATE
    // event is published only once the record is on disk. commit() then waits for it.
    struct Proposal {
        uint64_t number = 0, version = 0;
        flarelab::v1::Job before, after;
        bool cancel_before = false;
    };
    Proposal propose(Entry& entry,
                     const flarelab::v1::Job& before,
                     bool cancel_before,
                     const std::string& note);
    // With `lock` held: waits until the proposal's record was written; when it could not be, the
    // change is undone (each field it set that nothing changed since is as before, and recorded
    // again) and refused as UNAVAILABLE.
    grpc::Status commit(std::unique_lock<std::mutex>& lock, const Proposal& proposal);
    // With mutex_ held: queue the entry's record to be written, announcing nothing.
    void save(Entry& entry);
    // A job's record as the journal keeps it: with a cancel requested, CANCELLED already.
    static flarelab::v1::Job asWritten(flarelab::v1::Job job, bool cancelled);
    // With mutex_ held: announce `event`, after whatever the journal's thread has still to do.
    void emit(Entry& entry, flarelab::v1::JobEvent event);
    void publish(Entry& entry, flarelab::v1::JobEvent event);
    // With `lock` held on mutex_: waits (releasing it) until version `version` of job `number`
    // was written; its write's error, or OK (also when the job is gone meanwhile).
    grpc::Status waitRecorded(std::unique_lock<std::mutex>& lock,
                              uint64_t number,
                              uint64_t version);
    // With `lock` held: waits until version `version` of job `number` is on disk, then copies
    // the job to `job`; the journal's error when it could not be written.
    grpc::Status answer(std::unique_lock<std::mutex>& lock,
                        uint64_t number,
                        uint64_t version,
                        flarelab::v1::Job* job);
    static bool tookControl(const flarelab::v1::Job& before, const flarelab::v1::Job& now);
    // `refused`, after the control mayControl took for the call is given back.
    static grpc::Status undoControl(Entry& entry,
                                    const flarelab::v1::Job& before,
                                    grpc::Status refused);
    // With mutex_ held: the job as clients see it (told, with the frames on disk now).
    static flarelab::v1::Job shown(const Entry& entry);
    // With mutex_ held: forgets ended jobs beyond the options' count and age.
    void prune(double now_unix_s);
    grpc::Status find(const std::string& id, Entry** entry);
    grpc::Status findConst(const std::string& id, const Entry** entry) const;
    // The job named in `request`, when `client` may control it (taking control if asked).
    grpc::Status mayControl(const flarelab::v1::JobControlRequest& request,
                            const Caller& client,
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
    std::deque<Outgoing> outbox_;     // for the journal's thread, in order
    bool recording_ = false;          // the journal's thread holds a batch taken from outbox_
    std::condition_variable outbox_cv_;
    bool shutting_down_ = false;
    bool stop_now_ = false;
    bool recorder_stop_ = false;
    bool recorder_done_ = false;  // the journal's thread has ended: nothing more is written
    std::thread worker_, fitter_, recorder_;
};

}  // namespace flarelab::daemon
