#include "daemon/job_manager.h"

#include <google/protobuf/util/message_differencer.h>
#include <sys/stat.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>

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
// 8 KiB) and the other fields, all of which JSON may grow sixfold.
constexpr size_t kMaxWarningBytes = 1024;
constexpr size_t kMaxReasonBytes = 4096;
constexpr int64_t kRecordGrowthBytes =
    6 * (100 * (kMaxWarningBytes + 8) + kMaxReasonBytes + 8192 + 4096) + (64 << 10);

// Two output directories are the same when they are the same directory (device and inode; through
// links, bind mounts or different spellings), or, before they exist, the same path once the part
// that exists is resolved.
bool sameDirectory(const std::string& a, const std::string& b) {
    if (a == b) return true;
    struct stat sa {
    }, sb{};
    if (::stat(a.c_str(), &sa) == 0 && ::stat(b.c_str(), &sb) == 0)
        return sa.st_dev == sb.st_dev && sa.st_ino == sb.st_ino;
    std::error_code ea, eb;
    const fs::path ra = fs::weakly_canonical(a, ea), rb = fs::weakly_canonical(b, eb);
    return !ea && !eb && ra == rb;
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

    void setStopHook(std::function<void()> hook) override {
        std::lock_guard lock(manager_.mutex_);
        hook_ = std::move(hook);
    }

    // With the manager's mutex held.
    void requestStop() {
        stop_ = true;
        if (hook_) hook_();
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
        if (frames % 16 == 0) (void)manager_.journal_.save(e.job);
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
                if (auto saved = manager->journal_.save(job); !saved) return saved.error();
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
        e.job.set_updated_unix_s(unixNow());
        if (!e.job.request_id().empty()) manager->by_request_[e.job.request_id()] = number;
        manager->next_number_ = std::max(manager->next_number_, number + 1);
        if (!ended(e.job)) {
            if (auto saved = manager->journal_.save(e.job); !saved) return saved.error();
            logEvent(LogLevel::Info, "job.loaded",
                     {{"job", e.job.id()},
                      {"state", v1::JobState_Name(e.job.state())},
                      {"frames_done", std::to_string(e.job.frames_done())}});
        }
    }
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
}

bool JobManager::ended(const v1::Job& job) {
    return job.state() == v1::SUCCEEDED || job.state() == v1::FAILED ||
           job.state() == v1::CANCELLED;
}

void JobManager::emit(Entry& entry, v1::JobEvent event) {
    event.set_sequence(entry.next_sequence++);
    *event.mutable_job() = summary(entry.job);
    entry.events.push_back(std::move(event));
    while (entry.events.size() > options_.events_kept) entry.events.pop_front();
    changed_cv_.notify_all();
}

flarelab::Status JobManager::changed(Entry& entry, const std::string& log_note) {
    entry.job.set_updated_unix_s(unixNow());
    if (entry.job.reason().size() > kMaxReasonBytes)
        entry.job.set_reason(clipped(entry.job.reason(), kMaxReasonBytes));
    // A cancel a client was told about is on disk before the job stops, and stays there.
    v1::Job record = entry.job;
    if (entry.cancel_requested && !ended(record)) {
        record.set_state(v1::CANCELLED);
        record.set_resumable(false);
    }
    flarelab::Status saved = journal_.save(record);
    if (!saved)
        logEvent(LogLevel::Error, "journal.write_failed",
                 {{"job", entry.job.id()}, {"message", saved.error().message}});
    announce(entry, log_note);
    return saved;
}

void JobManager::announce(Entry& entry, const std::string& log_note) {
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
    emit(entry, std::move(event));
}

Status JobManager::commit(Entry& entry, const v1::Job& before, const std::string& note) {
    entry.job.set_updated_unix_s(unixNow());
    if (entry.job.reason().size() > kMaxReasonBytes)
        entry.job.set_reason(clipped(entry.job.reason(), kMaxReasonBytes));
    v1::Job record = entry.job;
    if (entry.cancel_requested && !ended(record)) record.set_state(v1::CANCELLED);
    if (flarelab::Status saved = journal_.save(record); !saved) {
        logEvent(LogLevel::Error, "journal.write_failed",
                 {{"job", entry.job.id()}, {"message", saved.error().message}, {"note", note}});
        entry.job = before;
        return Status(StatusCode::UNAVAILABLE,
                      entry.job.id() + ": the change is refused, the journal cannot record it: " +
                          saved.error().message);
    }
    announce(entry, note);
    return Status::OK;
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
                 << result.queue_high_water << "; fit queued";
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
}

void JobManager::work() {
    std::unique_lock lock(mutex_);
    for (;;) {
        Entry* next = nullptr;
        changed_cv_.wait(lock, [&] {
            if (shutting_down_) return true;
            for (auto& [number, e] : jobs_)
                if (e.job.state() == v1::QUEUED) {
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
    if (number == 0 || it == jobs_.end())
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

Status JobManager::start(const v1::StartSweepRequest& request,
                         const std::string& client,
                         v1::Job* job) {
    if (!request.request_id().empty() && !validRequestId(request.request_id()))
        return Status(StatusCode::INVALID_ARGUMENT,
                      "request_id: must be 1..64 characters of A-Z a-z 0-9 . _ -");
    {
        std::lock_guard lock(mutex_);
        if (shutting_down_) return Status(StatusCode::UNAVAILABLE, "the daemon is stopping");
        if (auto it = by_request_.find(request.request_id());
            !request.request_id().empty() && it != by_request_.end()) {
            const Entry& e = jobs_.at(it->second);
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
            const v1::SweepConfig& stored = e.job.config();
            if (!google::protobuf::util::MessageDifferencer::Equals(given, stored))
                return Status(StatusCode::ALREADY_EXISTS, "request_id: '" + request.request_id() +
                                                              "' started " + e.job.id() +
                                                              " with a different config");
            *job = e.job;
            return Status::OK;
        }
    }
    auto prepared =
        prepareSweep(request.config(), options_.runner.output_root, options_.runner.limits);
    if (!prepared) return Status(StatusCode::INVALID_ARGUMENT, prepared.error().message);
    std::lock_guard lock(mutex_);
    size_t waiting = 0;
    for (const auto& [number, e] : jobs_) {
        if (ended(e.job)) continue;
        if (e.job.state() != v1::RUNNING) ++waiting;
        if (sameDirectory(e.job.output_dir(), prepared->output_dir))
            return Status(StatusCode::INVALID_ARGUMENT, "config.output_dir: " + e.job.id() + " (" +
                                                            v1::JobState_Name(e.job.state()) +
                                                            ") writes to " + prepared->output_dir);
    }
    if (waiting >= options_.max_queued)
        return Status(StatusCode::RESOURCE_EXHAUSTED,
                      std::to_string(waiting) + " jobs are waiting, the most this daemon keeps");
    const uint64_t number = next_number_++;
    Entry& e = jobs_[number];
    e.job.set_id(jobId(number));
    e.job.set_request_id(request.request_id());
    e.job.set_client(client);
    e.job.set_controller(client);
    e.job.set_state(v1::QUEUED);
    e.job.set_phase(v1::JOB_PHASE_UNSPECIFIED);
    e.job.set_frames_total(static_cast<uint32_t>(prepared->angles_deg.size()));
    e.job.set_output_dir(prepared->output_dir);
    e.job.set_created_unix_s(unixNow());
    for (const std::string& w : prepared->warnings) e.job.add_warnings(w);
    *e.job.mutable_config() = prepared->config;
    e.job.mutable_config()->set_output_dir(prepared->output_dir);
    // Its record must read back at every later start, however it grows until the job ends.
    if (auto bytes = Journal::recordBytes(e.job);
        !bytes || *bytes + kRecordGrowthBytes > kJournalMaxRecordBytes) {
        const size_t lens = prepared->config.sim().lens().prescription_csv().size();
        const std::string message =
            bytes ? "config.sim.lens.prescription_csv: the job's journal record would take " +
                        std::to_string(*bytes) + " bytes (" + std::to_string(lens) +
                        " bytes of lens text, escaped as JSON), and with room to grow more than " +
                        "the " + std::to_string(kJournalMaxRecordBytes) +
                        " bytes a record may have; send a shorter lens file (comments can go)"
                  : "cannot record the job: " + bytes.error().message;
        jobs_.erase(number);
        --next_number_;
        return Status(bytes ? StatusCode::RESOURCE_EXHAUSTED : StatusCode::INTERNAL, message);
    }
    if (auto saved = journal_.save(e.job); !saved) {
        const std::string message = saved.error().message;
        jobs_.erase(number);
        --next_number_;
        return Status(StatusCode::UNAVAILABLE, "cannot record the job: " + message);
    }
    if (!request.request_id().empty()) by_request_[request.request_id()] = number;
    logEvent(LogLevel::Info, "job.start",
             {{"job", e.job.id()},
              {"client", client},
              {"request_id", request.request_id()},
              {"frames", std::to_string(e.job.frames_total())},
              {"output_dir", e.job.output_dir()}});
    changed(e, "queued");
    *job = e.job;
    return Status::OK;
}

Status JobManager::mayControl(const v1::JobControlRequest& request,
                              const std::string& client,
                              const char* what,
                              Entry** entry) {
    if (Status ok = find(request.job_id(), entry); !ok.ok()) return ok;
    Entry& e = **entry;
    if (e.job.controller() == client) return Status::OK;
    if (!request.take_control())
        return Status(StatusCode::PERMISSION_DENIED,
                      std::string(what) + " " + e.job.id() + ": the job is controlled by '" +
                          e.job.controller() + "'; set take_control to take it over");
    logEvent(LogLevel::Warn, "job.control_taken",
             {{"job", e.job.id()}, {"from", e.job.controller()}, {"to", client}});
    e.job.set_controller(client);
    return Status::OK;
}

Status JobManager::pause(const v1::JobControlRequest& request,
                         const std::string& client,
                         v1::Job* job) {
    std::lock_guard lock(mutex_);
    Entry* e = nullptr;
    if (Status ok = find(request.job_id(), &e); !ok.ok()) return ok;
    const v1::Job before = e->job;
    if (Status ok = mayControl(request, client, "pause", &e); !ok.ok()) return ok;
    const v1::JobState state = e->job.state();
    if (state != v1::QUEUED && state != v1::RUNNING && state != v1::PAUSED)
        return Status(StatusCode::FAILED_PRECONDITION,
                      "pause " + e->job.id() + ": the job is " + v1::JobState_Name(state));
    if (e->job.phase() == v1::FITTING)
        return Status(StatusCode::FAILED_PRECONDITION,
                      "pause " + e->job.id() +
                          ": the job is fitting, which holds no device; cancel it or let it end");
    if (state != v1::PAUSED) {
        e->job.set_state(v1::PAUSED);
        e->job.set_reason("paused by " + client);
        if (Status ok = commit(*e, before, "paused by a client"); !ok.ok()) return ok;
    }
    *job = e->job;
    return Status::OK;
}

Status JobManager::resume(const v1::JobControlRequest& request,
                          const std::string& client,
                          v1::Job* job) {
    std::lock_guard lock(mutex_);
    Entry* e = nullptr;
    if (Status ok = find(request.job_id(), &e); !ok.ok()) return ok;
    const v1::Job before = e->job;
    if (Status ok = mayControl(request, client, "resume", &e); !ok.ok()) return ok;
    const v1::JobState state = e->job.state();
    if (state == v1::RUNNING || state == v1::QUEUED) {
        *job = e->job;
        return Status::OK;
    }
    const bool failed_resumable = state == v1::FAILED && e->job.resumable() && !e->control;
    if (state != v1::PAUSED && state != v1::INTERRUPTED && !failed_resumable)
        return Status(
            StatusCode::FAILED_PRECONDITION,
            "resume " + e->job.id() + ": the job is " + v1::JobState_Name(state) +
                (state == v1::FAILED ? " for a reason a resume does not change: " + e->job.reason()
                                     : ""));
    if (failed_resumable) {
        // Another job may have taken its directory since it ended.
        for (const auto& [number, other] : jobs_)
            if (&other != e && !ended(other.job) &&
                sameDirectory(other.job.output_dir(), e->job.output_dir()))
                return Status(StatusCode::FAILED_PRECONDITION,
                              "resume " + e->job.id() + ": " + other.job.id() + " (" +
                                  v1::JobState_Name(other.job.state()) + ") writes to " +
                                  e->job.output_dir() + " now");
        // Its fit, if that is what failed, runs again on the sweep on disk.
        e->job.set_resumable(false);
        e->job.set_phase(v1::JOB_PHASE_UNSPECIFIED);
        e->cancel_requested = false;
    }
    e->job.set_state(e->control ? v1::RUNNING : v1::QUEUED);
    e->job.set_reason("");
    if (Status ok = commit(*e, before, "resumed by " + client); !ok.ok()) return ok;
    *job = e->job;
    return Status::OK;
}

Status JobManager::cancel(const v1::JobControlRequest& request,
                          const std::string& client,
                          v1::Job* job) {
    std::lock_guard lock(mutex_);
    Entry* e = nullptr;
    if (Status ok = find(request.job_id(), &e); !ok.ok()) return ok;
    const v1::Job before = e->job;
    if (Status ok = mayControl(request, client, "cancel", &e); !ok.ok()) return ok;
    if (ended(e->job))
        return Status(StatusCode::FAILED_PRECONDITION, "cancel " + e->job.id() + ": the job is " +
                                                           v1::JobState_Name(e->job.state()));
    // On disk first: a cancel that the journal does not hold could run the job again after a
    // restart.
    const bool was_requested = e->cancel_requested;
    e->cancel_requested = true;
    e->job.set_reason("cancelled by " + client);
    if (!e->control) e->job.set_state(v1::CANCELLED);
    if (Status ok = commit(*e, before, e->control ? "cancel requested" : "cancelled"); !ok.ok()) {
        e->cancel_requested = was_requested;
        return ok;
    }
    if (e->control) {
        // Its stage ends it: the capture once the frames captured so far are written, the fit
        // before its next frame.
        e->control->requestStop();
        changed_cv_.notify_all();
        logEvent(LogLevel::Info, "job.cancel_requested",
                 {{"job", e->job.id()}, {"client", client}});
    }
    *job = e->job;
    return Status::OK;
}

std::vector<v1::Job> JobManager::list() const {
    std::lock_guard lock(mutex_);
    std::vector<v1::Job> out;
    for (const auto& [number, e] : jobs_) {
        v1::Job job = e.job;
        job.mutable_config()->mutable_sim()->mutable_lens()->clear_prescription_csv();
        out.push_back(std::move(job));
    }
    return out;
}

Status JobManager::result(const std::string& id, v1::JobResult* result) const {
    std::lock_guard lock(mutex_);
    const Entry* e = nullptr;
    if (Status ok = findConst(id, &e); !ok.ok()) return ok;
    *result->mutable_job() = summary(e->job);
    const std::string dir = e->job.output_dir();
    result->set_sweep_dir(dir);
    std::error_code ec;
    const fs::path manifest = fs::path(dir) / hdr::kSweepManifestFile;
    if (fs::exists(manifest, ec)) result->set_manifest(manifest.string());
    if (!e->job.model_file().empty() && fs::exists(e->job.model_file(), ec)) {
        result->set_model_file(e->job.model_file());
        std::ifstream text(fs::path(dir) / hdr::kSweepModelText);
        std::stringstream s;
        s << text.rdbuf();
        result->set_model_summary(s.str().substr(0, 1 << 20));
    }
    const fs::path previews = fs::path(dir) / hdr::kSweepPreviewsDir;
    std::vector<std::string> files;
    for (fs::directory_iterator it(previews, ec), end; !ec && it != end; it.increment(ec))
        if (it->path().extension() == ".png") files.push_back(it->path().string());
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
    *first->mutable_job() = summary(e->job);
    first->set_message(e->job.reason());
    return Status::OK;
}

Status JobManager::watchNext(const std::string& id,
                             uint64_t* sequence,
                             std::chrono::milliseconds wait,
                             WatchBatch* batch) const {
    std::unique_lock lock(mutex_);
    const Entry* e = nullptr;
    if (Status ok = findConst(id, &e); !ok.ok()) return ok;
    changed_cv_.wait_for(lock, wait, [&] {
        return shutting_down_ || e->next_sequence - 1 > *sequence || ended(e->job);
    });
    batch->events.clear();
    for (const v1::JobEvent& event : e->events)
        if (event.sequence() > *sequence) batch->events.push_back(event);
    if (!batch->events.empty()) *sequence = batch->events.back().sequence();
    batch->ended = ended(e->job);
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
