#include "optics/row_tracer.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>

#include "common/units.h"
#include "optics/fresnel.h"
#include "optics/ghosts.h"
#include "optics/ray_grid.h"
#include "optics/tracer.h"
#include "tests/optics/lens_builders.h"
#include "tests/test_paths.h"

namespace flarelab::optics {
namespace {

using flarelab::testing::kShippedLenses;
using flarelab::testing::lensPath;

using testing::shippedLens;

// The half-diagonal field angle of the lens on its sensor.
double fieldLimit_rad(const Lens& lens) {
    const CameraDescription& c = lens.camera();
    return std::atan(0.5 * std::hypot(c.sensor_width_mm, c.sensor_height_mm) / c.focal_length_mm);
}

// ---- the coated reflectance polynomial ----

TEST(FresnelPolynomial, MeetsItsToleranceAgainstTheThinFilmFormulaWhereverItIsUsed) {
    struct Case {
        double n1, n2;
    };
    // Into glass, out of glass (total internal reflection below the critical angle), between two
    // glasses, and out of a glass denser than the layer (frustrated reflection in the layer).
    const Case cases[] = {{1.0, 1.5168}, {1.5168, 1.0}, {1.62, 1.5168}, {1.9, 1.0}};
    std::mt19937_64 rng(3);
    for (const Case& c : cases) {
        for (const double wavelength : {kLambdaBlue_nm, kLambdaGreen_nm, kLambdaRed_nm}) {
            const QuarterWaveCoating coat = designQuarterWaveCoating(c.n1, c.n2, 550.0);
            const FresnelPolynomial p =
                fitCoatedReflectance(c.n1, coat.index, coat.thickness_nm, c.n2, wavelength, 1e-5);
            SCOPED_TRACE(::testing::Message() << c.n1 << " -> " << c.n2 << " at " << wavelength);
            ASSERT_LT(p.lo, 1.0) << "no usable fit";
            // Within 1e-5 of the smallest R on the range (or 1e-13, for a coating that cancels
            // the reflection entirely), checked again at cosines the fit never saw.
            double smallest = 1.0;
            for (int i = 0; i <= 1000; ++i)
                smallest =
                    std::min(smallest, fresnelCoated(c.n1, coat.index, coat.thickness_nm, c.n2,
                                                     p.lo + (1.0 - p.lo) * i / 1000.0, wavelength)
                                           .reflectance);
            const double bound = std::max(1e-5 * smallest, 1e-13);
            EXPECT_LE(p.max_abs_error, bound);
            std::uniform_real_distribution<double> cosine(p.lo, 1.0);
            for (int i = 0; i < 2000; ++i) {
                const double ci = cosine(rng);
                const double exact =
                    fresnelCoated(c.n1, coat.index, coat.thickness_nm, c.n2, ci, wavelength)
                        .reflectance;
                ASSERT_NEAR(p(ci), exact, 2.0 * bound) << "cos " << ci;
            }
            // Where light meets a lens (incidence up to 60 degrees) the polynomial is used.
            if (c.n1 < c.n2) {
                EXPECT_LE(p.lo, 0.5);
            }
        }
    }
}

// ---- agreement with PathTracer ----

struct Worst {
    double position_px = 0.0, stop = 0.0, stop_shift_px = 0.0, throughput = 0.0, power = 0.0,
           differs = 0.0;
};

// Every shipped lens, its imaging path and a spread of its ghosts, on axis, at half the field and
// at the field's corner, at three wavelengths.
Worst worstOverShippedLenses(GridTracer tracer, int grid, int ghosts_per_lens) {
    Worst worst;
    RayGridOptions options;
    options.tracer = tracer;
    for (const char* file : kShippedLenses) {
        const Lens lens = shippedLens(file);
        const double px_per_mm = 1920.0 / lens.camera().sensor_width_mm;
        std::vector<GhostPath> paths{GhostPath{}};
        const auto ghosts = enumerateGhosts(lens);
        EXPECT_TRUE(ghosts) << file;
        if (!ghosts) continue;
        const size_t count = ghosts->ghosts.size();
        for (int i = 0; i < ghosts_per_lens && count > 0; ++i)
            paths.push_back(ghosts->ghosts[(i * 7919) % count]);
        const double field = fieldLimit_rad(lens);
        for (const GhostPath& path : paths) {
            for (const double theta : {0.0, 0.5 * field, field}) {
                for (const double wavelength : {kLambdaBlue_nm, kLambdaGreen_nm, kLambdaRed_nm}) {
                    const auto a =
                        compareWithExactGrid(lens, path, theta, 0.6, wavelength, grid, options);
                    EXPECT_TRUE(a) << file << " " << pathLabel(path);
                    if (!a) continue;
                    worst.position_px =
                        std::max(worst.position_px, a->max_position_error_mm * px_per_mm);
                    worst.stop = std::max(worst.stop, a->max_stop_error);
                    worst.stop_shift_px =
                        std::max(worst.stop_shift_px, a->max_stop_shift_mm * px_per_mm);
                    worst.throughput = std::max(worst.throughput, a->max_throughput_rel_error);
                    worst.power = std::max(worst.power, a->power_rel_error);
                    const double all = static_cast<double>(grid) * grid;
                    worst.differs = std::max(worst.differs, a->validity_differs / all);
                }
            }
        }
    }
    std::printf(
        "row tracer worst: %.3g px, stop %.3g (%.3g px), throughput %.3g, power %.3g, status "
        "%.3g\n",
        worst.position_px, worst.stop, worst.stop_shift_px, worst.throughput, worst.power,
        worst.differs);
    return worst;
}

TEST(RowTracer, DoubleLanesMatchThePathTracerOnEveryShippedLens) {
    const Worst w = worstOverShippedLenses(GridTracer::RowDouble, 16, 5);
    EXPECT_LT(w.position_px, 1e-3);  // the grid keeps positions in float
    EXPECT_LT(w.stop, 1e-5);
    // Only the Fresnel polynomial differs, by 1e-5 of R.
    EXPECT_LT(w.throughput, 1e-4);
    EXPECT_LT(w.power, 1e-4);
    EXPECT_LT(w.differs, 0.002);
}

TEST(RowTracer, TheGridsChoiceOfPrecisionStaysWithinItsToleranceOnEveryShippedLens) {
    const Worst w = worstOverShippedLenses(GridTracer::Auto, 40, 5);  // probed above 32 x 32
    // At 1920 pixels across the sensor, where float_tolerance_mm is 0.005 px: the probe stands
    // for the grid.
    EXPECT_LT(w.position_px, 0.02);
    EXPECT_LT(w.stop_shift_px, 0.02);
    EXPECT_LT(w.throughput, 1e-3);
    EXPECT_LT(w.power, 1e-3);
    EXPECT_LT(w.differs, 0.005);
}

TEST(RowTracer, Avx2AndSse2BuildsGiveTheSameBits) {
    const Lens lens = shippedLens("canon-tele-zoom-200.csv");
    const auto ghosts = enumerateGhosts(lens);
    ASSERT_TRUE(ghosts);
    ASSERT_FALSE(ghosts->ghosts.empty());
    for (const auto precision : {RowTracer::Precision::Float, RowTracer::Precision::Double}) {
        RowTracer::Options wide, narrow;
        wide.precision = narrow.precision = precision;
        narrow.allow_avx2 = false;
        const GhostPath path = ghosts->ghosts[ghosts->ghosts.size() / 3];
        const RowTracer a(lens, path, kLambdaGreen_nm, wide),
            b(lens, path, kLambdaGreen_nm, narrow);
        EXPECT_FALSE(b.usesAvx2());
        std::vector<double> xs, ys;
        for (int i = 0; i < 101; ++i) {  // not a multiple of any vector width
            xs.push_back(-12.0 + 0.24 * i);
            ys.push_back(3.0 - 0.05 * i);
        }
        const Eigen::Vector3d d = lightDirection(degToRad(7.0), 0.3);
        TracedRow ra, rb;
        a.trace(xs, ys, -5.0, d, ra);
        b.trace(xs, ys, -5.0, d, rb);
        EXPECT_EQ(ra.x_mm, rb.x_mm);
        EXPECT_EQ(ra.y_mm, rb.y_mm);
        EXPECT_EQ(ra.throughput, rb.throughput);
        EXPECT_EQ(ra.status, rb.status);
    }
}

// The probe narrows each coated crossing's fitted range to the cosines it met: lower degrees,
// the same throughput for rays inside the probe's range and for rays beyond it (the exact
// formula below the range), on lenses with many coated surfaces, on axis, at half the field
// and at its corner.
TEST(RowTracer, CoatingsNarrowedToTheProbesCosinesKeepTheThroughput) {
    for (const char* file : {"canon-tele-zoom-200.csv", "heliar-tronnier.csv"}) {
        const Lens lens = shippedLens(file);
        const auto ghosts = enumerateGhosts(lens);
        ASSERT_TRUE(ghosts);
        const double field_deg = radToDeg(fieldLimit_rad(lens));
        for (const double theta_deg : {0.0, 0.5 * field_deg, field_deg}) {
            int compared = 0;
            for (const GhostPath& path :
                 {GhostPath{}, ghosts->ghosts.front(), ghosts->ghosts.back()}) {
                const Eigen::Vector3d d = lightDirection(degToRad(theta_deg), 0.3);
                RowTracer::Options options;
                options.precision = RowTracer::Precision::Double;
                const RowTracer wide(lens, path, kLambdaGreen_nm, options);
                RowTracer narrow(lens, path, kLambdaGreen_nm, options);
                // The probe: the middle third of the entry's width; the rays: all of it and beyond.
                const double r = lens.surfaces().front().semi_aperture_mm;
                std::vector<double> px, py, xs, ys;
                for (int i = 0; i < 9; ++i)
                    for (int j = 0; j < 9; ++j) {
                        px.push_back(r * (-0.3 + 0.075 * i));
                        py.push_back(r * (-0.3 + 0.075 * j));
                    }
                for (int i = 0; i < 41; ++i)
                    for (int j = 0; j < 41; ++j) {
                        xs.push_back(r * (-1.2 + 0.06 * i));
                        ys.push_back(r * (-1.2 + 0.06 * j));
                    }
                const double z = lens.surfaces().front().z_mm - 5.0;
                narrow.choosePrecision(px, py, z, d, 1e-4);
                narrow.setPrecision(RowTracer::Precision::Double);
                size_t degrees_wide = 0, degrees_narrow = 0;
                for (size_t k = 0; k < wide.coatings().size(); ++k) {
                    degrees_wide += wide.coatings()[k].coefficients.size();
                    degrees_narrow += narrow.coatings()[k].coefficients.size();
                    EXPECT_GE(narrow.coatings()[k].lo, wide.coatings()[k].lo);
                }
                EXPECT_LT(degrees_narrow, degrees_wide) << file << " at " << theta_deg;
                TracedRow a, b;
                wide.trace(xs, ys, z, d, a);
                narrow.trace(xs, ys, z, d, b);
                for (size_t i = 0; i < xs.size(); ++i) {
                    ASSERT_EQ(a.status[i], b.status[i]) << i;
                    if (a.status[i] == 0 || !(a.throughput[i] > 0.0)) continue;
                    EXPECT_EQ(a.x_mm[i], b.x_mm[i]);
                    // Each series is within 1e-5 of the smallest reflectance on its range.
                    EXPECT_NEAR(b.throughput[i] / a.throughput[i], 1.0, 1e-4)
                        << file << " at " << theta_deg << ", ray " << i;
                    ++compared;
                }
            }
            EXPECT_GT(compared, 300) << file << " at " << theta_deg;
        }
    }
}

// ---- extremes ----

TEST(RowTracer, OnAxisLightGivesARotationallySymmetricRow) {
    const Lens lens = shippedLens("heliar-tronnier.csv");
    const RowTracer tracer(lens, GhostPath{}, kLambdaGreen_nm, {});
    const std::vector<double> xs{-5.0, -2.5, 0.0, 2.5, 5.0}, zeros(5, 0.0);
    TracedRow out;
    tracer.trace(xs, zeros, -10.0, Eigen::Vector3d::UnitZ(), out);
    ASSERT_EQ(out.status.size(), 5u);
    for (int i = 0; i < 5; ++i) {
        EXPECT_EQ(out.status[i], 1) << i;
        EXPECT_NEAR(out.x_mm[i], -out.x_mm[4 - i], 1e-5);
        EXPECT_EQ(out.y_mm[i], 0.0);
    }
    EXPECT_EQ(out.x_mm[2], 0.0);
}

TEST(RowTracer, GrazingAndMissingRaysEndWithoutGeometryNeverNaN) {
    const Lens lens = shippedLens("nikon-28-75mm.csv");
    const auto ghosts = enumerateGhosts(lens);
    ASSERT_TRUE(ghosts);
    std::vector<double> xs, ys;
    for (int i = 0; i < 64; ++i) {
        xs.push_back(-40.0 + 1.25 * i);  // well past the front element's rim at both ends
        ys.push_back(0.0);
    }
    for (const double theta_deg : {0.0, 45.0, 80.0, 89.9}) {
        const Eigen::Vector3d d = lightDirection(degToRad(theta_deg), 0.0);
        for (const GhostPath& path : {GhostPath{}, ghosts->ghosts.front(), ghosts->ghosts.back()}) {
            const RowTracer tracer(lens, path, kLambdaGreen_nm, {});
            TracedRow out;
            tracer.trace(xs, ys, -50.0, d, out);
            for (size_t i = 0; i < xs.size(); ++i) {
                if (out.status[i] == 0) continue;
                EXPECT_TRUE(std::isfinite(out.x_mm[i]) && std::isfinite(out.throughput[i]));
                EXPECT_GE(out.throughput[i], 0.0);
                EXPECT_LE(out.throughput[i], 1.0 + 1e-6);
                EXPECT_GE(out.aperture_ratio[i], 0.0);
                EXPECT_EQ(out.status[i] == 2, out.aperture_ratio[i] > 1.0) << i;
            }
        }
    }
}

TEST(RowTracer, FlatAndNearlyFlatSurfacesAgreeWithThePathTracer) {
    using namespace flarelab::optics::testing;
    for (const double radius : {0.0, 1e12, -1e9, 1e6}) {
        const Lens lens =
            lensOf({stop(5.0, 10.0), refracting(radius, 6.0, 1.5168, 20.0, 64.17, 550.0),
                    refracting(-100.0, 97.0, 1.0, 20.0, 0.0, 550.0)});
        for (const GhostPath& path : {GhostPath{}, GhostPath{1, 2}}) {
            const auto a = compareWithExactGrid(lens, path, degToRad(5.0), 0.0, kLambdaGreen_nm, 16,
                                                RayGridOptions{});
            ASSERT_TRUE(a) << a.error().message;
            EXPECT_GT(a->samples, 0);
            EXPECT_LT(a->max_position_error_mm, 1e-4) << "radius " << radius;
            EXPECT_LT(a->power_rel_error, 1e-3) << "radius " << radius;
        }
    }
}

TEST(RowTracer, AnEmptyRowIsFine) {
    const Lens lens = shippedLens("heliar-tronnier.csv");
    const RowTracer tracer(lens, GhostPath{}, kLambdaGreen_nm, {});
    TracedRow out;
    tracer.trace({}, {}, -10.0, Eigen::Vector3d::UnitZ(), out);
    EXPECT_TRUE(out.status.empty());
}

}  // namespace
}  // namespace flarelab::optics
