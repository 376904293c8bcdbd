// The daemon drives a GigE Vision camera: Aravis's fake camera, a process of its own speaking
// GVCP and GVSP on 127.0.0.1 inside this test's network namespace, calibrated with flarelab
// calibrate (its response is not linear), and a simulated head. A bracketed sweep is merged to
// HDR; the camera killed mid-sweep pauses the job, and a restarted one lets it resume; packet
// loss gives typed failures.
#include <gtest/gtest.h>

#include <chrono>
#include <set>
#include <sstream>

#include "apps/calibrate_command.h"
#include "drivers/calibration.h"
#include "hdr/raw_io.h"
#include "tests/apps/command_runner.h"
#include "tests/aravis/fake_gv_camera.h"
#include "tests/daemon/daemon_fixture.h"

namespace flarelab::daemon {
namespace {

using flarelab::testing::FakeGvCameraProcess;
namespace t = flarelab::daemon::testing;

constexpr const char* kCamera = "aravis:127.0.0.1?roi=0,0,256,192&timeout_s=2";
constexpr const char* kHead = "sim:?time=fast&settle_s=0";

class AravisDaemon : public ::testing::Test {
protected:
    void SetUp() override {
        ASSERT_EQ(flarelab::testing::isolateLoopback(), "")
            << "not in a network namespace of its own";
    }

    // flarelab calibrate against the running fake (below 1 ms it reads black: the dark frames).
    drivers::CameraCalibration calibrate(const std::string& dir) {
        const std::string file = dir + "/fake.cal.json";
        std::istringstream no_operator;
        const auto run = apps::testing::runCommand(
            [&](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
                apps::addCalibrateCommand(app, out, err, code, no_operator);
            },
            {"calibrate", "--camera", kCamera, "--yes", "--dark-exposure", "0.0005", "-o", file});
        EXPECT_EQ(run.code, 0) << run.err;
        EXPECT_NE(run.out.find("response: not linear"), std::string::npos) << run.out;
        auto calibration = drivers::readCalibration(file);
        EXPECT_TRUE(calibration) << calibration.error().message;
        return calibration ? *calibration : drivers::CameraCalibration{};
    }

    ManagerOptions rig(std::vector<drivers::CameraCalibration> calibrations) {
        ManagerOptions m;
        m.runner.limits.cameras = {kCamera};
        m.runner.limits.heads = {kHead};
        m.runner.calibrations = std::move(calibrations);
        return m;
    }

    v1::SweepConfig sweep(const std::string& dir, double to_deg) {
        v1::SweepConfig c;
        c.set_from_deg(0.0);
        c.set_to_deg(to_deg);
        c.set_step_deg(0.5);
        for (const double s : {0.002, 0.004, 0.008}) c.add_exposure_times_s(s);
        c.set_keep_raw(true);
        c.set_pixel_pitch_um(5.86);
        c.set_output_dir(dir);
        return c;
    }
};

TEST_F(AravisDaemon, ABracketedSweepIsMergedAndACameraKilledMidSweepPausesThenResumes) {
    FakeGvCameraProcess fake;
    ASSERT_EQ(fake.start(), "");
    t::TempDir dir;
    // Not linear and not calibrated: refused before a frame is taken.
    {
        t::Daemon daemon(dir.path + "/refuses", rig({}));
        auto stub = daemon.stub();
        v1::Job job;
        ASSERT_TRUE(t::startSweep(*stub, sweep("s", 0.5), &job).ok());
        const v1::Job failed = t::waitFor(*stub, job.id(), t::ended, 60);
        EXPECT_EQ(failed.state(), v1::FAILED);
        EXPECT_NE(failed.reason().find("not linear"), std::string::npos) << failed.reason();
    }
    const drivers::CameraCalibration calibration = calibrate(dir.path);
    ASSERT_FALSE(calibration.linear);

    t::Daemon daemon(dir.path + "/state", rig({calibration}));
    auto stub = daemon.stub();
    v1::Job job;
    // 41 frames: long enough (a few seconds) to kill the camera in the middle.
    ASSERT_TRUE(t::startSweep(*stub, sweep("fake", 20.0), &job).ok());
    t::waitFor(
        *stub, job.id(), [](const v1::Job& j) { return j.frames_done() >= 3; }, 60);
    fake.kill();
    const v1::Job paused = t::waitFor(
        *stub, job.id(), [](const v1::Job& j) { return j.state() == v1::PAUSED || t::ended(j); },
        60);
    ASSERT_EQ(paused.state(), v1::PAUSED) << paused.reason();
    EXPECT_NE(paused.reason().find("[disconnected]"), std::string::npos) << paused.reason();
    EXPECT_LT(paused.frames_done(), 41u);

    ASSERT_EQ(fake.start(), "");
    v1::JobControlRequest resume;
    resume.set_job_id(job.id());
    v1::Job resumed;
    auto ctx = t::context();
    ASSERT_TRUE(stub->ResumeJob(ctx.get(), resume, &resumed).ok());
    const v1::Job done = t::waitFor(*stub, job.id(), t::ended, 120);
    ASSERT_EQ(done.state(), v1::SUCCEEDED) << done.reason();

    auto swept = hdr::readSweep(daemon.output_root + "/fake", t::strictRead());
    ASSERT_TRUE(swept) << swept.error().message;
    ASSERT_EQ(swept->frames.size(), 41u);
    std::set<double> angles;
    for (const hdr::SweepFrame& f : swept->frames) {
        EXPECT_TRUE(angles.insert(f.angle_deg).second) << "angle " << f.angle_deg << " twice";
        // The raw brackets as the camera gave them: the fake's mean grows with the logarithm of
        // the exposure, by the same step per doubling (its documented response).
        ASSERT_EQ(f.raw_files.size(), 3u);
        std::vector<double> means;
        for (const std::string& raw : f.raw_files) {
            auto frame = hdr::readRaw(daemon.output_root + "/fake/" + raw);
            ASSERT_TRUE(frame) << frame.error().message;
            double sum = 0.0;
            for (const uint16_t v : frame->samples) sum += v;
            means.push_back(sum / frame->samples.size());
        }
        EXPECT_LT(means[0], means[1]);
        EXPECT_LT(means[1], means[2]);
        EXPECT_NEAR(means[2] - means[1], means[1] - means[0], 0.15 * (means[1] - means[0]))
            << "at " << f.angle_deg << " deg: " << means[0] << " " << means[1] << " " << means[2];
    }
    auto image = hdr::loadFrame(*swept, 0);
    ASSERT_TRUE(image) << image.error().message;
    EXPECT_EQ(image->image.width, 256);
}

TEST_F(AravisDaemon, PacketLossGivesTypedFailuresThatPauseTheJob) {
    FakeGvCameraProcess lossy(flarelab::testing::kFakeSerial, 700);  // 70 % of packets lost
    ASSERT_EQ(lossy.start(), "");
    t::TempDir dir;
    drivers::CameraCalibration calibration;
    {
        // Calibrated on a camera that loses nothing, as a lab would.
        lossy.kill();
        FakeGvCameraProcess clean;
        ASSERT_EQ(clean.start(), "");
        calibration = calibrate(dir.path);
        clean.kill();
        ASSERT_EQ(lossy.start(), "");
    }
    ManagerOptions m = rig({calibration});
    m.runner.camera_retries = 1;
    t::Daemon daemon(dir.path + "/state", m);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(t::startSweep(*stub, sweep("lossy", 1.0), &job).ok());
    const v1::Job paused = t::waitFor(
        *stub, job.id(), [](const v1::Job& j) { return j.state() == v1::PAUSED || t::ended(j); },
        90);
    ASSERT_EQ(paused.state(), v1::PAUSED) << paused.reason();
    EXPECT_NE(paused.reason().find("[bad-frame]"), std::string::npos) << paused.reason();
    bool retried = false;
    for (const auto& w : paused.warnings())
        retried |= w.find("(retry 1 of 1)") != std::string::npos;
    EXPECT_TRUE(retried);
    v1::JobControlRequest cancel;
    cancel.set_job_id(job.id());
    v1::Job cancelled;
    auto ctx = t::context();
    ASSERT_TRUE(stub->CancelJob(ctx.get(), cancel, &cancelled).ok());
    EXPECT_EQ(t::waitFor(*stub, job.id(), t::ended, 60).state(), v1::CANCELLED);
}

}  // namespace
}  // namespace flarelab::daemon
