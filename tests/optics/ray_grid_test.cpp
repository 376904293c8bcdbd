#include "optics/ray_grid.h"

#include <gtest/gtest.h>

#include <cmath>

#include "common/units.h"
#include "optics/ghosts.h"
#include "tests/optics/lens_builders.h"
#include "tests/test_paths.h"

namespace flarelab::optics {
namespace {

Lens heliar() {
    return *Lens::make(*loadPrescription(flarelab::testing::lensPath("heliar-tronnier.csv")),
                       CameraDescription{});
}

void expectAllFinite(const RayGrid& grid) {
    ASSERT_EQ(grid.samples.size(), static_cast<size_t>(grid.n) * grid.n);
    for (const GridSample& s : grid.samples) {
        ASSERT_TRUE(std::isfinite(s.sensor_x_mm) && std::isfinite(s.sensor_y_mm));
        ASSERT_TRUE(std::isfinite(s.stop_u) && std::isfinite(s.stop_v));
        ASSERT_TRUE(std::isfinite(s.throughput));
        ASSERT_GE(s.throughput, 0.0f);
        ASSERT_LE(s.throughput, 1.0f);
        if (!s.valid) {
            ASSERT_EQ(s.throughput, 0.0f);
        }
        if (!s.has_position) {
            ASSERT_FALSE(s.valid);
            ASSERT_EQ(s.sensor_x_mm, 0.0f);
        }
    }
    ASSERT_TRUE(std::isfinite(grid.entry_half_width_mm));
    ASSERT_GT(grid.entry_half_width_mm, 0.0);
}

TEST(TraceRayGrid, OneByOneGridIsTheRayThroughTheBeamCentre) {
    const Lens lens = heliar();
    const auto grid = traceRayGrid(lens, GhostPath{}, degToRad(3.0), 0.0, 550.0, 1);
    ASSERT_TRUE(grid);
    expectAllFinite(*grid);
    ASSERT_EQ(grid->samples.size(), 1u);
    EXPECT_TRUE(grid->samples[0].valid);
    EXPECT_LT(std::hypot(grid->samples[0].stop_u, grid->samples[0].stop_v), 0.1);
    EXPECT_EQ(grid->entryPoint(0, 0), grid->entry_centre_mm);
}

TEST(TraceRayGrid, OnAxisImagingGridFocusesOnTheAxisAndCoversTheWholeStop) {
    const Lens lens = heliar();
    const auto grid = traceRayGrid(lens, GhostPath{}, 0.0, 0.0, 550.0, 65);
    ASSERT_TRUE(grid);
    expectAllFinite(*grid);
    double max_r = 0.0;
    int inside = 0, outside = 0;
    for (const GridSample& s : grid->samples) {
        if (!s.valid) continue;
        if (lens.aperture().contains(s.stop_u, s.stop_v)) {
            ++inside;
            max_r = std::max<double>(max_r, std::hypot(s.sensor_x_mm, s.sensor_y_mm));
        } else {
            ++outside;
        }
    }
    EXPECT_GT(inside, 2000);
    EXPECT_GT(outside, 0);  // the margin reaches past the stop's edge
    // The table's image plane is 1.5 mm behind the paraxial focus: blur radius ~ 1.5 / (2 N).
    EXPECT_LT(max_r, 0.1);
    const GridSample& centre = grid->at(32, 32);
    EXPECT_NEAR(centre.stop_u, 0.0, 1e-6);
    EXPECT_NEAR(centre.stop_v, 0.0, 1e-6);
    EXPECT_NEAR(centre.sensor_x_mm, 0.0, 1e-6);
}

TEST(TraceRayGrid, GhostFootprintCentresOnTheExactGhostCentre) {
    const Lens lens = heliar();
    for (const GhostPath path : {GhostPath{2, 3}, GhostPath{6, 8}}) {
        const auto grid = traceRayGrid(lens, path, degToRad(5.0), degToRad(30.0), 550.0, 128);
        ASSERT_TRUE(grid);
        expectAllFinite(*grid);
        const auto exact = exactGhost(lens, path, {5.0, 30.0}, 550.0, 16);
        ASSERT_TRUE(exact);
        // The footprint of the rays inside the stop spans the exact rim's extent.
        double min_x = 1e9, max_x = -1e9;
        for (const GridSample& s : grid->samples) {
            if (!s.valid || !lens.aperture().contains(s.stop_u, s.stop_v)) continue;
            min_x = std::min<double>(min_x, s.sensor_x_mm);
            max_x = std::max<double>(max_x, s.sensor_x_mm);
        }
        EXPECT_NEAR(0.5 * (min_x + max_x), 0.5 * (exact->extent_mm[0] + exact->extent_mm[2]),
                    0.05 * exact->radius_mm)
            << pathLabel(path);
    }
}

TEST(TraceRayGrid, RaysCutByAClearApertureKeepTheirPlaceButCarryNoLight) {
    // With the stop wide open (the table's f/4) and the light far off axis the front lens cuts
    // part of the beam: those corners must still have a position, continuous with their valid
    // neighbours, so a renderer can fade the ghost out.
    const Lens lens = heliar().withStopSemiAperture(heliar().tableStopSemiAperture_mm());
    const auto grid = traceRayGrid(lens, GhostPath{}, degToRad(25.0), 0.0, 550.0, 64);
    ASSERT_TRUE(grid);
    expectAllFinite(*grid);
    int cut = 0, valid = 0;
    for (const GridSample& s : grid->samples) {
        cut += s.has_position && !s.valid;
        valid += s.valid;
    }
    EXPECT_GT(cut, 0);
    EXPECT_GT(valid, 0);
    // Neighbours across the cut stay close on the sensor: the geometry is continuous.
    double worst_jump = 0.0;
    int pairs = 0;
    for (int iy = 0; iy < grid->n; ++iy) {
        for (int ix = 0; ix + 1 < grid->n; ++ix) {
            const GridSample& a = grid->at(ix, iy);
            const GridSample& b = grid->at(ix + 1, iy);
            if (a.valid == b.valid || !a.has_position || !b.has_position) continue;
            ++pairs;
            worst_jump = std::max<double>(worst_jump, std::hypot(a.sensor_x_mm - b.sensor_x_mm,
                                                                 a.sensor_y_mm - b.sensor_y_mm));
        }
    }
    EXPECT_GT(pairs, 0);
    EXPECT_LT(worst_jump, 1.0);
}

TEST(TraceRayGrid, LargeGridStaysFinite) {
    const Lens lens = heliar();
    const auto grid = traceRayGrid(lens, GhostPath{3, 4}, degToRad(10.0), 0.0, 450.0, 1024);
    ASSERT_TRUE(grid);
    expectAllFinite(*grid);
    EXPECT_GT(grid->validCount(), 100000);
}

TEST(TraceRayGrid, LightPastTheFieldLimitGivesAnEmptyGridNotAnError) {
    const Lens lens = heliar();
    for (double theta_deg : {60.0, 80.0, 89.99}) {
        const auto grid = traceRayGrid(lens, GhostPath{3, 4}, degToRad(theta_deg), 0.0, 550.0, 16);
        ASSERT_TRUE(grid) << theta_deg;
        expectAllFinite(*grid);
        const auto imaging = traceRayGrid(lens, GhostPath{}, degToRad(theta_deg), 0.0, 550.0, 16);
        ASSERT_TRUE(imaging);
        expectAllFinite(*imaging);
    }
    const auto far = traceRayGrid(lens, GhostPath{}, degToRad(89.99), 0.0, 550.0, 16);
    EXPECT_EQ(far->validCount(), 0);
}

TEST(TraceRayGrid, RejectsArgumentsOutsideTheirRange) {
    const Lens lens = heliar();
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, degToRad(90.0), 0.0, 550.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, degToRad(135.0), 0.0, 550.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, -0.1, 0.0, 550.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, std::nan(""), 0.0, 550.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, 0.1, std::nan(""), 550.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, 0.1, 0.0, 550.0, 0));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, 0.1, 0.0, 550.0, 8193));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{}, 0.1, 0.0, 0.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{0, 5}, 0.1, 0.0, 550.0, 8));  // 5 is the stop
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{4, 2}, 0.1, 0.0, 550.0, 8));
    EXPECT_FALSE(traceRayGrid(lens, GhostPath{0, 40}, 0.1, 0.0, 550.0, 8));
    const auto error = traceRayGrid(lens, GhostPath{}, degToRad(95.0), 0.0, 550.0, 8);
    EXPECT_NE(error.error().message.find("theta"), std::string::npos);
}

TEST(TraceRayGrid, EveryGhostOfEveryShippedLensGivesFiniteGridsAtAllAngles) {
    for (const char* file : flarelab::testing::kShippedLenses) {
        SCOPED_TRACE(file);
        const Lens lens =
            *Lens::make(*loadPrescription(flarelab::testing::lensPath(file)), CameraDescription{});
        const auto ghosts = enumerateGhosts(lens);
        ASSERT_TRUE(ghosts);
        for (size_t k = 0; k < ghosts->ghosts.size(); k += 5) {
            for (double theta_deg : {0.0, 2.0, 25.0, 70.0}) {
                const auto grid = traceRayGrid(lens, ghosts->ghosts[k], degToRad(theta_deg),
                                               degToRad(-40.0), 650.0, 6);
                ASSERT_TRUE(grid);
                expectAllFinite(*grid);
            }
        }
    }
}

}  // namespace
}  // namespace flarelab::optics
