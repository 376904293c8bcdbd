#include "drivers/calibration_measure.h"

#include <gtest/gtest.h>

#include <cmath>
#include <set>

#include "drivers/sim_camera.h"
#include "optics/prescription.h"
#include "tests/test_lenses.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

using flarelab::testing::heliar;

// The Heliar's flare at 3 deg on 240 x 160 pixels (small render grids): a point light, its
// ghosts and the background span five decades, the scene a calibration wants. The sensor as
// simulated by default: black 64 DN, 4 e-/DN, read noise 3 e-, 12 bits; one pixel in a thousand
// hot.
SimCameraOptions scene(SimResponse response = SimResponse::Linear, uint64_t seed = 1) {
    SimCameraOptions o;
    o.width_px = 240;
    o.height_px = 160;
    o.render.base_grid = 32;
    o.render.probe_grid = 6;
    o.render.starburst_options.mask_size = 64;
    o.render.starburst_options.fft_size = 256;
    o.fixed_angle_deg = 3.0;
    o.hot_pixel_fraction = 1e-3;
    // A real camera's shortest exposure (the simulated default, 1 ns, is there for the light's
    // core in auto-bracketing); the exposure series plans its foot down to it.
    o.min_exposure_s = 1e-5;
    o.response = response;
    o.seed = seed;
    return o;
}

struct Measured {
    std::unique_ptr<SimCamera> camera;
    DarkFrames dark;
    std::vector<ExposureLevel> series;
    CameraCalibration calibration;
};

// What flarelab calibrate does, on the simulated camera: dark frames with the lens capped, a
// planned series without.
Measured calibrate(const SimCameraOptions& options, double gain = 1.0) {
    Measured m;
    auto camera = SimCamera::make(heliar(), options);
    EXPECT_TRUE(camera) << camera.error().message;
    m.camera = std::move(*camera);
    EXPECT_TRUE(m.camera->setGain(gain));
    const CalibrationCapture capture;
    m.camera->setLensCapped(true);
    auto dark = captureDarkFrames(*m.camera, capture);
    EXPECT_TRUE(dark) << dark.error().message;
    m.dark = std::move(*dark);
    m.camera->setLensCapped(false);
    auto measured_dark = measureDark(m.dark);
    EXPECT_TRUE(measured_dark) << measured_dark.error().message;
    auto plan = planSeriesExposures(*m.camera, measured_dark->black_level_dn, capture);
    EXPECT_TRUE(plan) << plan.error().message;
    auto series = captureSeries(*m.camera, *plan, capture);
    EXPECT_TRUE(series) << series.error().message;
    m.series = std::move(*series);
    auto calibration = buildCalibration(m.camera->identity(), m.dark, m.series);
    EXPECT_TRUE(calibration) << calibration.error().message;
    m.calibration = std::move(*calibration);
    return m;
}

const Measured& linearCamera() {
    static const Measured m = calibrate(scene());
    return m;
}

std::vector<int64_t> trueHotPixels(const SimCamera& camera) {
    std::vector<int64_t> hot;
    const auto& extra = camera.hotPixelDark_e_s();
    for (size_t i = 0; i < extra.size(); ++i)
        if (extra[i] > 0.0f) hot.push_back(static_cast<int64_t>(i));
    return hot;
}

TEST(CalibrationMeasure, RecoversTheSimulatedCamerasFiguresWithinFivePercent) {
    const Measured& m = linearCamera();
    const CameraCalibration& c = m.calibration;
    const SimCameraOptions truth = scene();
    EXPECT_TRUE(c.linear);
    EXPECT_LT(c.linearity_error, 0.01);
    EXPECT_NEAR(c.black_level_dn, truth.black_level_dn, 0.05 * truth.black_level_dn);
    EXPECT_NEAR(c.read_noise_e, truth.read_noise_e, 0.05 * truth.read_noise_e);
    EXPECT_NEAR(c.electrons_per_dn, truth.electrons_per_dn, 0.05 * truth.electrons_per_dn);
    EXPECT_NEAR(c.read_noise_dn, truth.read_noise_e / truth.electrons_per_dn,
                0.05 * truth.read_noise_e / truth.electrons_per_dn);
    const double white = std::ldexp(1.0, truth.bit_depth) - 1.0;
    EXPECT_NEAR(c.saturation_dn, white, 0.05 * white);
    EXPECT_EQ(c.hot_pixels, trueHotPixels(*m.camera));
    EXPECT_FALSE(c.hot_pixels.empty());
    EXPECT_FALSE(c.response_curve);
    EXPECT_EQ(c.camera_serial, truth.serial);
    EXPECT_EQ(c.width_px, truth.width_px);
    EXPECT_EQ(c.bit_depth, truth.bit_depth);
    EXPECT_TRUE(validateCalibration(c));
}

TEST(CalibrationMeasure, MeasuresConversionGainAtTheGainItIsGiven) {
    SimCameraOptions o = scene();
    o.width_px = 160;
    o.height_px = 107;
    o.hot_pixel_fraction = 0.0;
    const Measured m = calibrate(o, 2.0);
    const CameraCalibration& c = m.calibration;
    EXPECT_EQ(c.gain, 2.0);
    // Twice the gain: half the electrons per DN, twice the read noise in DN, the same in e-.
    EXPECT_NEAR(c.electrons_per_dn, 2.0, 0.05 * 2.0);
    EXPECT_NEAR(c.read_noise_dn, 1.5, 0.05 * 1.5);
    EXPECT_NEAR(c.read_noise_e, 3.0, 0.05 * 3.0);
    EXPECT_TRUE(c.hot_pixels.empty());
}

// The recovered curve against the simulated one, in stops, over the range it was measured on
// (above the noise floor), after the best common scale.
double curveError(const CameraCalibration& c, const SimCameraOptions& truth, double from_dn) {
    std::vector<double> errors;
    const double white = std::ldexp(1.0, truth.bit_depth) - 1.0;
    for (double z = from_dn; z <= c.saturation_dn; z += 1.0) {
        const double x = relativeExposure(*c.response_curve, c.black_level_dn, z);
        const double t =
            simResponseInverse(truth, (z - truth.black_level_dn) / (white - truth.black_level_dn));
        errors.push_back(std::log2(x / t));
    }
    double mean = 0.0;
    for (const double e : errors) mean += e;
    mean /= static_cast<double>(errors.size());
    double sum2 = 0.0;
    for (const double e : errors) sum2 += (e - mean) * (e - mean);
    return std::sqrt(sum2 / static_cast<double>(errors.size()));
}

TEST(CalibrationMeasure, FindsCurvedResponsesNotLinearAndRecoversThem) {
    for (const SimResponse response : {SimResponse::Gamma, SimResponse::Log}) {
        const SimCameraOptions truth = scene(response);
        const Measured m = calibrate(truth);
        const CameraCalibration& c = m.calibration;
        EXPECT_FALSE(c.linear);
        EXPECT_GT(c.linearity_error, 0.3);
        ASSERT_TRUE(c.response_curve);
        // Over the range the curve was measured on: from the noise floor to where it ends.
        auto dark = measureDark(m.dark);
        ASSERT_TRUE(dark);
        const double floor = c.black_level_dn + dark->noise_floor_dn;
        EXPECT_LT(curveError(c, truth, floor), 0.05) << static_cast<int>(response);
        EXPECT_GT(c.saturation_dn, 0.95 * 4095.0);

        // Linearized, two exposures a factor 4 apart differ by a factor 4 where neither is
        // near the floor or clipped (the pair of the series with the most such pixels).
        std::vector<double> ratios;
        double expected = 0.0;
        for (size_t j = 0; j + 2 < m.series.size(); ++j) {
            const ExposureLevel& low = m.series[j];
            const ExposureLevel& high = m.series[j + 2];
            auto a = applyCalibration(low.frames[0], c);
            auto b = applyCalibration(high.frames[0], c);
            ASSERT_TRUE(a && b);
            std::vector<double> r;
            for (size_t i = 0; i < a->samples.size(); ++i)
                if (a->samples[i] > 2000 && b->samples[i] < 30000)
                    r.push_back(static_cast<double>(b->samples[i]) / a->samples[i]);
            if (r.size() > ratios.size()) {
                ratios = std::move(r);
                expected = high.exposure_s / low.exposure_s;
            }
        }
        ASSERT_GT(ratios.size(), 100u);
        std::nth_element(ratios.begin(), ratios.begin() + ratios.size() / 2, ratios.end());
        EXPECT_NEAR(ratios[ratios.size() / 2], expected, 0.02 * expected);
    }
}

// Frames like those of Aravis's fake camera: a diagonal ramp that moves by a pixel every frame,
// scaled by 1 + log10(t / 10 ms), 8 bits.
hdr::RawFrame fakeCameraFrame(double exposure_s, int64_t frame_id) {
    hdr::RawFrame f;
    f.width = 96;
    f.height = 64;
    f.bit_depth = 8;
    f.exposure_s = exposure_s;
    f.camera = "Aravis Fake GV01";
    f.white_level_dn = 255.0;
    const double scale = 1.0 + std::log10(exposure_s / 0.01);
    for (int64_t y = 0; y < f.height; ++y)
        for (int64_t x = 0; x < f.width; ++x) {
            const double v = static_cast<double>((x + y + frame_id) % 255) * scale;
            f.samples.push_back(static_cast<uint16_t>(std::clamp(v, 0.0, 255.0)));
        }
    return f;
}

TEST(CalibrationMeasure, AMovingLogarithmicPatternIsNotSteadyAndNotLinear) {
    DarkFrames dark;
    int64_t id = 0;
    for (int k = 0; k < 4; ++k) dark.bias.push_back(fakeCameraFrame(1e-4, id++));  // all 0
    dark.long_dark.push_back(fakeCameraFrame(1e-4, id++));
    std::vector<ExposureLevel> series;
    for (double t = 0.02; t <= 20.0; t *= 2.0) {
        ExposureLevel level;
        level.exposure_s = t;
        for (int k = 0; k < 2; ++k) level.frames.push_back(fakeCameraFrame(t, id++));
        series.push_back(std::move(level));
    }
    auto d = measureDark(dark);
    ASSERT_TRUE(d) << d.error().message;
    auto r = measureResponse(series, d->black_level_dn, d->noise_floor_dn, d->hot_pixels);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_FALSE(r->steady);
    EXPECT_NE(r->steadiness.find("shifted"), std::string::npos) << r->steadiness;
    EXPECT_FALSE(r->linear);
    EXPECT_TRUE(r->curve);
    auto c = buildCalibration(DeviceIdentity{"aravis", "Aravis Fake", "GV01", ""}, dark, series);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_FALSE(c->linear);
    EXPECT_EQ(c->electrons_per_dn, 0.0);  // no pairs of a moving pattern
    // Its brightness is not a function of exposure alone (the ramp's value multiplies the
    // logarithm of the exposure), and the calibration says so.
    EXPECT_GT(c->response_curve->rms_error_stops, 0.1);
    bool said = false;
    for (const std::string& note : c->notes)
        said = said || note.find("not a function of exposure alone") != std::string::npos;
    EXPECT_TRUE(said);
}

TEST(CalibrationMeasure, RefusesDarkFramesThatSeeLight) {
    auto camera = SimCamera::make(heliar(), scene());
    ASSERT_TRUE(camera);
    CalibrationCapture capture;
    auto dark = captureDarkFrames(**camera, capture);  // the lens left uncapped
    ASSERT_TRUE(dark);
    auto measured = measureDark(*dark);
    ASSERT_FALSE(measured);
    EXPECT_NE(measured.error().message.find("cap the lens"), std::string::npos)
        << measured.error().message;
}

TEST(CalibrationMeasure, RefusesASeriesThatNeverClips) {
    // A noiseless linear ramp whose brightest pixel reaches a third of the range.
    std::vector<ExposureLevel> dim;
    for (const double t : {0.25, 0.5, 1.0, 2.0}) {
        ExposureLevel level;
        level.exposure_s = t;
        hdr::RawFrame f;
        f.width = 64;
        f.height = 32;
        f.bit_depth = 12;
        f.exposure_s = t;
        for (int64_t i = 0; i < f.width * f.height; ++i)
            f.samples.push_back(static_cast<uint16_t>(64.0 + 0.3 * i * t));
        level.frames = {f, f};
        dim.push_back(std::move(level));
    }
    auto r = measureResponse(dim, 64.0, 2.0, {});
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("lengthen"), std::string::npos) << r.error().message;
    EXPECT_FALSE(measureResponse(std::span(dim).first(2), 64.0, 2.0, {}));
}

TEST(CalibrationMeasure, OneFramePerExposureIsSaidToBiasTheFigures) {
    const Measured& m = linearCamera();
    std::vector<ExposureLevel> single = m.series;
    for (ExposureLevel& level : single) level.frames.resize(1);
    auto c = buildCalibration(m.camera->identity(), m.dark, single);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_TRUE(c->linear);
    EXPECT_EQ(c->electrons_per_dn, 0.0);  // photon transfer needs pairs
    bool said = false;
    for (const std::string& note : c->notes)
        said = said || note.find("one frame") != std::string::npos;
    EXPECT_TRUE(said);
}

}  // namespace
}  // namespace flarelab::drivers
