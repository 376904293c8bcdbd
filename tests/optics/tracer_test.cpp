#include "optics/tracer.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <random>

#include "common/units.h"
#include "optics/aim.h"
#include "optics/glass.h"
#include "optics/paraxial.h"
#include "tests/optics/lens_builders.h"

namespace flarelab::optics {
namespace {

using testing::lensOf;
using testing::refracting;
using testing::singlet;
using testing::stop;

// Distance of p from the surface c|p - v|^2 - 2 (p - v)_z = 0, in long double.
long double distanceToSurface(const Eigen::Vector3d& p, double vertex_z, double c) {
    const long double x = p.x(), y = p.y(), z = static_cast<long double>(p.z()) - vertex_z;
    const long double f = c * (x * x + y * y + z * z) - 2.0L * z;
    const long double gx = 2.0L * c * x, gy = 2.0L * c * y, gz = 2.0L * c * z - 2.0L;
    return std::fabs(f) / std::sqrt(gx * gx + gy * gy + gz * gz);
}

TEST(IntersectSurface, HitsLieOnTheSurfaceForRadiiFromOneMillimetreToTenKilometres) {
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<double> unit(-1.0, 1.0);
    int hits = 0;
    for (double radius : {1.0, -1.0, 7.5, -30.0, 100.0, -1e3, 1e5, -1e6, 1e7, -1e7}) {
        const double c = 1.0 / radius;
        const double h = std::min(std::abs(radius) * 0.95, 20.0);
        for (int i = 0; i < 20000; ++i) {
            const Eigen::Vector3d origin(h * unit(rng), h * unit(rng), -5.0 + 4.0 * unit(rng));
            Eigen::Vector3d dir(0.3 * unit(rng), 0.3 * unit(rng), 1.0);
            dir.normalize();
            const auto t = intersectSurface(origin, dir, 2.0, c);
            if (!t) continue;
            ++hits;
            const Eigen::Vector3d p = origin + *t * dir;
            ASSERT_LT(distanceToSurface(p, 2.0, c), 1e-10L * std::max(1.0, std::abs(p.z())))
                << "radius " << radius;
            ASSERT_LT(c * (p.z() - 2.0), 1.0) << "hit the far hemisphere, radius " << radius;
        }
    }
    EXPECT_GT(hits, 100000);
}

TEST(IntersectSurface, HugeRadiusDiffersFromFlatByExactlyTheSag) {
    // Sag of a 1e7 mm sphere at 10 mm height: 5e-6 mm. A centre-based formula loses it entirely.
    const Eigen::Vector3d origin(10.0, 0.0, -3.0), dir(0.0, 0.0, 1.0);
    const double flat = *intersectSurface(origin, dir, 0.0, 0.0);
    const double curved = *intersectSurface(origin, dir, 0.0, 1e-7);
    // R - sqrt(R^2 - h^2) written without cancellation (the plain form is off by 1e-10 here).
    const double sag = 100.0 / (1e7 + std::sqrt(1e14 - 100.0));
    EXPECT_NEAR(curved - flat, sag, 1e-15);  // the resolution of doubles near t = 3
    EXPECT_NEAR(sag, 5e-6, 1e-9);
}

TEST(IntersectSurface, FindsTheCapFromBeyondTheCentreOfCurvature) {
    // A ray starting 18 mm in front of a surface of radius -17.2 mm (concave towards it, centre
    // 17.2 mm in front): the near root of the quadratic is then the other one.
    const Eigen::Vector3d origin(0.0, 0.6, 0.0);
    Eigen::Vector3d dir(0.0, -0.012, 1.0);
    dir.normalize();
    const auto t = intersectSurface(origin, dir, 18.0, -1.0 / 17.214);
    ASSERT_TRUE(t);
    EXPECT_NEAR((origin + *t * dir).z(), 18.0, 0.05);
}

TEST(IntersectSurface, MissesReturnNullopt) {
    // Parallel to a plane, pointing away from it, and passing beside a small sphere.
    EXPECT_FALSE(intersectSurface({0, 0, -1}, {1, 0, 0}, 0.0, 0.0));
    EXPECT_FALSE(intersectSurface({0, 0, 1}, {0, 0, 1}, 0.0, 0.0));
    EXPECT_FALSE(intersectSurface({5.0, 0, -1}, {0, 0, 1}, 0.0, 1.0 / 2.0));
}

TEST(RefractDirection, ObeysSnellsLaw) {
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> unit(-1.0, 1.0), index(1.0, 2.0);
    for (int i = 0; i < 100000; ++i) {
        Eigen::Vector3d d(unit(rng), unit(rng), 1.0 + std::abs(unit(rng)));
        d.normalize();
        Eigen::Vector3d n(0.2 * unit(rng), 0.2 * unit(rng), -1.0);
        n.normalize();
        const double n1 = index(rng), n2 = index(rng);
        const auto t = refractDirection(d, n, n1, n2);
        const double sin1 = d.cross(n).norm();
        if (!t) {
            ASSERT_GT(n1 * sin1, n2 * (1.0 - 1e-12));
            continue;
        }
        ASSERT_NEAR(t->norm(), 1.0, 1e-12);
        ASSERT_NEAR(n1 * sin1, n2 * t->cross(n).norm(), 1e-12);
        ASSERT_NEAR(d.cross(n).normalized().dot(t->cross(n).normalized()), 1.0, 1e-9);
    }
}

TEST(RefractDirection, ReturnsNulloptBeyondCriticalAngle) {
    const Eigen::Vector3d n(0, 0, -1);
    const double critical = std::asin(1.0 / 1.5);
    const Eigen::Vector3d inside(std::sin(critical - 1e-6), 0, std::cos(critical - 1e-6));
    const Eigen::Vector3d beyond(std::sin(critical + 1e-6), 0, std::cos(critical + 1e-6));
    EXPECT_TRUE(refractDirection(inside, n, 1.5, 1.0));
    EXPECT_FALSE(refractDirection(beyond, n, 1.5, 1.0));
}

TEST(PathTracer, OnAxisRayOfImagingPathLandsOnTheAxis) {
    const Lens lens = singlet();
    const PathTracer tracer(lens, GhostPath{}, 550.0);
    Ray ray;
    ray.position = {0.0, 0.0, -10.0};
    ray.wavelength_nm = 550.0;
    const auto traced = tracer.trace(ray);
    ASSERT_TRUE(traced);
    EXPECT_EQ(traced->ray.position.x(), 0.0);
    EXPECT_EQ(traced->ray.position.y(), 0.0);
    const double n = refractiveIndex(1.5168, 64.17, 550.0);
    const double r = std::pow((n - 1.0) / (n + 1.0), 2);  // each bare face at normal incidence
    EXPECT_NEAR(traced->ray.throughput, (1.0 - r) * (1.0 - r), 1e-12);
}

TEST(PathTracer, ParaxialRaysFocusAtTheBackFocalPoint) {
    const Lens lens = singlet();
    const auto p = paraxialProperties(lens, 550.0);
    ASSERT_TRUE(p);
    // Move the image plane to the paraxial focus and trace a thin ray: it must cross the axis.
    std::vector<Surface> rows = {stop(5.0, 10.0), refracting(100.0, 6.0, 1.5168, 20.0, 64.17),
                                 refracting(-100.0, p->bfl_mm, 1.0, 20.0)};
    const Lens focused = lensOf(rows);
    const PathTracer tracer(focused, GhostPath{}, 550.0);
    Ray ray;
    ray.position = {0.0, 0.01, -10.0};
    ray.wavelength_nm = 550.0;
    const auto traced = tracer.trace(ray);
    ASSERT_TRUE(traced);
    EXPECT_NEAR(traced->ray.position.y(), 0.0, 1e-6);
}

TEST(PathTracer, ClipsAtClearApertureAndAtStop) {
    const Lens lens = singlet();
    const PathTracer clipping(lens, GhostPath{}, 550.0);
    const PathTracer recording(lens, GhostPath{}, 550.0,
                               TraceOptions{.clip_apertures = true, .clip_stop = false});
    Ray ray;
    ray.position = {0.0, 12.0, -10.0};  // outside the 10 mm stop, inside the 20 mm lens
    ray.wavelength_nm = 550.0;
    EXPECT_FALSE(clipping.trace(ray));
    const auto recorded = recording.trace(ray);
    ASSERT_TRUE(recorded);
    EXPECT_FALSE(recorded->inside_stop);
    EXPECT_NEAR(recorded->stop_v, 1.2, 1e-12);
    ray.position = {0.0, 25.0, -10.0};  // outside the lens's clear aperture
    EXPECT_FALSE(recording.trace(ray));
}

TEST(PathTracer, PolygonalStopBlocksTheCornersOfTheCircle) {
    CameraDescription camera;
    camera.aperture_blades = 6;
    const Lens lens = lensOf({stop(5.0, 10.0), refracting(100.0, 6.0, 1.5168, 20.0, 64.17),
                              refracting(-100.0, 97.0, 1.0, 20.0)},
                             camera);
    const PathTracer tracer(lens, GhostPath{}, 550.0);
    Ray ray;
    ray.wavelength_nm = 550.0;
    ray.position = {9.9, 0.0, -10.0};  // next to a corner (rotation 0 puts one on +x)
    EXPECT_TRUE(tracer.trace(ray));
    ray.position = {0.0, 9.5, -10.0};  // mid-edge distance is 10 cos(30 deg) = 8.66
    EXPECT_FALSE(tracer.trace(ray));
}

TEST(PathTracer, TotalInternalReflectionDropsTheRay) {
    // Light enters a flat glass block and must leave through a steep spherical face: rays far
    // off axis meet it beyond the critical angle.
    const Lens lens = lensOf(
        {stop(1.0, 20.0), refracting(0.0, 10.0, 1.8, 20.0), refracting(-20.5, 50.0, 1.0, 20.0)});
    const PathTracer tracer(lens, GhostPath{}, 550.0);
    Ray ray;
    ray.wavelength_nm = 550.0;
    ray.position = {0.0, 1.0, -5.0};
    EXPECT_TRUE(tracer.trace(ray));
    ray.position = {0.0, 15.0, -5.0};  // sin(incidence) = 15 / 20.5 > 1 / 1.8
    EXPECT_FALSE(tracer.trace(ray));
}

TEST(PathTracer, OneSurfaceLensImagesAndHasNoGhost) {
    const Lens lens = lensOf({stop(0.0, 5.0), refracting(50.0, 150.0, 1.5, 10.0)});
    const auto p = paraxialProperties(lens, kLambdaD_nm);
    ASSERT_TRUE(p);
    // A single refracting surface into glass: the rear focal length, which efl_mm reports, is
    // n R / (n - 1) = 150 mm, measured in the glass.
    EXPECT_NEAR(p->efl_mm, 150.0, 1e-9);
    const PathTracer tracer(lens, GhostPath{}, kLambdaD_nm);
    Ray ray;
    ray.wavelength_nm = kLambdaD_nm;
    ray.position = {0.0, 0.001, -1.0};
    const auto traced = tracer.trace(ray);
    ASSERT_TRUE(traced);
    EXPECT_NEAR(traced->ray.position.y(), 0.0, 1e-5);  // paraxial focus at n R/(n-1) = 150 mm
}

TEST(PathTracer, NearlyFlatSurfaceBendsRaysAsFirstOrderOpticsPredicts) {
    // A 1e7 mm face is a lens of focal length 1.7e7 mm: it moves the image by ~1e-5 mm. That
    // difference survives only if no digit is lost in the intersection.
    const Lens flat = lensOf(
        {stop(2.0, 10.0), refracting(0.0, 5.0, 1.6, 20.0), refracting(-60.0, 90.0, 1.0, 20.0)});
    const Lens near_flat = lensOf(
        {stop(2.0, 10.0), refracting(1e7, 5.0, 1.6, 20.0), refracting(-60.0, 90.0, 1.0, 20.0)});
    const PathTracer a(flat, GhostPath{}, 550.0), b(near_flat, GhostPath{}, 550.0);
    const double a_parax = paraxialProperties(flat, 550.0)->system_matrix(0, 0);
    const double b_parax = paraxialProperties(near_flat, 550.0)->system_matrix(0, 0);
    Ray ray;
    ray.wavelength_nm = 550.0;
    for (double y : {0.3, 1.0, 3.0}) {
        ray.position = {0.0, y, -5.0};
        const auto ta = a.trace(ray), tb = b.trace(ray);
        ASSERT_TRUE(ta && tb);
        const double exact = tb->ray.position.y() - ta->ray.position.y();
        const double first_order = y * (b_parax - a_parax);
        EXPECT_NEAR(exact, first_order, 0.02 * std::abs(first_order)) << y;
    }
}

TEST(TraceGhost, NeverGainsEnergyOverRandomRays) {
    const Lens lens = singlet(550.0);
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> unit(-1.0, 1.0);
    for (const GhostPath path : {GhostPath{}, GhostPath{1, 2}}) {
        for (double lambda : {450.0, 550.0, 650.0}) {
            const PathTracer tracer(lens, path, lambda);
            int traced_count = 0;
            for (int i = 0; i < 20000; ++i) {
                Ray ray;
                ray.wavelength_nm = lambda;
                ray.position = {12.0 * unit(rng), 12.0 * unit(rng), -10.0};
                ray.direction = Eigen::Vector3d(0.3 * unit(rng), 0.3 * unit(rng), 1.0).normalized();
                const auto traced = tracer.trace(ray);
                if (!traced) continue;
                ++traced_count;
                ASSERT_GE(traced->ray.throughput, 0.0);
                ASSERT_LE(traced->ray.throughput, 1.0);
                ASSERT_TRUE(std::isfinite(traced->ray.position.x()));
                ASSERT_NEAR(traced->ray.direction.norm(), 1.0, 1e-12);
            }
            EXPECT_GT(traced_count, 1000);
        }
    }
}

TEST(TraceGhost, GhostCarriesTheProductOfItsTwoReflectances) {
    const Lens lens = singlet();  // bare surfaces
    const PathTracer ghost(lens, GhostPath{1, 2}, kLambdaD_nm);
    Ray ray;
    ray.wavelength_nm = kLambdaD_nm;
    ray.position = {0.0, 0.0, -10.0};
    const auto traced = ghost.trace(ray);
    ASSERT_TRUE(traced);
    // On axis: enter the front face (T), reflect at the back face from inside (R), reflect at the
    // front face from inside (R), leave through the back face (T).
    const double r = std::pow((1.5168 - 1.0) / (1.5168 + 1.0), 2);
    EXPECT_NEAR(traced->ray.throughput, (1 - r) * r * r * (1 - r), 1e-12);
}

TEST(LightDirection, OnAxisIsForwardForAnyRoll) {
    for (double phi : {0.0, 1.0, -3.0, 1e6}) {
        const Eigen::Vector3d d = lightDirection(0.0, phi);
        EXPECT_EQ(d.z(), 1.0);
        EXPECT_EQ(d.x(), 0.0);
        EXPECT_EQ(d.y(), 0.0);
    }
}

TEST(AimAtStop, FindsTheRayThroughAnyStopPoint) {
    const Lens lens = singlet();
    const EntryPlane plane = defaultEntryPlane(lens);
    const PathTracer tracer(lens, GhostPath{}, 550.0,
                            TraceOptions{.clip_apertures = false, .clip_stop = false});
    for (double theta_deg : {0.0, 5.0, 20.0}) {
        const Eigen::Vector3d d = lightDirection(degToRad(theta_deg), 0.3);
        for (const Eigen::Vector2d& target : {Eigen::Vector2d(0, 0), Eigen::Vector2d(3, -7)}) {
            const auto guess =
                paraxialEntry(pathMatrices(lens, GhostPath{}, 550.0).to_stop, plane, d, target);
            ASSERT_TRUE(guess);
            const auto entry = aimAtStop(tracer, plane, d, target, *guess);
            ASSERT_TRUE(entry) << theta_deg;
            const Ray ray = rayThroughEntry(plane, *entry, d, 550.0);
            const auto at_stop = tracer.traceToStop(ray.position, ray.direction);
            ASSERT_TRUE(at_stop);
            EXPECT_NEAR((*at_stop - target).norm(), 0.0, 1e-8);
        }
    }
}

}  // namespace
}  // namespace flarelab::optics
