// The daemon's own devices (flarelabd --camera, --head): jobs that name them, jobs that mix them
// with simulated ones, and the requests that cannot run on them.
#include <gtest/gtest.h>

#include "tests/daemon/daemon_fixture.h"

namespace flarelab::daemon::testing {
namespace {

std::string simCameraUri() {
    return "sim:?lens=" + flarelab::testing::lensPath("heliar-tronnier.csv") +
           "&width=64&height=43&seed=5";
}

// A job for the daemon's devices: no sim settings, the size left to the camera.
v1::SweepConfig deviceConfig(const std::string& output_dir) {
    v1::SweepConfig c;
    c.set_from_deg(0.0);
    c.set_to_deg(0.4);
    c.set_step_deg(0.2);
    for (const double t : {0.01, 0.04}) c.add_exposure_times_s(t);
    c.set_output_dir(output_dir);
    c.set_pixel_pitch_um(562.5);
    c.set_lens_description("the lens on the test camera");
    return c;
}

ManagerOptions withDevices(std::vector<std::string> cameras, std::vector<std::string> heads) {
    ManagerOptions m;
    m.runner.limits.cameras = std::move(cameras);
    m.runner.limits.heads = std::move(heads);
    return m;
}

TEST(Devices, AJobRunsOnTheDaemonsCameraAndHeadAndDescribeRigNamesThem) {
    TempDir dir;
    const std::string head = "sim:?time=fast&settle_s=0";
    ServerOptions server;
    server.service.rig = "devices";
    server.service.cameras = {simCameraUri()};
    server.service.heads = {head};
    Daemon daemon(dir.path, withDevices({simCameraUri()}, {head}), server);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, deviceConfig("dev"), &job).ok());
    const v1::Job done = waitFor(*stub, job.id(), ended);
    ASSERT_EQ(done.state(), v1::SUCCEEDED) << done.reason();
    auto sweep = hdr::readSweep(daemon.output_root + "/dev", strictRead());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 3u);
    EXPECT_EQ(sweep->header.capture.width_px, 64);  // the camera's size
    EXPECT_EQ(sweep->header.camera.pixel_pitch_um, 562.5);
    EXPECT_NE(sweep->header.software_version.find(head), std::string::npos)
        << sweep->header.software_version;

    v1::RigDescription rig;
    auto ctx = context();
    ASSERT_TRUE(stub->DescribeRig(ctx.get(), {}, &rig).ok());
    EXPECT_EQ(rig.rig(), "devices");
    ASSERT_EQ(rig.cameras_size(), 1);
    ASSERT_EQ(rig.heads_size(), 1);
    EXPECT_EQ(rig.heads(0).uri(), head);
    EXPECT_EQ(rig.heads(0).serial(), "SIMHEAD-0");  // as the job's head named itself
    EXPECT_EQ(rig.camera().uri(), simCameraUri());
}

TEST(Devices, ADeviceTheDaemonLacksIsSimulatedFromTheConfig) {
    TempDir dir;
    // A real head (here the simulated one, named as a device), the camera from config.sim.
    Daemon daemon(dir.path, withDevices({}, {"sim:?time=fast"}));
    auto stub = daemon.stub();
    v1::Job job;
    v1::SweepConfig c = simConfig("mixed", 0.0, 0.2, 0.2);
    ASSERT_TRUE(startSweep(*stub, c, &job).ok());
    const v1::Job done = waitFor(*stub, job.id(), ended);
    EXPECT_EQ(done.state(), v1::SUCCEEDED) << done.reason();

    // Faults are injected into simulated devices only.
    c.set_output_dir("mixed2");
    c.mutable_sim()->mutable_faults()->set_head_hangs(1);
    const grpc::Status refused = startSweep(*stub, c, &job);
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_EQ(refused.error_message().rfind("config.sim.faults", 0), 0u) << refused.error_message();
}

TEST(Devices, RequestsTheDevicesCannotServeAreRefusedNamingTheField) {
    TempDir dir;
    Daemon daemon(dir.path, withDevices({simCameraUri()}, {"sim:?time=fast"}));
    auto stub = daemon.stub();
    v1::Job job;
    const auto refusal = [&](const v1::SweepConfig& c) {
        const grpc::Status s = startSweep(*stub, c, &job);
        EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
        return s.error_message();
    };
    v1::SweepConfig c = deviceConfig("x");
    c.set_camera("v4l2:/dev/video0");
    const std::string other = refusal(c);
    EXPECT_EQ(other.rfind("config.camera: 'v4l2:/dev/video0' is not a device of this daemon", 0),
              0u)
        << other;
    EXPECT_NE(other.find(simCameraUri()), std::string::npos) << "lists what it has";

    c = deviceConfig("x");
    *c.mutable_sim() = simConfig("x", 0, 1, 1).sim();
    EXPECT_EQ(refusal(c).rfind("config.sim: this job runs on real devices", 0), 0u);

    c = deviceConfig("x");
    c.set_pixel_pitch_um(-3.0);
    EXPECT_EQ(refusal(c).rfind("config.pixel_pitch_um", 0), 0u);

    // A size other than the camera's fails the job when it opens the camera, saying both.
    c = deviceConfig("size");
    c.set_width_px(100);
    c.set_height_px(50);
    ASSERT_TRUE(startSweep(*stub, c, &job).ok());
    const v1::Job failed = waitFor(*stub, job.id(), ended);
    EXPECT_EQ(failed.state(), v1::FAILED);
    EXPECT_NE(failed.reason().find("delivers 64 x 43 frames, not 100 x 50"), std::string::npos)
        << failed.reason();
}

TEST(Devices, WithoutDevicesAJobMustSayWhatToSimulate) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::Job job;
    v1::SweepConfig c = deviceConfig("x");
    const grpc::Status s = startSweep(*stub, c, &job);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_EQ(s.error_message().rfind("config.sim: is missing: this job's camera is simulated", 0),
              0u)
        << s.error_message();
    c.set_head("zaber:/dev/ttyUSB0");
    EXPECT_EQ(startSweep(*stub, c, &job).error_message().rfind("config.head", 0), 0u);
}

}  // namespace
}  // namespace flarelab::daemon::testing
