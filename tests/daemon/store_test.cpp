// The daemon under faults of its disk and memory: a journal record always reads back, a change the
// journal cannot record is refused, a failure on the capture side loses no captured frame, a
// failed flush ends the job, resume touches only its own sweep, memory is bounded in bytes, a job
// that keeps killing the daemon is quarantined, and hostile files in the state directory are set
// aside without blocking.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/file.h>
#include <sys/mount.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <sys/sysmacros.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <future>
#include <new>

#include "common/durable_io.h"
#include "common/file_descriptor.h"
#include "daemon/bounded_queue.h"
#include "daemon/journal.h"
#include "daemon/sweep_config.h"
#include "hdr/sweep.h"
#include "tests/daemon/daemon_fixture.h"
#include "tests/test_files.h"

extern char** environ;

namespace flarelab::daemon {
namespace {

using flarelab::testing::contains;

using namespace testing;

// The job `id` as the manager lists it, once `done(job)` or after `deadline_s`.
template <typename Pred>
v1::Job waitJob(JobManager& manager, const std::string& id, Pred done, double deadline_s = 120) {
    const auto end = std::chrono::steady_clock::now() +
                     std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3));
    v1::Job last;
    while (std::chrono::steady_clock::now() < end) {
        for (const v1::Job& j : manager.list())
            if (j.id() == id) last = j;
        if (done(last)) return last;
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    ADD_FAILURE() << "job " << id << " did not get there; last state "
                  << v1::JobState_Name(last.state()) << " reason " << last.reason();
    return last;
}

grpc::Status start(JobManager& manager, const v1::SweepConfig& config, v1::Job* job) {
    v1::StartSweepRequest request;
    *request.mutable_config() = config;
    return manager.start(request, Caller{"test", ""}, job);
}

grpc::Status control(JobManager& manager,
                     grpc::Status (JobManager::*what)(const v1::JobControlRequest&,
                                                      const Caller&,
                                                      v1::Job*),
                     const std::string& id,
                     v1::Job* job = nullptr) {
    v1::JobControlRequest request;
    request.set_job_id(id);
    v1::Job ignored;
    return (manager.*what)(request, Caller{"test", ""}, job ? job : &ignored);
}

// The job's record as the journal on disk holds it now.
v1::Job recordOnDisk(const std::string& state_dir, const std::string& id) {
    auto journal = Journal::open(state_dir);
    EXPECT_TRUE(journal);
    auto loaded = journal->load();
    EXPECT_TRUE(loaded);
    for (const v1::Job& job : loaded->jobs)
        if (job.id() == id) return job;
    ADD_FAILURE() << "no record of " << id;
    return {};
}

// Every frame of `a` equals the frame of `b` at the same index, bytes included.
void expectSameFrames(const std::string& a, const std::string& b) {
    auto sa = hdr::readSweep(a, strictRead());
    auto sb = hdr::readSweep(b, strictRead());
    ASSERT_TRUE(sa) << sa.error().message;
    ASSERT_TRUE(sb) << sb.error().message;
    ASSERT_EQ(sa->frames.size(), sb->frames.size());
    for (size_t i = 0; i < sa->frames.size(); ++i) {
        EXPECT_EQ(sa->frames[i], sb->frames[i]) << "frame " << i;
        EXPECT_EQ(readText(a + "/" + sa->frames[i].exr_file),
                  readText(b + "/" + sb->frames[i].exr_file))
            << "frame " << i << " differs";
    }
}

// A lens file of `bytes` bytes: the Heliar, then comment lines of characters that protobuf's JSON
// writer escapes to six bytes each ('<', '>', control characters).
std::string escapedLens(size_t bytes) {
    std::string text = readText(flarelab::testing::lensPath("heliar-tronnier.csv"));
    const std::string pattern = "<>\x01\x1f<<>>\x02\x7f";
    while (text.size() < bytes) {
        std::string line = "#";
        while (line.size() < 1000) line += pattern;
        text += line + "\n";
    }
    text.resize(bytes);
    return text;
}

// ---- 1. nothing accepted is lost ----

TEST(Journal, TheLargestLensFullOfEscapedCharactersSurvivesARestart) {
    TempDir dir;
    ManagerOptions options;
    options.resume = false;
    v1::SweepConfig config = simConfig("big-lens", 0.0, 0.0, 0.2);
    const std::string lens =
        escapedLens(static_cast<size_t>(options.runner.limits.max_prescription_bytes));
    config.mutable_sim()->mutable_lens()->set_prescription_csv(lens);
    std::string id;
    {
        Daemon daemon(dir.path, options);
        v1::Job job;
        const grpc::Status started = start(daemon.manager(), config, &job);
        ASSERT_TRUE(started.ok()) << started.error_message();
        id = job.id();
        waitJob(daemon.manager(), id, ended);
    }
    Daemon again(dir.path, options);
    EXPECT_TRUE(again.journal_warnings.empty()) << again.journal_warnings.front();
    const v1::Job record = recordOnDisk(dir.path, id);
    EXPECT_EQ(record.state(), v1::SUCCEEDED);
    EXPECT_EQ(record.config().sim().lens().prescription_csv(), lens);
}

TEST(Journal, ARequestWhoseRecordCouldNotBeReadBackIsRefusedNamingTheField) {
    TempDir dir;
    ManagerOptions options;
    options.runner.limits.max_prescription_bytes = 4 << 20;  // a daemon that allows more
    Daemon daemon(dir.path, options);
    v1::SweepConfig config = simConfig("too-big", 0.0, 0.0, 0.2);
    config.mutable_sim()->mutable_lens()->set_prescription_csv(escapedLens(3 << 20));
    v1::Job job;
    const grpc::Status refused = start(daemon.manager(), config, &job);
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_EQ(refused.error_message().rfind("config.sim.lens.prescription_csv: ", 0), 0u)
        << refused.error_message();
    EXPECT_TRUE(daemon.manager().list().empty());
    EXPECT_TRUE(fs::is_empty(dir.path + "/jobs"));
}

TEST(Capture, AFailureOnTheCaptureSideWritesEveryBracketAlreadyCapturedAndCanBeResumed) {
    TempDir dir;
    ManagerOptions options;
    std::atomic<bool> thrown{false};
    // Processing holds frame 0 while the capture runs ahead and fails at frame 5: frames 1..4
    // wait in the queue when it fails.
    options.runner.before_merge = [](size_t index) {
        if (index == 0) std::this_thread::sleep_for(std::chrono::milliseconds(600));
    };
    options.runner.before_capture = [&](size_t index) {
        if (index == 5 && !thrown.exchange(true)) throw std::bad_alloc();
    };
    Daemon daemon(dir.path, options);
    v1::Job job;
    ASSERT_TRUE(start(daemon.manager(), simConfig("queued", 0.0, 2.0, 0.2), &job).ok());
    const v1::Job failed = waitJob(daemon.manager(), job.id(), ended);
    ASSERT_EQ(failed.state(), v1::FAILED);
    EXPECT_TRUE(contains(failed.reason(), "out of memory")) << failed.reason();
    EXPECT_EQ(failed.frames_done(), 5u);
    EXPECT_TRUE(failed.resumable());
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 5u);
    // Resumed where its sweep ends, it finishes as if it had never failed.
    v1::Job resumed;
    ASSERT_TRUE(control(daemon.manager(), &JobManager::resume, job.id(), &resumed).ok());
    const v1::Job done = waitJob(daemon.manager(), job.id(), ended);
    EXPECT_EQ(done.state(), v1::SUCCEEDED) << done.reason();
    v1::Job reference;
    ASSERT_TRUE(start(daemon.manager(), simConfig("whole", 0.0, 2.0, 0.2), &reference).ok());
    EXPECT_EQ(waitJob(daemon.manager(), reference.id(), ended).state(), v1::SUCCEEDED);
    expectSameFrames(job.output_dir(), reference.output_dir());
}

TEST(Journal, AChangeTheJournalCannotRecordIsRefusedAndAnAcceptedCancelSurvivesARestart) {
    TempDir dir;
    std::string running, queued;
    const auto journal_fails = [&](int error) {
        return FileFaults{
            .write =
                [error](const std::string& path) { return contains(path, "/jobs/") ? error : 0; },
            .fsync = {}};
    };
    {
        Daemon daemon(dir.path);
        v1::Job a, b;
        ASSERT_TRUE(start(daemon.manager(), simConfig("a", 0.0, 4.0, 0.2, false), &a).ok());
        ASSERT_TRUE(start(daemon.manager(), simConfig("b", 0.0, 0.4, 0.2), &b).ok());
        running = a.id();
        queued = b.id();
        waitJob(daemon.manager(), running, [](const v1::Job& j) { return j.frames_done() >= 1; });
        {
            ScopedFileFaults read_only(journal_fails(EROFS));
            const grpc::Status cancel = control(daemon.manager(), &JobManager::cancel, queued);
            EXPECT_EQ(cancel.error_code(), grpc::StatusCode::UNAVAILABLE);
            EXPECT_TRUE(contains(cancel.error_message(), "Read-only file system"))
                << cancel.error_message();
            const grpc::Status pause = control(daemon.manager(), &JobManager::pause, running);
            EXPECT_EQ(pause.error_code(), grpc::StatusCode::UNAVAILABLE);
        }
        for (const v1::Job& j : daemon.manager().list()) {
            if (j.id() == queued) {
                EXPECT_EQ(j.state(), v1::QUEUED);
            }
            if (j.id() == running) {
                EXPECT_EQ(j.state(), v1::RUNNING);
            }
        }
        // Accepted: on disk before the job has even stopped.
        ASSERT_TRUE(control(daemon.manager(), &JobManager::cancel, running).ok());
        EXPECT_EQ(recordOnDisk(dir.path, running).state(), v1::CANCELLED);
        // From here on the disk is full: the job's end and everything after is not recorded.
        ScopedFileFaults full(journal_fails(ENOSPC));
        waitJob(daemon.manager(), running, ended);
        daemon.stop();
    }
    ManagerOptions options;
    options.resume = true;
    Daemon again(dir.path, options);
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    for (const v1::Job& j : again.manager().list()) {
        if (j.id() == running) {
            EXPECT_EQ(j.state(), v1::CANCELLED) << "it would run again";
        }
    }
    EXPECT_NE(again.manager().runningJob(), running);
}

TEST(Journal, AFailedFlushOfTheSweepFailsTheJobForGood) {
    TempDir dir;
    Daemon daemon(dir.path);
    std::atomic<int> log_flushes{0};
    ScopedFileFaults faults({.write = {}, .fsync = [&](const std::string& path) {
                                 // The log's creation, then frames 0, 1, 2: the fourth fails.
                                 if (!contains(path, "/flush/frames.log")) return 0;
                                 return ++log_flushes == 4 ? EIO : 0;
                             }});
    v1::Job job;
    ASSERT_TRUE(start(daemon.manager(), simConfig("flush", 0.0, 2.0, 0.2), &job).ok());
    const v1::Job failed = waitJob(daemon.manager(), job.id(), ended);
    ASSERT_EQ(failed.state(), v1::FAILED);
    EXPECT_TRUE(contains(failed.reason(), "fsync")) << failed.reason();
    EXPECT_FALSE(failed.resumable());
    EXPECT_EQ(log_flushes.load(), 4) << "a failed fsync was retried, or the writer went on";
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_GE(sweep->frames.size(), 2u);  // and frame 2, if its record reached the disk
    const grpc::Status resume = control(daemon.manager(), &JobManager::resume, job.id());
    EXPECT_EQ(resume.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
}

// ---- 7. a real full disk ----

// Fills the file system holding `dir` until a write fails; the file written.
std::string fillUp(const std::string& dir, const std::string& name) {
    const std::string path = dir + "/" + name;
    FileDescriptor fd(::open(path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644));
    const std::string block(4096, 'x');
    while (::write(fd.get(), block.data(), block.size()) > 0) {
    }
    return path;
}

TEST(DiskFull, ASweepOnAFullFileSystemFailsCleanlyAndResumesOnceThereIsRoom) {
    // A tmpfs mounted in a mount namespace of its own: root and unshare(1) are needed; the test
    // binary runs DiskFullInside there.
    if (::geteuid() != 0) GTEST_SKIP() << "needs root, to mount a small tmpfs";
    if (::access("/usr/bin/unshare", X_OK) != 0) GTEST_SKIP() << "needs /usr/bin/unshare";
    TempDir dir;
    const std::string log = dir.path + "/inside.log";
    const std::string env = "FLARELAB_DISK_FULL_DIR=" + dir.path;
    std::vector<std::string> args = {"/usr/bin/unshare",
                                     "--mount",
                                     "--propagation",
                                     "private",
                                     "--",
                                     "/proc/self/exe",
                                     "--gtest_filter=DiskFullInside.*"};
    std::vector<char*> argv, envp;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    for (char** e = environ; *e; ++e) envp.push_back(*e);
    envp.push_back(const_cast<char*>(env.c_str()));
    envp.push_back(nullptr);
    // /proc/self/exe is resolved by unshare: it must name this binary, so pass its real path.
    const std::string self = fs::read_symlink("/proc/self/exe").string();
    argv[5] = const_cast<char*>(self.c_str());
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_addopen(&actions, 1, log.c_str(), O_WRONLY | O_CREAT, 0644);
    posix_spawn_file_actions_adddup2(&actions, 1, 2);
    pid_t pid = -1;
    ASSERT_EQ(posix_spawn(&pid, argv[0], &actions, nullptr, argv.data(), envp.data()), 0);
    posix_spawn_file_actions_destroy(&actions);
    int status = 0;
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(240);
    while (::waitpid(pid, &status, WNOHANG) == 0) {
        if (std::chrono::steady_clock::now() > end) {
            ::kill(pid, SIGKILL);
            ::waitpid(pid, &status, 0);
            FAIL() << "the test in the namespace did not end\n" << readText(log);
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    const std::string output = readText(log);
    if (WIFEXITED(status) && WEXITSTATUS(status) == 1 && contains(output, "unshare: "))
        GTEST_SKIP() << "no mount namespace here: " << output;
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << output;
    EXPECT_TRUE(contains(output, "[  PASSED  ] 1 test")) << output;
}

TEST(DiskFullInside, TheSweepOnATmpfsThatFillsUp) {
    const char* outside = std::getenv("FLARELAB_DISK_FULL_DIR");
    if (!outside) GTEST_SKIP() << "DiskFull.* runs this in a mount namespace of its own";
    const std::string mnt = std::string(outside) + "/fs";
    fs::create_directories(mnt);
    ASSERT_EQ(::mount("flarelab-test", mnt.c_str(), "tmpfs", 0, "size=8m"), 0) << strerror(errno);
    // The state directory (the journal) is on the small file system too.
    const std::string state = mnt + "/state";
    fs::create_directories(state + "/output");
    ManagerOptions options;
    options.runner.min_free_bytes = 0;
    options.runner.free_bytes = [](const std::string&) { return int64_t{-1}; };  // no pre-check
    Daemon daemon(state, options);
    v1::SweepConfig config = simConfig("full", 0.0, 2.0, 0.2);
    config.set_width_px(160);
    config.set_height_px(107);
    // The sweep uninterrupted, first: what it takes on disk sizes the room left below.
    v1::SweepConfig whole = config;
    whole.set_output_dir("whole");
    v1::Job reference;
    ASSERT_TRUE(start(daemon.manager(), whole, &reference).ok());
    ASSERT_EQ(waitJob(daemon.manager(), reference.id(), ended).state(), v1::SUCCEEDED);
    int64_t sweep_bytes = 0;
    for (const auto& f : fs::recursive_directory_iterator(reference.output_dir()))
        if (f.is_regular_file()) sweep_bytes += static_cast<int64_t>(f.file_size());
    // Room for about half of it.
    const std::string ballast = state + "/ballast";
    {
        struct statvfs s {};
        ASSERT_EQ(::statvfs(mnt.c_str(), &s), 0);
        const int64_t free_bytes = static_cast<int64_t>(s.f_bavail) * s.f_frsize;
        FileDescriptor fd(::open(ballast.c_str(), O_WRONLY | O_CREAT, 0644));
        ASSERT_EQ(::posix_fallocate(fd.get(), 0, free_bytes - sweep_bytes / 2), 0);
    }
    v1::Job job;
    ASSERT_TRUE(start(daemon.manager(), config, &job).ok());
    const v1::Job failed = waitJob(daemon.manager(), job.id(), ended);
    ASSERT_EQ(failed.state(), v1::FAILED);
    EXPECT_TRUE(contains(failed.reason(), "No space left on device")) << failed.reason();
    EXPECT_TRUE(failed.resumable());
    EXPECT_GT(failed.frames_done(), 0u);
    EXPECT_LT(failed.frames_done(), 11u);
    // Every frame written before is intact, and nothing half-written is left behind.
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), failed.frames_done());
    for (const std::string& w : sweep->warnings) ADD_FAILURE() << w;
    // Full to the last block: the journal cannot record a new job, which is refused.
    const std::string filler = fillUp(state, "filler");
    v1::Job refused;
    const grpc::Status start_refused =
        start(daemon.manager(), simConfig("more", 0.0, 0.2, 0.2), &refused);
    EXPECT_EQ(start_refused.error_code(), grpc::StatusCode::UNAVAILABLE)
        << start_refused.error_message();
    // Room again: resumed, it ends as the uninterrupted sweep did.
    fs::remove(filler);
    fs::remove(ballast);
    ASSERT_TRUE(control(daemon.manager(), &JobManager::resume, job.id()).ok());
    const v1::Job done = waitJob(daemon.manager(), job.id(), ended);
    EXPECT_EQ(done.state(), v1::SUCCEEDED) << done.reason();
    expectSameFrames(job.output_dir(), reference.output_dir());
    daemon.stop();
    EXPECT_EQ(::umount(mnt.c_str()), 0);
}

// ---- 3. resume touches only its own sweep ----

// A sweep of 3 frames in `dir`/output/NAME, cancelled at a head stall at 0.5 deg.
std::string cutShortSweep(JobManager& manager, const std::string& name) {
    v1::SweepConfig stalled = simConfig(name, 0.0, 1.0, 0.2);
    stalled.mutable_sim()->mutable_faults()->set_head_stall_at_deg(0.5);
    v1::Job job;
    EXPECT_TRUE(start(manager, stalled, &job).ok());
    waitJob(manager, job.id(), [](const v1::Job& j) { return j.state() == v1::PAUSED; });
    EXPECT_TRUE(control(manager, &JobManager::cancel, job.id()).ok());
    waitJob(manager, job.id(), ended);
    return job.output_dir();
}

TEST(Resume, TakesTheSweepsLockAndChecksItsHeaderBeforeMovingAnythingAside) {
    TempDir dir;
    Daemon daemon(dir.path);
    const std::string output = cutShortSweep(daemon.manager(), "locked");
    const std::string stray = output + "/stray.txt";
    std::ofstream(stray) << "not this daemon's";
    v1::SweepConfig more = simConfig("locked", 0.0, 1.0, 0.2);
    more.set_resume_existing(true);
    {
        // Another writer (another flarelab) holds the sweep.
        FileDescriptor lock(::open((output + "/" + hdr::kSweepLockFile).c_str(), O_RDWR));
        ASSERT_EQ(::flock(lock.get(), LOCK_EX | LOCK_NB), 0);
        v1::Job job;
        ASSERT_TRUE(start(daemon.manager(), more, &job).ok());
        const v1::Job refused = waitJob(daemon.manager(), job.id(), ended);
        EXPECT_EQ(refused.state(), v1::FAILED);
        EXPECT_TRUE(contains(refused.reason(), "another sweep writer")) << refused.reason();
        EXPECT_TRUE(fs::exists(stray));
    }
    // Another sweep's settings: refused before anything is moved.
    more.set_gain(2.0);
    v1::Job other;
    ASSERT_TRUE(start(daemon.manager(), more, &other).ok());
    const v1::Job differs = waitJob(daemon.manager(), other.id(), ended);
    EXPECT_EQ(differs.state(), v1::FAILED);
    EXPECT_TRUE(contains(differs.reason(), "differs")) << differs.reason();
    EXPECT_TRUE(fs::exists(stray));
    EXPECT_FALSE(fs::exists(dir.path + "/recovered"));
}

TEST(Resume, OneDirectoryByAnotherNameIsStillTheSameDirectory) {
    TempDir dir;
    Daemon daemon(dir.path);
    fs::create_directories(daemon.output_root + "/real/s");
    fs::create_directory_symlink(daemon.output_root + "/real", daemon.output_root + "/alias");
    v1::Job a, b;
    ASSERT_TRUE(start(daemon.manager(), simConfig("real/s", 0.0, 2.0, 0.2, false), &a).ok());
    const grpc::Status same = start(daemon.manager(), simConfig("alias/s", 0.0, 0.4, 0.2), &b);
    EXPECT_EQ(same.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_TRUE(contains(same.error_message(), a.id())) << same.error_message();
    ASSERT_TRUE(control(daemon.manager(), &JobManager::cancel, a.id()).ok());
}

TEST(Resume, FilesAreSetAsideAcrossFileSystems) {
    if (!fs::exists("/dev/shm")) GTEST_SKIP() << "no tmpfs at /dev/shm";
    // The state directory (where files are set aside) on tmpfs, the sweeps on another file system.
    TempDir sweeps;
    char name[] = "/dev/shm/flarelabd-test-XXXXXX";
    const std::string state = ::mkdtemp(name);
    fs::create_directory_symlink(sweeps.path, state + "/output");
    {
        Daemon daemon(state);
        const std::string output = cutShortSweep(daemon.manager(), "across");
        auto listed = hdr::readSweepManifest(output);
        ASSERT_TRUE(listed);
        const std::string orphan = output + "/" + hdr::sweepFrameFileName(3, 0.6);
        fs::copy_file(output + "/" + listed->frames.back().exr_file, orphan);
        const std::string bytes = readText(orphan);
        v1::SweepConfig more = simConfig("across", 0.0, 1.0, 0.2);
        more.set_resume_existing(true);
        v1::Job job;
        ASSERT_TRUE(start(daemon.manager(), more, &job).ok());
        const v1::Job done = waitJob(daemon.manager(), job.id(), ended);
        EXPECT_EQ(done.state(), v1::SUCCEEDED) << done.reason();
        size_t kept = 0;
        for (const auto& f : fs::recursive_directory_iterator(state + "/recovered/" + job.id()))
            if (f.is_regular_file()) {
                ++kept;
                EXPECT_EQ(readText(f.path().string()), bytes);
            }
        EXPECT_EQ(kept, 1u);
    }
    fs::remove_all(state);
}

// ---- 4. memory bounded by bytes ----

TEST(Memory, ARequestWhoseFramesCannotFitTheBudgetIsRefusedWithTheFigure) {
    TempDir dir;
    ManagerOptions options;
    options.runner.limits.memory_budget_bytes = int64_t{256} << 20;
    Daemon daemon(dir.path, options);
    v1::SweepConfig large = simConfig("large", 0.0, 0.4, 0.2);
    large.set_width_px(4096);
    large.set_height_px(4096);
    v1::Job job;
    const grpc::Status refused = start(daemon.manager(), large, &job);
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    const std::string& m = refused.error_message();
    EXPECT_EQ(m.rfind("config.width_px: 4096 x 4096 frames", 0), 0u) << m;
    EXPECT_TRUE(contains(m, "memory budget of 256 MiB")) << m;
    const JobMemory need = jobMemory(4096, 4096, 2, true);
    EXPECT_TRUE(contains(m, std::to_string((need.minimum_bytes + (1 << 20) - 1) >> 20) + " MiB"))
        << m;
    v1::SweepPlan plan;
    EXPECT_FALSE(daemon.manager().check(large, &plan).ok());
    EXPECT_TRUE(start(daemon.manager(), simConfig("small", 0.0, 0.4, 0.2), &job).ok());
}

TEST(Memory, TheQueueBetweenCaptureAndProcessingIsBoundedInBytes) {
    BoundedQueue<std::vector<char>> queue(100, 1000,
                                          [](const std::vector<char>& v) { return v.size(); });
    std::thread producer([&] {
        for (int i = 0; i < 20; ++i) queue.push(std::vector<char>(300));
        queue.push(std::vector<char>(5000));  // larger than the bound: alone, but it passes
        queue.close();
    });
    size_t items = 0, bytes = 0;
    while (auto item = queue.pop()) {
        ++items;
        bytes += item->size();
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    producer.join();
    EXPECT_EQ(items, 21u);
    EXPECT_EQ(bytes, 20u * 300 + 5000);
    EXPECT_LE(queue.highWater(), 3u);
    EXPECT_LE(queue.highWaterBytes(), 5000u);
}

TEST(Memory, RunningOutOfMemoryFailsTheJobNotTheDaemon) {
    TempDir dir;
    ManagerOptions options;
    std::atomic<bool> thrown{false};
    options.runner.before_merge = [&](size_t index) {
        if (index == 2 && !thrown.exchange(true)) throw std::bad_alloc();
    };
    Daemon daemon(dir.path, options);
    v1::Job job;
    ASSERT_TRUE(start(daemon.manager(), simConfig("oom", 0.0, 1.0, 0.2), &job).ok());
    const v1::Job failed = waitJob(daemon.manager(), job.id(), ended);
    ASSERT_EQ(failed.state(), v1::FAILED);
    EXPECT_TRUE(contains(failed.reason(), "out of memory")) << failed.reason();
    EXPECT_EQ(failed.frames_done(), 2u);
    EXPECT_TRUE(failed.resumable());
    ASSERT_TRUE(control(daemon.manager(), &JobManager::resume, job.id()).ok());
    EXPECT_EQ(waitJob(daemon.manager(), job.id(), ended).state(), v1::SUCCEEDED);
}

TEST(Quarantine, AJobUnderWhichTheDaemonDiesThreeTimesWithoutProgressIsNotResumed) {
    TempDir dir;
    ManagerOptions options;
    options.resume = false;  // the job waits, so that its record can be edited
    std::string id, output;
    {
        Daemon daemon(dir.path, options);
        v1::Job job;
        ASSERT_TRUE(start(daemon.manager(), simConfig("crashing", 0.0, 1.0, 0.2), &job).ok());
        ASSERT_TRUE(control(daemon.manager(), &JobManager::pause, job.id()).ok());
        id = job.id();
        output = job.output_dir();
    }
    auto journal = Journal::open(dir.path);
    ASSERT_TRUE(journal);
    // What the daemon's death leaves: the record says RUNNING. Twice already, nothing on disk.
    const auto died = [&](uint32_t crashes) {
        v1::Job record = recordOnDisk(dir.path, id);
        record.set_state(v1::RUNNING);
        record.set_crashes(crashes);
        auto listed = hdr::readSweepManifest(output);
        record.set_frames_done(listed ? static_cast<uint32_t>(listed->frames.size()) : 0);
        ASSERT_TRUE(journal->save(record));
    };
    died(1);
    {
        Daemon daemon(dir.path, options);
        const v1::Job waiting = waitJob(daemon.manager(), id, [](const v1::Job&) { return true; });
        EXPECT_EQ(waiting.state(), v1::INTERRUPTED);
        EXPECT_EQ(waiting.crashes(), 2u);
    }
    died(2);
    options.resume = true;
    Daemon daemon(dir.path, options);
    const v1::Job quarantined = waitJob(daemon.manager(), id, [](const v1::Job&) { return true; });
    EXPECT_EQ(quarantined.state(), v1::FAILED);
    EXPECT_EQ(quarantined.reason().rfind("quarantined: the daemon died 3 times", 0), 0u)
        << quarantined.reason();
    EXPECT_TRUE(quarantined.resumable());
    EXPECT_EQ(recordOnDisk(dir.path, id).state(), v1::FAILED);
    EXPECT_TRUE(daemon.manager().runningJob().empty());
    // A person who found the cause resumes it by hand.
    ASSERT_TRUE(control(daemon.manager(), &JobManager::resume, id).ok());
    EXPECT_EQ(waitJob(daemon.manager(), id, ended).state(), v1::SUCCEEDED);
}

TEST(Quarantine, ADeathAfterProgressStartsTheCountAgain) {
    TempDir dir;
    ManagerOptions options;
    options.resume = false;
    std::string id;
    {
        Daemon daemon(dir.path, options);
        v1::Job job;
        ASSERT_TRUE(
            start(daemon.manager(), simConfig("progress", 0.0, 1.0, 0.2, false), &job).ok());
        id = job.id();
        waitJob(daemon.manager(), id, [](const v1::Job& j) { return j.frames_done() >= 2; });
    }
    v1::Job record = recordOnDisk(dir.path, id);
    record.set_state(v1::RUNNING);
    record.set_crashes(2);
    record.set_frames_done(0);  // the record lags the sweep on disk: the job got further
    auto journal = Journal::open(dir.path);
    ASSERT_TRUE(journal->save(record));
    Daemon daemon(dir.path, options);
    const v1::Job waiting = waitJob(daemon.manager(), id, [](const v1::Job&) { return true; });
    EXPECT_EQ(waiting.state(), v1::INTERRUPTED);
    EXPECT_EQ(waiting.crashes(), 1u);
    EXPECT_GE(waiting.frames_done(), 2u);
}

// ---- 7. hostile files ----

TEST(HostileFiles, JournalRecordsThatAreNotRegularFilesAreSetAsideWithoutBlocking) {
    TempDir dir;
    std::string id;
    {
        Daemon daemon(dir.path);
        v1::Job job;
        ASSERT_TRUE(start(daemon.manager(), simConfig("kept", 0.0, 0.2, 0.2), &job).ok());
        id = job.id();
        waitJob(daemon.manager(), id, ended);
    }
    const std::string jobs = dir.path + "/jobs/";
    ASSERT_EQ(::mkfifo((jobs + "job-000007.json").c_str(), 0644), 0);
    fs::create_symlink(jobs + id + ".json", jobs + "job-000008.json");
    std::ofstream(jobs + "job-000009.json").close();
    ASSERT_EQ(::truncate((jobs + "job-000009.json").c_str(), kJournalMaxRecordBytes + 1), 0);
    size_t expected = 3;
    if (::geteuid() == 0) {
        ASSERT_EQ(::mknod((jobs + "job-000010.json").c_str(), S_IFCHR | 0644, makedev(1, 5)), 0);
        ++expected;
    }
    auto opened = std::async(std::launch::async, [&] {
        std::vector<std::string> warnings;
        ManagerOptions options;
        options.runner.state_dir = dir.path;
        options.runner.output_root = fs::canonical(dir.path + "/output").string();
        auto manager = JobManager::open(options, &warnings);
        EXPECT_TRUE(manager);
        return warnings;
    });
    if (opened.wait_for(std::chrono::seconds(20)) != std::future_status::ready) {
        ADD_FAILURE() << "opening the journal blocked";
        ::close(::open((jobs + "job-000007.json").c_str(), O_WRONLY | O_NONBLOCK));
    }
    const std::vector<std::string> warnings = opened.get();
    EXPECT_EQ(warnings.size(), expected);
    for (const char* n : {"07", "08", "09"})
        EXPECT_TRUE(fs::exists(jobs + "job-0000" + n + ".json.corrupt")) << n;
    EXPECT_TRUE(fs::exists(jobs + id + ".json"));
}

TEST(HostileFiles, AResumeOntoASweepWithAFifoForItsLogOrLockFailsAtOnce) {
    TempDir dir;
    Daemon daemon(dir.path);
    const std::string output = cutShortSweep(daemon.manager(), "fifo");
    for (const char* name : {hdr::kSweepLockFile, hdr::kSweepManifestFile}) {
        const std::string path = output + "/" + name;
        const std::string kept = dir.path + "/kept";
        fs::rename(path, kept);
        ASSERT_EQ(::mkfifo(path.c_str(), 0644), 0);
        v1::SweepConfig more = simConfig("fifo", 0.0, 1.0, 0.2);
        more.set_resume_existing(true);
        v1::Job job;
        const grpc::Status started = start(daemon.manager(), more, &job);
        if (started.ok()) {
            const v1::Job failed = waitJob(daemon.manager(), job.id(), ended, 30);
            EXPECT_EQ(failed.state(), v1::FAILED);
            EXPECT_TRUE(contains(failed.reason(), name)) << failed.reason();
        } else {
            EXPECT_TRUE(contains(started.error_message(), name)) << started.error_message();
        }
        ::close(::open(path.c_str(), O_WRONLY | O_NONBLOCK));  // frees a reader, if one blocked
        fs::remove(path);
        fs::rename(kept, path);
    }
}

}  // namespace
}  // namespace flarelab::daemon
