#include "predict/playback.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "common/units.h"
#include "fit/model_eval.h"
#include "predict/figures.h"
#include "tests/predict/moving_disc_model.h"

namespace flarelab::predict {
namespace {

// A light at (theta, phi) for a camera looking north, level.
Vec3 lightInFrame(double theta_deg, double phi_deg) {
    const CameraFrame f = cameraFrame(CameraPose{});
    const double st = std::sin(degToRad(theta_deg)), ct = std::cos(degToRad(theta_deg));
    const double x = st * std::cos(degToRad(phi_deg)), y = st * std::sin(degToRad(phi_deg));
    Vec3 d;
    for (int k = 0; k < 3; ++k) d[k] = ct * f.forward[k] + x * f.right[k] - y * f.up[k];
    return d;
}

// The luminance-weighted centroid of an image, in pixels from its centre.
std::array<double, 2> centroid(const ImageRGB& image) {
    double sx = 0.0, sy = 0.0, s = 0.0;
    for (int64_t y = 0; y < image.height; ++y)
        for (int64_t x = 0; x < image.width; ++x) {
            const double v = image.at(x, y)[1];
            sx += v * (x + 0.5 - 0.5 * image.width);
            sy += v * (y + 0.5 - 0.5 * image.height);
            s += v;
        }
    return {sx / s, sy / s};
}

TEST(Playback, DrawsTheModelAtTheLightsAngleAndRoll) {
    const fit::FlareModel model = testing::movingDiscModel();
    const CameraFrame frame = cameraFrame(CameraPose{});
    // At 4 deg the disc sits 6 mm (12 px) on the far side of the light: left of the centre for a
    // light on the right, above it for a light below (phi 90, y down).
    const PlaybackLight right{"right", lightInFrame(4.0, 0.0), {1, 1, 1}};
    auto image = playback(model, frame, std::span(&right, 1));
    ASSERT_TRUE(image) << image.error().message;
    ASSERT_EQ(image->lights.size(), 1u);
    EXPECT_EQ(image->lights[0].state, LightState::Drawn);
    auto c = centroid(image->image);
    EXPECT_NEAR(c[0], -12.0, 0.2);
    EXPECT_NEAR(c[1], 0.0, 0.2);
    const PlaybackLight below{"below", lightInFrame(4.0, 90.0), {1, 1, 1}};
    image = playback(model, frame, std::span(&below, 1));
    ASSERT_TRUE(image);
    c = centroid(image->image);
    EXPECT_NEAR(c[0], 0.0, 0.2);
    EXPECT_NEAR(c[1], -12.0, 0.2);
    // The same as the model drawn directly.
    auto direct = fit::renderModel(model, 4.0, 90.0, 72, 48);
    ASSERT_TRUE(direct);
    EXPECT_EQ(direct->pixels, image->image.pixels);
}

TEST(Playback, LightsAddAndScaleByChannel) {
    const fit::FlareModel model = testing::movingDiscModel();
    const CameraFrame frame = cameraFrame(CameraPose{});
    const PlaybackLight a{"a", lightInFrame(2.0, 30.0), {1.0, 0.0, 0.5}};
    const PlaybackLight b{"b", lightInFrame(6.0, -120.0), {3.0, 3.0, 3.0}};
    const PlaybackLight both[] = {a, b};
    auto ia = playback(model, frame, std::span(&a, 1));
    auto ib = playback(model, frame, std::span(&b, 1));
    auto iab = playback(model, frame, both);
    ASSERT_TRUE(ia && ib && iab);
    double peak_green_a = 0.0;
    for (size_t i = 0; i < iab->image.pixels.size(); ++i) {
        EXPECT_NEAR(iab->image.pixels[i], ia->image.pixels[i] + ib->image.pixels[i], 1e-5);
        if (i % 3 == 1) peak_green_a = std::max<double>(peak_green_a, ia->image.pixels[i]);
    }
    EXPECT_EQ(peak_green_a, 0.0);  // light a has no green
    const FlareFigures fb = flareFigures(ib->image);
    EXPECT_NEAR(fb.max, 3.0 * 4.0, 0.05);  // inner intensity 4, three times the rig's light
}

TEST(Playback, LightsOutsideTheModelAreRefusedOrClampedNeverExtrapolated) {
    const fit::FlareModel model = testing::movingDiscModel();
    const CameraFrame frame = cameraFrame(CameraPose{});
    const PlaybackLight far{"far", lightInFrame(25.0, 0.0), {1, 1, 1}};
    auto refused = playback(model, frame, std::span(&far, 1));
    ASSERT_TRUE(refused);
    EXPECT_EQ(refused->lights[0].state, LightState::OutsideRange);
    EXPECT_FALSE(refused->lights[0].drawn());
    EXPECT_EQ(flareFigures(refused->image).max, 0.0);
    PlaybackOptions clamp;
    clamp.policy = RangePolicy::Clamp;
    auto clamped = playback(model, frame, std::span(&far, 1), clamp);
    ASSERT_TRUE(clamped);
    EXPECT_EQ(clamped->lights[0].state, LightState::Clamped);
    EXPECT_EQ(clamped->lights[0].model_theta_deg, 10.0);
    EXPECT_NEAR(clamped->lights[0].constellation.theta_deg, 25.0, 1e-9);
    auto edge = fit::renderModel(model, 10.0, 0.0, 72, 48);
    ASSERT_TRUE(edge);
    EXPECT_EQ(edge->pixels, clamped->image.pixels);
    // Exactly at the edge of the range: drawn, not clamped.
    const PlaybackLight at_edge{"edge", lightInFrame(10.0, 0.0), {1, 1, 1}};
    auto drawn = playback(model, frame, std::span(&at_edge, 1));
    ASSERT_TRUE(drawn);
    EXPECT_EQ(drawn->lights[0].state, LightState::Drawn);
    // Behind the camera and at its position: reported, nothing drawn, whatever the policy.
    const PlaybackLight behind{"behind", {0.0, -1.0, 0.0}, {1, 1, 1}};
    const PlaybackLight here{"here", {0.0, 0.0, 0.0}, {1, 1, 1}};
    const PlaybackLight two[] = {behind, here};
    auto skipped = playback(model, frame, two, clamp);
    ASSERT_TRUE(skipped);
    EXPECT_EQ(skipped->lights[0].state, LightState::BehindCamera);
    EXPECT_EQ(skipped->lights[1].state, LightState::AtCamera);
    EXPECT_EQ(flareFigures(skipped->image).max, 0.0);
}

TEST(Playback, ALightOnTheLeftPutsTheGhostOnTheRight) {
    const fit::FlareModel model = testing::movingDiscModel();
    const CameraFrame frame = cameraFrame(CameraPose{});
    const PlaybackLight light{"l", lightInFrame(4.0, 180.0), {1, 1, 1}};
    auto drawn = playback(model, frame, std::span(&light, 1));
    ASSERT_TRUE(drawn);
    const auto c = centroid(drawn->image);
    EXPECT_NEAR(c[0], 12.0, 0.2);
    EXPECT_NEAR(c[1], 0.0, 0.2);
}

TEST(Playback, SizesAndScalesAreChecked) {
    const fit::FlareModel model = testing::movingDiscModel();
    const CameraFrame frame = cameraFrame(CameraPose{});
    const PlaybackLight light{"l", lightInFrame(2.0, 0.0), {1, 1, 1}};
    PlaybackOptions o;
    o.width = 1920;
    o.height = 1080;  // 16:9 against the model's 3:2
    auto wrong = playback(model, frame, std::span(&light, 1), o);
    ASSERT_FALSE(wrong);
    EXPECT_NE(wrong.error().message.find("aspect"), std::string::npos);
    o.width = 1;
    o.height = 1;  // a single pixel is any aspect within its rounding
    EXPECT_TRUE(playback(model, frame, std::span(&light, 1), o));
    o.width = 1620;
    o.height = 1080;
    auto big = playback(model, frame, std::span(&light, 1), o);
    ASSERT_TRUE(big);
    EXPECT_EQ(big->image.width, 1620);
    o.width = 40000;
    EXPECT_FALSE(playback(model, frame, std::span(&light, 1), o));
    const PlaybackLight bad{"bad", lightInFrame(2.0, 0.0), {1, std::nan(""), 1}};
    auto refused = playback(model, frame, std::span(&bad, 1));
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("'bad'"), std::string::npos);
}

TEST(Playback, AModelWithNoGhostDrawsBlackAndStillPlacesItsLights) {
    const fit::FlareModel empty = testing::movingDiscModel(0);
    const PlaybackLight light{"l", lightInFrame(3.0, 0.0), {1, 1, 1}};
    auto image = playback(empty, cameraFrame(CameraPose{}), std::span(&light, 1));
    ASSERT_TRUE(image) << image.error().message;
    EXPECT_EQ(image->lights[0].state, LightState::Drawn);
    EXPECT_EQ(flareFigures(image->image).max, 0.0);
}

}  // namespace
}  // namespace flarelab::predict
