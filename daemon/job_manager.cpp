#include "daemon/job_manager.h"

#include <fcntl.h>
#include <google/protobuf/util/message_differencer.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <set>
#include <sstream>

#include "common/file_descriptor.h"
#include "daemon/log.h"
#include "hdr/sweep.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;
using grpc::Status;
using grpc::StatusCode;

double unixNow() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch())
        .count();
}

bool validRequestId(const std::string& id) {
    if (id.empty() || id.size() > 64) return false;
    for (const char c : id)
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '_' && c != '-')
            return false;
    return true;
}

// `text` cut to at most `bytes` bytes, at a UTF-8 character boundary.
std::string clipped(const std::string& text, size_t bytes) {
    if (text.size() <= bytes) return text;
    size_t end = bytes;
    while (end > 0 && (static_cast<unsigned char>(text[end]) & 0xC0) == 0x80) --end;
    return text.substr(0, end) + "...";
}

// What a job's record may grow by after it was accepted: its warnings (at most 100, each clipped
// to kMaxWarningBytes), its reason (kMaxReasonBytes), a controller's name (gRPC metadata, at most
// 8 KiB) and peer, and the other fields, all of which JSON may grow sixfold.
constexpr size_t kMaxWarningBytes = 1024;
constexpr size_t kMaxReasonBytes = 4096;
constexpr int64_t kRecordGrowthBytes =
    6 * (100 * (kMaxWarningBytes + 8) + kMaxReasonBytes + 8192 + 4096) + (64 << 10);

// An output directory as the start of a job resolves it: the part that exists with its links
// followed (so that another spelling, or a link to it, is the same directory), the rest as given.
// It reads the file system: never called under the manager's lock.
std::string directoryKey(const std::string& dir) {
    std::error_code ec;
    const fs::path resolved = fs::weakly_canonical(dir, ec);
    return ec ? fs::path(dir).lexically_normal().string() : resolved.string();
}

// Frames the sweep in `dir` lists now (0 without a readable one).
uint32_t framesOnDisk(const std::string& dir) {
    auto listed = hdr::readSweepManifest(dir);
    return listed ? static_cast<uint32_t>(listed->frames.size()) : 0;
}

// The job as events and listings carry it: without the lens text, which can be 1 MiB.
v1::Job summary(const v1::Job& job) {
    v1::Job out = job;
    out.clear_config();
    return out;
}

// The text of `path` when it is a regular file (the last component not a link) of at most
// max_bytes. Opened without blocking, so that a FIFO or a device put in a product's place is
// refused, not waited on; IoError naming the file otherwise.
Result<std::string> readRegularText(const std::string& path, int64_t max_bytes) {
    FileDescriptor fd(::open(path.c_str(), O_RDONLY | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC));
    if (!fd.valid())
        return makeError(
            errno == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
            path + ": cannot open: " +
                (errno == ELOOP ? std::string("it is a symbolic link") : osMessage(errno)));
    struct stat info {};
    if (::fstat(fd.get(), &info) != 0)
        return makeError(ErrorCode::IoError, path + ": cannot stat: " + osMessage(errno));
    if (!S_ISREG(info.st_mode))
        return makeError(ErrorCode::IoError, path + ": not a regular file; not read");
    if (info.st_size > max_bytes)
        return makeError(ErrorCode::IoError, path + ": " + std::to_string(info.st_size) +
                                                 " bytes, more than the " +
                                                 std::to_string(max_bytes) + " read; not read");
    std::string text(static_cast<size_t>(info.st_size), '\0');
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t got = ::read(fd.get(), text.data() + done, text.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": cannot read: " + osMessage(errno));
        if (got == 0) break;  // shrank meanwhile
        done += static_cast<size_t>(got);
    }
    text.resize(done);
    return text;
}

}  // namespace

// The running job's side of the manager (JobControl, daemon/sweep_runner.h).
class JobManager::Control final : public JobControl {
public:
    Control(JobManager& manager, uint64_t number) : manager_(manager), number_(number) {}

    bool checkpoint() override {
        std::unique_lock lock(manager_.mutex_);
        Entry& e = manager_.jobs_.at(number_);
        if (!stop_ && e.job.state() == v1::PAUSED) {
            // A pause takes effect between frames: say when it has.
            v1::JobEvent held;
            held.set_kind(v1::STATE);
            held.set_message(kHoldingMessage);
            manager_.emit(e, std::move(held));
            logEvent(LogLevel::Info, "job.holding", {{"job", e.job.id()}});
        }
        manager_.changed_cv_.wait(lock, [&] { return stop_ || e.job.state() != v1::PAUSED; });
        return !stop_;
    }

    bool pauseForFault(const std::string& reason) override {
        {
            std::lock_guard lock(manager_.mutex_);
            if (stop_) return false;
            Entry& e = manager_.jobs_.at(number_);
            e.job.set_state(v1::PAUSED);
            e.job.set_reason(reason);
            manager_.changed(e, "paused by a fault");
        }
        return checkpoint();
    }

    const std::atomic<bool>& stopFlag() const override { return stop_; }
    bool dropUnwritten() const override { return drop_unwritten_; }

    void setStopHook(std::function<void()> hook) override {
        std::lock_guard lock(manager_.mutex_);
        hook_ = std::move(hook);
        if (hook_ && stop_) hook_();
    }

    // With the manager's mutex held (so a hook being cleared is never running).
    void requestStop() {
        stop_ = true;
        if (hook_) hook_();
    }
    void requestStopNow() {
        drop_unwritten_ = true;
        requestStop();
    }

    void setPhase(v1::JobPhase phase) override {
        std::lock_guard lock(manager_.mutex_);
        Entry& e = manager_.jobs_.at(number_);
        if (e.job.phase() == phase) return;
        e.job.set_phase(phase);
        manager_.changed(e);
    }

    void setFramesDone(uint32_t frames) override {
        std::lock_guard lock(manager_.mutex_);
        Entry& e = manager_.jobs_.at(number_);
        if (frames > e.job.frames_done()) e.job.set_crashes(0);  // it gets further
        e.job.set_frames_done(frames);
        e.job.set_updated_unix_s(unixNow());
        // The journal is the job's record, not the sweep's: the sweep's manifest says which
        // frames are on disk. Saved every 16 frames so that `job list` after a crash is close.
        if (frames % 16 == 0) manager_.save(e);
    }

    void warning(const std::string& message) override {
        std::lock_guard lock(manager_.mutex_);
        Entry& e = manager_.jobs_.at(number_);
        if (e.job.warnings_size() < 100) e.job.add_warnings(clipped(message, kMaxWarningBytes));
        logEvent(LogLevel::Warn, "job.warning", {{"job", e.job.id()}, {"message", message}});
        v1::JobEvent event;
        event.set_kind(v1::WARNING);
        event.set_message(message);
        manager_.emit(e, std::move(event));
    }

    void event(v1::JobEvent event) override {
        std::lock_guard lock(manager_.mutex_);
        manager_.emit(manager_.jobs_.at(number_), std::move(event));
    }

    void deviceOpened(const std::string& uri,
                      const std::string& model,
                      const std::string& serial) override {
        std::lock_guard lock(manager_.mutex_);
        manager_.devices_seen_[uri] = {model, serial};
    }

private:
    JobManager& manager_;
    const uint64_t number_;
    std::atomic<bool> stop_{false};
    std::atomic<bool> drop_unwritten_{false};
    std::function<void()> hook_;
};

JobManager::JobManager(ManagerOptions options, Journal journal)
    : options_(std::move(options)), journal_(std::move(journal)) {}

Result<std::unique_ptr<JobManager>> JobManager::open(ManagerOptions options,
                                                     std::vector<std::string>* warnings) {
    auto journal = Journal::open(options.runner.state_dir);
    if (!journal) return journal.error();
    auto loaded = journal->load();
    if (!loaded) return loaded.error();
    std::unique_ptr<JobManager> manager(new JobManager(std::move(options), std::move(*journal)));
    if (warnings) *warnings = loaded->warnings;
    for (const std::string& w : loaded->warnings)
        logEvent(LogLevel::Warn, "journal.set_aside", {{"message", w}});
    for (v1::Job& job : loaded->jobs) {
        const uint64_t number = jobNumber(job.id());
        Entry& e = manager->jobs_[number];
        bool quarantined = false;
        if (job.state() == v1::RUNNING) {  // killed: it had no time to say so
            job.set_state(v1::INTERRUPTED);
            job.set_reason("the daemon stopped while the job ran");
            // Counted before the job runs again: a job that crashes the daemon must not take it
            // down at every start. Progress is what the sweep on disk holds beyond the record.
            const uint32_t on_disk = framesOnDisk(job.output_dir());
            job.set_crashes(on_disk > job.frames_done() ? 1 : job.crashes() + 1);
            job.set_frames_done(std::max(job.frames_done(), on_disk));
            const int limit = manager->options_.quarantine_after;
            if (limit > 0 && job.crashes() >= static_cast<uint32_t>(limit)) {
                quarantined = true;
                job.set_state(v1::FAILED);
                job.set_resumable(true);
                job.set_reason("quarantined: the daemon died " + std::to_string(job.crashes()) +
                               " times in a row while this job ran (phase " +
                               v1::JobPhase_Name(job.phase()) + ", " +
                               std::to_string(job.frames_done()) +
                               " frames on disk) without it getting further; it is not resumed "
                               "by itself again: find the cause in the daemon's log, then resume "
                               "it by hand");
                logEvent(LogLevel::Error, "job.quarantined",
                         {{"job", job.id()}, {"crashes", std::to_string(job.crashes())}});
            }
        }
        if (job.state() == v1::INTERRUPTED) job.set_restarts(job.restarts() + 1);
        if (job.state() == v1::INTERRUPTED && manager->options_.resume) {
            job.set_state(v1::QUEUED);
            job.add_warnings(
                "queued again after the daemon stopped under it; it resumes where "
                "its sweep on disk ends");
        }
        e.job = std::move(job);
        e.version = e.attempted = e.recorded = 1;
        e.told = e.job;
        e.directory_key = directoryKey(e.job.output_dir());
        if (!e.job.request_id().empty()) manager->by_request_[e.job.request_id()] = number;
        manager->next_number_ = std::max(manager->next_number_, number + 1);
        if (!ended(e.job) || quarantined) {
            // (An ended job keeps its time: the time it ended, by which it is pruned; a job
            // quarantined now ends now.)
            e.job.set_updated_unix_s(unixNow());
            // No thread runs yet: the record is written here, before the daemon says anything.
            if (auto saved = manager->journal_.save(e.job); !saved) return saved.error();
            e.told = e.job;
            logEvent(LogLevel::Info, "job.loaded",
                     {{"job", e.job.id()},
                      {"state", v1::JobState_Name(e.job.state())},
                      {"frames_done", std::to_string(e.job.frames_done())}});
        }
    }
    {
        std::lock_guard lock(manager->mutex_);
        manager->prune(unixNow());
    }
    manager->recorder_ = std::thread([m = manager.get()] { m->record(); });
    manager->worker_ = std::thread([m = manager.get()] { m->work(); });
    manager->fitter_ = std::thread([m = manager.get()] { m->fitWork(); });
    return manager;
}

JobManager::~JobManager() { shutdown(); }

void JobManager::shutdown() {
    {
        std::lock_guard lock(mutex_);
        shutting_down_ = true;
        for (auto& [number, e] : jobs_)
            if (e.control) e.control->requestStop();
        changed_cv_.notify_all();
    }
    if (worker_.joinable()) worker_.join();
    if (fitter_.joinable()) fitter_.join();
    // Last: what the workers changed on their way out is written before the daemon goes.
    {
        std::lock_guard lock(mutex_);
        recorder_stop_ = true;
        outbox_cv_.notify_all();
    }
    if (recorder_.joinable()) recorder_.join();
}

void JobManager::stopNow() {
    std::lock_guard lock(mutex_);
    stop_now_ = true;
    for (auto& [number, e] : jobs_)
        if (e.control) e.control->requestStopNow();
    changed_cv_.notify_all();
}

bool JobManager::ended(const v1::Job& job) {
    return job.state() == v1::SUCCEEDED || job.state() == v1::FAILED ||
           job.state() == v1::CANCELLED;
}

void JobManager::publish(Entry& entry, v1::JobEvent event) {
    event.set_sequence(entry.next_sequence++);
    entry.events.push_back(std::move(event));
    const size_t kept = ended(entry.job) ? options_.ended_events_kept : options_.events_kept;
    while (entry.events.size() > std::max<size_t>(1, kept)) entry.events.pop_front();
    changed_cv_.notify_all();
}

void JobManager::emit(Entry& entry, v1::JobEvent event) {
    *event.mutable_job() = summary(entry.job);
    if (outbox_.empty() && !recording_) return publish(entry, std::move(event));
    Outgoing out;
    out.number = jobNumber(entry.job.id());
    out.event = std::move(event);
    outbox_.push_back(std::move(out));
    outbox_cv_.notify_all();
}

v1::Job JobManager::asWritten(v1::Job job, bool cancelled) {
    // A cancel a client was told about is on disk before the job stops, and stays there.
    if (cancelled && !ended(job)) {
        job.set_state(v1::CANCELLED);
        job.set_resumable(false);
    }
    return job;
}

void JobManager::save(Entry& entry) {
    Outgoing out;
    out.number = jobNumber(entry.job.id());
    out.record = entry.job;
    out.cancelled = entry.cancel_requested;
    out.version = ++entry.version;
    outbox_.push_back(std::move(out));
    outbox_cv_.notify_all();
}

void JobManager::record() {
    std::unique_lock lock(mutex_);
    for (;;) {
        outbox_cv_.wait(lock, [&] { return !outbox_.empty() || recorder_stop_; });
        if (outbox_.empty()) {  // stopping, and everything is written
            recorder_done_ = true;
            changed_cv_.notify_all();
            return;
        }
        std::deque<Outgoing> batch;
        batch.swap(outbox_);
        recording_ = true;
        lock.unlock();
        // Only the newest record of a job in the batch is written: it holds every change before.
        std::map<uint64_t, size_t> newest;
        for (size_t i = 0; i < batch.size(); ++i)
            if (batch[i].record || batch[i].forget) newest[batch[i].number] = i;
        std::vector<std::string> errors(batch.size());
        for (const auto& [number, i] : newest) {
            const Outgoing& out = batch[i];
            if (out.forget) {
                if (auto gone = journal_.remove(jobId(number)); !gone)
                    logEvent(LogLevel::Warn, "journal.remove_failed",
                             {{"job", jobId(number)}, {"message", gone.error().message}});
                continue;
            }
            if (options_.before_journal_write) options_.before_journal_write(out.record->id());
            const v1::Job written =
                out.cancelled ? asWritten(*out.record, true) : v1::Job(*out.record);
            if (auto saved = journal_.save(written); !saved) {
                errors[i] = saved.error().message;
                logEvent(LogLevel::Error, "journal.write_failed",
                         {{"job", out.record->id()}, {"message", errors[i]}});
            }
        }
        lock.lock();
        for (size_t i = 0; i < batch.size(); ++i) {
            Outgoing& out = batch[i];
            auto it = jobs_.find(out.number);
            if (it == jobs_.end()) continue;  // forgotten meanwhile
            Entry& e = it->second;
            if (out.record && newest[out.number] == i) {
                e.attempted = std::max(e.attempted, out.version);
                e.record_error = errors[i];
                if (errors[i].empty() && out.version > e.recorded) e.recorded = out.version;
                // The daemon's own change is told even when the disk refused it (it happened,
                // and the next record carries it); a client's refused change is undone instead.
                if (errors[i].empty() || !out.refusable) e.told = std::move(*out.record);
            }
            // A client's change the journal could not record is not announced: it is undone.
            const auto written = newest.find(out.number);
            const bool refused =
                out.refusable && written != newest.end() && !errors[written->second].empty();
            if (out.event && !refused) publish(e, std::move(*out.event));
        }
        recording_ = false;
        changed_cv_.notify_all();
    }
}

Status JobManager::waitRecorded(std::unique_lock<std::mutex>& lock,
                                uint64_t number,
                                uint64_t version) {
    Status status = Status::OK;
    changed_cv_.wait(lock, [&] {
        const auto it = jobs_.find(number);
        if (it == jobs_.end()) return true;
        if (it->second.attempted < version) {
            if (!recorder_done_) return false;
            status =
                Status(StatusCode::UNAVAILABLE, "the daemon stopped before " + it->second.job.id() +
                                                    "'s change was written");
            return true;
        }
        if (it->second.recorded < version)
            status = Status(StatusCode::UNAVAILABLE, "the journal could not record " +
                                                         it->second.job.id() + ": " +
                                                         it->second.record_error);
        return true;
    });
    return status;
}

v1::Job JobManager::shown(const Entry& entry) {
    v1::Job job = entry.told;
    job.set_frames_done(std::max(job.frames_done(), entry.job.frames_done()));
    return job;
}

void JobManager::prune(double now_unix_s) {
    std::vector<uint64_t> ended_jobs;  // oldest first (job numbers grow)
    for (const auto& [number, e] : jobs_)
        // (Not one a client's change to is being written: a refused change is undone.)
        if (ended(e.job) && !e.control && e.recorded > 0 && e.proposals == 0)
            ended_jobs.push_back(number);
    const size_t beyond =
        ended_jobs.size() > options_.keep_ended ? ended_jobs.size() - options_.keep_ended : 0;
    for (size_t i = 0; i < ended_jobs.size(); ++i) {
        const uint64_t number = ended_jobs[i];
        Entry& e = jobs_.at(number);
        if (i >= beyond && e.job.updated_unix_s() >= now_unix_s - options_.keep_ended_s) continue;
        logEvent(LogLevel::Info, "job.forgotten",
                 {{"job", e.job.id()},
                  {"state", v1::JobState_Name(e.job.state())},
                  {"output_dir", e.job.output_dir()}});
        if (auto it = by_request_.find(e.job.request_id());
            it != by_request_.end() && it->second == number)
            by_request_.erase(it);
        jobs_.erase(number);
        Outgoing out;
        out.number = number;
        out.forget = true;
        outbox_.push_back(std::move(out));
    }
    if (!outbox_.empty()) outbox_cv_.notify_all();
}

uint64_t JobManager::changed(Entry& entry, const std::string& log_note, bool refusable) {
    entry.job.set_updated_unix_s(unixNow());
    if (entry.job.reason().size() > kMaxReasonBytes)
        entry.job.set_reason(clipped(entry.job.reason(), kMaxReasonBytes));
    logEvent(LogLevel::Info, "job.state",
             {{"job", entry.job.id()},
              {"state", v1::JobState_Name(entry.job.state())},
              {"phase", v1::JobPhase_Name(entry.job.phase())},
              {"frames_done", std::to_string(entry.job.frames_done())},
              {"reason", entry.job.reason()},
              {"note", log_note}});
    v1::JobEvent event;
    event.set_kind(v1::STATE);
    event.set_message(entry.job.reason());
    *event.mutable_job() = summary(entry.job);
    Outgoing out;
    out.number = jobNumber(entry.job.id());
    out.record = entry.job;
    out.cancelled = entry.cancel_requested;
    out.version = ++entry.version;
    out.refusable = refusable;
    out.event = std::move(event);
    outbox_.push_back(std::move(out));
    outbox_cv_.notify_all();
    return out.version;
}

JobManager::Proposal JobManager::propose(Entry& entry,
                                         const v1::Job& before,
                                         bool cancel_before,
                                         const std::string& note) {
    Proposal p;
    p.number = jobNumber(entry.job.id());
    p.before = before;
    p.cancel_before = cancel_before;
    p.version = changed(entry, note, true);
    p.after = entry.job;
    ++entry.proposals;
    return p;
}

Status JobManager::commit(std::unique_lock<std::mutex>& lock, const Proposal& p) {
    const Status recorded = waitRecorded(lock, p.number, p.version);
    const auto it = jobs_.find(p.number);
    if (it == jobs_.end()) return recorded;
    Entry& e = it->second;
    --e.proposals;
    changed_cv_.notify_all();  // the worker may take the job now
    if (recorded.ok()) return recorded;
    // Undone: each field the change set, unless the daemon changed it since (the job went on, or
    // ended, meanwhile). A running job's state stays RUNNING only while it has its worker.
    const v1::Job& b = p.before;
    const v1::Job& a = p.after;
    if (e.job.state() == a.state() && a.state() != b.state() &&
        (b.state() != v1::RUNNING || e.control))
        e.job.set_state(b.state());
    if (e.job.reason() == a.reason()) e.job.set_reason(b.reason());
    if (e.job.phase() == a.phase()) e.job.set_phase(b.phase());
    if (e.job.resumable() == a.resumable()) e.job.set_resumable(b.resumable());
    if (e.job.controller() == a.controller() && e.job.controller_peer() == a.controller_peer()) {
        e.job.set_controller(b.controller());
        e.job.set_controller_peer(b.controller_peer());
    }
    if (!ended(e.job)) e.cancel_requested = p.cancel_before;
    // Written again: a later record of the daemon's own may have carried the change to disk.
    changed(e, "a client's change undone: " + recorded.error_message());
    return Status(StatusCode::UNAVAILABLE,
                  e.job.id() + ": the change is refused: " + recorded.error_message());
}

// With mutex_ held: the job after a stage, as `result` says.
void JobManager::finish(Entry& e, const RunResult& result) {
    e.job.set_frames_done(std::max(e.job.frames_done(), result.frames_on_disk));
    std::ostringstream note;
    switch (result.outcome) {
        case RunOutcome::Captured:  // on to the fit thread
            e.job.set_phase(v1::FITTING);
            fit_queue_.push_back(jobNumber(e.job.id()));
            note << "captured in " << result.capture_wall_s << " s, queue high water "
                 << result.queue_high_water << " brackets, " << result.queue_high_water_bytes
                 << " bytes; fit queued";
            changed(e, note.str());
            return;
        case RunOutcome::Succeeded:
            e.job.set_state(v1::SUCCEEDED);
            e.job.set_phase(v1::FINISHED);
            e.job.set_model_file(result.model_file);
            break;
        case RunOutcome::Failed:
            e.job.set_state(v1::FAILED);
            e.job.set_reason(result.reason);
            e.job.set_resumable(result.resumable && !e.cancel_requested);
            break;
        case RunOutcome::Stopped:
            if (e.cancel_requested) {
                e.job.set_state(v1::CANCELLED);
                if (e.job.reason().empty()) e.job.set_reason("cancelled");
            } else if (e.job.state() != v1::PAUSED) {
                e.job.set_state(v1::INTERRUPTED);
                e.job.set_reason("the daemon stopped; it resumes the job at its next start");
            }
            break;
    }
    e.control.reset();
    if (result.capture_wall_s > 0.0)
        note << "capture " << result.capture_wall_s << " s, queue high water "
             << result.queue_high_water << " brackets, " << result.queue_high_water_bytes
             << " bytes";
    if (result.fit_wall_s > 0.0) note << "fit " << result.fit_wall_s << " s";
    changed(e, note.str());
    if (ended(e.job)) prune(unixNow());
}

void JobManager::work() {
    std::unique_lock lock(mutex_);
    for (;;) {
        Entry* next = nullptr;
        changed_cv_.wait(lock, [&] {
            if (shutting_down_) return true;
            for (auto& [number, e] : jobs_)
                // Not before its first record is on disk, nor while a client's change to it is
                // being written (it may be refused and undone).
                if (e.job.state() == v1::QUEUED && e.recorded > 0 && e.proposals == 0) {
                    next = &e;
                    return true;
                }
            return false;
        });
        if (shutting_down_) return;
        const uint64_t number = jobNumber(next->job.id());
        next->job.set_state(v1::RUNNING);
        next->job.set_reason("");
        next->job.set_phase(v1::HOMING);
        next->control = std::make_unique<Control>(*this, number);
        changed(*next, "started");
        Control& control = *next->control;
        running_ = next->job.id();
        const v1::Job job = next->job;
        lock.unlock();
        const RunResult result = runSweepJob(job, options_.runner, control);
        lock.lock();
        running_.clear();
        finish(jobs_.at(number), result);
    }
}

void JobManager::fitWork() {
    std::unique_lock lock(mutex_);
    for (;;) {
        changed_cv_.wait(lock, [&] { return shutting_down_ || !fit_queue_.empty(); });
        if (shutting_down_) {
            // Fits not begun: their jobs resume at the next start (the frames are on disk).
            for (const uint64_t number : fit_queue_) {
                Entry& e = jobs_.at(number);
                RunResult stopped;
                stopped.outcome = RunOutcome::Stopped;
                finish(e, stopped);
            }
            fit_queue_.clear();
            return;
        }
        const uint64_t number = fit_queue_.front();
        fit_queue_.pop_front();
        Entry& e = jobs_.at(number);
        const v1::Job job = e.job;
        Control& control = *e.control;
        lock.unlock();
        RunResult result;
        result.outcome = RunOutcome::Stopped;  // cancelled while waiting for this thread
        result.frames_on_disk = job.frames_done();
        if (!control.stopFlag()) result = fitSweepJob(job, options_.runner, control);
        lock.lock();
        finish(jobs_.at(number), result);
    }
}

Status JobManager::find(const std::string& id, Entry** entry) {
    const uint64_t number = jobNumber(id);
    auto it = jobs_.find(number);
    // A job whose first record is not on disk yet is not known to clients.
    if (number == 0 || it == jobs_.end() || it->second.recorded == 0)
        return Status(StatusCode::NOT_FOUND, "job_id: no job '" + id.substr(0, 64) + "'");
    *entry = &it->second;
    return Status::OK;
}

Status JobManager::findConst(const std::string& id, const Entry** entry) const {
    return const_cast<JobManager*>(this)->find(id, const_cast<Entry**>(entry));
}

Status JobManager::check(const v1::SweepConfig& config, v1::SweepPlan* plan) {
    auto prepared = prepareSweep(config, options_.runner.output_root, options_.runner.limits);
    if (!prepared) return Status(StatusCode::INVALID_ARGUMENT, prepared.error().message);
    plan->set_frames(static_cast<uint32_t>(prepared->angles_deg.size()));
    plan->set_exposures(
        static_cast<uint32_t>(prepared->angles_deg.size() * prepared->exposure_times_s.size()));
    plan->set_rig_time_s(prepared->rig_time_s);
    plan->set_output_dir(prepared->output_dir);
    for (const std::string& w : prepared->warnings) plan->add_warnings(w);
    return Status::OK;
}

Status JobManager::start(const v1::StartSweepRequest& request, const Caller& client, v1::Job* job) {
    if (!request.request_id().empty() && !validRequestId(request.request_id()))
        return Status(StatusCode::INVALID_ARGUMENT,
                      "request_id: must be 1..64 characters of A-Z a-z 0-9 . _ -");
    // Preparing a sweep reads the file system (the output directory's parts): never under the
    // lock. A retried start is compared with the job it started; a start that finds its request
    // id taken while it prepared is such a retry.
    for (;;) {
        std::unique_lock lock(mutex_);
        if (shutting_down_) return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
        if (auto it = by_request_.find(request.request_id());
            !request.request_id().empty() && it != by_request_.end()) {
            const uint64_t number = it->second;
            if (Status ok = waitRecorded(lock, number, 1); !ok.ok()) return ok;
            auto found = jobs_.find(number);
            if (found == jobs_.end() || found->second.recorded == 0) continue;  // forgotten
            const v1::Job stored = found->second.told;
            lock.unlock();
            // The stored config has its defaults filled in; compare what prepareSweep makes of
            // the retried one (whose directory may hold the first one's sweep by now).
            v1::SweepConfig given = request.config();
            given.set_resume_existing(true);
            auto prepared =
                prepareSweep(given, options_.runner.output_root, options_.runner.limits);
            given = request.config();
            if (prepared) {
                given = prepared->config;
                given.set_resume_existing(request.config().resume_existing());
                given.set_output_dir(prepared->output_dir);
            }
            if (!google::protobuf::util::MessageDifferencer::Equals(given, stored.config()))
                return Status(StatusCode::ALREADY_EXISTS, "request_id: '" + request.request_id() +
                                                              "' started " + stored.id() +
                                                              " with a different config");
            *job = stored;
            return Status::OK;
        }
        lock.unlock();
        auto prepared =
            prepareSweep(request.config(), options_.runner.output_root, options_.runner.limits);
        if (!prepared) return Status(StatusCode::INVALID_ARGUMENT, prepared.error().message);
        // Its record must read back at every later start, however it grows until the job ends.
        // (Printed here, without the lock: a record may take megabytes.)
        {
            v1::Job probe;
            probe.set_id(jobId(999999));  // as long as the ids of the next million jobs
            probe.set_request_id(request.request_id());
            probe.set_client(client.name);
            probe.set_controller(client.name);
            probe.set_controller_peer(client.peer);
            probe.set_output_dir(prepared->output_dir);
            for (const std::string& w : prepared->warnings) probe.add_warnings(w);
            *probe.mutable_config() = prepared->config;
            probe.mutable_config()->set_output_dir(prepared->output_dir);
            auto bytes = Journal::recordBytes(probe);
            if (!bytes)
                return Status(StatusCode::INTERNAL,
                              "cannot record the job: " + bytes.error().message);
            if (*bytes + kRecordGrowthBytes > kJournalMaxRecordBytes) {
                const size_t lens = prepared->config.sim().lens().prescription_csv().size();
                return Status(
                    StatusCode::RESOURCE_EXHAUSTED,
                    "config.sim.lens.prescription_csv: the job's journal record would take " +
                        std::to_string(*bytes) + " bytes (" + std::to_string(lens) +
                        " bytes of lens text, escaped as JSON), and with room to grow more than "
                        "the " +
                        std::to_string(kJournalMaxRecordBytes) +
                        " bytes a record may have; send a shorter lens file (comments can go)");
            }
        }
        const std::string directory_key = directoryKey(prepared->output_dir);
        lock.lock();
        if (shutting_down_) return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
        if (!request.request_id().empty() && by_request_.count(request.request_id())) continue;
        prune(unixNow());
        size_t waiting = 0;
        for (const auto& [number, e] : jobs_) {
            if (ended(e.job)) continue;
            if (e.job.state() != v1::RUNNING) ++waiting;
            // The same directory by another spelling or through a link is the same directory.
            if (e.job.output_dir() == prepared->output_dir || e.directory_key == directory_key)
                return Status(StatusCode::INVALID_ARGUMENT,
                              "config.output_dir: " + e.job.id() + " (" +
                                  v1::JobState_Name(e.job.state()) + ") writes to " +
                                  prepared->output_dir);
        }
        if (waiting >= options_.max_queued)
            return Status(
                StatusCode::RESOURCE_EXHAUSTED,
                std::to_string(waiting) + " jobs are waiting, the most this daemon keeps");
        const uint64_t number = next_number_++;
        Entry& e = jobs_[number];
        e.job.set_id(jobId(number));
        e.job.set_request_id(request.request_id());
        e.job.set_client(client.name);
        e.job.set_controller(client.name);
        e.job.set_controller_peer(client.peer);
        e.job.set_state(v1::QUEUED);
        e.job.set_phase(v1::JOB_PHASE_UNSPECIFIED);
        e.job.set_frames_total(static_cast<uint32_t>(prepared->angles_deg.size()));
        e.job.set_output_dir(prepared->output_dir);
        e.job.set_created_unix_s(unixNow());
        for (const std::string& w : prepared->warnings) e.job.add_warnings(w);
        *e.job.mutable_config() = std::move(prepared->config);
        e.job.mutable_config()->set_output_dir(prepared->output_dir);
        e.directory_key = directory_key;
        if (!request.request_id().empty()) by_request_[request.request_id()] = number;
        logEvent(LogLevel::Info, "job.start",
                 {{"job", e.job.id()},
                  {"client", client.name},
                  {"peer", client.peer},
                  {"request_id", request.request_id()},
                  {"frames", std::to_string(e.job.frames_total())},
                  {"output_dir", e.job.output_dir()}});
        changed(e, "queued");
        // Not known to anyone, nor run, until its record is on disk.
        if (Status recorded = waitRecorded(lock, number, 1); !recorded.ok()) {
            if (auto it = by_request_.find(request.request_id());
                it != by_request_.end() && it->second == number)
                by_request_.erase(it);
            jobs_.erase(number);
            return Status(StatusCode::UNAVAILABLE,
                          "cannot record the job: " + recorded.error_message());
        }
        changed_cv_.notify_all();  // the worker may take it now
        auto it = jobs_.find(number);
        if (it == jobs_.end())
            return Status(StatusCode::NOT_FOUND, "the job ended and was forgotten");
        *job = shown(it->second);
        return Status::OK;
    }
}

Status JobManager::mayControl(const v1::JobControlRequest& request,
                              const Caller& client,
                              const char* what,
                              Entry** entry) {
    if (Status ok = find(request.job_id(), entry); !ok.ok()) return ok;
    Entry& e = **entry;
    if (e.job.controller() == client.name && e.job.controller_peer() == client.peer)
        return Status::OK;
    if (!request.take_control()) {
        const std::string who = e.job.controller() + (e.job.controller_peer().empty()
                                                          ? std::string()
                                                          : " (" + e.job.controller_peer() + ")");
        return Status(StatusCode::PERMISSION_DENIED, std::string(what) + " " + e.job.id() +
                                                         ": the job is controlled by '" + who +
                                                         "'; set take_control to take it over");
    }
    logEvent(LogLevel::Warn, "job.control_taken",
             {{"job", e.job.id()},
              {"from", e.job.controller()},
              {"from_peer", e.job.controller_peer()},
              {"to", client.name},
              {"to_peer", client.peer}});
    e.job.set_controller(client.name);
    e.job.set_controller_peer(client.peer);
    return Status::OK;
}

Status JobManager::pause(const v1::JobControlRequest& request, const Caller& client, v1::Job* job) {
    std::unique_lock lock(mutex_);
    Entry* e = nullptr;
    if (shutting_down_) return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
    if (Status ok = find(request.job_id(), &e); !ok.ok()) return ok;
    const v1::Job before = e->job;
    const uint64_t number = jobNumber(e->job.id());
    if (Status ok = mayControl(request, client, "pause", &e); !ok.ok()) return ok;
    const v1::JobState state = e->job.state();
    if (state != v1::QUEUED && state != v1::RUNNING && state != v1::PAUSED)
        return undoControl(
            *e, before,
            Status(StatusCode::FAILED_PRECONDITION,
                   "pause " + e->job.id() + ": the job is " + v1::JobState_Name(state)));
    if (e->job.phase() == v1::FITTING)
        return undoControl(
            *e, before,
            Status(StatusCode::FAILED_PRECONDITION,
                   "pause " + e->job.id() +
                       ": the job is fitting, which holds no device; cancel it or let it end"));
    if (state != v1::PAUSED) {
        e->job.set_state(v1::PAUSED);
        e->job.set_reason("paused by " + client.name);
    }
    if (state != v1::PAUSED || tookControl(before, e->job)) {
        const Proposal p = propose(*e, before, e->cancel_requested,
                                   state != v1::PAUSED ? "paused by a client" : "control taken");
        if (Status ok = commit(lock, p); !ok.ok()) return ok;
        return answer(lock, number, p.version, job);
    }
    return answer(lock, number, e->version, job);
}

Status JobManager::resume(const v1::JobControlRequest& request,
                          const Caller& client,
                          v1::Job* job) {
    std::unique_lock lock(mutex_);
    Entry* e = nullptr;
    if (shutting_down_) return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
    if (Status ok = find(request.job_id(), &e); !ok.ok()) return ok;
    const v1::Job before = e->job;
    const bool cancel_before = e->cancel_requested;
    const uint64_t number = jobNumber(e->job.id());
    if (Status ok = mayControl(request, client, "resume", &e); !ok.ok()) return ok;
    const v1::JobState state = e->job.state();
    if (state != v1::RUNNING && state != v1::QUEUED) {
        const bool failed_resumable = state == v1::FAILED && e->job.resumable() && !e->control;
        if (state != v1::PAUSED && state != v1::INTERRUPTED && !failed_resumable)
            return undoControl(
                *e, before,
                Status(StatusCode::FAILED_PRECONDITION,
                       "resume " + e->job.id() + ": the job is " + v1::JobState_Name(state) +
                           (state == v1::FAILED
                                ? " for a reason a resume does not change: " + e->job.reason()
                                : "")));
        if (failed_resumable) {
            // Another job may have taken its directory since it ended.
            for (const auto& [other_number, other] : jobs_)
                if (&other != e && !ended(other.job) &&
                    (other.job.output_dir() == e->job.output_dir() ||
                     other.directory_key == e->directory_key))
                    return undoControl(*e, before,
                                       Status(StatusCode::FAILED_PRECONDITION,
                                              "resume " + e->job.id() + ": " + other.job.id() +
                                                  " (" + v1::JobState_Name(other.job.state()) +
                                                  ") writes to " + e->job.output_dir() + " now"));
            // Its fit, if that is what failed, runs again on the sweep on disk.
            e->job.set_resumable(false);
            e->job.set_phase(v1::JOB_PHASE_UNSPECIFIED);
            e->cancel_requested = false;
        }
        e->job.set_state(e->control ? v1::RUNNING : v1::QUEUED);
        e->job.set_reason("");
    }
    const bool resumed = state != v1::RUNNING && state != v1::QUEUED;
    if (resumed || tookControl(before, e->job)) {
        const Proposal p = propose(*e, before, cancel_before,
                                   resumed ? "resumed by " + client.name : "control taken");
        if (Status ok = commit(lock, p); !ok.ok()) return ok;
        return answer(lock, number, p.version, job);
    }
    return answer(lock, number, e->version, job);
}

Status JobManager::cancel(const v1::JobControlRequest& request,
                          const Caller& client,
                          v1::Job* job) {
    std::unique_lock lock(mutex_);
    Entry* e = nullptr;
    if (shutting_down_) return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
    if (Status ok = find(request.job_id(), &e); !ok.ok()) return ok;
    const v1::Job before = e->job;
    const bool cancel_before = e->cancel_requested;
    const uint64_t number = jobNumber(e->job.id());
    if (Status ok = mayControl(request, client, "cancel", &e); !ok.ok()) return ok;
    if (ended(e->job))
        return undoControl(
            *e, before,
            Status(StatusCode::FAILED_PRECONDITION,
                   "cancel " + e->job.id() + ": the job is " + v1::JobState_Name(e->job.state())));
    // On disk first: a cancel that the journal does not hold could run the job again after a
    // restart. Its record says CANCELLED (asWritten) while the job still stops.
    e->cancel_requested = true;
    e->job.set_reason("cancelled by " + client.name);
    const bool running = e->control != nullptr;
    if (!running) e->job.set_state(v1::CANCELLED);
    const Proposal p =
        propose(*e, before, cancel_before, running ? "cancel requested" : "cancelled");
    if (Status ok = commit(lock, p); !ok.ok()) return ok;
    if (auto it = jobs_.find(number); it != jobs_.end() && it->second.control) {
        // Its stage ends it: the capture stops the rig at once and writes the frames captured so
        // far, the fit stops before its next frame.
        it->second.control->requestStop();
        changed_cv_.notify_all();
        logEvent(LogLevel::Info, "job.cancel_requested",
                 {{"job", it->second.job.id()}, {"client", client.name}, {"peer", client.peer}});
    }
    return answer(lock, number, p.version, job);
}

bool JobManager::tookControl(const v1::Job& before, const v1::Job& now) {
    return before.controller() != now.controller() ||
           before.controller_peer() != now.controller_peer();
}

Status JobManager::undoControl(Entry& entry, const v1::Job& before, Status refused) {
    // A refused call takes no control either.
    entry.job.set_controller(before.controller());
    entry.job.set_controller_peer(before.controller_peer());
    return refused;
}

Status JobManager::answer(std::unique_lock<std::mutex>& lock,
                          uint64_t number,
                          uint64_t version,
                          v1::Job* job) {
    // A change is answered once it is on disk, as it is announced.
    if (Status recorded = waitRecorded(lock, number, version); !recorded.ok()) return recorded;
    const auto found = jobs_.find(number);
    if (found == jobs_.end()) return Status(StatusCode::NOT_FOUND, "job_id: the job was forgotten");
    *job = shown(found->second);
    return Status::OK;
}

std::vector<v1::Job> JobManager::list() const {
    std::lock_guard lock(mutex_);
    std::vector<v1::Job> out;
    for (const auto& [number, e] : jobs_) {
        if (e.recorded == 0) continue;
        v1::Job job = shown(e);
        job.mutable_config()->mutable_sim()->mutable_lens()->clear_prescription_csv();
        out.push_back(std::move(job));
    }
    return out;
}

Status JobManager::result(const std::string& id, v1::JobResult* result) const {
    v1::Job job;
    {
        std::lock_guard lock(mutex_);
        const Entry* e = nullptr;
        if (Status ok = findConst(id, &e); !ok.ok()) return ok;
        job = summary(shown(*e));
    }
    // The files are looked at without the lock: a slow or hostile file holds up this call only.
    const std::string dir = job.output_dir();
    *result->mutable_job() = std::move(job);
    result->set_sweep_dir(dir);
    std::error_code ec;
    const fs::path manifest = fs::path(dir) / hdr::kSweepManifestFile;
    if (fs::is_regular_file(fs::symlink_status(manifest, ec)))
        result->set_manifest(manifest.string());
    const std::string& model = result->job().model_file();
    if (!model.empty() && fs::is_regular_file(fs::symlink_status(model, ec))) {
        result->set_model_file(model);
        auto text = readRegularText((fs::path(dir) / hdr::kSweepModelText).string(), 1 << 20);
        if (text)
            result->set_model_summary(std::move(*text));
        else if (text.error().code != ErrorCode::NotFound)
            result->add_warnings(text.error().message);
    }
    const fs::path previews = fs::path(dir) / hdr::kSweepPreviewsDir;
    std::vector<std::string> files;
    if (fs::is_directory(fs::symlink_status(previews, ec)))
        for (fs::directory_iterator it(previews, ec), end;
             !ec && it != end &&
             files.size() < static_cast<size_t>(options_.runner.limits.max_frames);
             it.increment(ec))
            if (it->path().extension() == ".png" && it->is_regular_file(ec) && !it->is_symlink(ec))
                files.push_back(it->path().string());
    std::sort(files.begin(), files.end());
    for (std::string& f : files) result->add_previews(std::move(f));
    return Status::OK;
}

Status JobManager::watchStart(const std::string& id,
                              v1::JobEvent* first,
                              uint64_t* sequence) const {
    std::lock_guard lock(mutex_);
    const Entry* e = nullptr;
    if (Status ok = findConst(id, &e); !ok.ok()) return ok;
    *sequence = e->next_sequence - 1;
    first->set_sequence(*sequence);
    first->set_kind(v1::STATE);
    // The job as on disk: a change not yet written is not told.
    *first->mutable_job() = summary(shown(*e));
    first->set_message(first->job().reason());
    return Status::OK;
}

Status JobManager::watchNext(const std::string& id,
                             uint64_t* sequence,
                             std::chrono::milliseconds wait,
                             WatchBatch* batch) const {
    std::unique_lock lock(mutex_);
    const Entry* e = nullptr;
    if (Status ok = findConst(id, &e); !ok.ok()) return ok;
    const uint64_t number = jobNumber(id);
    // The entry is found again after each wait: an ended job may be forgotten meanwhile.
    const auto announcedEnd = [](const Entry& entry) {
        if (entry.events.empty())  // a job read from the journal
            return ended(entry.job) && entry.recorded >= entry.version;
        return ended(entry.events.back().job());
    };
    changed_cv_.wait_for(lock, wait, [&] {
        const auto it = jobs_.find(number);
        if (it == jobs_.end()) return true;
        return shutting_down_ || it->second.next_sequence - 1 > *sequence ||
               announcedEnd(it->second);
    });
    const auto it = jobs_.find(number);
    if (it == jobs_.end())
        return Status(StatusCode::NOT_FOUND, "job_id: " + id + " ended and was forgotten");
    e = &it->second;
    batch->events.clear();
    for (const v1::JobEvent& event : e->events)
        if (event.sequence() > *sequence) batch->events.push_back(event);
    if (!batch->events.empty()) *sequence = batch->events.back().sequence();
    // Ended once the end is announced (on disk), and this watcher has seen the events before it.
    batch->ended = announcedEnd(*e) && *sequence >= e->next_sequence - 1;
    if (shutting_down_ && batch->events.empty() && !batch->ended)
        return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
    return Status::OK;
}

std::string JobManager::runningJob() const {
    std::lock_guard lock(mutex_);
    return running_;
}

size_t JobManager::queuedJobs() const {
    std::lock_guard lock(mutex_);
    size_t n = 0;
    for (const auto& [number, e] : jobs_) n += e.job.state() == v1::QUEUED;
    return n;
}

std::pair<std::string, std::string> JobManager::deviceIdentity(const std::string& uri) const {
    std::lock_guard lock(mutex_);
    const auto it = devices_seen_.find(uri);
    return it == devices_seen_.end() ? std::pair<std::string, std::string>{} : it->second;
}

}  // namespace flarelab::daemon
