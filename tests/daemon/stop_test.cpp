// Stop means stop: a cancel or a SIGTERM ends a job within moments even during a 30 s exposure or
// a long head move (the real-time simulated rig), a second SIGTERM drops the captured frames not
// yet written (nothing on disk is lost, and the job takes them again), and the head's stop hook
// ends with its job.
#include <gtest/gtest.h>

#include <set>

#include "daemon/journal.h"
#include "daemon/sweep_runner.h"
#include "tests/daemon/daemon_process.h"

namespace flarelab::daemon {
namespace {

using namespace testing;
using Clock = std::chrono::steady_clock;

double since(Clock::time_point t) {
    return std::chrono::duration<double>(Clock::now() - t).count();
}

// One frame of one 30 s exposure, in real time.
v1::SweepConfig longExposure(const std::string& output) {
    v1::SweepConfig c = simConfig(output, 0.0, 0.0, 0.2, false);
    c.clear_exposure_times_s();
    c.add_exposure_times_s(30.0);
    return c;
}

v1::Job recordOf(const std::string& state_dir, const std::string& id) {
    auto journal = Journal::open(state_dir);
    EXPECT_TRUE(journal);
    auto loaded = journal->load();
    EXPECT_TRUE(loaded);
    for (const v1::Job& j : loaded->jobs)
        if (j.id() == id) return j;
    ADD_FAILURE() << "no record of " << id;
    return {};
}

TEST(Stop, ACancelDuringA30SecondExposureEndsTheJobAtOnce) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, longExposure("long"), &job).ok());
    std::vector<v1::JobEvent> events;
    std::thread watcher([&] { events = watchToEnd(*daemon.stub(), job.id(), "watcher", 90.0); });
    waitFor(*stub, job.id(), [](const v1::Job& j) { return j.phase() == v1::CAPTURE; });
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // well into the exposure
    const auto cancelled_at = Clock::now();
    v1::JobControlRequest request;
    request.set_job_id(job.id());
    v1::Job answer;
    auto ctx = context();
    ASSERT_TRUE(stub->CancelJob(ctx.get(), request, &answer).ok());
    // 20 s: less than the exposure left, so that only a stopped exposure gets there.
    const v1::Job last = waitFor(*stub, job.id(), ended, 20.0);
    std::printf("cancelled job ended %.2f s after the cancel\n", since(cancelled_at));
    EXPECT_EQ(last.state(), v1::CANCELLED) << last.reason();
    watcher.join();
    int exposures = 0;
    for (const auto& e : events) exposures += e.kind() == v1::EXPOSURE;
    EXPECT_EQ(exposures, 0) << "the 30 s exposure ran to its end";
    EXPECT_EQ(last.frames_done(), 0u);
}

TEST(Stop, ASigtermDuringA30SecondExposureStopsTheDaemonAtOnceAndTheJobIsResumedLater) {
    TempDir dir;
    const std::string state = privateStateDir(dir.path), log = dir.path + "/flarelabd.log";
    FlarelabdProcess daemon({"--state-dir", state}, log);
    auto stub = connectWhenUp(state + "/flarelabd.sock");
    ASSERT_TRUE(stub) << readText(log);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, longExposure("long"), &job).ok());
    waitFor(*stub, job.id(), [](const v1::Job& j) { return j.phase() == v1::CAPTURE; });
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    const auto signalled = Clock::now();
    ::kill(daemon.pid, SIGTERM);
    const auto status = daemon.waitExit(20.0);
    std::printf("flarelabd exited %.2f s after SIGTERM\n", since(signalled));
    ASSERT_TRUE(status) << "flarelabd still waits for its exposure\n" << readText(log);
    EXPECT_TRUE(exitedWith(status, 0)) << readText(log);
    const v1::Job record = recordOf(state, job.id());
    EXPECT_EQ(record.state(), v1::INTERRUPTED) << record.reason();
    EXPECT_EQ(record.frames_done(), 0u);
    EXPECT_NE(readText(log).find("event=sweep.rig_stopping"), std::string::npos);
}

TEST(Stop, ASecondStopDropsTheCapturedFramesNotYetWrittenAndTheResumedJobTakesThemAgain) {
    TempDir dir;
    ManagerOptions slow;
    // A slow disk: every frame's write waits 2 s, so that captured frames wait in the queue (in a
    // ThreadSanitizer build too, where the simulated camera renders several times slower).
    slow.runner.free_bytes = [](const std::string&) {
        std::this_thread::sleep_for(std::chrono::milliseconds(2000));
        return int64_t{1} << 40;
    };
    std::string id, output;
    {
        Daemon daemon(dir.path, slow);
        auto stub = daemon.stub();
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, simConfig("hurried", 0.0, 3.0, 0.2), &job).ok());
        id = job.id();
        output = job.output_dir();
        // Frame 3 captured whole while at most one frame is on disk: two or more are queued.
        auto ctx = context("watcher", 60.0);
        v1::WatchJobRequest watch;
        watch.set_job_id(id);
        auto reader = stub->WatchJob(ctx.get(), watch);
        bool queued = false;
        for (v1::JobEvent e; !queued && reader->Read(&e);)
            queued = e.kind() == v1::EXPOSURE && e.frame_index() >= 3 && e.bracket_index() == 1 &&
                     e.job().frames_done() <= 1;
        ctx->TryCancel();
        (void)reader->Finish();
        ASSERT_TRUE(queued) << "the capture did not get ahead of the slow disk";
        daemon.manager().stopNow();  // the second signal...
        daemon.stop();               // ...and the first one's stop, which it hurries
    }
    const v1::Job record = recordOf(dir.path, id);
    EXPECT_EQ(record.state(), v1::INTERRUPTED);
    bool told = false;
    for (const auto& w : record.warnings()) told |= w.find("not written") != std::string::npos;
    EXPECT_TRUE(told) << "no captured frame was dropped: " << record.DebugString();
    auto partial = hdr::readSweep(output, strictRead());
    ASSERT_TRUE(partial) << partial.error().message;
    EXPECT_LT(partial->frames.size(), 16u);
    // Nothing on disk was lost: the resumed job finishes the sweep, every angle once.
    Daemon again(dir.path);
    auto stub = again.stub();
    const v1::Job last = waitFor(*stub, id, ended, 120.0);
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    auto whole = hdr::readSweep(output, strictRead());
    ASSERT_TRUE(whole) << whole.error().message;
    ASSERT_EQ(whole->frames.size(), 16u);
    std::set<double> angles;
    for (const auto& f : whole->frames) EXPECT_TRUE(angles.insert(f.angle_deg).second);
}

// A job's control, driven directly: it stops the job right after a checkpoint of the capture
// passed, and records the stop hook's life.
class StoppingControl final : public JobControl {
public:
    bool checkpoint() override {
        std::lock_guard lock(mutex_);
        if (phase_ == v1::CAPTURE && stop_after_checkpoint_) {
            stop_after_checkpoint_ = false;
            stopLocked();
            return true;  // the stop comes just after the checkpoint let the move go
        }
        return !stop_;
    }
    bool pauseForFault(const std::string& reason) override {
        ADD_FAILURE() << "paused: " << reason;
        return false;
    }
    const std::atomic<bool>& stopFlag() const override { return stop_; }
    void setStopHook(std::function<void()> hook) override {
        std::lock_guard lock(mutex_);
        hook_ = std::move(hook);
        if (hook_) hook_was_set_ = true;
        if (hook_ && stop_) hook_();
    }
    void setPhase(v1::JobPhase phase) override {
        std::lock_guard lock(mutex_);
        phase_ = phase;
    }
    void setFramesDone(uint32_t) override {}
    void warning(const std::string&) override {}
    void event(v1::JobEvent e) override { exposures_ += e.kind() == v1::EXPOSURE; }

    void stop() {
        std::lock_guard lock(mutex_);
        stopLocked();
    }
    bool hookSet() {
        std::lock_guard lock(mutex_);
        return static_cast<bool>(hook_);
    }
    bool stop_after_checkpoint_ = false;
    bool hook_was_set_ = false;
    std::atomic<int> exposures_{0};

private:
    void stopLocked() {
        stop_ = true;
        if (hook_) hook_();
    }
    std::mutex mutex_;
    std::atomic<bool> stop_{false};
    std::function<void()> hook_;
    v1::JobPhase phase_ = v1::JOB_PHASE_UNSPECIFIED;
};

RunnerOptions runnerIn(const std::string& dir) {
    fs::create_directories(dir + "/output");
    RunnerOptions o;
    o.state_dir = dir;
    o.output_root = fs::canonical(dir + "/output").string();
    return o;
}

TEST(Stop, AStopBetweenTheCheckpointAndALongMoveStopsTheMove) {
    TempDir dir;
    const RunnerOptions options = runnerIn(dir.path);
    v1::Job job;
    job.set_id("job-000001");
    // One frame at 60 degrees: a move of 3 s from home, in real time.
    *job.mutable_config() = simConfig("far", 60.0, 60.0, 0.2, false);
    StoppingControl control;
    control.stop_after_checkpoint_ = true;
    const auto start = Clock::now();
    const RunResult result = runSweepJob(job, options, control);
    std::printf("stopped %.2f s after the start of a 3 s move\n", since(start));
    EXPECT_EQ(result.outcome, RunOutcome::Stopped) << result.reason;
    EXPECT_EQ(control.exposures_.load(), 0) << "the move ran to its end and the frame was taken";
    EXPECT_EQ(result.frames_on_disk, 0u);
}

TEST(Stop, TheStopHookEndsWithItsJobAndIsNeverCalledOnItsDevicesAfter) {
    TempDir dir;
    const RunnerOptions options = runnerIn(dir.path);
    v1::Job job;
    job.set_id("job-000001");
    *job.mutable_config() = simConfig("short", 0.0, 0.4, 0.2);
    StoppingControl control;
    const RunResult result = runSweepJob(job, options, control);
    EXPECT_EQ(result.outcome, RunOutcome::Succeeded) << result.reason;
    EXPECT_TRUE(control.hook_was_set_);
    EXPECT_FALSE(control.hookSet()) << "a finished job's devices can still be stopped";
    control.stop();  // a cancel that comes later (during a fit) touches no device
}

}  // namespace
}  // namespace flarelab::daemon
