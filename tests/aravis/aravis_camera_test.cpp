// AravisCamera against Aravis's fake GigE Vision camera over GVCP/GVSP on loopback, each test in
// a network namespace of its own (in_netns.sh). Timings are printed, never asserted.
#include "drivers/aravis_camera.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <future>
#include <numeric>
#include <thread>

#include "tests/aravis/fake_gv_camera.h"

namespace flarelab::drivers {
namespace {

using flarelab::testing::FakeGvCamera;
using flarelab::testing::FakeGvCameraProcess;
using flarelab::testing::fakePatternMatches;
using Clock = std::chrono::steady_clock;

// GigE Vision bootstrap register SCPS0: stream channel 0 packet size in its low 16 bits.
constexpr uint32_t kScps0 = 0x0d04;
constexpr const char* kRoi = "roi=16,8,128,64";  // 16 KiB a Mono16 frame: a dozen packets

double seconds(Clock::time_point since) {
    return std::chrono::duration<double>(Clock::now() - since).count();
}

std::optional<DeviceFault> faultOf(const Error& e) { return deviceFaultOf(e); }

double mean(const hdr::RawFrame& f) {
    return std::accumulate(f.samples.begin(), f.samples.end(), 0.0) /
           static_cast<double>(f.samples.size());
}

int64_t stat(const Camera& camera, const std::string& name) {
    for (const auto& [key, value] : camera.statistics())
        if (key == name) return value;
    return -1;
}

std::unique_ptr<AravisCamera> openCamera(const std::string& text) {
    auto uri = parseDeviceUri(text);
    EXPECT_TRUE(uri) << text;
    if (!uri) return nullptr;
    auto camera = AravisCamera::open(*uri);
    EXPECT_TRUE(camera) << text << ": " << (camera ? "" : camera.error().message);
    return camera ? std::move(*camera) : nullptr;
}

class AravisFake : public ::testing::Test {
protected:
    void SetUp() override {
        const std::string isolated = flarelab::testing::isolateLoopback();
        ASSERT_EQ(isolated, "") << "not in a network namespace of its own";
    }
};

class AravisCameraTest : public AravisFake {
protected:
    void SetUp() override {
        AravisFake::SetUp();
        if (HasFatalFailure()) return;
        fake_ = std::make_unique<FakeGvCamera>();
        ASSERT_TRUE(fake_->running()) << "Aravis's fake camera did not start on 127.0.0.1";
    }
    std::unique_ptr<FakeGvCamera> fake_;
};

TEST_F(AravisCameraTest, ListsTheFakeWithItsIdentityAndFormats) {
    // A USB3 Vision camera on the test machine is no business of this test.
    arv_disable_interface("USB3Vision");
    const auto t0 = Clock::now();
    const auto listed = listAravisCameras();
    std::printf("listing took %.2f s\n", seconds(t0));
    ASSERT_EQ(listed.size(), 1u);
    const DeviceListing& d = listed[0];
    EXPECT_EQ(d.uri, "aravis:Aravis-Fake-GV01");
    EXPECT_EQ(d.kind, "camera");
    EXPECT_EQ(d.backend, "aravis");
    EXPECT_EQ(d.model, "Aravis Fake");
    EXPECT_EQ(d.serial, "GV01");
    const auto has = [&](const std::string& line) {
        return std::find(d.details.begin(), d.details.end(), line) != d.details.end();
    };
    EXPECT_TRUE(has("vendor: Aravis"));
    EXPECT_TRUE(has("address: 127.0.0.1"));
    EXPECT_TRUE(has("protocol: GigEVision"));
    EXPECT_TRUE(has("pixel formats: BayerBG8, BayerGB8, BayerGR8, BayerRG8, Mono8, RGB8, Mono16"));
    EXPECT_TRUE(
        has("raw formats flarelab takes, best first: Mono16, Mono8, BayerBG8, BayerGB8, "
            "BayerGR8, BayerRG8"));
}

TEST_F(AravisCameraTest, OpensByIdByAddressAndThroughTheRegistry) {
    for (const std::string& uri : {std::string("aravis:Aravis-Fake-GV01?") + kRoi,
                                   std::string("aravis:127.0.0.1?") + kRoi}) {
        auto camera = openCamera(uri);
        ASSERT_TRUE(camera);
        EXPECT_EQ(camera->identity().backend, "aravis");
        EXPECT_EQ(camera->identity().model, "Aravis Fake");
        EXPECT_EQ(camera->identity().serial, "GV01");
        EXPECT_EQ(camera->identity().uri, uri);
        auto frame = camera->capture(2.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_EQ(frame->camera, "Aravis Fake GV01");
    }
    CameraRegistry registry;
    ASSERT_TRUE(addAravisCameraBackend(registry));
    auto camera = registry.open(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera) << camera.error().message;
    EXPECT_EQ((*camera)->capabilities().width_px, 128);
    EXPECT_EQ((*camera)->capabilities().height_px, 64);
}

TEST_F(AravisCameraTest, AbsentCameraIsNotFoundWithinItsTimeout) {
    auto uri = parseDeviceUri("aravis:Nobody-Here-1?timeout_s=0.5");
    ASSERT_TRUE(uri);
    const auto t0 = Clock::now();
    auto camera = AravisCamera::open(*uri);
    std::printf("not found after %.2f s\n", seconds(t0));
    ASSERT_FALSE(camera);
    EXPECT_EQ(camera.error().code, ErrorCode::NotFound);
    EXPECT_NE(camera.error().message.find("Nobody-Here-1"), std::string::npos);
}

TEST_F(AravisCameraTest, RefusesRegionsAndFormatsTheCameraCannotTake) {
    for (const char* text :
         {"aravis:Aravis-Fake-GV01?roi=2000,0,128,64", "aravis:Aravis-Fake-GV01?roi=0,0,4096,64"}) {
        auto uri = parseDeviceUri(text);
        ASSERT_TRUE(uri);
        auto camera = AravisCamera::open(*uri);
        ASSERT_FALSE(camera) << text;
        EXPECT_EQ(camera.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(camera.error().message.find("roi="), std::string::npos) << camera.error().message;
        EXPECT_NE(camera.error().message.find("2048 x 2048"), std::string::npos);
    }
    auto uri = parseDeviceUri("aravis:Aravis-Fake-GV01?pixel_format=Mono12");
    ASSERT_TRUE(uri);
    auto camera = AravisCamera::open(*uri);
    ASSERT_FALSE(camera);
    EXPECT_NE(camera.error().message.find("pixel_format=Mono12 is not offered"), std::string::npos)
        << camera.error().message;
}

TEST_F(AravisCameraTest, PrefersMono16AndCapturesEveryRawFormatTheFakeOffers) {
    {
        auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
        ASSERT_TRUE(camera);
        EXPECT_EQ(camera->pixelFormatName(), "Mono16");
        for (const std::string& n : camera->notes())
            EXPECT_EQ(n.find("warning"), std::string::npos) << n;
        const CameraCapabilities caps = camera->capabilities();
        EXPECT_EQ(caps.bit_depth, 16);
        EXPECT_EQ(caps.white_level_dn, 65535.0);
        EXPECT_EQ(caps.formats,
                  (std::vector<hdr::RawFormat>{hdr::RawFormat::Mono, hdr::RawFormat::BayerBGGR,
                                               hdr::RawFormat::BayerGBRG, hdr::RawFormat::BayerGRBG,
                                               hdr::RawFormat::BayerRGGB}));
        // setFormat picks the best of a layout: the fake's Bayer formats have 8 bits.
        ASSERT_TRUE(camera->setFormat(hdr::RawFormat::BayerRGGB));
        EXPECT_EQ(camera->pixelFormatName(), "BayerRG8");
        auto bayer = camera->capture(2.0);
        ASSERT_TRUE(bayer) << bayer.error().message;
        EXPECT_EQ(bayer->format, hdr::RawFormat::BayerRGGB);
        EXPECT_EQ(bayer->bit_depth, 8);
        ASSERT_TRUE(camera->setFormat(hdr::RawFormat::Mono));
        EXPECT_EQ(camera->pixelFormatName(), "Mono16");
    }
    struct Case {
        const char* name;
        hdr::RawFormat layout;
        int bits;
    };
    for (const Case c :
         {Case{"Mono16", hdr::RawFormat::Mono, 16}, Case{"Mono8", hdr::RawFormat::Mono, 8},
          Case{"BayerRG8", hdr::RawFormat::BayerRGGB, 8},
          Case{"BayerBG8", hdr::RawFormat::BayerBGGR, 8},
          Case{"BayerGR8", hdr::RawFormat::BayerGRBG, 8},
          Case{"BayerGB8", hdr::RawFormat::BayerGBRG, 8}}) {
        SCOPED_TRACE(c.name);
        auto camera =
            openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi + "&pixel_format=" + c.name);
        ASSERT_TRUE(camera);
        ASSERT_TRUE(camera->setExposure(0.02));
        auto frame = camera->capture(2.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_EQ(frame->format, c.layout);
        EXPECT_EQ(frame->bit_depth, c.bits);
        EXPECT_EQ(frame->white_level_dn, std::ldexp(1.0, c.bits) - 1.0);
        EXPECT_EQ(frame->width, 128);
        EXPECT_EQ(frame->height, 64);
        ASSERT_EQ(frame->samples.size(), 128u * 64u);
        EXPECT_GT(*std::max_element(frame->samples.begin(), frame->samples.end()), 0);
        if (c.bits == 8) {
            EXPECT_LE(*std::max_element(frame->samples.begin(), frame->samples.end()), 255);
            ASSERT_FALSE(camera->notes().empty());
            EXPECT_NE(camera->notes()[0].find("warning: pixel format " + std::string(c.name) +
                                              " has 8 bits"),
                      std::string::npos);
        }
        // Grey frames are exactly the fake's pattern: bytes unpacked in the right order.
        if (c.layout == hdr::RawFormat::Mono) {
            EXPECT_TRUE(fakePatternMatches(*frame, 20000, 0));
        }
    }
    // RGB8 is offered but is no raw sensor format.
    auto uri = parseDeviceUri("aravis:Aravis-Fake-GV01?pixel_format=RGB8");
    ASSERT_TRUE(uri);
    const auto refused = AravisCamera::open(*uri);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("pixel_format=RGB8"), std::string::npos);
}

// The fake's response (fake_gv_camera.h): s = 1 + GainRaw + log10(t / 10 ms) scales a ramp, so
// the mean grows with log t, not with t, and is 0 at 1 ms and below.
TEST_F(AravisCameraTest, FrameMeansRiseWithTheLogarithmOfTheExposure) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    EXPECT_EQ(camera->capabilities().response, CameraResponse::NonLinear);
    EXPECT_NE(camera->capabilities().response_note.find("logarithm of the exposure"),
              std::string::npos);
    std::vector<double> means;
    for (const double t : {0.0005, 0.002, 0.004, 0.008, 0.016}) {
        ASSERT_TRUE(camera->setExposure(t));
        auto frame = camera->capture(2.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_TRUE(fakePatternMatches(*frame, static_cast<uint32_t>(std::lround(t * 1e6)), 0))
            << "exposure " << t;
        means.push_back(mean(*frame));
        std::printf("exposure %.4f s: mean %.1f DN\n", t, means.back());
    }
    EXPECT_EQ(means[0], 0.0);  // below 1 ms the scale is negative: clipped to black
    for (size_t i = 2; i < means.size(); ++i) EXPECT_GT(means[i], means[i - 1]);
    // Each doubling of the exposure adds the same (log10 2 to the scale) while little of the
    // ramp clips (scales 0.3, 0.6, 0.9): a linear camera would double the mean instead.
    EXPECT_NEAR((means[3] - means[2]) / (means[2] - means[1]), 1.0, 0.05);
    EXPECT_LT(means[3] / means[1], 3.5);  // 4 x the exposure
    // At 16 ms (scale 1.2) the ramp's top clips at 65535: the step shrinks.
    EXPECT_LT(means[4] - means[3], 0.9 * (means[3] - means[2]));
}

TEST_F(AravisCameraTest, ReadsBackTheExposureAndGainTheCameraApplied) {
    // GainRaw steps of 6.0206 dB: raw 1 is x2, raw 2 is x4.
    auto camera =
        openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi + "&gain_db_per_raw=6.0206");
    ASSERT_TRUE(camera);
    const CameraCapabilities caps = camera->capabilities();
    EXPECT_NEAR(caps.min_exposure_s, 10e-6, 1e-12);  // ExposureTimeAbs: 10 us .. 10 s
    EXPECT_NEAR(caps.max_exposure_s, 10.0, 1e-9);
    EXPECT_NEAR(caps.min_gain, 1.0, 1e-12);  // GainRaw 0 .. 10
    EXPECT_NEAR(caps.max_gain, std::pow(10.0, 60.206 / 20.0), 1e-6);

    // The fake keeps whole microseconds: 1234.6 us becomes 1234 us.
    ASSERT_TRUE(camera->setExposure(0.0012346));
    EXPECT_NEAR(camera->exposure_s(), 0.001234, 1e-12);
    // Gain 3 is 9.54 dB: the nearest raw step is 2 (12.04 dB), gain 4.
    ASSERT_TRUE(camera->setGain(3.0));
    EXPECT_NEAR(camera->gain(), 4.0, 1e-4);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_EXPOSURE_TIME_US), 1234u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_GAIN_RAW), 2u);
    auto frame = camera->capture(2.0);
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_NEAR(frame->exposure_s, 0.001234, 1e-12);
    EXPECT_NEAR(frame->gain, 4.0, 1e-4);
    EXPECT_TRUE(fakePatternMatches(*frame, 1234, 2));  // taken with what was read back

    const Status too_long = camera->setExposure(20.0);
    ASSERT_FALSE(too_long);
    EXPECT_EQ(faultOf(too_long.error()), DeviceFault::OutOfRange);
    EXPECT_NE(too_long.error().message.find("exposure_s"), std::string::npos);
    EXPECT_NEAR(camera->exposure_s(), 0.001234, 1e-12);  // a failed call changes nothing

    // Without a scale for GainRaw only unity is offered, and the message says what to add.
    camera.reset();  // one controller at a time
    auto plain = openCamera(std::string("aravis:127.0.0.1?") + kRoi);
    ASSERT_TRUE(plain);
    EXPECT_EQ(plain->capabilities().max_gain, 1.0);
    const Status gain2 = plain->setGain(2.0);
    ASSERT_FALSE(gain2);
    EXPECT_EQ(faultOf(gain2.error()), DeviceFault::OutOfRange);
    EXPECT_NE(gain2.error().message.find("gain_db_per_raw"), std::string::npos);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_GAIN_RAW), 0u);
}

TEST_F(AravisCameraTest, TakesABracketOfThreeExposuresOneFrameEach) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    const std::vector<double> exposures = {0.004, 0.016, 0.064};
    std::vector<hdr::RawFrame> bracket;
    const auto t0 = Clock::now();
    for (const double t : exposures) {
        ASSERT_TRUE(camera->setExposure(t));
        const int64_t before = [] {
            timespec ts{};
            clock_gettime(CLOCK_REALTIME, &ts);
            return int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
        }();
        auto frame = camera->capture(2.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_GE(frame->host_timestamp_ns, before);
        bracket.push_back(std::move(*frame));
    }
    std::printf("bracket of 3 took %.3f s\n", seconds(t0));
    for (size_t i = 0; i < 3; ++i) {
        EXPECT_NEAR(bracket[i].exposure_s, exposures[i], 1e-12);
        EXPECT_EQ(bracket[i].timestamp_marks, hdr::TimestampMark::ExposureStart);
        EXPECT_GT(bracket[i].timestamp_ns, 0);
        if (i == 0) continue;
        // One frame per trigger: consecutive frame ids, later timestamps, brighter frames.
        EXPECT_EQ(bracket[i].sequence, bracket[i - 1].sequence + 1);
        EXPECT_GT(bracket[i].timestamp_ns, bracket[i - 1].timestamp_ns);
        EXPECT_GT(bracket[i].host_timestamp_ns, bracket[i - 1].host_timestamp_ns);
        EXPECT_GT(mean(bracket[i]), mean(bracket[i - 1]));
    }
    EXPECT_EQ(stat(*camera, "completed_buffers"), 3);
    EXPECT_EQ(stat(*camera, "failures"), 0);
}

TEST_F(AravisCameraTest, SingleFrameAcquisitionTakesOneFrameAtEachExposure) {
    auto camera =
        openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi + "&trigger=single-frame");
    ASSERT_TRUE(camera);
    EXPECT_EQ(camera->trigger(), AravisTrigger::SingleFrame);
    for (const double t : {0.004, 0.032, 0.004}) {
        ASSERT_TRUE(camera->setExposure(t));
        auto frame = camera->capture(2.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_TRUE(fakePatternMatches(*frame, static_cast<uint32_t>(std::lround(t * 1e6)), 0))
            << "exposure " << t;
    }
}

TEST_F(AravisCameraTest, SetsThePacketSizeAndSocketBuffer) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi +
                             "&packet_size=1000&socket_buffer=65536");
    ASSERT_TRUE(camera);
    EXPECT_EQ(camera->packetSize(), 1000);
    EXPECT_EQ(fake_->reg(kScps0) & 0xffff, 1000u);
    const int frames = 3;
    for (int i = 0; i < frames; ++i) ASSERT_TRUE(camera->capture(2.0));
    // A 16384-byte frame in packets of 1000 bytes, 36 of them headers (IP, UDP, GVSP):
    // 17 payload packets, a leader and a trailer.
    EXPECT_EQ(stat(*camera, "received_packets"), frames * (17 + 2));
    EXPECT_EQ(stat(*camera, "missing_packets"), 0);

    const auto limit = kernelReceiveBufferLimit();
    ASSERT_TRUE(limit);
    auto uri =
        parseDeviceUri("aravis:Aravis-Fake-GV01?socket_buffer=" + std::to_string(*limit + 1));
    ASSERT_TRUE(uri);
    const auto refused = AravisCamera::open(*uri);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("net.core.rmem_max"), std::string::npos);
    EXPECT_NE(
        refused.error().message.find("sysctl -w net.core.rmem_max=" + std::to_string(*limit + 1)),
        std::string::npos);
}

TEST_F(AravisCameraTest, NoFrameFromALiveCameraIsATimeout) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    fake_->setLostPacketRatio(1.0);  // every GVSP packet dropped; GVCP still answers
    const auto t0 = Clock::now();
    auto frame = camera->capture(0.3);
    std::printf("timeout after %.2f s (asked 0.3 s)\n", seconds(t0));
    ASSERT_FALSE(frame);
    EXPECT_EQ(faultOf(frame.error()), DeviceFault::Timeout) << frame.error().message;
    EXPECT_TRUE(camera->connected());
    fake_->setLostPacketRatio(0.0);
    auto next = camera->capture(2.0);
    ASSERT_TRUE(next) << next.error().message;
}

TEST_F(AravisCameraTest, InjectedPacketLossGivesTypedFailuresThenRetakes) {
    // The fake draws its losses from GLib's global generator: seeded, the run repeats.
    g_random_set_seed(17);
    auto camera =
        openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi + "&retries=2&packet_size=1000");
    ASSERT_TRUE(camera);
    // Half the packets lost: no 19-packet frame arrives whole, some part of each arrives.
    fake_->setLostPacketRatio(0.5);
    const auto t0 = Clock::now();
    auto damaged = camera->capture(2.0);
    std::printf("3 damaged takes in %.2f s\n", seconds(t0));
    ASSERT_FALSE(damaged);
    EXPECT_EQ(faultOf(damaged.error()), DeviceFault::BadFrame) << damaged.error().message;
    EXPECT_NE(damaged.error().message.find("buffer status "), std::string::npos);
    EXPECT_NE(damaged.error().message.find("3 takes, retries=2"), std::string::npos)
        << damaged.error().message;
    EXPECT_EQ(stat(*camera, "retaken_frames"), 2);
    EXPECT_EQ(stat(*camera, "failures"), 3);
    EXPECT_GT(stat(*camera, "missing_packets"), 0);
    EXPECT_EQ(stat(*camera, "resent_packets"), 0);  // the fake cannot resend
    EXPECT_TRUE(camera->connected());
    camera.reset();  // one controller at a time

    // 3 % lost: about half the frames arrive whole; retakes hide the others.
    fake_->setLostPacketRatio(0.03);
    // Through the UDP socket this time (socket_buffer), not Aravis's packet socket.
    auto patient = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi +
                              "&retries=20&packet_size=1000&socket_buffer=262144");
    ASSERT_TRUE(patient);
    for (int i = 0; i < 8; ++i) {
        auto frame = patient->capture(2.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_TRUE(fakePatternMatches(*frame, 10000, 0));  // whole frames only
    }
    EXPECT_GT(stat(*patient, "retaken_frames"), 0);
    EXPECT_EQ(stat(*patient, "completed_buffers"), 8);
    EXPECT_EQ(stat(*patient, "failures"), stat(*patient, "retaken_frames"));
    for (const auto& [key, value] : patient->statistics())
        std::printf("  %s = %lld\n", key.c_str(), static_cast<long long>(value));
}

TEST_F(AravisCameraTest, CameraGoneBetweenFramesIsDisconnected) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    ASSERT_TRUE(camera->capture(2.0));
    fake_->stop();
    const auto t0 = Clock::now();
    auto frame = camera->capture(10.0);
    std::printf("[disconnected] after %.2f s\n", seconds(t0));
    ASSERT_FALSE(frame);
    EXPECT_EQ(faultOf(frame.error()), DeviceFault::Disconnected) << frame.error().message;
    EXPECT_FALSE(camera->connected());
    EXPECT_EQ(stat(*camera, "disconnects"), 1);
    // The next call tries to reopen: no camera, still [disconnected], and soon.
    const auto t1 = Clock::now();
    const Status again = camera->setExposure(0.01);
    std::printf("reopen attempt answered after %.2f s\n", seconds(t1));
    ASSERT_FALSE(again);
    EXPECT_EQ(faultOf(again.error()), DeviceFault::Disconnected) << again.error().message;
    EXPECT_NE(again.error().message.find("reopening failed"), std::string::npos);
    // Within the back-off the answer comes at once, without a search.
    const auto t2 = Clock::now();
    const Status backoff = camera->setExposure(0.01);
    ASSERT_FALSE(backoff);
    EXPECT_NE(backoff.error().message.find("next reopen attempt in"), std::string::npos)
        << backoff.error().message;
    std::printf("within the back-off: %.4f s\n", seconds(t2));
}

TEST_F(AravisCameraTest, CameraGoneWhileWaitingForAFrameIsDisconnectedBeforeTheTimeout) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    fake_->setLostPacketRatio(1.0);  // the frame never comes: capture waits
    std::promise<void> started;
    std::thread killer([&, ready = started.get_future()]() mutable {
        ready.wait();
        std::this_thread::sleep_for(std::chrono::milliseconds(300));
        fake_->stop();
    });
    started.set_value();
    const auto t0 = Clock::now();
    auto frame = camera->capture(30.0);
    const double took = seconds(t0);
    killer.join();
    std::printf("[disconnected] %.2f s into a capture with a 30 s timeout\n", took);
    ASSERT_FALSE(frame);
    // Not [timeout]: the wait ended because the control channel went quiet.
    EXPECT_EQ(faultOf(frame.error()), DeviceFault::Disconnected) << frame.error().message;
}

TEST_F(AravisCameraTest, AbortFromAnotherThreadEndsAWaitingCaptureAsStoppedAndStays) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    fake_->setLostPacketRatio(1.0);  // the frame never comes: capture waits its whole timeout
    std::promise<void> started;
    std::thread stopper([&, ready = started.get_future()]() mutable {
        ready.wait();
        std::this_thread::sleep_for(std::chrono::milliseconds(300));
        camera->abort();
    });
    started.set_value();
    const auto t0 = Clock::now();
    auto frame = camera->capture(30.0);
    const double took = seconds(t0);
    stopper.join();
    std::printf("[stopped] %.2f s into a capture with a 30 s timeout\n", took);
    ASSERT_FALSE(frame);
    // Not [timeout] after 30 s, nor [disconnected]: the wait ended because it was told to.
    EXPECT_EQ(faultOf(frame.error()), DeviceFault::Stopped) << frame.error().message;
    fake_->setLostPacketRatio(0.0);
    auto after = camera->capture(2.0);
    ASSERT_FALSE(after);
    EXPECT_EQ(faultOf(after.error()), DeviceFault::Stopped) << after.error().message;
}

TEST_F(AravisCameraTest, RestartedCameraIsReopenedWithItsSettingsAppliedAgain) {
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi +
                             "&gain_db_per_raw=6.0206&packet_size=1000");
    ASSERT_TRUE(camera);
    ASSERT_TRUE(camera->setExposure(0.02));
    ASSERT_TRUE(camera->setGain(2.0));  // GainRaw 1
    auto first = camera->capture(2.0);
    ASSERT_TRUE(first);

    fake_->stop();
    auto lost = camera->capture(5.0);
    ASSERT_FALSE(lost);
    EXPECT_EQ(faultOf(lost.error()), DeviceFault::Disconnected);

    // Power on again: Mono8, 512 x 512, 10 ms, GainRaw 0, packets of 1400 bytes.
    ASSERT_TRUE(fake_->start());
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_WIDTH), 512u);
    const auto t0 = Clock::now();
    std::optional<hdr::RawFrame> frame;
    int calls = 0;
    // Calls within the back-off answer at once; retry as a paused job resumed by hand would.
    ASSERT_TRUE(flarelab::testing::waitFor(
        [&] {
            ++calls;
            auto f = camera->capture(2.0);
            if (f) frame = std::move(*f);
            return f.has_value();
        },
        30.0));
    std::printf("reopened after %.2f s and %d calls\n", seconds(t0), calls);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_PIXEL_FORMAT), ARV_PIXEL_FORMAT_MONO_16);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_X_OFFSET), 16u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_Y_OFFSET), 8u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_WIDTH), 128u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_HEIGHT), 64u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_EXPOSURE_TIME_US), 20000u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_GAIN_RAW), 1u);
    EXPECT_EQ(fake_->reg(kScps0) & 0xffff, 1000u);
    EXPECT_EQ(fake_->reg(ARV_FAKE_CAMERA_REGISTER_TRIGGER_MODE), 1u);
    ASSERT_TRUE(frame);
    EXPECT_EQ(frame->width, 128);
    EXPECT_EQ(frame->bit_depth, 16);
    EXPECT_NEAR(frame->exposure_s, 0.02, 1e-12);
    EXPECT_NEAR(frame->gain, 2.0, 1e-4);
    EXPECT_TRUE(fakePatternMatches(*frame, 20000, 1));
    EXPECT_GT(frame->sequence, first->sequence);  // continues across the restart
    EXPECT_EQ(stat(*camera, "disconnects"), 1);
    EXPECT_EQ(stat(*camera, "reopens"), 1);
    EXPECT_GE(stat(*camera, "completed_buffers"), 2);  // summed over both connections
}

TEST_F(AravisCameraTest, SecondControllerIsBusy) {
    auto first = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(first);
    auto uri = parseDeviceUri(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(uri);
    const auto t0 = Clock::now();
    auto second = AravisCamera::open(*uri);
    std::printf("[busy] after %.2f s\n", seconds(t0));
    ASSERT_FALSE(second);
    EXPECT_EQ(faultOf(second.error()), DeviceFault::Busy) << second.error().message;
    EXPECT_NE(second.error().message.find("another application controls the camera"),
              std::string::npos);
    ASSERT_TRUE(first->capture(2.0));  // the first keeps the camera
}

// The same with the arv-fake-gv-camera-0.8 tool killed by SIGKILL, as a daemon test would.
TEST_F(AravisFake, KilledCameraProcessIsDisconnectedAndARestartedOneResumes) {
    FakeGvCameraProcess process;
    ASSERT_EQ(process.start(), "");
    auto camera = openCamera(std::string("aravis:Aravis-Fake-GV01?") + kRoi);
    ASSERT_TRUE(camera);
    ASSERT_TRUE(camera->setExposure(0.005));
    ASSERT_TRUE(camera->capture(2.0));
    process.kill();
    const auto t0 = Clock::now();
    auto lost = camera->capture(10.0);
    std::printf("[disconnected] after %.2f s\n", seconds(t0));
    ASSERT_FALSE(lost);
    EXPECT_EQ(faultOf(lost.error()), DeviceFault::Disconnected) << lost.error().message;
    ASSERT_EQ(process.start(), "");
    const auto t1 = Clock::now();
    std::optional<hdr::RawFrame> frame;
    ASSERT_TRUE(flarelab::testing::waitFor(
        [&] {
            auto f = camera->capture(2.0);
            if (f) frame = std::move(*f);
            return f.has_value();
        },
        30.0));
    std::printf("resumed %.2f s after the restart\n", seconds(t1));
    EXPECT_TRUE(fakePatternMatches(*frame, 5000, 0));
}

}  // namespace
}  // namespace flarelab::drivers
