// Journal and resume: a daemon stopped, killed with SIGKILL or restarted mid-sweep picks its job
// up where the sweep on disk ends, and the sweep it finishes equals an uninterrupted one.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>

#include "daemon/journal.h"
#include "daemon/sweep_config.h"
#include "fit/model_file.h"
#include "hdr/digest.h"
#include "hdr/sweep.h"
#include "tests/daemon/daemon_fixture.h"

extern char** environ;

namespace flarelab::daemon {
namespace {

using namespace testing;

// The journal of the state directory `dir` holds one job record: `record`.
void readOnlyRecord(const std::string& dir, v1::Job* record) {
    auto journal = Journal::open(dir);
    ASSERT_TRUE(journal);
    auto loaded = journal->load();
    ASSERT_TRUE(loaded);
    ASSERT_EQ(loaded->jobs.size(), 1u);
    *record = loaded->jobs[0];
}

// Every frame of `a` equals the frame of `b` at the same index: angle, file name, bracket
// statistics and the EXR's bytes.
void expectSameSweep(const std::string& a, const std::string& b) {
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
    std::set<double> angles;
    for (const auto& f : sa->frames) EXPECT_TRUE(angles.insert(f.angle_deg).second);
}

TEST(Resume, AStoppedDaemonInterruptsItsJobAndTheNextOneFinishesItIdentically) {
    TempDir dir;
    std::string job_id, output;
    {
        Daemon daemon(dir.path);
        auto stub = daemon.stub();
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, simConfig("resumed", 0.0, 2.0, 0.2, false), &job).ok());
        job_id = job.id();
        output = job.output_dir();
        waitFor(*stub, job.id(), [](const v1::Job& j) { return j.frames_done() >= 3; });
        daemon.stop();
    }
    v1::Job record;
    ASSERT_NO_FATAL_FAILURE(readOnlyRecord(dir.path, &record));
    EXPECT_EQ(record.state(), v1::INTERRUPTED);
    auto partial = hdr::readSweepManifest(output);
    ASSERT_TRUE(partial);
    EXPECT_GE(partial->frames.size(), 3u);
    EXPECT_LT(partial->frames.size(), 11u);

    Daemon again(dir.path);
    auto stub = again.stub();
    const v1::Job last = waitFor(*stub, job_id, ended);
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    EXPECT_EQ(last.restarts(), 1u);
    bool told = false;
    for (const auto& w : last.warnings()) told |= w.find("resuming at frame") != std::string::npos;
    EXPECT_TRUE(told);
    // The same sweep, uninterrupted, in simulated time.
    v1::Job reference;
    ASSERT_TRUE(startSweep(*stub, simConfig("reference", 0.0, 2.0, 0.2, true), &reference).ok());
    EXPECT_EQ(waitFor(*stub, reference.id(), ended).state(), v1::SUCCEEDED);
    expectSameSweep(output, reference.output_dir());
}

TEST(Resume, APlannedBracketIsKeptOnResumeAndTheSweepEqualsAnUninterruptedOne) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig c = simConfig("whole", 0.0, 1.0, 0.2, true);
    c.clear_exposure_times_s();  // planned at the first angle
    v1::Job whole;
    ASSERT_TRUE(startSweep(*stub, c, &whole).ok());
    const v1::Job done = waitFor(*stub, whole.id(), ended);
    ASSERT_EQ(done.state(), v1::SUCCEEDED) << done.reason();
    bool planned = false;
    for (const auto& w : done.warnings()) planned |= w.rfind("bracket: ", 0) == 0;
    EXPECT_TRUE(planned) << "the plan's reasons reach the job's warnings";
    auto sweep = hdr::readSweepManifest(done.output_dir());
    ASSERT_TRUE(sweep);
    const std::vector<double> bracket = sweep->header.capture.exposure_times_s;
    ASSERT_GE(bracket.size(), 2u);

    // The same sweep cut after 2 frames, as a crash leaves it, then resumed by a job that gives no
    // bracket: it takes the sweep's own, and the frames it adds equal the uninterrupted ones (the
    // probes do not shift the camera's frame sequence).
    const std::string cut = daemon.output_root + "/cut";
    fs::create_directories(cut);
    hdr::Sweep partial = *sweep;
    partial.frames.resize(2);
    for (const hdr::SweepFrame& f : partial.frames)
        fs::copy_file(done.output_dir() + "/" + f.exr_file, cut + "/" + f.exr_file);
    auto text = hdr::formatSweepManifest(partial);
    ASSERT_TRUE(text);
    std::ofstream(cut + "/" + hdr::kSweepManifestFile) << *text;
    c.set_output_dir("cut");
    c.set_resume_existing(true);
    v1::Job resumed;
    ASSERT_TRUE(startSweep(*stub, c, &resumed).ok());
    const v1::Job finished = waitFor(*stub, resumed.id(), ended);
    ASSERT_EQ(finished.state(), v1::SUCCEEDED) << finished.reason();
    for (const auto& w : finished.warnings()) EXPECT_NE(w.rfind("bracket: ", 0), 0u) << w;
    auto again = hdr::readSweepManifest(cut);
    ASSERT_TRUE(again);
    EXPECT_EQ(again->header.capture.exposure_times_s, bracket);
    expectSameSweep(cut, done.output_dir());
}

TEST(Resume, ADaemonStoppedDuringAFitFitsAgainAtItsNextStart) {
    TempDir dir;
    std::string job_id, output;
    {
        Daemon daemon(dir.path);
        auto stub = daemon.stub();
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, fitConfig("fit-stopped", 3.0), &job).ok());
        job_id = job.id();
        output = job.output_dir();
        const v1::Job fitting = waitFor(*stub, job.id(), fittingOrEnded);
        ASSERT_EQ(fitting.phase(), v1::FITTING);
        daemon.stop();
    }
    v1::Job record;
    ASSERT_NO_FATAL_FAILURE(readOnlyRecord(dir.path, &record));
    EXPECT_EQ(record.state(), v1::INTERRUPTED);
    EXPECT_EQ(record.phase(), v1::FITTING);
    EXPECT_FALSE(fs::exists(output + "/model.flm"));

    Daemon again(dir.path);
    auto stub = again.stub();
    const v1::Job last = waitFor(*stub, job_id, ended, 300);
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    EXPECT_EQ(last.frames_done(), 16u);
    EXPECT_TRUE(fs::exists(output + "/model.flm"));
    auto sweep = hdr::readSweep(output, strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 16u);
    // The sweep and the model record the prescription's digest: the file's, whose text the client
    // sent.
    auto digest = hdr::sha256File(flarelab::testing::lensPath("heliar-tronnier.csv"));
    ASSERT_TRUE(digest) << digest.error().message;
    EXPECT_EQ(sweep->header.lens.prescription_sha256, *digest);
    auto model = fit::readModel(output + "/model.flm");
    ASSERT_TRUE(model) << model.error().message;
    EXPECT_EQ(model->lens.prescription_file, "heliar-tronnier.csv");
    EXPECT_EQ(model->lens.prescription_sha256, *digest);
}

TEST(Resume, WithoutResumeAnInterruptedJobWaitsForAClient) {
    TempDir dir;
    std::string job_id;
    {
        Daemon daemon(dir.path);
        auto stub = daemon.stub();
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, simConfig("waits", 0.0, 2.0, 0.2, false), &job).ok());
        job_id = job.id();
        waitFor(*stub, job.id(), [](const v1::Job& j) { return j.frames_done() >= 1; });
    }
    ManagerOptions options;
    options.resume = false;
    Daemon again(dir.path, options);
    auto stub = again.stub();
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    const v1::Job waiting = waitFor(*stub, job_id, [](const v1::Job&) { return true; });
    EXPECT_EQ(waiting.state(), v1::INTERRUPTED);
    v1::JobControlRequest resume;
    resume.set_job_id(job_id);
    v1::Job out;
    auto ctx = context();
    ASSERT_TRUE(stub->ResumeJob(ctx.get(), resume, &out).ok());
    EXPECT_EQ(waitFor(*stub, job_id, ended).state(), v1::SUCCEEDED);
}

TEST(Resume, FilesTheManifestDoesNotListAreSetAsideNotLost) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    // A sweep cut short: the head stalls at 0.5 deg, the job pauses and is cancelled.
    v1::SweepConfig stalled = simConfig("orphans", 0.0, 1.0, 0.2);
    stalled.mutable_sim()->mutable_faults()->set_head_stall_at_deg(0.5);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, stalled, &job).ok());
    waitFor(*stub, job.id(), [](const v1::Job& j) { return j.state() == v1::PAUSED; });
    v1::JobControlRequest cancel;
    cancel.set_job_id(job.id());
    v1::Job out;
    auto ctx = context();
    ASSERT_TRUE(stub->CancelJob(ctx.get(), cancel, &out).ok());
    ASSERT_EQ(waitFor(*stub, job.id(), ended).state(), v1::CANCELLED);
    // What a crash between a frame's EXR and its manifest entry leaves: a frame on disk that
    // the manifest does not list; and a temporary file.
    auto sweep = hdr::readSweepManifest(job.output_dir());
    ASSERT_TRUE(sweep);
    const std::string last = sweep->frames.back().exr_file;
    fs::copy_file(job.output_dir() + "/" + last,
                  job.output_dir() + "/" + hdr::sweepFrameFileName(3, 0.6));
    std::ofstream(job.output_dir() + "/manifest.json.tmp-1") << "{";
    v1::SweepConfig more = simConfig("orphans", 0.0, 1.0, 0.2);
    more.set_resume_existing(true);
    v1::Job second;
    ASSERT_TRUE(startSweep(*stub, more, &second).ok());
    const v1::Job done = waitFor(*stub, second.id(), ended);
    ASSERT_EQ(done.state(), v1::SUCCEEDED) << done.reason();
    auto full = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(full) << full.error().message;
    EXPECT_EQ(full->frames.size(), 6u);
    EXPECT_TRUE(full->warnings.empty());
    const fs::path recovered = fs::path(dir.path) / "recovered" / second.id();
    size_t kept = 0;
    for (auto& f : fs::recursive_directory_iterator(recovered)) kept += f.is_regular_file();
    EXPECT_EQ(kept, 2u);
}

TEST(Resume, AJournalRecordThatCannotBeReadIsSetAsideAndReported) {
    TempDir dir;
    {
        Daemon daemon(dir.path);
        auto stub = daemon.stub();
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, simConfig("kept", 0.0, 0.2, 0.2), &job).ok());
        waitFor(*stub, job.id(), ended);
    }
    std::ofstream(dir.path + "/jobs/job-000007.json") << "{\"id\": \"job-000007\", \"state\": ";
    std::ofstream(dir.path + "/jobs/job-000008.json")
        << "{\"id\": \"job-000009\", \"state\": \"QUEUED\"}";
    std::ofstream(dir.path + "/jobs/job-000010.json") << "{\"id\": \"job-000010\", \"unknown\": 1}";
    Daemon again(dir.path);
    EXPECT_EQ(again.journal_warnings.size(), 3u);
    EXPECT_TRUE(fs::exists(dir.path + "/jobs/job-000007.json.corrupt"));
    EXPECT_EQ(again.manager().list().size(), 1u);
    // Ids continue after the highest record kept.
    auto stub = again.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("next", 0.0, 0.2, 0.2), &job).ok());
    EXPECT_EQ(job.id(), "job-000002");
    EXPECT_FALSE(Journal::parse("[]", "x"));
    EXPECT_FALSE(Journal::parse("{\"id\": \"job-1\"}", "x"));  // no state
    EXPECT_EQ(jobNumber("job-000042"), 42u);
    EXPECT_EQ(jobNumber("job-"), 0u);
    EXPECT_EQ(jobNumber("job-12a"), 0u);
    EXPECT_EQ(jobId(42), "job-000042");
}

// ---- the daemon as a process ----

struct Process {
    pid_t pid = -1;
    // Starts `argv`, its standard error into `log`.
    Process(const std::vector<std::string>& argv, const std::string& log) {
        posix_spawn_file_actions_t actions;
        posix_spawn_file_actions_init(&actions);
        posix_spawn_file_actions_addopen(&actions, 2, log.c_str(), O_WRONLY | O_CREAT | O_APPEND,
                                         0644);
        std::vector<char*> args;
        for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
        args.push_back(nullptr);
        EXPECT_EQ(posix_spawn(&pid, args[0], &actions, nullptr, args.data(), environ), 0);
        posix_spawn_file_actions_destroy(&actions);
    }
    int wait() {
        int status = 0;
        ::waitpid(pid, &status, 0);
        pid = -1;
        return status;
    }
    ~Process() {
        if (pid > 0) {
            ::kill(pid, SIGKILL);
            wait();
        }
    }
};

std::string daemonBinary() { return std::string(FLARELAB_BINARY_DIR) + "/apps/flarelabd"; }

std::unique_ptr<v1::FlareLab::Stub> connect(const std::string& socket) {
    for (int i = 0; i < 500 && !fs::exists(socket); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    auto stub = v1::FlareLab::NewStub(
        grpc::CreateChannel("unix:" + socket, grpc::InsecureChannelCredentials()));
    v1::RigDescription rig;
    auto ctx = context("test", 30.0);
    ctx->set_wait_for_ready(true);  // through gRPC's reconnection, past a stale socket file
    const grpc::Status status = stub->DescribeRig(ctx.get(), {}, &rig);
    EXPECT_TRUE(status.ok()) << "no daemon answers on " << socket << ": " << status.error_message();
    return stub;
}

TEST(Resume, AfterSigkillMidSweepARestartedDaemonResumesAndEveryAngleIsThereOnceAsUninterrupted) {
    if (!fs::exists(daemonBinary())) GTEST_SKIP() << "flarelabd is not built";
    TempDir dir;
    const std::string state = dir.path + "/state", log = dir.path + "/flarelabd.log";
    const std::string socket = state + "/flarelabd.sock";
    std::string job_id, output;
    {
        Process daemon({daemonBinary(), "--state-dir", state}, log);
        auto stub = connect(socket);
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, simConfig("killed", 0.0, 3.0, 0.2, false), &job).ok());
        job_id = job.id();
        output = job.output_dir();
        for (int i = 0; i < 1000; ++i) {
            auto m = hdr::readSweepManifest(output);
            if (m && m->frames.size() >= 4) break;
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        ::kill(daemon.pid, SIGKILL);
        daemon.wait();
    }
    auto partial = hdr::readSweepManifest(output);
    ASSERT_TRUE(partial);
    EXPECT_LT(partial->frames.size(), 16u) << "the sweep ended before the kill; test too slow?";
    {
        Process daemon({daemonBinary(), "--state-dir", state}, log);
        auto stub = connect(socket);
        const v1::Job last = waitFor(*stub, job_id, ended, 300);
        EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason() << "\n" << readText(log);
        EXPECT_EQ(last.restarts(), 1u);
        v1::Job reference;
        ASSERT_TRUE(startSweep(*stub, simConfig("whole", 0.0, 3.0, 0.2, true), &reference).ok());
        EXPECT_EQ(waitFor(*stub, reference.id(), ended, 300).state(), v1::SUCCEEDED);
        expectSameSweep(output, reference.output_dir());
        // SIGTERM: a clean stop, the socket removed.
        ::kill(daemon.pid, SIGTERM);
        const int status = daemon.wait();
        EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << readText(log);
        EXPECT_FALSE(fs::exists(socket));
    }
    const std::string text = readText(log);
    EXPECT_NE(text.find("event=daemon.stopped"), std::string::npos);
    EXPECT_NE(text.find("event=job.loaded job=" + job_id + " state=QUEUED"), std::string::npos)
        << text;
}

TEST(Resume, ASecondDaemonOnTheSameStateDirectoryIsRefused) {
    if (!fs::exists(daemonBinary())) GTEST_SKIP() << "flarelabd is not built";
    TempDir dir;
    const std::string state = dir.path + "/state", log = dir.path + "/flarelabd.log";
    Process first({daemonBinary(), "--state-dir", state}, log);
    connect(state + "/flarelabd.sock");
    Process second({daemonBinary(), "--state-dir", state}, dir.path + "/second.log");
    const int status = second.wait();
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 1);
    EXPECT_NE(readText(dir.path + "/second.log").find("is owned by another flarelabd"),
              std::string::npos);
    Process remote({daemonBinary(), "--state-dir", dir.path + "/other", "--listen", "0.0.0.0:0"},
                   dir.path + "/remote.log");
    const int refused = remote.wait();
    EXPECT_TRUE(WIFEXITED(refused) && WEXITSTATUS(refused) == 2);
    EXPECT_NE(readText(dir.path + "/remote.log").find("--allow-remote"), std::string::npos);
}

// ---- the configuration's pieces ----

TEST(SweepConfig, OutputDirectoriesStayBelowTheRoot) {
    TempDir dir;
    const std::string root = fs::canonical(dir.path).string();
    EXPECT_EQ(*resolveOutputDir("a/b", root, "f"), root + "/a/b");
    EXPECT_EQ(*resolveOutputDir("a/b/", root, "f"), root + "/a/b");
    EXPECT_EQ(*resolveOutputDir(root + "/x/./y", root, "f"), root + "/x/y");
    EXPECT_FALSE(resolveOutputDir(root, root, "f"));
    EXPECT_FALSE(resolveOutputDir(".", root, "f"));
    EXPECT_FALSE(resolveOutputDir(root + "-sibling/a", root, "f"));
    EXPECT_FALSE(resolveOutputDir("a/../../b", root, "f"));
    fs::create_symlink("/tmp", root + "/out");
    const auto escaped = resolveOutputDir("out/deeper/sweep", root, "field.x");
    ASSERT_FALSE(escaped);
    EXPECT_EQ(escaped.error().message.rfind("field.x: ", 0), 0u);
    std::ofstream(root + "/file") << "x";
    EXPECT_FALSE(resolveOutputDir("file", root, "f"));
}

TEST(SweepConfig, AnglesFollowTheStepGridAndEndAtTheLastAngle) {
    EXPECT_EQ(sweepAngles(0.0, 1.0, 0.2), (std::vector<double>{0.0, 0.2, 0.4, 0.6, 0.8, 1.0}));
    EXPECT_EQ(sweepAngles(0.0, 0.9, 0.2), (std::vector<double>{0.0, 0.2, 0.4, 0.6, 0.8}));
    EXPECT_EQ(sweepAngles(-0.3, -0.3, 0.2), (std::vector<double>{-0.3}));
    EXPECT_EQ(sweepAngles(0.0, 30.0, 0.2).size(), 151u);
}

}  // namespace
}  // namespace flarelab::daemon
