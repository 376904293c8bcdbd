// The daemon's own devices (flarelabd --camera, --head): jobs that name them, jobs that mix them
// with simulated ones, and the requests that cannot run on them.
#include <gtest/gtest.h>

#include <algorithm>
#include <sstream>

#include "apps/calibrate_command.h"
#include "drivers/calibration.h"
#include "tests/apps/command_runner.h"
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

// A sweep of frames 0 .. 0.4 deg on the daemon's camera `camera`, its EXRs' green channel.
std::vector<std::vector<float>> sweepOn(const std::string& state_dir,
                                        const std::string& camera,
                                        const std::vector<drivers::CameraCalibration>& calibrations,
                                        v1::Job* job) {
    ManagerOptions m = withDevices({camera}, {"sim:?time=fast"});
    m.runner.calibrations = calibrations;
    Daemon daemon(state_dir, m);
    auto stub = daemon.stub();
    v1::SweepConfig c = deviceConfig("s");
    c.clear_exposure_times_s();
    for (const double t : {0.05, 0.2, 0.8}) c.add_exposure_times_s(t);
    v1::Job started;
    EXPECT_TRUE(startSweep(*stub, c, &started).ok());
    *job = waitFor(*stub, started.id(), ended);
    std::vector<std::vector<float>> frames;
    if (job->state() != v1::SUCCEEDED) return frames;
    auto sweep = hdr::readSweep(daemon.output_root + "/s");
    EXPECT_TRUE(sweep) << sweep.error().message;
    for (size_t i = 0; sweep && i < sweep->frames.size(); ++i) {
        auto image = hdr::loadFrame(*sweep, i);
        EXPECT_TRUE(image) << image.error().message;
        std::vector<float> green;
        for (size_t k = 1; image && k < image->image.pixels.size(); k += 3)
            green.push_back(image->image.pixels[k]);
        frames.push_back(std::move(green));
    }
    return frames;
}

TEST(Devices, ACameraThatIsNotLinearIsMergedOnlyThroughItsCalibration) {
    const std::string curved = simCameraUri() + "&response=gamma";
    v1::Job job;
    {
        TempDir dir;
        const auto none = sweepOn(dir.path, curved, {}, &job);
        EXPECT_EQ(job.state(), v1::FAILED);
        EXPECT_NE(job.reason().find("not linear"), std::string::npos) << job.reason();
        EXPECT_NE(job.reason().find("flarelab calibrate"), std::string::npos) << job.reason();
    }
    // Calibrated as a lab would (the simulated camera caps its own lens for the dark frames).
    TempDir dir;
    const std::string file = dir.path + "/curved.cal.json";
    std::istringstream no_input;
    const auto run = apps::testing::runCommand(
        [&](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
            apps::addCalibrateCommand(app, out, err, code, no_input);
        },
        {"calibrate", "--camera", curved, "--yes", "-o", file});
    ASSERT_EQ(run.code, 0) << run.err;
    auto calibration = drivers::readCalibration(file);
    ASSERT_TRUE(calibration) << calibration.error().message;
    ASSERT_FALSE(calibration->linear);

    TempDir a, b;
    const auto through = sweepOn(a.path, curved, {*calibration}, &job);
    ASSERT_EQ(job.state(), v1::SUCCEEDED) << job.reason();
    v1::Job linear_job;
    const auto linear = sweepOn(b.path, simCameraUri(), {}, &linear_job);
    ASSERT_EQ(linear_job.state(), v1::SUCCEEDED) << linear_job.reason();
    // Linearized, the curved camera's frames are proportional to the linear camera's (the curve
    // gives relative exposure, so the scale is its own): over 8 x 8 blocks (sums, so that the dim
    // background's noise averages out) the ratio of the two varies by a few percent from the
    // background to the ghosts and the light, which span two decades. A straight "curve" in place
    // of the measured one (the gamma left in) bends the ratio far beyond that: the check can fail.
    drivers::CameraCalibration straight = *calibration;
    for (size_t k = 0; k < straight.response_curve->dn.size(); ++k)
        straight.response_curve->relative_exposure[k] =
            (straight.response_curve->dn[k] - straight.black_level_dn) /
            (straight.saturation_dn - straight.black_level_dn);
    TempDir c;
    v1::Job straight_job;
    const auto bent = sweepOn(c.path, curved, {straight}, &straight_job);
    ASSERT_EQ(straight_job.state(), v1::SUCCEEDED) << straight_job.reason();
    ASSERT_EQ(through.size(), linear.size());
    const auto blocks = [](const std::vector<float>& green) {
        std::vector<double> sums;
        for (int by = 0; by + 8 <= 43; by += 8)
            for (int bx = 0; bx + 8 <= 64; bx += 8) {
                double sum = 0.0;
                for (int y = by; y < by + 8; ++y)
                    for (int x = bx; x < bx + 8; ++x) sum += green[y * 64 + x];
                sums.push_back(sum);
            }
        return sums;
    };
    for (size_t f = 0; f < through.size(); ++f) {
        const std::vector<double> t = blocks(through[f]), l = blocks(linear[f]);
        std::vector<double> ratios;
        for (size_t k = 0; k < l.size(); ++k)
            if (l[k] > 0.0) ratios.push_back(t[k] / l[k]);
        ASSERT_GE(ratios.size(), 30u);
        std::sort(ratios.begin(), ratios.end());
        const double median = ratios[ratios.size() / 2];
        const double lo = ratios[ratios.size() / 20], hi = ratios[ratios.size() * 19 / 20];
        const auto [dim, bright] = std::minmax_element(l.begin(), l.end());
        EXPECT_GT(*bright / *dim, 50.0) << "frame " << f;
        EXPECT_LT((hi - lo) / median, 0.1) << "frame " << f << ": ratios " << lo << " .. " << hi;
        const auto spread = [&](const std::vector<float>& frame) {
            const std::vector<double> t2 = blocks(frame);
            std::vector<double> r;
            for (size_t k = 0; k < l.size(); ++k)
                if (l[k] > 0.0) r.push_back(t2[k] / l[k]);
            std::sort(r.begin(), r.end());
            return (r[r.size() * 19 / 20] - r[r.size() / 20]) / r[r.size() / 2];
        };
        EXPECT_GT(spread(bent[f]), 0.3) << "frame " << f;
    }
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
