// The daemon through its gRPC API, in process: whole sweeps, retried starts, malformed and
// oversized requests, faults of the simulated rig, clients that watch, leave and take control,
// tokens, rate limits, many watchers.
#include <grpcpp/generic/generic_stub.h>
#include <gtest/gtest.h>
#include <sys/stat.h>

#include <atomic>
#include <mutex>
#include <thread>

#include "hdr/sweep.h"
#include "tests/daemon/daemon_fixture.h"

namespace flarelab::daemon {
namespace {

using namespace testing;

TEST(Service, RunsAWholeSweepWithFitAndPreviewsAndReportsItsProducts) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("a/sweep", 0.0, 1.0, 0.2);
    config.set_previews(true);
    config.set_fit(true);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    // The worker may take the job as soon as its record is on disk, before the reply is built
    // (JobManager::start and work wake on the same change): queued or already running.
    EXPECT_TRUE(job.state() == v1::QUEUED || job.state() == v1::RUNNING) << job.state();
    EXPECT_EQ(job.frames_total(), 6u);
    EXPECT_EQ(job.output_dir(), daemon.output_root + "/a/sweep");
    const auto events = watchToEnd(*stub, job.id());
    ASSERT_FALSE(events.empty());
    EXPECT_EQ(events.back().job().state(), v1::SUCCEEDED) << events.back().job().reason();
    size_t frames = 0, exposures = 0;
    for (size_t i = 0; i < events.size(); ++i) {
        if (i > 0) {
            EXPECT_GT(events[i].sequence(), events[i - 1].sequence());
        }
        frames += events[i].kind() == v1::FRAME;
        exposures += events[i].kind() == v1::EXPOSURE;
    }
    EXPECT_EQ(frames, 6u);
    EXPECT_EQ(exposures, 12u);

    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 6u);
    EXPECT_TRUE(sweep->warnings.empty());  // the model and previews are products, not strays
    EXPECT_EQ(sweep->frames[5].angle_deg, 1.0);
    EXPECT_EQ(sweep->frames[0].brackets.size(), 2u);

    v1::JobResult result;
    auto ctx = context();
    v1::GetJobResultRequest request;
    request.set_job_id(job.id());
    ASSERT_TRUE(stub->GetJobResult(ctx.get(), request, &result).ok());
    EXPECT_EQ(result.sweep_dir(), job.output_dir());
    EXPECT_TRUE(fs::exists(result.manifest()));
    EXPECT_TRUE(fs::exists(result.model_file()));
    EXPECT_NE(result.model_summary().find("ghosts:"), std::string::npos);
    EXPECT_EQ(result.previews_size(), 6);
}

// A job asks for the camera's Bayer mosaic: its frames are colour, the sweep says so, and a
// format the camera does not have fails the job naming the field and the camera.
TEST(Service, AColourSweepRecordsItsRawFormat) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("colour", 0.0, 0.2, 0.2);
    config.set_raw_format("bayer-rggb");
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    auto events = watchToEnd(*stub, job.id());
    ASSERT_FALSE(events.empty());
    ASSERT_EQ(events.back().job().state(), v1::SUCCEEDED) << events.back().job().reason();
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->header.camera.raw_format, hdr::RawFormat::BayerRGGB);
    auto frame = hdr::loadFrame(*sweep, 0);
    ASSERT_TRUE(frame) << frame.error().message;
    bool colour = false;
    for (size_t i = 0; i < frame->image.pixels.size(); i += 3)
        colour = colour || frame->image.pixels[i] != frame->image.pixels[i + 2];
    EXPECT_TRUE(colour);
    EXPECT_EQ(frame->lower_bound.size(), frame->image.pixels.size() / 3);

    config = simConfig("other", 0.0, 0.2, 0.2);
    config.set_raw_format("bayer-bggr");  // the simulated camera has mono and bayer-rggb
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    events = watchToEnd(*stub, job.id());
    ASSERT_FALSE(events.empty());
    EXPECT_EQ(events.back().job().state(), v1::FAILED);
    EXPECT_NE(events.back().job().reason().find("config.raw_format: [out-of-range] sim camera"),
              std::string::npos)
        << events.back().job().reason();
}

TEST(Service, ARetriedStartWithTheSameRequestIdStartsOneJob) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    const v1::SweepConfig config = simConfig("retried", 0.0, 0.4, 0.2);
    v1::Job first, second, other;
    ASSERT_TRUE(startSweep(*stub, config, &first, "test", "req-1").ok());
    ASSERT_TRUE(startSweep(*stub, config, &second, "test", "req-1").ok());
    EXPECT_EQ(first.id(), second.id());
    v1::SweepConfig changed = config;
    changed.set_to_deg(0.6);
    const grpc::Status reused = startSweep(*stub, changed, &other, "test", "req-1");
    EXPECT_EQ(reused.error_code(), grpc::StatusCode::ALREADY_EXISTS);
    EXPECT_NE(reused.error_message().find("request_id"), std::string::npos);
    EXPECT_EQ(startSweep(*stub, config, &other, "test", "bad id!").error_code(),
              grpc::StatusCode::INVALID_ARGUMENT);
    watchToEnd(*stub, first.id());
    // Retried after the job finished (its directory now holds the sweep): still the same job.
    v1::Job late;
    ASSERT_TRUE(startSweep(*stub, config, &late, "test", "req-1").ok());
    EXPECT_EQ(late.id(), first.id());
    EXPECT_EQ(late.state(), v1::SUCCEEDED);
    v1::ListJobsResponse list;
    auto ctx = context();
    ASSERT_TRUE(stub->ListJobs(ctx.get(), {}, &list).ok());
    EXPECT_EQ(list.jobs_size(), 1);
}

TEST(Service, MalformedConfigsAreRefusedNamingTheField) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    fs::create_directories(dir.path + "/elsewhere");
    fs::create_symlink(dir.path + "/elsewhere", daemon.output_root + "/link");
    const v1::SweepConfig good = simConfig("ok", 0.0, 1.0, 0.2);
    struct Case {
        const char* field;
        std::function<void(v1::SweepConfig&)> spoil;
    };
    const Case cases[] = {
        {"config.step_deg", [](auto& c) { c.set_step_deg(-0.2); }},
        {"config.step_deg", [](auto& c) { c.set_step_deg(0.0); }},
        {"config.step_deg", [](auto& c) { c.set_step_deg(1e-9); }},  // too many frames
        {"config.from_deg", [](auto& c) { c.set_from_deg(std::nan("")); }},
        {"config.to_deg", [](auto& c) { c.set_to_deg(-1.0); }},
        {"config.to_deg", [](auto& c) { c.set_to_deg(1e300); }},
        {"config.exposure_times_s[1]", [](auto& c) { c.set_exposure_times_s(1, 0.0); }},
        {"config.exposure_times_s[0]", [](auto& c) { c.set_exposure_times_s(0, INFINITY); }},
        {"config.gain", [](auto& c) { c.set_gain(100.0); }},
        {"config.width_px", [](auto& c) { c.set_width_px(40000); }},
        {"config.raw_format", [](auto& c) { c.set_raw_format("rggb"); }},
        {"config.sim", [](auto& c) { c.clear_sim(); }},
        {"config.sim.lens.prescription_csv",
         [](auto& c) { c.mutable_sim()->mutable_lens()->clear_prescription_csv(); }},
        {"config.sim.lens.prescription_csv",
         [](auto& c) {
             c.mutable_sim()->mutable_lens()->set_prescription_csv("kind,radius\n1,2");
         }},
        {"config.sim.lens.f_number",
         [](auto& c) { c.mutable_sim()->mutable_lens()->set_f_number(-2); }},
        {"config.sim.lens.aperture_blades",
         [](auto& c) { c.mutable_sim()->mutable_lens()->set_aperture_blades(2); }},
        {"config.output_dir", [](auto& c) { c.set_output_dir(""); }},
        {"config.output_dir", [](auto& c) { c.set_output_dir("../escape"); }},
        {"config.output_dir", [](auto& c) { c.set_output_dir("a/../../escape"); }},
        {"config.output_dir", [](auto& c) { c.set_output_dir("/etc/flarelab"); }},
        {"config.output_dir", [](auto& c) { c.set_output_dir("link/sweep"); }},
        {"config.output_dir", [](auto& c) { c.set_output_dir(std::string("a\nb")); }},
        {"config.fit",
         [](auto& c) {
             c.set_to_deg(0.0);
             c.set_fit(true);
         }},
    };
    for (const Case& k : cases) {
        v1::SweepConfig config = good;
        k.spoil(config);
        v1::Job job;
        const grpc::Status s = startSweep(*stub, config, &job);
        EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << k.field;
        EXPECT_EQ(s.error_message().rfind(k.field, 0), 0u)
            << "expected the message to start with " << k.field << ": " << s.error_message();
        v1::CheckSweepRequest check;
        *check.mutable_config() = config;
        v1::SweepPlan plan;
        auto ctx = context();
        EXPECT_EQ(stub->CheckSweep(ctx.get(), check, &plan).error_code(),
                  grpc::StatusCode::INVALID_ARGUMENT);
    }
    EXPECT_FALSE(fs::exists(dir.path + "/elsewhere/sweep"));
    // The good one checks, with its plan.
    v1::CheckSweepRequest check;
    *check.mutable_config() = good;
    v1::SweepPlan plan;
    auto ctx = context();
    ASSERT_TRUE(stub->CheckSweep(ctx.get(), check, &plan).ok());
    EXPECT_EQ(plan.frames(), 6u);
    EXPECT_EQ(plan.exposures(), 12u);
    EXPECT_GT(plan.rig_time_s(), 6 * (0.05 + 0.06));
    // Unknown jobs and bad control requests.
    v1::JobControlRequest control;
    control.set_job_id("job-999999");
    v1::Job job;
    auto ctx2 = context();
    EXPECT_EQ(stub->CancelJob(ctx2.get(), control, &job).error_code(), grpc::StatusCode::NOT_FOUND);
    control.set_job_id(std::string(10000, 'x'));
    auto ctx3 = context();
    EXPECT_EQ(stub->PauseJob(ctx3.get(), control, &job).error_code(), grpc::StatusCode::NOT_FOUND);
}

TEST(Service, OversizedAndGarbledRequestsAreRefusedAndTheDaemonGoesOn) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("big", 0.0, 1.0, 0.2);
    config.mutable_sim()->mutable_lens()->set_prescription_csv(std::string(3 << 20, '#'));
    v1::Job job;
    EXPECT_EQ(startSweep(*stub, config, &job).error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    // A lens text under the transport limit but over the daemon's 1 MiB.
    config.mutable_sim()->mutable_lens()->set_prescription_csv(std::string(1500000, '#'));
    const grpc::Status big = startSweep(*stub, config, &job);
    EXPECT_EQ(big.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(big.error_message().find("prescription_csv"), std::string::npos);

    // Bytes that are no protobuf message at all.
    auto channel = grpc::CreateChannel("unix:" + daemon.socket, grpc::InsecureChannelCredentials());
    grpc::GenericStub generic(channel);
    for (const std::string& garbage :
         {std::string("\xff\xff\xff\xff\x0f", 5), std::string("\x0a\xff\xff\xff\x7f", 5),
          std::string(100, '\x0a')}) {
        grpc::Slice slice(garbage);
        grpc::ByteBuffer request(&slice, 1), response;
        grpc::ClientContext ctx;
        ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
        std::atomic<bool> done{false};
        grpc::Status status;
        generic.UnaryCall(&ctx, "/flarelab.v1.FlareLab/StartSweep", grpc::StubOptions(), &request,
                          &response, [&](grpc::Status s) {
                              status = s;
                              done = true;
                          });
        while (!done) std::this_thread::sleep_for(std::chrono::milliseconds(5));
        EXPECT_FALSE(status.ok());
    }
    v1::RigDescription rig;
    auto ctx = context();
    ASSERT_TRUE(stub->DescribeRig(ctx.get(), {}, &rig).ok());
    EXPECT_EQ(rig.api_version(), 1u);
    EXPECT_EQ(rig.output_root(), daemon.output_root);
}

TEST(Service, ShortCameraTimeoutsAreRetriedAndTheSweepCompletes) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("timeouts", 0.0, 1.0, 0.2);
    config.mutable_sim()->mutable_faults()->set_camera_timeouts(2);
    config.mutable_sim()->mutable_faults()->set_camera_timeouts_from_capture(5);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    const auto events = watchToEnd(*stub, job.id());
    const v1::Job& last = events.back().job();
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    size_t retries = 0;
    for (const auto& w : last.warnings()) retries += w.find("(retry") != std::string::npos;
    EXPECT_EQ(retries, 2u);
    auto sweep = hdr::readSweep(job.output_dir());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 6u);
}

TEST(Service, PersistentCameraTimeoutsPauseTheJobUntilResumed) {
    TempDir dir;
    ManagerOptions options;
    options.runner.camera_retries = 3;
    Daemon daemon(dir.path, options);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("stuck", 0.0, 1.0, 0.2);
    config.mutable_sim()->mutable_faults()->set_camera_timeouts(5);
    config.mutable_sim()->mutable_faults()->set_camera_timeouts_from_capture(3);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    const v1::Job paused =
        waitFor(*stub, job.id(), [](const v1::Job& j) { return j.state() == v1::PAUSED; });
    EXPECT_NE(paused.reason().find("camera failed 4 times"), std::string::npos) << paused.reason();
    waitFor(*stub, job.id(),
            [](const v1::Job& j) { return j.state() == v1::PAUSED && j.frames_done() == 1; });
    v1::JobControlRequest resume;
    resume.set_job_id(job.id());
    v1::Job resumed;
    auto ctx = context();
    ASSERT_TRUE(stub->ResumeJob(ctx.get(), resume, &resumed).ok());
    const v1::Job last = waitFor(*stub, job.id(), ended);
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    auto sweep = hdr::readSweep(job.output_dir());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 6u);
}

TEST(Service, AStalledHeadStopsTheRigAndKeepsWhatWasWritten) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("stall", 0.0, 1.0, 0.2);
    config.mutable_sim()->mutable_faults()->set_head_stall_at_deg(0.5);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    const v1::Job paused =
        waitFor(*stub, job.id(), [](const v1::Job& j) { return j.state() == v1::PAUSED; });
    EXPECT_NE(paused.reason().find("head stalled"), std::string::npos) << paused.reason();
    EXPECT_NE(paused.reason().find("rig is stopped"), std::string::npos) << paused.reason();
    // 0, 0.2 and 0.4 deg: the last may still be on its way to disk when the capture pauses.
    waitFor(*stub, job.id(),
            [](const v1::Job& j) { return j.state() == v1::PAUSED && j.frames_done() == 3; });
    v1::JobControlRequest cancel;
    cancel.set_job_id(job.id());
    v1::Job cancelled;
    auto ctx = context();
    ASSERT_TRUE(stub->CancelJob(ctx.get(), cancel, &cancelled).ok());
    const v1::Job last = waitFor(*stub, job.id(), ended);
    EXPECT_EQ(last.state(), v1::CANCELLED);
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 3u);
}

TEST(Service, HeadMovesThatDoNotArriveAreRetried) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::SweepConfig config = simConfig("hang", 0.0, 0.4, 0.2);
    config.mutable_sim()->mutable_faults()->set_head_hangs(1);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    const auto events = watchToEnd(*stub, job.id());
    EXPECT_EQ(events.back().job().state(), v1::SUCCEEDED) << events.back().job().reason();
}

TEST(Service, AFullDiskFailsTheJobWithEveryWrittenFrameIntact) {
    TempDir dir;
    ManagerOptions options;
    auto calls = std::make_shared<std::atomic<int>>(0);
    options.runner.free_bytes = [calls](const std::string&) -> int64_t {
        return ++*calls <= 3 ? int64_t{1} << 40 : int64_t{10} << 20;
    };
    Daemon daemon(dir.path, options);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("full", 0.0, 2.0, 0.2), &job).ok());
    const auto events = watchToEnd(*stub, job.id());
    const v1::Job& last = events.back().job();
    EXPECT_EQ(last.state(), v1::FAILED);
    EXPECT_NE(last.reason().find("disk full"), std::string::npos) << last.reason();
    EXPECT_NE(last.reason().find("3 frame(s) written before are intact"), std::string::npos)
        << last.reason();
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 3u);
}

TEST(Service, AWatcherThatLeavesDoesNotStopTheJobAndASecondClientWatchesButCannotControl) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    // Real time, so that the job is still running while clients come and go.
    v1::SweepConfig config = simConfig("shared", 0.0, 1.2, 0.2, /*fast=*/false);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job, "alice").ok());
    {
        auto ctx = context("alice");
        v1::WatchJobRequest request;
        request.set_job_id(job.id());
        auto reader = stub->WatchJob(ctx.get(), request);
        v1::JobEvent e;
        ASSERT_TRUE(reader->Read(&e));
        EXPECT_EQ(e.kind(), v1::STATE);
        ctx->TryCancel();  // alice goes away mid-stream
        while (reader->Read(&e)) {
        }
        (void)reader->Finish();
    }
    v1::JobControlRequest request;
    request.set_job_id(job.id());
    v1::Job out;
    auto ctx = context("bob");
    const grpc::Status denied = stub->PauseJob(ctx.get(), request, &out);
    EXPECT_EQ(denied.error_code(), grpc::StatusCode::PERMISSION_DENIED);
    EXPECT_NE(denied.error_message().find("alice"), std::string::npos);
    std::vector<v1::JobEvent> bob_events;
    std::thread bob([&] { bob_events = watchToEnd(*stub, job.id(), "bob"); });
    const auto alice_events = watchToEnd(*stub, job.id(), "alice");
    bob.join();
    EXPECT_EQ(alice_events.back().job().state(), v1::SUCCEEDED);
    ASSERT_FALSE(bob_events.empty());
    EXPECT_EQ(bob_events.back().job().state(), v1::SUCCEEDED);
    EXPECT_EQ(bob_events.back().job().frames_done(), 7u);

    // Taking control is explicit, and then the first client is the one refused.
    v1::Job second;
    ASSERT_TRUE(
        startSweep(*stub, simConfig("shared2", 0.0, 4.0, 0.2, false), &second, "alice").ok());
    v1::JobControlRequest take;
    take.set_job_id(second.id());
    take.set_take_control(true);
    auto ctx2 = context("bob");
    ASSERT_TRUE(stub->PauseJob(ctx2.get(), take, &out).ok());
    EXPECT_EQ(out.controller(), "bob");
    EXPECT_EQ(out.state(), v1::PAUSED);
    v1::JobControlRequest plain;
    plain.set_job_id(second.id());
    auto ctx3 = context("alice");
    EXPECT_EQ(stub->ResumeJob(ctx3.get(), plain, &out).error_code(),
              grpc::StatusCode::PERMISSION_DENIED);
    auto ctx4 = context("bob");
    ASSERT_TRUE(stub->CancelJob(ctx4.get(), plain, &out).ok());
    EXPECT_EQ(waitFor(*stub, second.id(), ended).state(), v1::CANCELLED);
}

TEST(Service, TheRigGoesOnWithTheNextJobWhileTheLastOneFits) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    // A fit of some seconds, a capture of a few milliseconds.
    v1::SweepConfig fitted = simConfig("fitted", 0.0, 4.0, 0.2);
    fitted.set_width_px(320);
    fitted.set_height_px(213);
    fitted.set_fit(true);
    v1::Job a, b;
    ASSERT_TRUE(startSweep(*stub, fitted, &a).ok());
    ASSERT_TRUE(startSweep(*stub, simConfig("next", 0.0, 0.2, 0.2), &b).ok());
    const v1::Job fitting = waitFor(*stub, a.id(), fittingOrEnded);
    EXPECT_EQ(fitting.phase(), v1::FITTING);
    // A fit holds no device: it cannot pause, but b captures meanwhile and ends first.
    v1::JobControlRequest pause;
    pause.set_job_id(a.id());
    v1::Job out;
    auto ctx = context();
    EXPECT_EQ(stub->PauseJob(ctx.get(), pause, &out).error_code(),
              grpc::StatusCode::FAILED_PRECONDITION);
    const v1::Job last_b = waitFor(*stub, b.id(), ended);
    const v1::Job now_a = waitFor(*stub, a.id(), [](const v1::Job&) { return true; });
    EXPECT_EQ(last_b.state(), v1::SUCCEEDED);
    EXPECT_EQ(now_a.phase(), v1::FITTING) << "the fit ended before the next capture did";
    const v1::Job last_a = waitFor(*stub, a.id(), ended);
    EXPECT_EQ(last_a.state(), v1::SUCCEEDED) << last_a.reason();
    EXPECT_TRUE(fs::exists(last_a.model_file()));
}

TEST(Service, CancellingAFitStopsItAndKeepsTheSweep) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, fitConfig("cancelled-fit", 3.0), &job).ok());
    waitFor(*stub, job.id(), fittingOrEnded);
    v1::JobControlRequest cancel;
    cancel.set_job_id(job.id());
    v1::Job out;
    auto ctx = context();
    ASSERT_TRUE(stub->CancelJob(ctx.get(), cancel, &out).ok());
    const v1::Job last = waitFor(*stub, job.id(), ended);
    EXPECT_EQ(last.state(), v1::CANCELLED);
    EXPECT_FALSE(fs::exists(job.output_dir() + "/model.flm"));
    auto sweep = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 16u);
}

TEST(Service, PauseAndResumeHoldTheRigBetweenFrames) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("pause", 0.0, 1.6, 0.2, false), &job).ok());
    // Every event of the job, as a second client sees them.
    std::vector<v1::JobEvent> events;
    std::mutex events_mutex;
    std::thread watcher([&] {
        auto ctx = context("watcher", 300.0);
        v1::WatchJobRequest request;
        request.set_job_id(job.id());
        auto reader = stub->WatchJob(ctx.get(), request);
        v1::JobEvent e;
        while (reader->Read(&e)) {
            std::lock_guard lock(events_mutex);
            events.push_back(e);
        }
        (void)reader->Finish();
    });
    waitFor(*stub, job.id(), [](const v1::Job& j) { return j.frames_done() >= 2; });
    v1::JobControlRequest request;
    request.set_job_id(job.id());
    v1::Job out;
    auto ctx = context();
    ASSERT_TRUE(stub->PauseJob(ctx.get(), request, &out).ok());
    EXPECT_EQ(out.state(), v1::PAUSED);
    // The rig holds after the frame under way: the daemon says so, and from then on no exposure
    // is taken and, once that frame is written, no frame lands.
    size_t held_at = 0;
    uint32_t captured = 0;
    for (int i = 0; i < 3000 && held_at == 0; ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        std::lock_guard lock(events_mutex);
        for (size_t k = 0; k < events.size(); ++k) {
            if (events[k].kind() == v1::EXPOSURE)
                captured = std::max(captured, events[k].frame_index() + 1);
            if (events[k].message() == kHoldingMessage) {
                held_at = k + 1;
                break;
            }
        }
    }
    ASSERT_GT(held_at, 0u) << "the paused job never said its rig holds";
    EXPECT_LE(captured, out.frames_done() + 2);  // one in the queue, one under way
    const v1::Job written =
        waitFor(*stub, job.id(), [&](const v1::Job& j) { return j.frames_done() == captured; });
    std::this_thread::sleep_for(std::chrono::milliseconds(1000));
    const v1::Job still = waitFor(*stub, job.id(), [](const v1::Job&) { return true; });
    EXPECT_EQ(still.state(), v1::PAUSED);
    EXPECT_EQ(still.frames_done(), written.frames_done());
    {
        std::lock_guard lock(events_mutex);
        for (size_t k = held_at; k < events.size(); ++k)
            EXPECT_NE(events[k].kind(), v1::EXPOSURE) << "an exposure while paused";
    }
    auto ctx2 = context();
    ASSERT_TRUE(stub->ResumeJob(ctx2.get(), request, &out).ok());
    EXPECT_EQ(waitFor(*stub, job.id(), ended).state(), v1::SUCCEEDED);
    watcher.join();
    auto sweep = hdr::readSweep(job.output_dir());
    ASSERT_TRUE(sweep);
    EXPECT_EQ(sweep->frames.size(), 9u);
}

TEST(Service, ManyConcurrentWatchersOnLoopbackAllSeeTheEnd) {
    TempDir dir;
    ServerOptions server;
    server.tcp_address = "127.0.0.1:0";
    server.service.token = "loopback-token-0123456789";
    testToken() = server.service.token;
    Daemon daemon(dir.path, {}, server);
    const std::string target = "127.0.0.1:" + std::to_string(daemon.server().tcpPort());
    auto stub = daemon.stub(target);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("load", 0.0, 1.0, 0.2, false), &job).ok());
    constexpr int kWatchers = 48;
    std::atomic<int> saw_end{0};
    std::vector<std::thread> watchers;
    for (int i = 0; i < kWatchers; ++i)
        watchers.emplace_back([&, i] {
            auto own = daemon.stub(target);
            const auto events = watchToEnd(*own, job.id(), "watcher-" + std::to_string(i));
            if (!events.empty() && events.back().job().state() == v1::SUCCEEDED) ++saw_end;
        });
    for (auto& t : watchers) t.join();
    EXPECT_EQ(saw_end.load(), kWatchers);
    testToken().clear();
}

TEST(Service, WatchersBeyondTheLimitAreRefused) {
    TempDir dir;
    ServerOptions server;
    server.service.max_watchers = 2;
    Daemon daemon(dir.path, {}, server);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("limit", 0.0, 1.0, 0.2, false), &job).ok());
    std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
    std::vector<std::unique_ptr<grpc::ClientReader<v1::JobEvent>>> readers;
    v1::WatchJobRequest request;
    request.set_job_id(job.id());
    for (int i = 0; i < 2; ++i) {
        contexts.push_back(context());
        readers.push_back(stub->WatchJob(contexts.back().get(), request));
        v1::JobEvent e;
        ASSERT_TRUE(readers.back()->Read(&e));
    }
    auto ctx = context();
    auto third = stub->WatchJob(ctx.get(), request);
    v1::JobEvent e;
    EXPECT_FALSE(third->Read(&e));
    EXPECT_EQ(third->Finish().error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    for (size_t i = 0; i < readers.size(); ++i) {
        contexts[i]->TryCancel();
        while (readers[i]->Read(&e)) {
        }
        (void)readers[i]->Finish();
    }
}

TEST(Service, ATokenIsAskedForWhenSet) {
    TempDir dir;
    ServerOptions server;
    server.service.token = "0123456789abcdef-secret";
    Daemon daemon(dir.path, {}, server);
    auto stub = daemon.stub();
    v1::RigDescription rig;
    auto none = context();
    EXPECT_EQ(stub->DescribeRig(none.get(), {}, &rig).error_code(),
              grpc::StatusCode::UNAUTHENTICATED);
    auto wrong = context();
    wrong->AddMetadata("authorization", "Bearer 0123456789abcdef-secreT");
    EXPECT_EQ(stub->DescribeRig(wrong.get(), {}, &rig).error_code(),
              grpc::StatusCode::UNAUTHENTICATED);
    auto right = context();
    right->AddMetadata("authorization", "Bearer 0123456789abcdef-secret");
    EXPECT_TRUE(stub->DescribeRig(right.get(), {}, &rig).ok());
    EXPECT_TRUE(sameSecret("abc", "abc"));
    EXPECT_FALSE(sameSecret("abc", "abcd"));
    EXPECT_FALSE(sameSecret("", "a"));
}

TEST(Service, CallsBeyondTheRateAreRefusedAndBadClientNamesToo) {
    TempDir dir;
    ServerOptions server;
    server.service.calls_per_s = 2.0;
    server.service.burst = 5.0;
    Daemon daemon(dir.path, {}, server);
    auto stub = daemon.stub();
    int ok = 0, refused = 0;
    for (int i = 0; i < 20; ++i) {
        v1::ListJobsResponse list;
        auto ctx = context("eager");
        const grpc::Status s = stub->ListJobs(ctx.get(), {}, &list);
        (s.ok() ? ok : refused) += 1;
        if (!s.ok()) {
            EXPECT_EQ(s.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
        }
    }
    EXPECT_GE(ok, 5);
    EXPECT_LE(ok, 7);
    EXPECT_EQ(ok + refused, 20);
    v1::ListJobsResponse list;
    // The budget is the peer's (this process's uid), whatever name its clients give: renaming
    // does not buy more calls.
    int renamed_ok = 0;
    for (int i = 0; i < 20; ++i) {
        auto renamed = context("renamed-" + std::to_string(i));
        renamed_ok += stub->ListJobs(renamed.get(), {}, &list).ok();
    }
    EXPECT_LE(renamed_ok, 2);
    auto bad = context("has space");
    EXPECT_EQ(stub->ListJobs(bad.get(), {}, &list).error_code(),
              grpc::StatusCode::INVALID_ARGUMENT);
}

TEST(Service, TheSocketIsReadableByOwnerAndGroupOnly) {
    TempDir dir;
    Daemon daemon(dir.path);
    struct stat s {};
    ASSERT_EQ(::stat(daemon.socket.c_str(), &s), 0);
    EXPECT_TRUE(S_ISSOCK(s.st_mode));
    EXPECT_EQ(s.st_mode & 0777, 0660u);
    daemon.stop();
    EXPECT_FALSE(fs::exists(daemon.socket));
}

TEST(Service, TwoJobsCannotWriteOneDirectoryAndJobsQueueInOrder) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::Job a, b, c;
    ASSERT_TRUE(startSweep(*stub, simConfig("one", 0.0, 0.6, 0.2, false), &a).ok());
    const grpc::Status same = startSweep(*stub, simConfig("one", 0.0, 0.4, 0.2), &b);
    EXPECT_EQ(same.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(same.error_message().find(a.id()), std::string::npos);
    ASSERT_TRUE(startSweep(*stub, simConfig("two", 0.0, 0.4, 0.2), &c).ok());
    EXPECT_EQ(c.state(), v1::QUEUED);
    const v1::Job last_c = waitFor(*stub, c.id(), ended);
    const v1::Job last_a = waitFor(*stub, a.id(), ended);
    EXPECT_EQ(last_a.state(), v1::SUCCEEDED);
    EXPECT_EQ(last_c.state(), v1::SUCCEEDED);
    EXPECT_LE(last_a.updated_unix_s(), last_c.updated_unix_s());
    // A finished sweep's directory is refused unless resuming it.
    const grpc::Status done = startSweep(*stub, simConfig("two", 0.0, 0.4, 0.2), &b);
    EXPECT_EQ(done.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(done.error_message().find("already holds a sweep"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::daemon
