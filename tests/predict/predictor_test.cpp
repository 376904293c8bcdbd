#include "predict/predictor.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <string>

#include "fit/model_file.h"
#include "tests/predict/moving_disc_model.h"

namespace flarelab::predict {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono;

// A model file in a fresh folder, removed with the fixture.
class PredictorTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("flarelab_predictor_" + std::to_string(::getpid()) + "_" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::create_directories(dir_);
        model_path_ = (dir_ / "disc.flm").string();
        ASSERT_TRUE(fit::writeModel(model_path_, testing::movingDiscModel()));
    }
    void TearDown() override { fs::remove_all(dir_); }

    SceneCamera camera(const std::string& name = "cam") const {
        SceneCamera c;
        c.name = name;
        c.model_path = model_path_;
        c.exposure_s = 0.5;
        return c;
    }

    fs::path dir_;
    std::string model_path_;
};

SceneLight relativeLight(const std::string& name, const Vec3& direction, double relative) {
    SceneLight l;
    l.name = name;
    l.direction = direction;
    l.intensity.relative = relative;
    return l;
}

// A light at (theta, phi) for a camera looking north, level.
Vec3 lightAt(double theta_deg, double phi_deg) {
    const double t = theta_deg * M_PI / 180.0, p = phi_deg * M_PI / 180.0;
    return {std::sin(t) * std::cos(p), std::cos(t), -std::sin(t) * std::sin(p)};
}

TEST_F(PredictorTest, FixedLightsAreTheTablesFiguresScaledByEquation83) {
    SceneCamera c = camera();
    c.f_number = 4.0;  // two stops more light than the capture's f/8
    c.gain = 2.0;
    c.scene_min_dn = 10.0;
    c.scene_max_dn = 1000.0;
    auto prepared = prepareCamera(c);
    ASSERT_TRUE(prepared) << prepared.error().message;
    ASSERT_EQ(prepared->notes.size(), 1u);  // the other f-number is noted
    EXPECT_NE(prepared->notes[0].find("f/4"), std::string::npos);
    const SceneLight lights[] = {relativeLight("a", lightAt(3.0, 20.0), 1.5),
                                 relativeLight("b", lightAt(6.0, -70.0), 1.0)};
    auto figures = fixedLightFigures(*prepared, lights, RangePolicy::Refuse);
    ASSERT_TRUE(figures) << figures.error().message;
    ASSERT_EQ(figures->lights.size(), 2u);
    const double scale = 4.0 * 0.5 * 2.0;  // (8/4)^2 x 0.5 s x gain 2
    const auto a = prepared->table.at(3.0, 20.0);
    ASSERT_TRUE(a);
    EXPECT_NEAR(figures->lights[0].figures.mean, 1.5 * scale * a->mean, 1e-9 * a->mean);
    EXPECT_NEAR(figures->lights[0].placed.constellation.theta_deg, 3.0, 1e-9);
    EXPECT_NEAR(figures->sum.mean,
                figures->lights[0].figures.mean + figures->lights[1].figures.mean, 1e-12);
    EXPECT_NEAR(figures->lights[0].figures.total, figures->lights[0].figures.mean * 72 * 48, 1e-6);
    ASSERT_TRUE(figures->contrast_ratio);
    EXPECT_NEAR(*figures->contrast_ratio, 1010.0 / (1010.0 + 2.0 * figures->sum.mean), 1e-12);
    // A light outside the model: the camera's figures are unknown under refuse.
    const SceneLight far[] = {lights[0], relativeLight("far", lightAt(30.0, 0.0), 1.0)};
    auto unknown = fixedLightFigures(*prepared, far, RangePolicy::Refuse);
    ASSERT_TRUE(unknown);
    EXPECT_FALSE(unknown->known);
    EXPECT_FALSE(unknown->contrast_ratio);
    auto clamped = fixedLightFigures(*prepared, far, RangePolicy::Clamp);
    ASSERT_TRUE(clamped);
    EXPECT_TRUE(clamped->known);
    EXPECT_EQ(clamped->lights[1].placed.state, LightState::Clamped);
}

TEST_F(PredictorTest, CamerasSharingAModelShareItsTableAndWrongSizesAreNamed) {
    const SceneCamera cams[] = {camera("one"), camera("two")};
    auto prepared = prepareCameras(cams);
    ASSERT_TRUE(prepared) << prepared.error().message;
    ASSERT_EQ(prepared->size(), 2u);
    EXPECT_EQ((*prepared)[0].table.at(4.0, 10.0)->mean, (*prepared)[1].table.at(4.0, 10.0)->mean);
    SceneCamera wide = camera("wide");
    wide.width_px = 1920;
    wide.height_px = 1080;
    auto refused = prepareCamera(wide);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("camera 'wide'"), std::string::npos);
    SceneCamera missing = camera("missing");
    missing.model_path = (dir_ / "nothing.flm").string();
    auto absent = prepareCamera(missing);
    ASSERT_FALSE(absent);
    EXPECT_NE(absent.error().message.find("nothing.flm"), std::string::npos);
}

TEST_F(PredictorTest, PhotometricLightsNeedTheRigsIlluminance) {
    auto prepared = prepareCamera(camera());
    ASSERT_TRUE(prepared);
    SceneLight lamp;
    lamp.name = "lamp";
    lamp.position_m = Vec3{0.0, 20.0, 1.0};
    lamp.intensity.intensity_cd = 40000.0;
    const SceneLight lights[] = {lamp};
    EXPECT_FALSE(fixedLightFigures(*prepared, lights, RangePolicy::Refuse));
    SceneCamera c = camera();
    c.rig_illuminance_lux = 100.0;
    auto lit = prepareCamera(c);
    ASSERT_TRUE(lit);
    auto figures = fixedLightFigures(*lit, lights, RangePolicy::Refuse);
    ASSERT_TRUE(figures) << figures.error().message;
    // 40000 cd at sqrt(401) m: 99.75 lux, about the rig's 100.
    const auto& lf = figures->lights[0];
    const auto t =
        lit->table.at(lf.placed.constellation.theta_deg, lf.placed.constellation.phi_deg);
    ASSERT_TRUE(t);
    EXPECT_NEAR(lf.figures.mean, 0.5 * (40000.0 / 401.0) / 100.0 * t->mean, 1e-9 * t->mean);
}

TEST_F(PredictorTest, TheSunsTimelineAddsTheFixedLightsAndKnowsWhenItCannotSay) {
    SceneSun sun;
    sun.site.latitude_deg = 48.2;
    sun.site.longitude_deg = 16.37;
    sun.site.elevation_m = 170.0;
    sun.from = sys_days{year{2026} / 6 / 21} + hours{14};
    sun.to = sun.from + minutes{40};
    sun.step = seconds{20};
    sun.intensity.relative = 2.0;
    // The camera looks 4 deg above where the sun stands at the middle of the span.
    auto middle = sunPosition(sun.site, sun.from + minutes{20});
    ASSERT_TRUE(middle);
    SceneCamera c = camera();
    c.pose.pan_deg = middle->azimuth_deg;
    c.pose.tilt_deg = middle->elevation_deg + 4.0;
    c.scene_min_dn = 5.0;
    c.scene_max_dn = 500.0;
    c.scene_log_average_dn = 80.0;
    auto prepared = prepareCamera(c);
    ASSERT_TRUE(prepared);
    const SceneLight lights[] = {relativeLight(
        "fixed",
        [&] {
            // 2 deg to the right of the camera's axis, level with it.
            const CameraFrame f = cameraFrame(c.pose);
            const double a = 2.0 * M_PI / 180.0;
            return Vec3{std::cos(a) * f.forward[0] + std::sin(a) * f.right[0],
                        std::cos(a) * f.forward[1] + std::sin(a) * f.right[1],
                        std::cos(a) * f.forward[2] + std::sin(a) * f.right[2]};
        }(),
        1.0)};
    const PreparedCamera cams[] = {*prepared};
    auto timeline = predictTimeline(sun, cams, lights, RangePolicy::Refuse);
    ASSERT_TRUE(timeline) << timeline.error().message;
    ASSERT_EQ(timeline->sun.positions.size(), 121u);
    const CameraTimeline& ct = timeline->cameras[0];
    auto fixed = fixedLightFigures(*prepared, lights, RangePolicy::Refuse);
    ASSERT_TRUE(fixed);
    // The middle step: the sun 4 deg below the axis.
    const size_t mid = 60;
    EXPECT_EQ(ct.sun_state[mid], LightState::Drawn);
    const auto& s = timeline->sun.positions[mid];
    const LightAtCamera placed =
        placeLight(prepared->model, prepared->frame, sunDirection(s.zenith_deg, s.azimuth_deg),
                   RangePolicy::Refuse);
    EXPECT_NEAR(placed.constellation.theta_deg, 4.0, 0.01);
    EXPECT_NEAR(placed.constellation.phi_deg, 90.0, 0.5);
    const auto t = prepared->table.at(placed.constellation.theta_deg, placed.constellation.phi_deg);
    ASSERT_TRUE(t);
    EXPECT_NEAR(ct.flare_mean[mid], fixed->sum.mean + 2.0 * 0.5 * t->mean, 1e-9);
    EXPECT_NEAR(ct.contrast_loss[mid], 1.0 - 505.0 / (505.0 + 2.0 * ct.flare_mean[mid]), 1e-12);
    EXPECT_NEAR(ct.glare_indicator[mid], ct.flare_mean[mid] / 80.0, 1e-12);
    EXPECT_EQ(
        ct.steps_drawn + ct.steps_refused + ct.steps_clamped + ct.steps_behind + ct.steps_sun_down,
        121);
    // The sun leaves the model's 10 deg within the span: those steps are unknown, not zero.
    int64_t unknown = 0;
    for (double v : ct.flare_mean) unknown += std::isnan(v);
    EXPECT_EQ(unknown, ct.steps_refused);
    // At night only the fixed lights remain.
    SceneSun night = sun;
    night.from = sys_days{year{2026} / 6 / 21} + hours{23};
    night.to = night.from + minutes{1};
    auto dark = predictTimeline(night, cams, lights, RangePolicy::Refuse);
    ASSERT_TRUE(dark);
    EXPECT_EQ(dark->cameras[0].steps_sun_down, 4);
    EXPECT_NEAR(dark->cameras[0].flare_mean[0], fixed->sum.mean, 1e-12);
    // The switching series are the timeline's.
    const auto series = switchingFigures(*timeline, SwitchFigure::ContrastLoss);
    ASSERT_EQ(series.size(), 1u);
    EXPECT_EQ(series[0].size(), 121u);
    const auto glare = switchingFigures(*timeline, SwitchFigure::GlareIndicator);
    ASSERT_EQ(glare.size(), 1u);
    EXPECT_EQ(glare[0][mid], ct.glare_indicator[mid]);
    EXPECT_NEAR(fixed->glare_indicator.value(), fixed->sum.mean / 80.0, 1e-12);
}

TEST_F(PredictorTest, AFrameDrawsTheFixedLightsAndTheSun) {
    auto prepared = prepareCamera(camera());
    ASSERT_TRUE(prepared);
    const SceneLight lights[] = {relativeLight("a", lightAt(3.0, 0.0), 1.0)};
    SunLight sun{lightAt(5.0, 90.0), {}, {1.0, 1.0, 1.0}};
    sun.intensity.relative = 1.0;
    auto frame = drawCameraFrame(*prepared, lights, sun, RangePolicy::Refuse);
    ASSERT_TRUE(frame) << frame.error().message;
    ASSERT_EQ(frame->lights.size(), 2u);
    EXPECT_EQ(frame->image.width, 72);
    auto only = drawCameraFrame(*prepared, lights, std::nullopt, RangePolicy::Refuse);
    ASSERT_TRUE(only);
    EXPECT_GT(flareFigures(frame->image).mean, flareFigures(only->image).mean);
}

}  // namespace
}  // namespace flarelab::predict
