// The V4L2 camera's logic against recorded devices played back (v4l2_playback.h): format
// choice, control mapping, buffer handling and stale-frame dropping. The streaming path against
// a real driver is scripts/vivid_test.sh (tests/drivers/v4l2_vivid_check.cpp).
#include "drivers/v4l2_camera.h"

#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "drivers/v4l2_dump.h"
#include "drivers/v4l2_playback.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

V4l2DeviceDump dump(const std::string& name) {
    auto d = loadV4l2Dump(flarelab::testing::sourcePath("tests/data/v4l2/" + name));
    EXPECT_TRUE(d) << (d ? "" : d.error().message);
    return d ? std::move(*d) : V4l2DeviceDump{};
}

// A camera on a played-back dump; `device` keeps a view of the device for the test to inspect.
struct Rig {
    V4l2Playback* device = nullptr;
    std::unique_ptr<V4l2Camera> camera;
};

Result<Rig> open(const std::string& name,
                 const V4l2CameraOptions& options = {},
                 V4l2PlaybackOptions playback = {}) {
    auto device = makeV4l2Playback(dump(name), std::move(playback));
    if (!device) return device.error();
    Rig rig;
    rig.device = device->get();
    auto camera = V4l2Camera::open(std::move(*device), options, "v4l2:test");
    if (!camera) return camera.error();
    rig.camera = std::move(*camera);
    return rig;
}

Rig mustOpen(const std::string& name,
             const V4l2CameraOptions& options = {},
             V4l2PlaybackOptions playback = {}) {
    auto rig = open(name, options, std::move(playback));
    EXPECT_TRUE(rig) << (rig ? "" : rig.error().message);
    return rig ? std::move(*rig) : Rig{};
}

int64_t controlOf(V4l2Device& device, uint32_t id) {
    v4l2_control c{id, 0};
    EXPECT_EQ(device.ioctl(VIDIOC_G_CTRL, &c), 0);
    return c.value;
}

V4l2CameraOptions sized(const std::string& format, int64_t w, int64_t h) {
    V4l2CameraOptions o;
    o.format = format;
    o.width_px = w;
    o.height_px = h;
    return o;
}

int64_t statistic(const Camera& camera, const std::string& name) {
    for (const auto& [key, value] : camera.statistics())
        if (key == name) return value;
    ADD_FAILURE() << "no statistic " << name;
    return -1;
}

std::optional<DeviceFault> faultOf(const Status& s) {
    return s ? std::nullopt : deviceFaultOf(s.error());
}

// ---- format choice ----------------------------------------------------------------------------

TEST(V4l2Camera, PrefersY16AtTheLargestSizeOfVivid) {
    Rig rig = mustOpen("vivid-default.txt");
    ASSERT_TRUE(rig.camera);
    EXPECT_STREQ(rig.camera->pixelFormat().name, "Y16");
    const CameraCapabilities caps = rig.camera->capabilities();
    EXPECT_EQ(caps.width_px, 3840);
    EXPECT_EQ(caps.height_px, 2160);
    EXPECT_EQ(caps.bit_depth, 16);
    EXPECT_EQ(caps.white_level_dn, 65535.0);
    EXPECT_EQ(caps.response, CameraResponse::Linear);
    // vivid offers grey and all four Bayer orders raw; YUV luma is not listed beside raw.
    EXPECT_EQ(caps.formats.size(), 5u);
    EXPECT_EQ(rig.camera->identity().backend, "v4l2");
    EXPECT_EQ(rig.camera->identity().model, "vivid");
    EXPECT_EQ(rig.camera->identity().serial, "platform:vivid-000");
}

TEST(V4l2Camera, TakesTheFormatAndSizeAsked) {
    Rig rig = mustOpen("vivid-default.txt", sized("RG12", 320, 180));
    ASSERT_TRUE(rig.camera);
    EXPECT_STREQ(rig.camera->pixelFormat().name, "RG12");
    EXPECT_EQ(rig.camera->format(), hdr::RawFormat::BayerRGGB);
    EXPECT_EQ(rig.camera->capabilities().bit_depth, 12);
    EXPECT_EQ(rig.camera->capabilities().white_level_dn, 4095.0);
    v4l2_format f{};
    f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    ASSERT_EQ(rig.device->ioctl(VIDIOC_G_FMT, &f), 0);
    EXPECT_EQ(f.fmt.pix.pixelformat, V4L2_PIX_FMT_SRGGB12);
    EXPECT_EQ(f.fmt.pix.width, 320u);
}

TEST(V4l2Camera, RefusesAFormatOrSizeTheDeviceDoesNotOffer) {
    auto packed = open("vivid-default.txt", sized("pRAA", 0, 0));
    ASSERT_FALSE(packed);
    EXPECT_EQ(deviceFaultOf(packed.error()), DeviceFault::OutOfRange);
    EXPECT_NE(packed.error().message.find("format 'pRAA' is not offered"), std::string::npos)
        << packed.error().message;
    auto rgb = open("vivid-default.txt", sized("RGB3", 0, 0));
    ASSERT_FALSE(rgb);
    EXPECT_NE(rgb.error().message.find("not one flarelab reads"), std::string::npos);
    auto size = open("vivid-default.txt", sized("Y16", 100, 100));
    ASSERT_FALSE(size);
    EXPECT_EQ(deviceFaultOf(size.error()), DeviceFault::OutOfRange);
    EXPECT_NE(size.error().message.find("width x height 100x100"), std::string::npos)
        << size.error().message;
}

TEST(V4l2Camera, SwitchesBetweenTheLayoutsOffered) {
    Rig rig = mustOpen("vivid-default.txt", sized("", 320, 180));
    ASSERT_TRUE(rig.camera);
    ASSERT_TRUE(rig.camera->setFormat(hdr::RawFormat::BayerGBRG));
    EXPECT_STREQ(rig.camera->pixelFormat().name, "GB16");
    EXPECT_EQ(rig.camera->capabilities().width_px, 320);
    auto frame = rig.camera->capture(5.0);
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_EQ(frame->format, hdr::RawFormat::BayerGBRG);
    // Streaming stops for the change and starts again at the next capture.
    ASSERT_TRUE(rig.camera->setFormat(hdr::RawFormat::Mono));
    EXPECT_STREQ(rig.camera->pixelFormat().name, "Y16");
    EXPECT_TRUE(rig.camera->capture(5.0));
}

TEST(V4l2Camera, TakesTheLumaOfYuvWhenNothingRawIsOfferedAndSaysItIsNotKnownLinear) {
    Rig rig = mustOpen("uvc-webcam-handwritten.txt");
    ASSERT_TRUE(rig.camera);
    EXPECT_STREQ(rig.camera->pixelFormat().name, "YUYV");
    const CameraCapabilities caps = rig.camera->capabilities();
    EXPECT_EQ(caps.response, CameraResponse::Unknown);
    EXPECT_NE(caps.response_note.find("gamma"), std::string::npos);
    EXPECT_EQ(caps.bit_depth, 8);
    EXPECT_EQ(caps.width_px, 1280);  // the largest YUYV size
    ASSERT_FALSE(rig.camera->warnings().empty());
    EXPECT_NE(rig.camera->warnings().front().find("no raw format"), std::string::npos);
}

TEST(V4l2Camera, WarnsWhenOnly8BitRawIsTaken) {
    Rig rig = mustOpen("csi-sensor-handwritten.txt", sized("RGGB", 64, 48));
    ASSERT_TRUE(rig.camera);
    EXPECT_EQ(rig.camera->capabilities().bit_depth, 8);
    ASSERT_FALSE(rig.camera->warnings().empty());
    EXPECT_NE(rig.camera->warnings().front().find("8-bit"), std::string::npos);
}

TEST(V4l2Camera, RefusesCompressedOnlyAndMultiplanarDevices) {
    auto mjpeg = open("mjpeg-only-handwritten.txt");
    ASSERT_FALSE(mjpeg);
    EXPECT_EQ(mjpeg.error().code, ErrorCode::Unsupported);
    EXPECT_NE(mjpeg.error().message.find("MJPG, H264"), std::string::npos) << mjpeg.error().message;
    auto planes = open("vivid-multiplanar.txt");
    ASSERT_FALSE(planes);
    EXPECT_EQ(planes.error().code, ErrorCode::Unsupported);
    EXPECT_NE(planes.error().message.find("multi-planar"), std::string::npos);
}

// ---- exposure and gain ----------------------------------------------------------------------

TEST(V4l2Camera, UsesTheFrameIntervalWhereThereIsNoExposureControl) {
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180));
    ASSERT_TRUE(rig.camera);
    EXPECT_EQ(rig.camera->exposureMode(), V4l2ExposureMode::FrameInterval);
    EXPECT_DOUBLE_EQ(rig.camera->frameInterval_s(), 0.2);  // vivid's 5 fps
    const CameraCapabilities caps = rig.camera->capabilities();
    EXPECT_DOUBLE_EQ(caps.min_exposure_s, 0.2);
    EXPECT_DOUBLE_EQ(caps.max_exposure_s, 0.2);
    EXPECT_TRUE(rig.camera->setExposure(0.2));
    const Status other = rig.camera->setExposure(0.1);
    EXPECT_EQ(faultOf(other), DeviceFault::OutOfRange);
    EXPECT_NE(other.error().message.find("exposure_s = 0.1"), std::string::npos);
}

TEST(V4l2Camera, AsksForTheFrameRateOfTheUri) {
    V4l2CameraOptions o = sized("Y16", 320, 180);
    o.fps = 30.0;
    Rig rig = mustOpen("vivid-default.txt", o);
    ASSERT_TRUE(rig.camera);
    EXPECT_NEAR(rig.camera->frameInterval_s(), 0.033, 1e-9);  // the nearest listed interval
}

TEST(V4l2Camera, LeavesAGainWithoutKnownUnityAloneUnlessTheUriGivesIt) {
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180));
    ASSERT_TRUE(rig.camera);
    EXPECT_EQ(rig.camera->gainControl(), 0u);
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_AUTOGAIN), 1);  // untouched
    EXPECT_TRUE(rig.camera->setGain(1.0));
    EXPECT_EQ(faultOf(rig.camera->setGain(2.0)), DeviceFault::OutOfRange);
    ASSERT_FALSE(rig.camera->warnings().empty());

    V4l2CameraOptions o = sized("Y16", 320, 180);
    o.gain_unity = 100.0;
    Rig mapped = mustOpen("vivid-default.txt", o);
    ASSERT_TRUE(mapped.camera);
    EXPECT_EQ(mapped.camera->gainControl(), uint32_t{V4L2_CID_GAIN});
    EXPECT_EQ(controlOf(*mapped.device, V4L2_CID_AUTOGAIN), 0);
    EXPECT_DOUBLE_EQ(mapped.camera->capabilities().min_gain, 0.01);
    EXPECT_DOUBLE_EQ(mapped.camera->capabilities().max_gain, 2.55);
    ASSERT_TRUE(mapped.camera->setGain(1.5));
    EXPECT_EQ(controlOf(*mapped.device, V4L2_CID_GAIN), 150);
    EXPECT_DOUBLE_EQ(mapped.camera->gain(), 1.5);
    const Status high = mapped.camera->setGain(3.0);
    EXPECT_EQ(faultOf(high), DeviceFault::OutOfRange);
    EXPECT_NE(high.error().message.find("gain = 3"), std::string::npos) << high.error().message;
    EXPECT_EQ(controlOf(*mapped.device, V4L2_CID_GAIN), 150);  // a failed call changes nothing
}

TEST(V4l2Camera, SetsAbsoluteExposureInManualModeAndReadsItBack) {
    Rig rig = mustOpen("uvc-webcam-handwritten.txt", sized("YUYV", 640, 480));
    ASSERT_TRUE(rig.camera);
    EXPECT_EQ(rig.camera->exposureMode(), V4l2ExposureMode::Absolute);
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL);
    EXPECT_DOUBLE_EQ(rig.camera->exposure_s(), 0.025);  // 250 x 100 us
    const CameraCapabilities caps = rig.camera->capabilities();
    EXPECT_DOUBLE_EQ(caps.min_exposure_s, 3e-4);
    EXPECT_DOUBLE_EQ(caps.max_exposure_s, 0.2047);
    ASSERT_TRUE(rig.camera->setExposure(0.01));
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_EXPOSURE_ABSOLUTE), 100);
    EXPECT_DOUBLE_EQ(rig.camera->exposure_s(), 0.01);
    // Rounded to the control's step (100 us).
    ASSERT_TRUE(rig.camera->setExposure(0.01234));
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_EXPOSURE_ABSOLUTE), 123);
    for (double bad : {0.5, 1e-5, -1.0, std::nan("")}) {
        const Status s = rig.camera->setExposure(bad);
        EXPECT_EQ(faultOf(s), DeviceFault::OutOfRange) << bad;
        EXPECT_NE(s.error().message.find("exposure_s"), std::string::npos);
    }
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_EXPOSURE_ABSOLUTE), 123);
}

TEST(V4l2Camera, TimesExposureInLinesFromBlankingAndPixelRate) {
    Rig rig = mustOpen("csi-sensor-handwritten.txt", sized("pRAA", 1920, 1080));
    ASSERT_TRUE(rig.camera);
    EXPECT_EQ(rig.camera->exposureMode(), V4l2ExposureMode::Lines);
    const double line_s = (1920.0 + 1528.0) / 182400000.0;  // (width + hblank) / pixel rate
    EXPECT_DOUBLE_EQ(rig.camera->lineTime_s(), line_s);
    EXPECT_EQ(rig.camera->settleFrames(), 2);
    EXPECT_DOUBLE_EQ(rig.camera->exposure_s(), 1000 * line_s);
    ASSERT_TRUE(rig.camera->setExposure(0.01));
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_EXPOSURE), std::lround(0.01 / line_s));
    EXPECT_DOUBLE_EQ(rig.camera->exposure_s(), std::lround(0.01 / line_s) * line_s);
    // Analogue gain from 16 means 16 is unity.
    EXPECT_EQ(rig.camera->gainControl(), uint32_t{V4L2_CID_ANALOGUE_GAIN});
    ASSERT_TRUE(rig.camera->setGain(2.0));
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_ANALOGUE_GAIN), 32);
}

TEST(V4l2Camera, TakesTheLineTimeAndSettleFramesOfTheUri) {
    V4l2CameraOptions o = sized("RG10", 640, 480);
    o.line_time_us = 20.0;
    o.settle_frames = 0;
    Rig rig = mustOpen("csi-sensor-handwritten.txt", o);
    ASSERT_TRUE(rig.camera);
    EXPECT_DOUBLE_EQ(rig.camera->lineTime_s(), 20e-6);
    EXPECT_EQ(rig.camera->settleFrames(), 0);
    ASSERT_TRUE(rig.camera->setExposure(0.001));
    EXPECT_EQ(controlOf(*rig.device, V4L2_CID_EXPOSURE), 50);
}

TEST(V4l2Camera, RefusesExposureInLinesWithoutALineTime) {
    V4l2DeviceDump d = dump("csi-sensor-handwritten.txt");
    std::erase_if(d.controls, [](const V4l2DumpControl& c) { return c.id == V4L2_CID_PIXEL_RATE; });
    auto device = makeV4l2Playback(std::move(d));
    ASSERT_TRUE(device);
    auto camera = V4l2Camera::open(std::move(*device), sized("RG10", 640, 480));
    ASSERT_FALSE(camera);
    EXPECT_EQ(camera.error().code, ErrorCode::Unsupported);
    EXPECT_NE(camera.error().message.find("line_time_us"), std::string::npos);
}

// ---- frames -----------------------------------------------------------------------------------

// Every sample says the exposure control's value the frame was exposed with.
V4l2PlaybackOptions exposureScene(uint32_t control) {
    V4l2PlaybackOptions p;
    p.scene = [control](int64_t, int64_t, const V4l2PlaybackFrame& f) {
        return static_cast<uint32_t>(f.controls.at(control));
    };
    return p;
}

TEST(V4l2Camera, CapturesFramesWithTheirMetadata) {
    V4l2CameraOptions o = sized("Y12", 320, 180);
    o.gain_unity = 100.0;
    o.black_level_dn = 64.0;
    Rig rig = mustOpen("vivid-default.txt", o);
    ASSERT_TRUE(rig.camera);
    ASSERT_TRUE(rig.camera->setGain(2.0));
    auto frame = rig.camera->capture(5.0);
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_EQ(frame->width, 320);
    EXPECT_EQ(frame->height, 180);
    EXPECT_EQ(frame->bit_depth, 12);
    EXPECT_EQ(frame->white_level_dn, 4095.0);
    EXPECT_EQ(frame->black_level_dn, 64.0);
    EXPECT_DOUBLE_EQ(frame->exposure_s, 0.2);
    EXPECT_DOUBLE_EQ(frame->gain, 2.0);
    EXPECT_EQ(frame->timestamp_marks, hdr::TimestampMark::FrameArrival);
    EXPECT_GT(frame->host_timestamp_ns, frame->timestamp_ns);  // the playback's realtime clock
    // The default scene: (x + 2 y) modulo 2^12.
    EXPECT_EQ(frame->samples[0], 0);
    EXPECT_EQ(frame->samples[static_cast<size_t>(5 * 320 + 7)], 17);
    auto next = rig.camera->capture(5.0);
    ASSERT_TRUE(next);
    EXPECT_GT(next->sequence, frame->sequence);
    EXPECT_GT(next->timestamp_ns, frame->timestamp_ns);
}

TEST(V4l2Camera, UnpacksMipiPackedFramesFromTheSensor) {
    V4l2PlaybackOptions p;
    p.scene = [](int64_t x, int64_t y, const V4l2PlaybackFrame&) {
        return static_cast<uint32_t>((x * 37 + y * 11) & 1023);
    };
    Rig rig = mustOpen("csi-sensor-handwritten.txt", sized("pRAA", 66, 16), p);
    ASSERT_TRUE(rig.camera);
    auto frame = rig.camera->capture(5.0);
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_EQ(frame->bit_depth, 10);
    for (int64_t y = 0; y < 16; ++y)
        for (int64_t x = 0; x < 66; ++x)
            ASSERT_EQ(frame->samples[static_cast<size_t>(y * 66 + x)], (x * 37 + y * 11) & 1023)
                << x << "," << y;
}

TEST(V4l2Camera, MarksStartOfExposureAndUnknownClocks) {
    V4l2PlaybackOptions soe;
    soe.start_of_exposure = true;
    Rig a = mustOpen("vivid-default.txt", sized("Y16", 320, 180), soe);
    ASSERT_TRUE(a.camera);
    auto frame = a.camera->capture(5.0);
    ASSERT_TRUE(frame);
    EXPECT_EQ(frame->timestamp_marks, hdr::TimestampMark::ExposureStart);

    V4l2PlaybackOptions copy;
    copy.timestamp_type = V4L2_BUF_FLAG_TIMESTAMP_COPY;
    Rig b = mustOpen("vivid-default.txt", sized("Y16", 320, 180), copy);
    ASSERT_TRUE(b.camera);
    frame = b.camera->capture(5.0);
    ASSERT_TRUE(frame);
    EXPECT_EQ(frame->timestamp_marks, hdr::TimestampMark::Unknown);
}

TEST(V4l2Camera, NeverReturnsAFrameExposedBeforeTheExposureChange) {
    // A UVC camera applies the change at once; frames in flight still carry the old exposure.
    for (int latency : {0}) {
        V4l2PlaybackOptions p = exposureScene(V4L2_CID_EXPOSURE_ABSOLUTE);
        p.control_latency_frames = latency;
        Rig rig = mustOpen("uvc-webcam-handwritten.txt", sized("YUYV", 160, 120), p);
        ASSERT_TRUE(rig.camera);
        ASSERT_TRUE(rig.camera->capture(5.0));
        for (int value : {20, 200, 30, 100}) {
            ASSERT_TRUE(rig.camera->setExposure(value * 1e-4));
            auto frame = rig.camera->capture(5.0);
            ASSERT_TRUE(frame) << frame.error().message;
            EXPECT_EQ(frame->samples[0], value);
            EXPECT_DOUBLE_EQ(frame->exposure_s, value * 1e-4);
        }
        EXPECT_GT(statistic(*rig.camera, "dropped-stale"), 0);
    }
}

TEST(V4l2Camera, SettleFramesCoverADriverThatAppliesExposureLate) {
    // A sensor latching exposure two frames late: settle_frames 2 (its default with exposure in
    // lines) drops the frames still exposed with the old value; without them they come back,
    // which is what this test would catch.
    const auto run = [](std::optional<int> settle) {
        V4l2PlaybackOptions p = exposureScene(V4L2_CID_EXPOSURE);
        p.control_latency_frames = 2;
        p.exposure_s = [](const V4l2PlaybackFrame& f) {
            return static_cast<double>(f.controls.at(V4L2_CID_EXPOSURE)) * 20e-6;
        };
        V4l2CameraOptions o = sized("RG10", 64, 48);
        o.line_time_us = 20.0;
        o.settle_frames = settle;
        Rig rig = mustOpen("csi-sensor-handwritten.txt", o, p);
        EXPECT_TRUE(rig.camera->capture(5.0));
        EXPECT_TRUE(rig.camera->setExposure(500 * 20e-6));
        auto frame = rig.camera->capture(5.0);
        EXPECT_TRUE(frame) << frame.error().message;
        return frame ? frame->samples[0] : uint16_t{0};
    };
    EXPECT_EQ(run(std::nullopt), 500);
    EXPECT_EQ(run(0), 1000 & 1023);  // the old exposure, 1000 lines
}

TEST(V4l2Camera, DropsFramesExposedBeforeTheCall) {
    V4l2PlaybackOptions p;
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180), p);
    ASSERT_TRUE(rig.camera);
    auto first = rig.camera->capture(5.0);
    ASSERT_TRUE(first);
    // The node runs on while nobody captures: its buffers fill with frames of the past.
    rig.device->advance(3'000'000'000);
    const int64_t called = rig.device->monotonicNs();
    auto frame = rig.camera->capture(5.0);
    ASSERT_TRUE(frame) << frame.error().message;
    // vivid's stamps mark the end of the frame; the exposure (a frame interval) and a readout
    // (another) before it must lie after the call.
    EXPECT_GE(frame->timestamp_ns - 2 * 200'000'000, called);
    EXPECT_GE(statistic(*rig.camera, "dropped-stale"), 4);
    EXPECT_GT(statistic(*rig.camera, "sequence-gaps"), 0);
}

TEST(V4l2Camera, DropsWhatIsDoneAndTheFrameUnderWayWhenTimestampsAreNotTheHostsClock) {
    V4l2PlaybackOptions p;
    p.timestamp_type = V4L2_BUF_FLAG_TIMESTAMP_UNKNOWN;
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180), p);
    ASSERT_TRUE(rig.camera);
    auto first = rig.camera->capture(5.0);
    ASSERT_TRUE(first);
    rig.device->advance(3'000'000'000);
    const int64_t called = rig.device->monotonicNs();
    auto frame = rig.camera->capture(5.0);
    ASSERT_TRUE(frame) << frame.error().message;
    // The playback's stamps are still its clock, so the test can check what the camera could not.
    EXPECT_GE(frame->timestamp_ns - 200'000'000 - 2'000'000, called);
}

TEST(V4l2Camera, SkipsAndCountsBuffersFlaggedAsErrors) {
    V4l2PlaybackOptions p;
    p.error_every = 2;
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180), p);
    ASSERT_TRUE(rig.camera);
    for (int i = 0; i < 4; ++i) {
        auto frame = rig.camera->capture(5.0);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_EQ(frame->sequence % 2, 0) << "frame " << frame->sequence << " was flagged";
    }
    EXPECT_GE(statistic(*rig.camera, "buffer-errors"), 3);
}

TEST(V4l2Camera, TimesOutWithoutBlockingPastTheTimeout) {
    V4l2PlaybackOptions p;
    p.exposure_s = [](const V4l2PlaybackFrame&) { return 30.0; };
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180), p);
    ASSERT_TRUE(rig.camera);
    const int64_t start = rig.device->monotonicNs();
    auto frame = rig.camera->capture(1.5);
    ASSERT_FALSE(frame);
    EXPECT_EQ(deviceFaultOf(frame.error()), DeviceFault::Timeout);
    EXPECT_NE(frame.error().message.find("within 1.5 s"), std::string::npos);
    const int64_t waited = rig.device->monotonicNs() - start;
    EXPECT_GE(waited, 1'500'000'000);
    EXPECT_LE(waited, 1'501'000'000);
    for (double bad : {0.0, -1.0, std::nan(""), 1e300}) {
        auto refused = rig.camera->capture(bad);
        ASSERT_FALSE(refused);
        EXPECT_EQ(deviceFaultOf(refused.error()), DeviceFault::OutOfRange);
        EXPECT_NE(refused.error().message.find("timeout_s"), std::string::npos);
    }
}

TEST(V4l2Camera, SaysDisconnectedWhenTheDeviceIsGone) {
    V4l2PlaybackOptions p;
    p.disconnect_after_frames = 2;
    Rig rig = mustOpen("vivid-default.txt", sized("Y16", 320, 180), p);
    ASSERT_TRUE(rig.camera);
    ASSERT_TRUE(rig.camera->capture(5.0));
    Result<hdr::RawFrame> frame = rig.camera->capture(5.0);
    while (frame) frame = rig.camera->capture(5.0);
    EXPECT_EQ(deviceFaultOf(frame.error()), DeviceFault::Disconnected) << frame.error().message;
    EXPECT_EQ(frame.error().code, ErrorCode::NotFound);
}

TEST(V4l2Camera, ShiftsMsbAlignedWordsOfTheUri) {
    V4l2CameraOptions o = sized("Y16", 320, 180);
    o.bits = 12;
    o.align = "msb";
    V4l2PlaybackOptions p;
    p.scene = [](int64_t x, int64_t, const V4l2PlaybackFrame&) {
        return static_cast<uint32_t>((x & 0xfff) << 4);
    };
    Rig rig = mustOpen("vivid-default.txt", o, p);
    ASSERT_TRUE(rig.camera);
    EXPECT_EQ(rig.camera->capabilities().bit_depth, 12);
    auto frame = rig.camera->capture(5.0);
    ASSERT_TRUE(frame);
    EXPECT_EQ(frame->bit_depth, 12);
    EXPECT_EQ(frame->white_level_dn, 4095.0);
    EXPECT_EQ(frame->samples[300], 300);
    // bits is for 16-bit words only.
    o.format = "Y10";
    auto refused = open("vivid-default.txt", o);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("bits applies to 16-bit word formats"),
              std::string::npos);
}

// ---- URI, registry, listing -----------------------------------------------------------------

TEST(V4l2CameraOptions, ReadTheUriAndRefuseUnknownParametersByName) {
    auto uri = parseDeviceUri(
        "v4l2:/dev/video0?format=Y16&width=1280&height=720&line_time_us=14.5&buffers=6&"
        "settle_frames=1&fps=10&bits=12&align=msb&gain_unity=16&black_level=64");
    ASSERT_TRUE(uri);
    auto o = v4l2CameraOptions(*uri);
    ASSERT_TRUE(o) << o.error().message;
    EXPECT_EQ(o->format, "Y16");
    EXPECT_EQ(o->width_px, 1280);
    EXPECT_EQ(o->height_px, 720);
    EXPECT_DOUBLE_EQ(o->line_time_us, 14.5);
    EXPECT_EQ(o->buffers, 6);
    EXPECT_EQ(o->settle_frames, 1);
    EXPECT_DOUBLE_EQ(o->fps, 10.0);
    EXPECT_EQ(o->bits, 12);
    EXPECT_EQ(o->align, "msb");
    EXPECT_DOUBLE_EQ(o->gain_unity, 16.0);
    EXPECT_DOUBLE_EQ(o->black_level_dn, 64.0);

    const std::pair<const char*, const char*> bad[] = {
        {"v4l2:/dev/video0?exposure=1", "'exposure'"},
        {"v4l2:/dev/video0?width=640", "width and height"},
        {"v4l2:/dev/video0?buffers=1", "buffers"},
        {"v4l2:/dev/video0?buffers=2.5", "buffers='2.5' is not a whole number"},
        {"v4l2:/dev/video0?bits=12", "align=msb"},
        {"v4l2:/dev/video0?align=left&bits=10", "align"},
        {"v4l2:/dev/video0?format=TOOLONG", "format 'TOOLONG'"},
        {"v4l2:/dev/video0?fps=fast", "fps='fast'"},
        {"v4l2:/dev/video0?settle_frames=40", "settle_frames"},
    };
    for (const auto& [text, expect] : bad) {
        auto parsed = parseDeviceUri(text);
        ASSERT_TRUE(parsed) << text;
        auto options = v4l2CameraOptions(*parsed);
        ASSERT_FALSE(options) << text;
        EXPECT_EQ(options.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(options.error().message.find(expect), std::string::npos)
            << text << ": " << options.error().message;
    }
}

TEST(V4l2Backend, OpensRealNodesAndNamesWhatIsWrong) {
    CameraRegistry registry;
    ASSERT_TRUE(addV4l2CameraBackend(registry));
    auto no_path = registry.open("v4l2:");
    ASSERT_FALSE(no_path);
    EXPECT_NE(no_path.error().message.find("v4l2:/dev/video0"), std::string::npos);
    auto missing = registry.open("v4l2:/nonexistent/video7");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_NE(missing.error().message.find("/nonexistent/video7"), std::string::npos);
    // A character device that is not V4L2: the real ioctl answers ENOTTY.
    auto null = registry.open("v4l2:/dev/null");
    ASSERT_FALSE(null);
    EXPECT_NE(null.error().message.find("VIDIOC_QUERYCAP"), std::string::npos)
        << null.error().message;
    auto file = registry.open("v4l2:" + flarelab::testing::sourcePath("tests/data/v4l2/README.md"));
    ASSERT_FALSE(file);
    EXPECT_NE(file.error().message.find("not a character device"), std::string::npos);
}

TEST(ListV4l2Devices, ListsNodesByNumberAndSaysWhyOneCannotBeOpened) {
    const std::filesystem::path dir =
        std::filesystem::temp_directory_path() / ("v4l2-list-" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    for (const char* name : {"video10", "video2", "videoX", "media0"})
        std::ofstream(dir / name) << "x";
    const std::vector<DeviceListing> found = listV4l2Devices(dir.string());
    std::filesystem::remove_all(dir);
    ASSERT_EQ(found.size(), 2u);
    EXPECT_EQ(found[0].uri, "v4l2:" + (dir / "video2").string());
    EXPECT_EQ(found[1].uri, "v4l2:" + (dir / "video10").string());
    EXPECT_EQ(found[0].kind, "camera");
    ASSERT_FALSE(found[0].details.empty());
    EXPECT_NE(found[0].details[0].find("not a character device"), std::string::npos);
    EXPECT_TRUE(listV4l2Devices("/nonexistent-dev").empty());
}

TEST(DescribeV4l2Device, ListsCardBusFormatsAndControls) {
    auto device = makeV4l2Playback(dump("vivid-default.txt"));
    ASSERT_TRUE(device);
    const DeviceListing d = describeV4l2Device(**device, "v4l2:/dev/video0");
    EXPECT_EQ(d.backend, "v4l2");
    EXPECT_EQ(d.model, "vivid");
    EXPECT_EQ(d.serial, "platform:vivid-000");
    const auto has = [&](const std::string& text) {
        for (const std::string& line : d.details)
            if (line.find(text) != std::string::npos) return true;
        return false;
    };
    EXPECT_TRUE(has("driver: vivid 6.1.192"));
    EXPECT_TRUE(has("format: Y16 (16-bit Greyscale), grey 16 bit"));
    EXPECT_TRUE(has("format: RG12 (12-bit Bayer RGRG/GBGB), Bayer RGGB 12 bit, LSB-aligned"));
    EXPECT_TRUE(has("sizes 320x180 640x360 640x480 1280x720 1920x1080 3840x2160"));
    EXPECT_TRUE(has("formats flarelab does not read: YUVO"));
    EXPECT_TRUE(has("opens as: Y16"));
    EXPECT_TRUE(has("exposure: no control"));
    EXPECT_TRUE(has("gain: gain 0..255"));

    auto sensor = makeV4l2Playback(dump("csi-sensor-handwritten.txt"));
    ASSERT_TRUE(sensor);
    const DeviceListing s = describeV4l2Device(**sensor, "v4l2:/dev/video3");
    bool stepwise = false, lines = false;
    for (const std::string& line : s.details) {
        stepwise = stepwise || line.find("16x16 to 3280x2464 in steps of 2x2") != std::string::npos;
        lines = lines || line.find("exposure: exposure 4..1759 lines") != std::string::npos;
    }
    EXPECT_TRUE(stepwise);
    EXPECT_TRUE(lines);

    auto planes = makeV4l2Playback(dump("vivid-multiplanar.txt"));
    ASSERT_TRUE(planes);
    const DeviceListing m = describeV4l2Device(**planes, "v4l2:/dev/video2");
    EXPECT_NE(m.details.back().find("multi-planar"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::drivers
