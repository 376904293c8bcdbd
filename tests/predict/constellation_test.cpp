#include "predict/constellation.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>

#include "common/units.h"

namespace flarelab::predict {
namespace {

double dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

Constellation of(const CameraPose& pose, const Vec3& to_light) {
    auto c = constellationOf(cameraFrame(pose), to_light);
    EXPECT_TRUE(c) << c.error().message;
    return c ? *c : Constellation{};
}

TEST(Constellation, ALightAheadRightAndAboveHasTheImageSidesOfTheOptics) {
    CameraPose north;  // pan 0: looking north, level
    EXPECT_NEAR(of(north, {0, 10, 0}).theta_deg, 0.0, 1e-12);
    EXPECT_EQ(of(north, {0, 10, 0}).phi_deg, 0.0);  // on the axis the roll is 0
    // East is the image's right: phi 0. Up is the image's -y: phi -90 (y points down).
    EXPECT_NEAR(of(north, {10, 10, 0}).theta_deg, 45.0, 1e-12);
    EXPECT_NEAR(of(north, {10, 10, 0}).phi_deg, 0.0, 1e-12);
    EXPECT_NEAR(of(north, {0, 10, 10}).theta_deg, 45.0, 1e-12);
    EXPECT_NEAR(of(north, {0, 10, 10}).phi_deg, -90.0, 1e-12);
    EXPECT_NEAR(of(north, {-1, 2, -1}).phi_deg, 135.0, 1e-12);    // left and below
    EXPECT_NEAR(of(north, {0, -10, 0}).theta_deg, 180.0, 1e-12);  // behind
    // Turned east (pan 90), a light to the north is on the left.
    CameraPose east;
    east.pan_deg = 90.0;
    EXPECT_NEAR(of(east, {1, 0, 0}).theta_deg, 0.0, 1e-12);
    EXPECT_NEAR(std::abs(of(east, {0, 1, 0}).phi_deg), 180.0, 1e-12);
    // Rolled clockwise by 90: the image's right points down, so the world's east is the image's up.
    CameraPose rolled;
    rolled.roll_deg = 90.0;
    EXPECT_NEAR(of(rolled, {1, 1, 0}).phi_deg, -90.0, 1e-12);
}

TEST(Constellation, RecoversEveryAngleItWasBuiltFromAnyPose) {
    std::mt19937_64 rng(11);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    for (int i = 0; i < 2000; ++i) {
        CameraPose pose;
        pose.pan_deg = 720.0 * u(rng) - 360.0;
        pose.tilt_deg = 180.0 * u(rng) - 90.0;
        pose.roll_deg = 720.0 * u(rng) - 360.0;
        const CameraFrame f = cameraFrame(pose);
        // The frame is orthonormal and right-handed (up = right x forward) at any pose,
        // tilt +-90 included.
        EXPECT_NEAR(dot(f.forward, f.forward), 1.0, 1e-12);
        EXPECT_NEAR(dot(f.right, f.right), 1.0, 1e-12);
        EXPECT_NEAR(dot(f.up, f.up), 1.0, 1e-12);
        EXPECT_NEAR(dot(f.forward, f.right), 0.0, 1e-12);
        EXPECT_NEAR(dot(f.forward, f.up), 0.0, 1e-12);
        EXPECT_NEAR(dot(f.right, f.up), 0.0, 1e-12);
        const Vec3 cross = {f.right[1] * f.forward[2] - f.right[2] * f.forward[1],
                            f.right[2] * f.forward[0] - f.right[0] * f.forward[2],
                            f.right[0] * f.forward[1] - f.right[1] * f.forward[0]};
        EXPECT_NEAR(dot(cross, f.up), 1.0, 1e-12);
        const double theta = 179.0 * u(rng) + 0.5, phi = 359.0 * u(rng) - 179.0;
        const double st = std::sin(degToRad(theta)), ct = std::cos(degToRad(theta));
        const double x = st * std::cos(degToRad(phi)), y = st * std::sin(degToRad(phi));
        Vec3 d;
        for (int k = 0; k < 3; ++k) d[k] = ct * f.forward[k] + x * f.right[k] - y * f.up[k];
        const double scale = 1e-3 + 1e6 * u(rng);  // any distance
        for (double& v : d) v *= scale;
        const Constellation c = of(pose, d);
        EXPECT_NEAR(c.theta_deg, theta, 1e-9);
        EXPECT_NEAR(std::remainder(c.phi_deg - phi, 360.0), 0.0, 1e-9);
    }
}

TEST(Constellation, GrazingAndOnAxisLightsKeepTheirPrecision) {
    CameraPose pose;
    // 1e-7 degrees off the axis: acos would lose it in rounding; atan2 does not.
    const double tiny = degToRad(1e-7);
    EXPECT_NEAR(of(pose, {std::sin(tiny), std::cos(tiny), 0.0}).theta_deg, 1e-7, 1e-15);
    const double grazing = degToRad(90.0 - 1e-9);
    EXPECT_LT(of(pose, {std::sin(grazing), std::cos(grazing), 0.0}).theta_deg, 90.0);
    EXPECT_NEAR(of(pose, {1.0, 0.0, 0.0}).theta_deg, 90.0, 1e-12);
}

TEST(Constellation, ALightWithNoDirectionIsRefused) {
    const CameraFrame f = cameraFrame(CameraPose{});
    EXPECT_FALSE(constellationOf(f, {0.0, 0.0, 0.0}));
    EXPECT_FALSE(constellationOf(f, {1e-12, 0.0, 0.0}));
    EXPECT_FALSE(constellationOf(f, {std::nan(""), 1.0, 0.0}));
    EXPECT_FALSE(constellationOf(f, {INFINITY, 1.0, 0.0}));
    auto c = constellationOf(f, {0.0, 0.0, 0.0});
    ASSERT_FALSE(c);
    EXPECT_NE(c.error().message.find("camera's position"), std::string::npos);
}

TEST(PoseLookingAt, PutsTheTargetOnTheAxis) {
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> u(-100.0, 100.0);
    for (int i = 0; i < 200; ++i) {
        const Vec3 from = {u(rng), u(rng), u(rng)}, to = {u(rng), u(rng), u(rng)};
        auto pose = poseLookingAt(from, to);
        ASSERT_TRUE(pose);
        const Vec3 d = {to[0] - from[0], to[1] - from[1], to[2] - from[2]};
        EXPECT_NEAR(of(*pose, d).theta_deg, 0.0, 1e-6);
        EXPECT_EQ(pose->roll_deg, 0.0);
    }
    // Straight up and straight down are poses too.
    auto up = poseLookingAt({0, 0, 0}, {0, 0, 5});
    ASSERT_TRUE(up);
    EXPECT_NEAR(up->tilt_deg, 90.0, 1e-12);
    EXPECT_NEAR(of(*up, {0, 0, 1}).theta_deg, 0.0, 1e-9);
    EXPECT_FALSE(poseLookingAt({1, 2, 3}, {1, 2, 3.0005}));
    EXPECT_FALSE(poseLookingAt({1, 2, std::nan("")}, {1, 2, 3}));
}

TEST(SunDirection, PointsAtTheZenithAndAlongTheCompass) {
    const Vec3 zenith = sunDirection(0.0, 123.0);
    EXPECT_NEAR(zenith[2], 1.0, 1e-12);
    const Vec3 east = sunDirection(90.0, 90.0);
    EXPECT_NEAR(east[0], 1.0, 1e-12);
    EXPECT_NEAR(east[1], 0.0, 1e-12);
    const Vec3 south = sunDirection(60.0, 180.0);  // 30 deg up, due south
    EXPECT_NEAR(south[1], -std::cos(degToRad(30.0)), 1e-12);
    EXPECT_NEAR(south[2], 0.5, 1e-12);
}

TEST(BrightnessScale, FollowsEquation83) {
    CameraExposure scene{4.0, 0.5, 2.0};
    auto k = brightnessScale(8.0, scene, 3.0);
    ASSERT_TRUE(k);
    // (8 / 4)^2 * 0.5 s * 2 * 3: a stop of aperture is twice the light.
    EXPECT_DOUBLE_EQ(*k, 4.0 * 0.5 * 2.0 * 3.0);
    EXPECT_DOUBLE_EQ(*brightnessScale(8.0, CameraExposure{8.0 * std::sqrt(2.0), 1.0, 1.0}, 1.0),
                     0.5);
    EXPECT_EQ(*brightnessScale(8.0, CameraExposure{8.0, 1.0, 1.0}, 0.0), 0.0);  // a dark light
    EXPECT_FALSE(brightnessScale(0.0, scene, 1.0));
    EXPECT_FALSE(brightnessScale(8.0, CameraExposure{-1.0, 1.0, 1.0}, 1.0));
    EXPECT_FALSE(brightnessScale(8.0, CameraExposure{4.0, 0.0, 1.0}, 1.0));
    EXPECT_FALSE(brightnessScale(8.0, CameraExposure{4.0, 1.0, std::nan("")}, 1.0));
    EXPECT_FALSE(brightnessScale(8.0, scene, -1.0));
    EXPECT_FALSE(brightnessScale(8.0, scene, INFINITY));
}

}  // namespace
}  // namespace flarelab::predict
