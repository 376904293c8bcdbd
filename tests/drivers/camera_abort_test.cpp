// Camera::abort(): another thread ends a capture in progress as [stopped], for every backend that
// can run here (the simulated camera in real time, V4L2 on a played-back device, the replay); the
// GigE Vision backend's is in tests/aravis, libcamera's has no camera to run against (see
// docs/lab.md). A capture after an abort is [stopped] too: an abort that comes just before a
// capture begins is never lost.
#include <gtest/gtest.h>

#include <chrono>
#include <future>
#include <thread>

#include "drivers/replay.h"
#include "drivers/sim_camera.h"
#include "drivers/v4l2_camera.h"
#include "drivers/v4l2_dump.h"
#include "drivers/v4l2_playback.h"
#include "optics/prescription.h"
#include "tests/test_lenses.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

using Clock = std::chrono::steady_clock;

using flarelab::testing::heliar;

SimCameraOptions tiny() {
    SimCameraOptions o;
    o.width_px = 64;
    o.height_px = 43;
    o.render.base_grid = 16;
    o.render.probe_grid = 6;
    o.render.starburst_options.mask_size = 32;
    o.render.starburst_options.fft_size = 128;
    return o;
}

std::optional<DeviceFault> faultOf(const Result<hdr::RawFrame>& frame) {
    return frame ? std::nullopt : deviceFaultOf(frame.error());
}

// Captures on a thread of its own; the result, or nothing when it has not returned within
// `patience` (the capture then runs on to its own end before the test returns).
std::optional<Result<hdr::RawFrame>> captureAborted(Camera& camera,
                                                    double timeout_s,
                                                    std::chrono::milliseconds abort_after,
                                                    std::chrono::seconds patience) {
    auto running = std::async(std::launch::async, [&] { return camera.capture(timeout_s); });
    std::this_thread::sleep_for(abort_after);
    camera.abort();
    if (running.wait_for(patience) != std::future_status::ready) {
        running.wait();
        return std::nullopt;
    }
    return running.get();
}

TEST(CameraAbort, SimulatedCameraInRealTimeStopsA30SecondExposureAtOnce) {
    auto clock = std::make_shared<SimClock>(SimTime::RealTime);
    SimCameraOptions o = tiny();
    o.exposure_s = 30.0;
    auto made = SimCamera::make(heliar(), o, clock);
    ASSERT_TRUE(made) << made.error().message;
    SimCamera& camera = **made;
    const auto start = Clock::now();
    const auto frame =
        captureAborted(camera, 200.0, std::chrono::milliseconds(200), std::chrono::seconds(20));
    ASSERT_TRUE(frame) << "the capture ran on to the end of its 30 s exposure";
    EXPECT_EQ(faultOf(*frame), DeviceFault::Stopped)
        << (*frame ? "a frame came back" : frame->error().message);
    std::printf("stopped %.3f s into a 30 s exposure\n",
                std::chrono::duration<double>(Clock::now() - start).count());
    // Sticky: the next capture does not begin.
    EXPECT_EQ(faultOf(camera.capture(200.0)), DeviceFault::Stopped);
}

TEST(CameraAbort, SimulatedCameraStopsWhileWaitingOutAnInjectedTimeout) {
    auto clock = std::make_shared<SimClock>(SimTime::RealTime);
    auto made = SimCamera::make(heliar(), tiny(), clock);
    ASSERT_TRUE(made) << made.error().message;
    SimCameraFaults faults;
    faults.time_out_captures = 1;
    (*made)->setFaults(faults);
    const auto frame =
        captureAborted(**made, 60.0, std::chrono::milliseconds(100), std::chrono::seconds(20));
    ASSERT_TRUE(frame) << "the capture waited out its 60 s timeout";
    EXPECT_EQ(faultOf(*frame), DeviceFault::Stopped);
}

TEST(CameraAbort, AnAbortBeforeTheCaptureIsNotLostInFastModeEither) {
    auto made = SimCamera::make(heliar(), tiny());  // simulated time: nothing sleeps
    ASSERT_TRUE(made) << made.error().message;
    ASSERT_TRUE((*made)->capture(100.0));
    (*made)->abort();
    (*made)->abort();  // more than once is allowed
    const auto frame = (*made)->capture(100.0);
    ASSERT_FALSE(frame);
    EXPECT_EQ(faultOf(frame), DeviceFault::Stopped);
    EXPECT_NE(frame.error().message.find("aborted"), std::string::npos) << frame.error().message;
}

TEST(CameraAbort, V4l2CaptureStopsWithinOnePollSliceOfALongExposure) {
    auto dump = loadV4l2Dump(flarelab::testing::sourcePath("tests/data/v4l2/vivid-default.txt"));
    ASSERT_TRUE(dump) << dump.error().message;
    // The played-back device runs on its own clock; the abort comes from the frame callback, as
    // from another thread while the camera waits for a 30 s exposure.
    Camera* armed = nullptr;
    V4l2PlaybackOptions p;
    p.exposure_s = [&](const V4l2PlaybackFrame&) {
        if (armed) armed->abort();
        return 30.0;
    };
    auto device = makeV4l2Playback(std::move(*dump), std::move(p));
    ASSERT_TRUE(device) << device.error().message;
    V4l2Playback* playback = device->get();
    V4l2CameraOptions options;
    options.format = "Y16";
    options.width_px = 320;
    options.height_px = 180;
    auto camera = V4l2Camera::open(std::move(*device), options, "v4l2:test");
    ASSERT_TRUE(camera) << camera.error().message;
    armed = camera->get();
    const int64_t start = playback->monotonicNs();
    const auto frame = (*camera)->capture(100.0);
    const int64_t waited = playback->monotonicNs() - start;
    ASSERT_FALSE(frame) << "a 30 s frame came back";
    EXPECT_EQ(deviceFaultOf(frame.error()), DeviceFault::Stopped) << frame.error().message;
    EXPECT_LE(waited, 200'000'000) << "waited " << waited * 1e-9 << " s of the device's time";
    EXPECT_EQ(faultOf((*camera)->capture(100.0)), DeviceFault::Stopped);
}

TEST(CameraAbort, ReplayCameraRefusesCapturesOnceAborted) {
    auto rig = openReplay(flarelab::testing::sourcePath("tests/data/sweeps/heliar-raw"));
    ASSERT_TRUE(rig) << rig.error().message;
    ASSERT_TRUE(rig->head->home(1.0));
    ASSERT_TRUE(rig->camera->setExposure(rig->sweep->frames[0].exposure_times_s[0]));
    ASSERT_TRUE(rig->camera->capture(1.0));
    rig->camera->abort();
    EXPECT_EQ(faultOf(rig->camera->capture(1.0)), DeviceFault::Stopped);
}

}  // namespace
}  // namespace flarelab::drivers
