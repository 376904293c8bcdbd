// libFuzzer target for the daemon's job state machine (daemon/job_manager.h), driven as clients
// drive it over gRPC: the bytes are a program of StartSweep, WatchJob, PauseJob, ResumeJob,
// CancelJob and restarts of the daemon (the manager shut down and opened again on its journal),
// run against an in-process JobManager whose jobs are tiny sweeps of the fast simulated rig.
//
// After every step the manager is checked against its journal on disk and against what it said
// before: every job is on disk and every record reads back; a job the manager shows ended is
// recorded ended the same way, and a record that says ended is that state in memory or becomes it
// within seconds (the journal is written before the manager shows a change); an ended job never
// changes again, across restarts too (a cancelled job never runs again); frames done never exceed
// frames planned; no call answers with an error outside the API's (INTERNAL, UNKNOWN). Every
// violation is a trap, so libFuzzer records the input.
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "daemon/job_manager.h"
#include "daemon/journal.h"
#include "daemon/log.h"

namespace {

namespace fs = std::filesystem;
using namespace flarelab;
using namespace flarelab::daemon;

void require(bool condition) {
    if (!condition) __builtin_trap();
}

// A three-surface toy lens (data/lenses/lensbaby-toy.csv): few ghosts, quick to render.
constexpr char kLens[] =
    "# focal_length_mm: 129; f_number: 11\n"
    "kind,radius_mm,thickness_mm,ior_d,abbe,semi_aperture_mm,coating_wavelength_nm\n"
    "surface,65.22,9.6,1.5,50,24,620\n"
    "surface,-62.03,4.2,1.5,50,24,620\n"
    "surface,-1240.67,5,1,,24,620\n"
    "stop,0,105,1,,20,\n";

class Program {
public:
    Program(const uint8_t* data, size_t size) : data_(data), size_(size) {}
    bool done() const { return at_ >= size_; }
    uint8_t next() { return at_ < size_ ? data_[at_++] : 0; }

private:
    const uint8_t* data_;
    size_t size_;
    size_t at_ = 0;
};

bool ended(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

v1::SweepConfig config(uint8_t a, uint8_t b) {
    v1::SweepConfig c;
    auto* sim = c.mutable_sim();
    sim->set_fast(true);
    sim->set_seed(1 + a % 3);
    sim->mutable_lens()->set_prescription_csv(kLens);
    sim->mutable_lens()->set_name("lensbaby-toy.csv");
    if (b & 8) sim->mutable_faults()->set_head_stall_at_deg(0.2);  // the job pauses on a fault
    c.set_from_deg(0.0);
    c.set_to_deg(0.2 * (a % 4));
    c.set_step_deg(0.2);
    c.add_exposure_times_s(0.01);
    if (a & 4) c.add_exposure_times_s(0.02);
    c.set_width_px(8);
    c.set_height_px(6);
    c.set_output_dir("d" + std::to_string(b % 4));
    c.set_resume_existing(b & 4);
    return c;
}

// What the manager has said so far: ended jobs and their states, every id.
struct Seen {
    std::map<std::string, v1::JobState> ended;
    std::set<std::string> ids;
};

std::map<std::string, v1::Job> byId(const std::vector<v1::Job>& jobs) {
    std::map<std::string, v1::Job> out;
    for (const v1::Job& j : jobs) {
        require(out.emplace(j.id(), j).second);  // ids are unique
        require(j.state() != v1::JOB_STATE_UNSPECIFIED);
        require(j.frames_done() <= j.frames_total());
    }
    return out;
}

// A record on disk that says ended must be what the manager shows, or become it. The manager writes
// a change to the journal before it shows it (a client is never told what the disk does not hold),
// so a job that ends by itself is on disk for as long as the recorder takes to come back to the
// manager's lock, fsyncing the journal's directory and writing the batch's other records, before
// list() shows it: the manager may be behind, for a moment, but never ended otherwise. A cancel is
// recorded before the capture it stops has ended, so a cancelled record may show running or paused
// until then.
void caughtUp(JobManager& manager, const std::string& id, v1::JobState state, v1::JobState now) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    for (;;) {
        if (now == state) return;
        if (state == v1::CANCELLED && (now == v1::RUNNING || now == v1::PAUSED)) return;
        require(!ended(now));  // ended differently from its record: never right
        require(std::chrono::steady_clock::now() < deadline);  // it never caught up
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
        const auto jobs = byId(manager.list());
        require(jobs.count(id));
        now = jobs.at(id).state();
    }
}

void check(JobManager& manager, const std::string& state_dir, Seen& seen) {
    const auto before = byId(manager.list());
    auto journal = Journal::open(state_dir);
    require(journal.has_value());
    auto loaded = journal->load();
    require(loaded.has_value() && loaded->warnings.empty());  // every record reads back
    const auto after = byId(manager.list());
    std::map<std::string, v1::JobState> on_disk;
    for (const v1::Job& j : loaded->jobs) on_disk[j.id()] = j.state();
    for (const auto& [id, job] : before) {
        require(on_disk.count(id));  // recorded before it was shown
        if (ended(job.state())) require(on_disk[id] == job.state());
    }
    for (const auto& [id, state] : on_disk) {
        require(after.count(id));
        if (ended(state)) caughtUp(manager, id, state, after.at(id).state());
    }
    for (const auto& [id, job] : after) {
        auto was = seen.ended.find(id);
        if (was != seen.ended.end()) require(job.state() == was->second);  // ended for good
        if (ended(job.state())) seen.ended[id] = job.state();
        seen.ids.insert(id);
    }
    for (const std::string& id : seen.ids) require(after.count(id));  // nothing lost
}

bool apiError(const grpc::Status& s) {
    return s.error_code() != grpc::StatusCode::INTERNAL &&
           s.error_code() != grpc::StatusCode::UNKNOWN;
}

const fs::path& root() {
    static const fs::path path = [] {
        std::string name = (fs::temp_directory_path() / "flarelab-job-fuzz-XXXXXX").string();
        const char* made = ::mkdtemp(name.data());
        require(made != nullptr);
        setLogLevel(LogLevel::Error);  // a line per state change would slow the fuzzer down
        return fs::path(made);
    }();
    // Registered once `path` is made, so that it runs before `path` is destroyed.
    static const bool cleaned_at_exit = std::atexit([] {
                                            std::error_code ec;
                                            fs::remove_all(root(), ec);
                                        }) == 0;
    (void)cleaned_at_exit;
    return path;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    static int run = 0;
    const fs::path dir = root() / std::to_string(run++);
    fs::remove_all(dir);
    fs::create_directories(dir / "output");
    ManagerOptions options;
    options.runner.state_dir = dir.string();
    options.runner.output_root = fs::canonical(dir / "output").string();
    options.runner.software_version = "job_control_fuzzer";
    options.events_kept = 64;
    std::vector<std::string> warnings;
    auto opened = JobManager::open(options, &warnings);
    require(opened.has_value() && warnings.empty());
    std::unique_ptr<JobManager> manager = std::move(*opened);

    Program program(data, size);
    Seen seen;
    for (int step = 0; step < 48 && !program.done(); ++step) {
        const uint8_t op = program.next();
        const Caller client{(op & 0x10) ? "a" : "b", ""};
        std::vector<std::string> ids(seen.ids.begin(), seen.ids.end());
        const auto pick = [&] {
            const uint8_t i = program.next();
            if (ids.empty() || i == 0xff) return std::string("job-999999");
            return ids[i % ids.size()];
        };
        v1::JobControlRequest control;
        control.set_take_control(op & 0x20);
        v1::Job job;
        grpc::Status status;
        switch (op % 8) {
            case 0: {
                v1::StartSweepRequest request;
                const uint8_t a = program.next(), b = program.next();
                *request.mutable_config() = config(a, b);
                if (op & 0x40) request.set_request_id("r" + std::to_string(b % 3));
                status = manager->start(request, client, &job);
                if (status.ok()) seen.ids.insert(job.id());
                break;
            }
            case 1:
                control.set_job_id(pick());
                status = manager->pause(control, client, &job);
                break;
            case 2:
                control.set_job_id(pick());
                status = manager->resume(control, client, &job);
                // The one way out of an end: a failure that may pass, resumed.
                if (status.ok()) seen.ended.erase(control.job_id());
                break;
            case 3:
                control.set_job_id(pick());
                status = manager->cancel(control, client, &job);
                if (status.ok()) require(job.state() == v1::CANCELLED || !ended(job.state()));
                break;
            case 4: {
                const std::string id = pick();
                v1::JobEvent first;
                uint64_t sequence = 0;
                status = manager->watchStart(id, &first, &sequence);
                if (status.ok()) {
                    WatchBatch batch;
                    status = manager->watchNext(
                        id, &sequence, std::chrono::milliseconds(program.next() % 8), &batch);
                    for (size_t i = 1; i < batch.events.size(); ++i)
                        require(batch.events[i].sequence() > batch.events[i - 1].sequence());
                }
                break;
            }
            case 5: {  // the daemon stops (its jobs interrupted) and starts again
                options.resume = program.next() & 1;
                manager.reset();
                warnings.clear();
                auto again = JobManager::open(options, &warnings);
                require(again.has_value() && warnings.empty());
                manager = std::move(*again);
                // Nothing runs yet that was not queued: ended jobs stay ended.
                for (const v1::Job& j : manager->list()) {
                    auto was = seen.ended.find(j.id());
                    if (was != seen.ended.end()) require(j.state() == was->second);
                }
                break;
            }
            case 6:
                std::this_thread::sleep_for(std::chrono::milliseconds(program.next() % 16));
                break;
            case 7: {
                v1::JobResult result;
                status = manager->result(pick(), &result);
                break;
            }
        }
        require(apiError(status));
        check(*manager, dir.string(), seen);
    }
    manager.reset();
    std::error_code ec;
    fs::remove_all(dir, ec);
    return 0;
}
