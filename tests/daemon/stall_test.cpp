// One slow thing does not freeze everything: a journal write that hangs holds no lock (calls are
// answered, the rig goes on, and nothing is announced before it is on disk), a FIFO or a link in a
// product's place is refused rather than waited on, and a standard error nobody reads (a stalled
// log pipe) neither blocks the daemon nor its job.
#include <gtest/gtest.h>
#include <sys/stat.h>

#include <condition_variable>
#include <mutex>

#include "daemon/journal.h"
#include "daemon/log.h"
#include "tests/daemon/daemon_process.h"

namespace flarelab::daemon {
namespace {

using namespace testing;

// A gate the journal's writes wait at while it is closed.
struct Gate {
    std::mutex mutex;
    std::condition_variable cv;
    bool closed = false;
    int waiting = 0;
    void pass() {
        std::unique_lock lock(mutex);
        ++waiting;
        cv.notify_all();
        // Bounded: a test that fails never leaves the daemon hanging.
        cv.wait_for(lock, std::chrono::seconds(60), [&] { return !closed; });
        --waiting;
    }
    void close() {
        std::lock_guard lock(mutex);
        closed = true;
    }
    void open() {
        {
            std::lock_guard lock(mutex);
            closed = false;
        }
        cv.notify_all();
    }
    bool someoneWaits(double deadline_s) {
        std::unique_lock lock(mutex);
        return cv.wait_for(lock, std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3)),
                           [&] { return waiting > 0; });
    }
};

TEST(Stall, AJournalWriteThatHangsHoldsNoLockTheRigGoesOnAndNothingIsAnnouncedEarly) {
    TempDir dir;
    auto gate = std::make_shared<Gate>();
    ManagerOptions options;
    options.before_journal_write = [gate](const std::string&) { gate->pass(); };
    Daemon daemon(dir.path, options);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("stalled", 0.0, 6.0, 0.2), &job).ok());
    waitFor(*stub, job.id(), [](const v1::Job& j) { return j.phase() == v1::CAPTURE; });
    gate->close();
    // The next record (every 16 frames, and the job's end) hangs on the "disk".
    ASSERT_TRUE(gate->someoneWaits(60.0)) << "no journal write came";
    // Meanwhile calls are answered and the rig goes on to the sweep's end.
    // (Up to 60 s: a sanitizer build renders the simulated frames several times slower.)
    // The frame count is told only after the manifest naming the frame is written, so both are
    // waited for: the last frame can be on disk a moment before it is counted.
    constexpr size_t kFrames = 31;  // 0 to 6 deg in 0.2 deg steps
    const auto counted = [&] {
        v1::ListJobsResponse jobs;
        auto ctx = context("lister", 5.0);
        if (!stub->ListJobs(ctx.get(), {}, &jobs).ok() || jobs.jobs_size() != 1) return false;
        return jobs.jobs(0).frames_done() == kFrames;
    };
    const auto written = [&] {
        const auto manifest = hdr::readSweepManifest(job.output_dir());
        return manifest && manifest->frames.size() == kFrames;
    };
    for (int i = 0; i < 1200 && !(written() && counted()); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    auto manifest = hdr::readSweepManifest(job.output_dir());
    ASSERT_TRUE(manifest);
    EXPECT_EQ(manifest->frames.size(), 31u) << "the capture waited on the journal";
    v1::ListJobsResponse list;
    auto ctx = context("lister", 5.0);
    ASSERT_TRUE(stub->ListJobs(ctx.get(), {}, &list).ok());
    ASSERT_EQ(list.jobs_size(), 1);
    // Its end is not on disk yet, so it is not told.
    EXPECT_EQ(list.jobs(0).state(), v1::RUNNING);
    EXPECT_EQ(list.jobs(0).frames_done(), 31u);
    v1::JobResult result;
    auto rctx = context("reader", 5.0);
    v1::GetJobResultRequest get;
    get.set_job_id(job.id());
    EXPECT_TRUE(stub->GetJobResult(rctx.get(), get, &result).ok());
    // A watcher sees the state on disk first, and the end only once it is written.
    auto wctx = context("watcher", 30.0);
    v1::WatchJobRequest watch;
    watch.set_job_id(job.id());
    auto reader = stub->WatchJob(wctx.get(), watch);
    v1::JobEvent first;
    ASSERT_TRUE(reader->Read(&first));
    EXPECT_EQ(first.job().state(), v1::RUNNING);
    gate->open();
    v1::JobEvent e, last;
    while (reader->Read(&e)) last = e;
    EXPECT_TRUE(reader->Finish().ok());
    EXPECT_EQ(last.job().state(), v1::SUCCEEDED);
    auto journal = Journal::open(dir.path);
    ASSERT_TRUE(journal);
    auto loaded = journal->load();
    ASSERT_TRUE(loaded);
    ASSERT_EQ(loaded->jobs.size(), 1u);
    EXPECT_EQ(loaded->jobs[0].state(), v1::SUCCEEDED);
}

// A job that ended fitted, as the journal has it, with its products in `dir`.
void fittedJob(const std::string& state_dir, const std::string& dir) {
    fs::create_directories(dir);
    std::ofstream(dir + "/model.flm") << "model";
    v1::Job job;
    job.set_id("job-000001");
    job.set_state(v1::SUCCEEDED);
    job.set_phase(v1::FINISHED);
    job.set_output_dir(dir);
    job.set_model_file(dir + "/model.flm");
    job.set_updated_unix_s(
        std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count());
    auto journal = Journal::open(state_dir);
    ASSERT_TRUE(journal);
    ASSERT_TRUE(journal->save(job));
}

TEST(Stall, AFifoOrALinkNamedLikeAProductIsRefusedNotWaitedOn) {
    TempDir dir;
    const std::string sweep = dir.path + "/output/fitted";
    ASSERT_NO_FATAL_FAILURE(fittedJob(dir.path, sweep));
    const std::string text = sweep + "/" + hdr::kSweepModelText;
    ASSERT_EQ(::mkfifo(text.c_str(), 0644), 0);
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::GetJobResultRequest get;
    get.set_job_id("job-000001");
    v1::JobResult result;
    auto ctx = context("reader", 5.0);
    const grpc::Status status = stub->GetJobResult(ctx.get(), get, &result);
    if (!status.ok()) {
        // Blocked in open(): let the reader go, so that the daemon can stop.
        const int unblock = ::open(text.c_str(), O_WRONLY | O_NONBLOCK);
        if (unblock >= 0) ::close(unblock);
    }
    ASSERT_TRUE(status.ok()) << "GetJobResult waited on a FIFO: " << status.error_message();
    EXPECT_EQ(result.model_summary(), "");
    ASSERT_EQ(result.warnings_size(), 1);
    EXPECT_NE(result.warnings(0).find("not a regular file"), std::string::npos)
        << result.warnings(0);
    // Other calls were never held up by it.
    v1::ListJobsResponse list;
    auto lctx = context("lister", 5.0);
    EXPECT_TRUE(stub->ListJobs(lctx.get(), {}, &list).ok());

    // A link to another file is not followed, and an oversized description is not read.
    fs::remove(text);
    std::ofstream(dir.path + "/elsewhere.txt") << "someone else's";
    fs::create_symlink(dir.path + "/elsewhere.txt", text);
    result.Clear();
    auto again = context("reader", 5.0);
    ASSERT_TRUE(stub->GetJobResult(again.get(), get, &result).ok());
    EXPECT_EQ(result.model_summary(), "");
    ASSERT_EQ(result.warnings_size(), 1);
    EXPECT_NE(result.warnings(0).find("symbolic link"), std::string::npos) << result.warnings(0);
    fs::remove(text);
    std::ofstream(text) << std::string((1 << 20) + 1, 'x');
    result.Clear();
    auto big = context("reader", 5.0);
    ASSERT_TRUE(stub->GetJobResult(big.get(), get, &result).ok());
    EXPECT_EQ(result.model_summary(), "");
    ASSERT_EQ(result.warnings_size(), 1);
    EXPECT_NE(result.warnings(0).find("more than"), std::string::npos) << result.warnings(0);
    fs::remove(text);
    std::ofstream(text) << "fitted: 12 ghosts";
    result.Clear();
    auto good = context("reader", 5.0);
    ASSERT_TRUE(stub->GetJobResult(good.get(), get, &result).ok());
    EXPECT_EQ(result.model_summary(), "fitted: 12 ghosts");
    EXPECT_EQ(result.warnings_size(), 0);
}

// Standard error replaced by a pipe of `size` bytes that the test fills, for one test.
class FullStderr {
public:
    FullStderr() {
        int fds[2];
        EXPECT_EQ(::pipe2(fds, O_CLOEXEC), 0);
        read_ = fds[0];
        write_ = fds[1];
        ::fcntl(write_, F_SETPIPE_SZ, 4096);
        const int flags = ::fcntl(write_, F_GETFL);
        ::fcntl(write_, F_SETFL, flags | O_NONBLOCK);
        const std::string fill(4096, '.');
        while (::write(write_, fill.data(), fill.size()) > 0) {
        }
        ::fcntl(write_, F_SETFL, flags);
    }
    ~FullStderr() {
        ::close(read_);
        ::close(write_);
    }
    // Everything in the pipe until `until` shows up or the deadline passes.
    std::string drain(const std::string& until, double deadline_s) {
        const int flags = ::fcntl(read_, F_GETFL);
        ::fcntl(read_, F_SETFL, flags | O_NONBLOCK);
        std::string text;
        const auto end = std::chrono::steady_clock::now() +
                         std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3));
        char buffer[4096];
        while (std::chrono::steady_clock::now() < end) {
            const ssize_t n = ::read(read_, buffer, sizeof buffer);
            if (n > 0) {
                text.append(buffer, static_cast<size_t>(n));
                if (!until.empty() && text.find(until) != std::string::npos) break;
            } else {
                std::this_thread::sleep_for(std::chrono::milliseconds(10));
            }
        }
        return text;
    }
    int writeEnd() const { return write_; }

private:
    int read_ = -1, write_ = -1;
};

TEST(Stall, AStalledLogPipeStopsNeitherTheDaemonNorItsJob) {
    TempDir dir;
    const std::string state = privateStateDir(dir.path);
    FullStderr stderr_pipe;  // full before the daemon writes its first line
    FlarelabdProcess daemon({"--state-dir", state, "--log-level", "debug"}, "", {},
                            stderr_pipe.writeEnd());
    auto stub = connectWhenUp(state + "/flarelabd.sock", 30.0);
    ASSERT_TRUE(stub) << "the daemon did not come up with its standard error stalled";
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("logged", 0.0, 2.0, 0.2), &job).ok());
    const v1::Job last = waitFor(*stub, job.id(), ended, 60.0);
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    // Once someone reads again, the lines come, and so does the count of those dropped.
    ::kill(daemon.pid, SIGTERM);
    const std::string text = stderr_pipe.drain("event=daemon.stopped", 30.0);
    EXPECT_TRUE(exitedWith(daemon.waitExit(30.0), 0));
    EXPECT_NE(text.find("event=job.start"), std::string::npos) << text.substr(0, 2000);
    EXPECT_NE(text.find("event=daemon.stopped"), std::string::npos);
}

// Standard error of this test process replaced for a while by `fd`.
class StderrRedirect {
public:
    explicit StderrRedirect(int fd) : saved_(::dup(2)) { ::dup2(fd, 2); }
    ~StderrRedirect() {
        ::dup2(saved_, 2);
        ::close(saved_);
    }

private:
    int saved_;
};

TEST(Log, LinesForAStalledStderrAreDroppedAndCountedNeverWaitedOn) {
    FullStderr full;
    StderrRedirect redirect(full.writeEnd());
    std::atomic<bool> done{false};
    std::thread logger([&] {
        for (int i = 0; i < 20000; ++i)
            logEvent(LogLevel::Info, "test.line", {{"i", std::to_string(i)}});
        done = true;
    });
    for (int i = 0; i < 500 && !done; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    const bool finished = done.load();
    // Someone reads from here on, so that the test ends whatever happened.
    std::string text;
    std::atomic<bool> reading{true};
    std::thread reader([&] {
        while (reading) text += full.drain("", 0.05);
        text += full.drain("", 0.05);
    });
    logger.join();
    EXPECT_TRUE(finished) << "logEvent waited on a stalled standard error";
    EXPECT_GT(droppedLogLines(), 0u);
    EXPECT_TRUE(flushLog(10.0));
    reading = false;
    reader.join();
    EXPECT_NE(text.find("event=log.dropped lines="), std::string::npos);
    EXPECT_NE(text.find("ts="), std::string::npos);
}

TEST(Log, UnderSystemdEachLineCarriesItsPriorityForTheJournal) {
    int fds[2];
    ASSERT_EQ(::pipe2(fds, O_CLOEXEC), 0);
    {
        StderrRedirect redirect(fds[1]);
        struct stat info {};
        ASSERT_EQ(::fstat(2, &info), 0);
        const std::string stream = std::to_string(info.st_dev) + ":" + std::to_string(info.st_ino);
        ::setenv("JOURNAL_STREAM", stream.c_str(), 1);
        EXPECT_EQ(detectLogTarget(), LogTarget::Journal);
        ::setenv("JOURNAL_STREAM", "1:2", 1);
        EXPECT_EQ(detectLogTarget(), LogTarget::Terminal);  // inherited; stderr is another file
        ::unsetenv("JOURNAL_STREAM");
        EXPECT_EQ(detectLogTarget(), LogTarget::Terminal);
        setLogTarget(LogTarget::Journal);
        logEvent(LogLevel::Warn, "test.journal", {{"x", "1"}});
        logEvent(LogLevel::Info, "test.journal", {{"x", "2"}});
        setLogTarget(LogTarget::Terminal);
        logEvent(LogLevel::Info, "test.terminal");
        EXPECT_TRUE(flushLog(10.0));
    }
    ::close(fds[1]);
    std::string text;
    char buffer[4096];
    for (ssize_t n; (n = ::read(fds[0], buffer, sizeof buffer)) > 0;)
        text.append(buffer, static_cast<size_t>(n));
    ::close(fds[0]);
    EXPECT_NE(text.find("<4>level=warning event=test.journal x=1\n"), std::string::npos) << text;
    EXPECT_NE(text.find("<6>level=info event=test.journal x=2\n"), std::string::npos) << text;
    EXPECT_NE(text.find("Z level=info event=test.terminal\n"), std::string::npos) << text;
}

}  // namespace
}  // namespace flarelab::daemon
