#include "drivers/sim_camera.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "optics/prescription.h"
#include "tests/test_lenses.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

using flarelab::testing::heliar;

// 64 x 43 with small grids: milliseconds per render.
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

// No light: a flat field of background_e_s electrons per second.
SimCameraOptions flat(double background_e_s) {
    SimCameraOptions o = tiny();
    o.light_rgb = {0.0f, 0.0f, 0.0f};
    o.background_e_s = background_e_s;
    o.dark_current_e_s = 0.0;
    return o;
}

std::unique_ptr<SimCamera> camera(const SimCameraOptions& o) {
    auto c = SimCamera::make(heliar(), o);
    EXPECT_TRUE(c) << (c ? "" : c.error().message);
    return std::move(*c);
}

hdr::RawFrame shoot(Camera& c, double exposure_s, double gain = 1.0) {
    EXPECT_TRUE(c.setExposure(exposure_s));
    EXPECT_TRUE(c.setGain(gain));
    auto frame = c.capture(100.0);
    EXPECT_TRUE(frame) << (frame ? "" : frame.error().message);
    return std::move(*frame);
}

struct Stats {
    double mean = 0.0, variance = 0.0;
};
Stats stats(const hdr::RawFrame& f) {
    double sum = 0.0, sum2 = 0.0;
    for (uint16_t v : f.samples) {
        sum += v;
        sum2 += static_cast<double>(v) * v;
    }
    const double n = static_cast<double>(f.samples.size());
    return {sum / n, sum2 / n - (sum / n) * (sum / n)};
}

DeviceFault faultOf(const Error& e) {
    const auto fault = deviceFaultOf(e);
    EXPECT_TRUE(fault) << e.message;
    return fault.value_or(DeviceFault::Busy);
}

TEST(SimCamera, FramesCarryTheirMetadata) {
    SimCameraOptions o = tiny();
    o.fixed_angle_deg = 3.0;
    auto c = camera(o);
    const CameraCapabilities caps = c->capabilities();
    EXPECT_EQ(caps.width_px, 64);
    EXPECT_EQ(caps.bit_depth, 12);
    EXPECT_EQ(caps.white_level_dn, 4095.0);
    const hdr::RawFrame a = shoot(*c, 0.25, 2.0);
    const hdr::RawFrame b = shoot(*c, 1.0, 1.0);
    EXPECT_EQ(a.width, 64);
    EXPECT_EQ(a.height, 43);
    EXPECT_EQ(a.samples.size(), 64u * 43u);
    EXPECT_EQ(a.format, hdr::RawFormat::Mono);
    EXPECT_EQ(a.exposure_s, 0.25);
    EXPECT_EQ(a.gain, 2.0);
    EXPECT_EQ(a.bit_depth, 12);
    EXPECT_EQ(a.black_level_dn, 64.0);
    EXPECT_EQ(a.white_level_dn, 4095.0);
    EXPECT_DOUBLE_EQ(a.electrons_per_dn, 2.0);  // 4 e/DN at gain 1
    EXPECT_DOUBLE_EQ(a.read_noise_dn, 1.5);     // 3 e
    EXPECT_DOUBLE_EQ(b.electrons_per_dn, 4.0);
    EXPECT_EQ(a.angle_deg, 3.0);
    EXPECT_EQ(a.sequence, 0);
    EXPECT_EQ(b.sequence, 1);
    // The second exposure starts when the first and its readout are over.
    EXPECT_EQ(b.timestamp_ns - a.timestamp_ns, secondsToNs(0.25 + 0.03));
    EXPECT_NE(a.camera.find("SIMCAM-0"), std::string::npos);
    for (uint16_t v : a.samples) ASSERT_LE(v, 4095);
}

TEST(SimCamera, MeanSignalScalesWithExposureAndGainUntilItClips) {
    auto c = camera(flat(400.0));  // 100 DN/s at gain 1
    const double black = 64.0;
    const double m1 = stats(shoot(*c, 1.0)).mean - black;
    EXPECT_NEAR(m1, 100.0, 2.0);
    EXPECT_NEAR(stats(shoot(*c, 4.0)).mean - black, 4.0 * m1, 4.0);
    EXPECT_NEAR(stats(shoot(*c, 0.25)).mean - black, 0.25 * m1, 1.0);
    EXPECT_NEAR(stats(shoot(*c, 1.0, 4.0)).mean - black, 4.0 * m1, 4.0);
    // 60 s at gain 16 is 96000 DN: every sample clips at white.
    const hdr::RawFrame clipped = shoot(*c, 60.0, 16.0);
    for (uint16_t v : clipped.samples) ASSERT_EQ(v, 4095);
}

TEST(SimCamera, NoiseFollowsShotAndReadNoise) {
    for (double gain : {1.0, 4.0}) {
        auto c = camera(flat(2000.0));
        const hdr::RawFrame f = shoot(*c, 1.0, gain);
        const Stats s = stats(f);
        const double signal_dn = s.mean - f.black_level_dn;
        // Poisson electrons: variance mean / (e per DN) in DN^2, plus read noise and the
        // converter's rounding (1/12 DN^2).
        const double expected =
            signal_dn / f.electrons_per_dn + f.read_noise_dn * f.read_noise_dn + 1.0 / 12.0;
        EXPECT_NEAR(s.variance / expected, 1.0, 0.1) << gain;
    }
}

TEST(SimCamera, ElectronCountsArePoisson) {
    // One electron per DN, no read noise: the samples are the electron counts plus black.
    for (double mean_e : {0.5, 3.0, 9.9, 10.0, 40.0, 300.0, 3000.0}) {
        SimCameraOptions o = flat(mean_e);
        o.width_px = 128;
        o.height_px = 128;
        o.electrons_per_dn = 1.0;
        o.read_noise_e = 0.0;
        o.black_level_dn = 0.0;
        auto c = camera(o);
        const hdr::RawFrame f = shoot(*c, 1.0);
        const Stats s = stats(f);
        const double n = static_cast<double>(f.samples.size());
        EXPECT_NEAR(s.mean, mean_e, 4.0 * std::sqrt(mean_e / n)) << mean_e;
        EXPECT_NEAR(s.variance / mean_e, 1.0, 4.0 * std::sqrt(2.0 / n)) << mean_e;
        if (mean_e < 1.0) {
            double zeros = 0.0;
            for (uint16_t v : f.samples) zeros += v == 0;
            EXPECT_NEAR(zeros / n, std::exp(-mean_e), 0.015);
        }
    }
}

TEST(SimCamera, DarkFrameIsBlackLevelPlusReadNoise) {
    SimCameraOptions o = flat(0.0);
    o.read_noise_e = 8.0;  // 2 DN
    auto c = camera(o);
    const Stats s = stats(shoot(*c, 0.5));
    EXPECT_NEAR(s.mean, 64.0, 0.15);
    EXPECT_NEAR(std::sqrt(s.variance), std::sqrt(4.0 + 1.0 / 12.0), 0.15);
}

TEST(SimCamera, DarkCurrentGrowsWithExposureAndHotPixelsStandOut) {
    SimCameraOptions o = flat(0.0);
    o.dark_current_e_s = 40.0;  // 10 DN/s
    o.hot_pixel_fraction = 0.01;
    o.hot_pixel_dark_e_s = 4000.0;
    auto c = camera(o);
    const hdr::RawFrame f = shoot(*c, 2.0);
    int hot = 0;
    for (uint16_t v : f.samples) hot += v > 64 + 20 + 1000;
    EXPECT_EQ(hot, 28);  // 1 % of 2752 pixels, unless two draws hit the same pixel
    const hdr::RawFrame g = shoot(*c, 2.0);
    for (size_t i = 0; i < f.samples.size(); ++i)
        ASSERT_EQ(f.samples[i] > 1084, g.samples[i] > 1084) << i;  // a fixed pattern
    o.hot_pixel_fraction = 0.0;
    auto d = camera(o);
    EXPECT_NEAR(stats(shoot(*d, 2.0)).mean - 64.0, 20.0, 0.5);
    EXPECT_NEAR(stats(shoot(*d, 8.0)).mean - 64.0, 80.0, 1.0);
}

TEST(SimCamera, TheSameSeedRepeatsFramesAndAnotherDoesNot) {
    SimCameraOptions o = tiny();
    o.fixed_angle_deg = 4.0;
    auto a = camera(o), b = camera(o);
    for (int i = 0; i < 2; ++i) EXPECT_EQ(shoot(*a, 1.0), shoot(*b, 1.0)) << i;
    o.seed = 2;
    auto c = camera(o);
    shoot(*c, 1.0);
    EXPECT_NE(shoot(*c, 1.0).samples, shoot(*a, 1.0).samples);
}

TEST(SimCamera, RejectsBadSettingsNamingTheField) {
    auto c = camera(tiny());
    for (double bad : {0.0, 1e-10, 61.0, std::nan("")}) {
        const Status s = c->setExposure(bad);
        ASSERT_FALSE(s) << bad;
        EXPECT_EQ(faultOf(s.error()), DeviceFault::OutOfRange);
        EXPECT_NE(s.error().message.find("exposure_s"), std::string::npos);
    }
    for (double bad : {0.5, 17.0, -1.0}) {
        const Status s = c->setGain(bad);
        ASSERT_FALSE(s) << bad;
        EXPECT_NE(s.error().message.find("gain"), std::string::npos);
    }
    EXPECT_EQ(c->exposure_s(), 1.0);  // unchanged
    EXPECT_EQ(c->gain(), 1.0);
    const Status format = c->setFormat(hdr::RawFormat::BayerGBRG);
    ASSERT_FALSE(format);
    EXPECT_NE(format.error().message.find("format"), std::string::npos);
    const auto capture = c->capture(-1.0);
    ASSERT_FALSE(capture);
    EXPECT_NE(capture.error().message.find("timeout_s"), std::string::npos);
    SimCameraOptions o = tiny();
    o.bit_depth = 20;
    const auto made = SimCamera::make(heliar(), o);
    ASSERT_FALSE(made);
    EXPECT_NE(made.error().message.find("bit_depth"), std::string::npos);
}

TEST(SimCamera, TimeoutsAndDisconnectsAreDeviceErrors) {
    auto c = camera(tiny());
    ASSERT_TRUE(c->setExposure(4.0));
    const int64_t before = c->clock()->now_ns();
    const auto late = c->capture(2.0);
    ASSERT_FALSE(late);
    EXPECT_EQ(faultOf(late.error()), DeviceFault::Timeout);
    EXPECT_EQ(c->clock()->now_ns() - before, secondsToNs(2.0));
    SimCameraFaults faults;
    faults.time_out_captures = 1;
    c->setFaults(faults);
    EXPECT_EQ(faultOf(c->capture(10.0).error()), DeviceFault::Timeout);
    EXPECT_TRUE(c->capture(10.0));
    faults.disconnected = true;
    c->setFaults(faults);
    EXPECT_EQ(faultOf(c->capture(10.0).error()), DeviceFault::Disconnected);
    EXPECT_EQ(faultOf(c->setExposure(1.0).error()), DeviceFault::Disconnected);
}

TEST(SimCamera, FollowsTheHeadAndRendersABracketOnce) {
    SimHeadOptions ho;
    ho.homed = true;
    std::shared_ptr<SimHead> head = SimHead::make(ho).value();
    auto made = SimCamera::make(heliar(), tiny(), head);
    ASSERT_TRUE(made);
    SimCamera& c = **made;
    std::vector<std::vector<float>> images;
    for (double angle : {0.0, 5.0, 15.0}) {
        ASSERT_TRUE(head->moveTo(angle, 10.0));
        const int64_t renders = c.renders();
        for (double t : {0.25, 1.0, 4.0}) {
            const hdr::RawFrame f = shoot(c, t);
            EXPECT_EQ(f.angle_deg, angle);
        }
        EXPECT_EQ(c.renders(), renders + 1) << angle;
        images.push_back(*c.meanRate_e_s(angle));
    }
    EXPECT_EQ(c.renders(), 3);
    for (size_t i = 0; i + 1 < images.size(); ++i) {
        double change = 0.0, total = 0.0;
        for (size_t p = 0; p < images[i].size(); ++p) {
            change += std::abs(images[i + 1][p] - images[i][p]);
            total += images[i][p];
        }
        EXPECT_GT(change, 0.05 * total) << i;  // the flare moves
    }
    // A head that lost its position cannot stamp frames.
    SimHeadFaults lose;
    lose.lose_position_in_moves = 1;
    head->setFaults(lose);
    EXPECT_FALSE(head->moveTo(1.0, 10.0));
    const auto lost = c.capture(10.0);
    ASSERT_FALSE(lost);
    EXPECT_EQ(faultOf(lost.error()), DeviceFault::NotHomed);
}

TEST(SimCamera, RendersAtTheTrueAngleSoBacklashShows) {
    SimHeadOptions ho;
    ho.homed = true;
    ho.backlash_deg = 1.0;
    std::shared_ptr<SimHead> head = SimHead::make(ho).value();
    auto c = SimCamera::make(heliar(), tiny(), head).value();
    ASSERT_TRUE(head->moveTo(5.0, 10.0));
    ASSERT_TRUE(c->capture(10.0));
    ASSERT_TRUE(head->moveTo(8.0, 10.0));
    ASSERT_TRUE(head->moveTo(5.0, 10.0));
    const auto f = c->capture(10.0);
    ASSERT_TRUE(f);
    EXPECT_EQ(f->angle_deg, 5.0);
    EXPECT_EQ(c->renders(), 2);  // 4.5 deg and 5.5 deg: two different images
}

// The power the sweep records for the lab figures is what the frame holds of the light on axis:
// the light's image holds nearly all of it (its ghosts are some thousandths), for a monochrome
// sensor's green, a luminance one and a colour one, and it follows the light and quantum scale.
TEST(SimCamera, TheRecordedLightPowerIsWhatTheFrameHoldsOnAxis) {
    for (auto [format, mono] : {std::pair{hdr::RawFormat::Mono, MonoResponse::Green},
                                std::pair{hdr::RawFormat::Mono, MonoResponse::Luminance},
                                std::pair{hdr::RawFormat::BayerRGGB, MonoResponse::Green}}) {
        SimCameraOptions o = tiny();
        o.format = format;
        o.mono = mono;
        o.background_e_s = 0.0;
        o.light_rgb = {0.5f, 1.0f, 2.0f};
        auto c = camera(o);
        double sum_e_s = 0.0;
        if (format == hdr::RawFormat::Mono) {
            const auto rate = c->meanRate_e_s(0.0);
            ASSERT_TRUE(rate);
            for (float v : *rate) sum_e_s += v;
        } else {
            const auto rgb = c->meanRateRgb_e_s(0.0);
            ASSERT_TRUE(rgb);
            for (size_t k = 0; k < rgb->pixels.size(); k += 3)
                sum_e_s += 0.2126 * rgb->pixels[k] + 0.7152 * rgb->pixels[k + 1] +
                           0.0722 * rgb->pixels[k + 2];
        }
        const auto power = c->lightPowerDnPerS();
        ASSERT_TRUE(power);
        EXPECT_NEAR(*power, sum_e_s / o.electrons_per_dn, 0.02 * *power);
        // Twice the quantum scale, twice the power; a dark light has none.
        SimCameraOptions brighter = o;
        brighter.quantum_scale *= 2.0;
        EXPECT_NEAR(simLightPower(heliar(), brighter).value(), 2.0 * *power, 1e-9 * *power);
        SimCameraOptions dark = o;
        dark.light_rgb = {0.0f, 0.0f, 0.0f};
        EXPECT_FALSE(simLightPower(heliar(), dark));
    }
}

TEST(SimCamera, ImagesAreFiniteAtEveryAngleAndFormat) {
    for (auto format : {hdr::RawFormat::Mono, hdr::RawFormat::BayerRGGB}) {
        SimCameraOptions o = tiny();
        o.format = format;
        o.mono = MonoResponse::Luminance;
        auto c = camera(o);
        for (double angle : {-20.0, -0.2, 0.0, 0.2, 10.0, 30.0, 60.0, 89.9, 90.0, 120.0}) {
            const auto rate = c->meanRate_e_s(angle);
            ASSERT_TRUE(rate) << angle;
            double sum = 0.0;
            for (float v : *rate) {
                ASSERT_TRUE(std::isfinite(v)) << angle;
                ASSERT_GE(v, 20.0f) << angle;  // the background at least
                sum += v;
            }
            EXPECT_GT(sum, 0.0);
        }
    }
}

TEST(SimCamera, TheLightsImageKeepsItsPowerFromAngleToAngle) {
    // Near the axis the light's image holds nearly all the power in the frame; it must not
    // depend on where its centre falls between pixel centres.
    SimCameraOptions o = tiny();
    o.background_e_s = 0.0;
    auto c = camera(o);
    std::vector<double> sums;
    for (double angle : {0.0, 0.01, 0.1, 0.2, 0.5, 1.0, 2.0}) {
        const auto rate = c->meanRate_e_s(angle);
        ASSERT_TRUE(rate);
        double sum = 0.0;
        for (float v : *rate) sum += v;
        sums.push_back(sum);
    }
    const auto [lo, hi] = std::minmax_element(sums.begin(), sums.end());
    EXPECT_GT(*lo, 0.0);
    EXPECT_LT(*hi / *lo, 1.05) << *lo << " .. " << *hi;
}

TEST(SimCamera, BayerPixelsSeeTheirFilterColour) {
    SimCameraOptions o = tiny();
    o.format = hdr::RawFormat::BayerRGGB;
    o.light_rgb = {1.0f, 0.0f, 0.0f};  // a red light
    o.background_e_s = 0.0;
    o.fixed_angle_deg = 2.0;
    auto c = camera(o);
    const auto rate = c->meanRate_e_s(2.0);
    ASSERT_TRUE(rate);
    double red = 0.0, other = 0.0;
    for (int64_t y = 0; y < 43; ++y)
        for (int64_t x = 0; x < 64; ++x)
            (x % 2 == 0 && y % 2 == 0 ? red : other) += (*rate)[y * 64 + x];
    EXPECT_GT(red, 0.0);
    EXPECT_EQ(other, 0.0);
    const hdr::RawFrame f = shoot(*c, 1.0);
    EXPECT_EQ(f.format, hdr::RawFormat::BayerRGGB);
}

// The colour truth of a Bayer capture (sim_truth.h): at every pixel the rate its filter's
// channel sees in the mosaic, and in green the monochrome camera's rate.
TEST(SimCamera, TheRgbRateHoldsTheMosaicsAndTheMonoCamerasChannels) {
    SimCameraOptions o = tiny();
    o.fixed_angle_deg = 6.0;
    o.format = hdr::RawFormat::BayerRGGB;
    auto bayer = camera(o);
    const auto mosaic = bayer->meanRate_e_s(6.0);
    const auto rgb = bayer->meanRateRgb_e_s(6.0);
    o.format = hdr::RawFormat::Mono;
    const auto mono = camera(o)->meanRate_e_s(6.0);
    ASSERT_TRUE(mosaic && rgb && mono);
    ASSERT_EQ(rgb->width, 64);
    ASSERT_EQ(rgb->height, 43);
    double channel_sum[3] = {0.0, 0.0, 0.0};
    for (int64_t y = 0; y < 43; ++y)
        for (int64_t x = 0; x < 64; ++x) {
            const int own = x % 2 == 0 && y % 2 == 0 ? 0 : (x % 2 == 1 && y % 2 == 1 ? 2 : 1);
            const size_t i = static_cast<size_t>(y * 64 + x);
            EXPECT_EQ(rgb->at(x, y)[own], (*mosaic)[i]) << x << ", " << y;
            EXPECT_EQ(rgb->at(x, y)[1], (*mono)[i]) << x << ", " << y;
            for (int c = 0; c < 3; ++c) channel_sum[c] += rgb->at(x, y)[c];
        }
    // The ghosts' colours differ (the coating's reflectance depends on the wavelength): the
    // channels are not copies of each other.
    EXPECT_NE(channel_sum[0], channel_sum[1]);
    EXPECT_NE(channel_sum[2], channel_sum[1]);
}

TEST(SimCamera, RealTimeCaptureTakesTheExposure) {
    SimHeadOptions ho;
    ho.homed = true;
    std::shared_ptr<SimHead> head =
        SimHead::make(ho, std::make_shared<SimClock>(SimTime::RealTime)).value();
    auto c = SimCamera::make(heliar(), tiny(), head).value();
    ASSERT_TRUE(c->setExposure(0.2));
    ASSERT_TRUE(c->capture(10.0));  // renders
    const auto wall = std::chrono::steady_clock::now();
    ASSERT_TRUE(c->capture(10.0));
    EXPECT_GE(std::chrono::duration<double>(std::chrono::steady_clock::now() - wall).count(), 0.2);
}

TEST(SimCameraBackend, OpensByUriWithALensParameter) {
    CameraRegistry registry;
    ASSERT_TRUE(addSimCameraBackend(registry, nullptr, tiny()));
    const auto listed = registry.enumerate();
    ASSERT_EQ(listed.size(), 1u);
    EXPECT_EQ(listed[0].uri, "sim:");
    EXPECT_EQ(listed[0].kind, "camera");
    const auto none = registry.open("sim:");
    ASSERT_FALSE(none);
    EXPECT_NE(none.error().message.find("lens"), std::string::npos);
    const auto c = registry.open("sim:?lens=" + flarelab::testing::lensPath("heliar-tronnier.csv") +
                                 "&width=32&height=20&bits=14&format=rggb&angle_deg=2");
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_EQ((*c)->capabilities().width_px, 32);
    EXPECT_EQ((*c)->capabilities().white_level_dn, 16383.0);
    EXPECT_EQ((*c)->format(), hdr::RawFormat::BayerRGGB);
    const auto frame = (*c)->capture(10.0);
    ASSERT_TRUE(frame);
    EXPECT_EQ(frame->angle_deg, 2.0);
    // The colour camera by the name `flarelab capture --format` takes too; other mosaics are
    // refused by name.
    const auto named =
        registry.open("sim:?lens=" + flarelab::testing::lensPath("heliar-tronnier.csv") +
                      "&width=32&height=20&format=bayer-rggb");
    ASSERT_TRUE(named) << named.error().message;
    EXPECT_EQ((*named)->format(), hdr::RawFormat::BayerRGGB);
    const auto bggr = registry.open(
        "sim:?lens=" + flarelab::testing::lensPath("heliar-tronnier.csv") + "&format=bayer-bggr");
    ASSERT_FALSE(bggr);
    EXPECT_NE(bggr.error().message.find("format must be mono or bayer-rggb"), std::string::npos)
        << bggr.error().message;
    const auto bad = registry.open("sim:?lens=x.csv&colour=red");
    ASSERT_FALSE(bad);
    EXPECT_NE(bad.error().message.find("colour"), std::string::npos);
}

// The figure for the sweep speed: a 0..30 deg sweep at 0.2 deg, three brackets each, at 640 x 427
// with the default render settings, in fast mode. Not a test with a time limit; run with
//   drivers_test --gtest_also_run_disabled_tests --gtest_filter='*SweepTiming*'
TEST(SimCameraTiming, DISABLED_SweepTiming) {
    SimHeadOptions ho;
    ho.homed = true;
    std::shared_ptr<SimHead> head = SimHead::make(ho).value();
    auto c = SimCamera::make(heliar(), SimCameraOptions{}, head).value();
    const auto start = std::chrono::steady_clock::now();
    double render_ms = 0.0;
    int angles = 0;
    for (int step = 0; step <= 150; ++step, ++angles) {
        ASSERT_TRUE(head->moveTo(0.2 * step, 10.0));
        for (double t : {0.25, 1.0, 4.0}) {
            ASSERT_TRUE(c->setExposure(t));
            ASSERT_TRUE(c->capture(10.0));
        }
        render_ms += c->lastRender_ms();
    }
    const double total_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::printf(
        "%d angles x 3 brackets at 640x427: %.2f s, %.1f ms per angle (render %.1f ms); "
        "rig time %.1f s\n",
        angles, total_s, 1000.0 * total_s / angles, render_ms / angles,
        c->clock()->now_ns() * 1e-9);
}

}  // namespace
}  // namespace flarelab::drivers
