// Pixel-area integration in the simulator's rasterizer (ghost_quads.h): against a 16 x 16
// supersampled truth drawn by the same code, against the model renderer's area means on a disc
// and a polygon, and at vignetting edges.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <string>
#include <utility>
#include <vector>

#include "common/units.h"
#include "optics/ghosts.h"
#include "optics/paraxial.h"
#include "optics/prescription.h"
#include "optics/ray_grid.h"
#include "render/ghost_quads.h"
#include "render/metrics.h"
#include "render/model_ghost.h"
#include "render/scene.h"
#include "render/tiles.h"
#include "tests/test_paths.h"

namespace flarelab::render {
namespace {

optics::Lens loadLens(const std::string& file, int blades = 0) {
    optics::CameraDescription camera;
    camera.aperture_blades = blades;
    return *optics::Lens::make(*optics::loadPrescription(testing::lensPath(file)), camera);
}

// The light's angle whose image lands on the sensor's corner.
double fieldLimitDeg(const optics::Lens& lens) {
    const auto paraxial = optics::paraxialProperties(lens, kLambdaGreen_nm);
    EXPECT_TRUE(paraxial.has_value());
    const double half_diagonal =
        0.5 * std::hypot(lens.camera().sensor_width_mm, lens.camera().sensor_height_mm);
    return paraxial ? radToDeg(std::atan(half_diagonal / paraxial->efl_mm)) : 0.0;
}

// sqrt(sum (a - b)^2 / sum b^2) over the green channel.
double relativeL2(const ImageRGB& a, const ImageRGB& b) {
    double diff = 0.0, norm = 0.0;
    for (int64_t y = 0; y < a.height; ++y)
        for (int64_t x = 0; x < a.width; ++x) {
            const double d = static_cast<double>(a.at(x, y)[1]) - b.at(x, y)[1];
            diff += d * d;
            norm += static_cast<double>(b.at(x, y)[1]) * b.at(x, y)[1];
        }
    return std::sqrt(diff / norm);
}

// A ghost drawn by hand: an n x n grid of square cells of `step` pixels centred on (cx, cy),
// throughput 1 everywhere, stop coordinates (p - centre) / radius, so the stop's image is the
// aperture shape scaled to `radius` pixels; aperture ratios from `ratio(x, y)`. Each cell stands
// for its own area, so a lit pixel gets exactly 1.
template <typename Ratio>
GhostQuads handGhost(double cx, double cy, double radius, double step, int n, Ratio ratio) {
    GhostQuads ghost;
    ghost.cell_area_mm2 = step * step;
    const double x0 = cx - 0.5 * step * n, y0 = cy - 0.5 * step * n;
    const auto corner = [&](int i, int j) {
        QuadCorner c;
        c.position_px = {x0 + step * i, y0 + step * j};
        c.throughput = 1.0f;
        c.stop_u = static_cast<float>((c.position_px.x() - cx) / radius);
        c.stop_v = static_cast<float>((c.position_px.y() - cy) / radius);
        c.aperture_ratio = static_cast<float>(ratio(c.position_px.x(), c.position_px.y()));
        return c;
    };
    for (int j = 0; j < n; ++j)
        for (int i = 0; i < n; ++i)
            ghost.quads.push_back(
                Quad{{corner(i, j), corner(i + 1, j), corner(i + 1, j + 1), corner(i, j + 1)}});
    return ghost;
}

ImageRGB draw(const GhostQuads& ghost,
              int64_t w,
              int64_t h,
              const optics::ApertureShape& aperture,
              int supersample) {
    ImageRGB image(w, h);
    RasterOptions options;
    options.supersample = supersample;
    rasterizeReference(image, ghost, 1, 1.0f, aperture, options);
    return image;
}

// The model renderer's drawing of a closed loop (pixels) filled with 1, its edge a step.
ImageRGB drawModel(const std::vector<Eigen::Vector2d>& control_points_px, int64_t w, int64_t h) {
    SensorToImage m;
    m.px_per_mm_x = m.px_per_mm_y = 10.0;
    m.centre_x_px = 0.5 * static_cast<double>(w);
    m.centre_y_px = 0.5 * static_cast<double>(h);
    BezierLoop loop;
    for (const Eigen::Vector2d& p : control_points_px)
        loop.control_points_mm.push_back(
            {(p.x() - m.centre_x_px) / m.px_per_mm_x, (p.y() - m.centre_y_px) / m.px_per_mm_y});
    GhostShading shading;
    shading.border_rgb = shading.inner_rgb = {1.0, 1.0, 1.0};
    shading.inner_falloff_mm = shading.outer_falloff_mm = 1e-6;  // a step: 1e-5 pixel
    GhostDrawOptions draw;  // the default (fast) evaluation, with a finer Newton distance
    draw.distance = FastDistanceOptions{8, 8};
    const auto ghost = prepareGhostPrimitive(loop, shading, m, w, h, draw);
    EXPECT_TRUE(ghost.has_value());
    ImageRGB image(w, h);
    if (ghost) {
        EXPECT_TRUE(renderTiled(image, {}, {&*ghost, 1}, optics::ApertureShape{}).has_value());
    }
    return image;
}

// A uniform disc of radius R drawn by the simulator and by the model renderer: both give each
// pixel its covered area, so they agree far below the sqrt(1 / (6 R)) that sampling the pixel
// centre costs (9% at 20 px).
TEST(AreaIntegration, AUniformDiscMatchesTheModelRenderer) {
    const int64_t w = 160, h = 120;
    const double cx = 80.3, cy = 59.6;
    const auto clear = [](double, double) { return 0.0; };
    for (const double radius : {7.0, 20.0, 45.0}) {
        SCOPED_TRACE("radius " + std::to_string(radius));
        // Cells of 3.7 px: the disc's edge crosses them anywhere.
        const int n = static_cast<int>(std::ceil(2.4 * radius / 3.7));
        const GhostQuads ghost = handGhost(cx, cy, radius, 3.7, n, clear);
        std::vector<Eigen::Vector2d> points;
        for (int k = 0; k < 4; ++k) {
            // The four-arc circle: each quarter from angle k pi/2 with handles kCircleHandle R.
            const double a = k * 0.5 * std::numbers::pi, b = a + 0.5 * std::numbers::pi;
            const Eigen::Vector2d p(std::cos(a), std::sin(a)), q(std::cos(b), std::sin(b));
            const Eigen::Vector2d tp(-p.y(), p.x()), tq(-q.y(), q.x());
            const Eigen::Vector2d c(cx, cy);
            points.push_back(c + radius * p);
            points.push_back(c + radius * (p + kCircleHandle * tp));
            points.push_back(c + radius * (q - kCircleHandle * tq));
        }
        const ImageRGB model = drawModel(points, w, h);
        const ImageRGB area = draw(ghost, w, h, optics::ApertureShape{}, 0);
        const ImageRGB centre = draw(ghost, w, h, optics::ApertureShape{}, 1);
        EXPECT_LT(relativeL2(area, model), 0.005);
        // The ruler this replaces: centre sampling misses by more than ten times as much.
        EXPECT_GT(relativeL2(centre, model), 0.05);
        // Energy: the disc's area.
        EXPECT_NEAR(imageSum(area), std::numbers::pi * radius * radius, 2e-3 * imageSum(area));
    }
}

// A hexagonal stop's image, drawn by both: straight edges and corners.
TEST(AreaIntegration, APolygonMatchesTheModelRenderer) {
    const int64_t w = 128, h = 128;
    const double cx = 63.2, cy = 64.7, radius = 30.0;
    optics::ApertureShape hexagon;
    hexagon.blades = 6;
    hexagon.rotation_rad = 0.3;
    const GhostQuads ghost = handGhost(cx, cy, radius, 4.3, 16, [](double, double) { return 0.0; });
    std::vector<Eigen::Vector2d> points;
    for (int k = 0; k < 6; ++k) {
        const double a = hexagon.rotation_rad + k * std::numbers::pi / 3.0;
        const double b = a + std::numbers::pi / 3.0;
        const Eigen::Vector2d p(cx + radius * std::cos(a), cy + radius * std::sin(a));
        const Eigen::Vector2d q(cx + radius * std::cos(b), cy + radius * std::sin(b));
        points.push_back(p);
        points.push_back(p + (q - p) / 3.0);
        points.push_back(p + 2.0 * (q - p) / 3.0);
    }
    const ImageRGB model = drawModel(points, w, h);
    const ImageRGB area = draw(ghost, w, h, hexagon, 0);
    EXPECT_LT(relativeL2(area, model), 0.005);
    EXPECT_GT(relativeL2(draw(ghost, w, h, hexagon, 1), model), 0.02);
    const double hexagon_area = 1.5 * std::sqrt(3.0) * radius * radius;
    EXPECT_NEAR(imageSum(area), hexagon_area, 1e-3 * hexagon_area);
}

// A vignetting edge (the interpolated aperture ratio crossing 1 along a slanted line) lands where
// the ratio says, whatever the grid: coarse and fine cells give the same image, both the
// half-plane's exact coverage.
TEST(AreaIntegration, AVignettingEdgeDoesNotDependOnTheGridSize) {
    const int64_t w = 96, h = 96;
    const double cx = 48.0, cy = 48.0;
    // ratio = 1 on the line through (51.3, 48) at 20 degrees from the vertical.
    const double nx = std::cos(0.35), ny = std::sin(0.35);
    const auto ratio = [&](double x, double y) {
        return 1.0 + 0.02 * (nx * (x - 51.3) + ny * (y - 48.0));
    };
    for (const double step : {2.9, 11.3}) {
        SCOPED_TRACE("cell " + std::to_string(step));
        const int n = static_cast<int>(std::ceil(80.0 / step));
        const GhostQuads ghost = handGhost(cx, cy, 1e6, step, n, ratio);
        const ImageRGB area = draw(ghost, w, h, optics::ApertureShape{}, 0);
        const ImageRGB truth = draw(ghost, w, h, optics::ApertureShape{}, 16);
        double worst = 0.0;
        for (int64_t y = 30; y < 66; ++y)
            for (int64_t x = 30; x < 66; ++x) {
                // Coverage of the pixel by nx (x - 51.3) + ny (y - 48) <= 0: each column x'
                // is inside below y = 48 - nx (x' - 51.3) / ny; its length integrated over x'
                // (piecewise linear, to 1e-6 by 1000 midpoints).
                double expected = 0.0;
                for (int i = 0; i < 1000; ++i) {
                    const double column = x + (i + 0.5) / 1000.0;
                    const double top = 48.0 - nx * (column - 51.3) / ny;
                    expected += std::clamp(top - static_cast<double>(y), 0.0, 1.0) / 1000.0;
                }
                worst = std::max(worst, std::abs(area.at(x, y)[1] - expected));
                EXPECT_NEAR(truth.at(x, y)[1], expected, 1.0 / 16.0 + 1e-6);
            }
        EXPECT_LT(worst, 1e-3);
    }
}

// Real lenses, real grids: ghosts traced at the size eq. 13 gives them (base 13 on a 96 x 64
// image: cells of about 6 px, as base 256 gives at 1920 x 1080), drawn with pixel-area
// integration and with 16 x 16 point samples per pixel; at least 50 dB apart, on axis, off axis
// and near the field's edge, with a circular stop and with seven blades. (Measured when written:
// 67 to 86 dB.)
TEST(AreaIntegration, MatchesA16x16SupersampledTruthOnShippedLenses) {
    const int64_t w = 96, h = 64;
    int drawn = 0;
    const std::pair<const char*, int> cases[] = {{"heliar-tronnier.csv", 0},
                                                 {"double-gauss-tronnier-50mm.csv", 7},
                                                 {"canon-tele-zoom-200.csv", 0}};
    for (const auto& [file, blades] : cases) {
        {
            const optics::Lens lens = loadLens(file, blades);
            const double limit_deg = fieldLimitDeg(lens);
            const auto ghosts = optics::enumerateGhosts(lens);
            ASSERT_TRUE(ghosts.has_value());
            const SensorToImage mapping = sensorToImage(lens.camera(), w, h);
            const double sensor_area =
                lens.camera().sensor_width_mm * lens.camera().sensor_height_mm;
            for (const double theta_deg : {0.0, 0.4 * limit_deg, 0.95 * limit_deg}) {
                // Two ghosts from the enumeration (different sizes and focus).
                const size_t count = ghosts->ghosts.size();
                for (const size_t g : {size_t{1}, count - 1}) {
                    const optics::GhostPath& path = ghosts->ghosts[g];
                    SCOPED_TRACE(std::string(file) + " blades " + std::to_string(blades) +
                                 " theta " + std::to_string(theta_deg) + " ghost " +
                                 optics::pathLabel(path));
                    const double theta = degToRad(theta_deg), phi = degToRad(-30.0);
                    const auto probe =
                        optics::traceRayGrid(lens, path, theta, phi, kLambdaGreen_nm, 16);
                    ASSERT_TRUE(probe.has_value());
                    if (probe->validCount() == 0) continue;
                    double lo_x = 1e300, hi_x = -1e300, lo_y = 1e300, hi_y = -1e300;
                    for (const optics::GridSample& s : probe->samples) {
                        if (!s.valid) continue;
                        lo_x = std::min<double>(lo_x, s.sensor_x_mm);
                        hi_x = std::max<double>(hi_x, s.sensor_x_mm);
                        lo_y = std::min<double>(lo_y, s.sensor_y_mm);
                        hi_y = std::max<double>(hi_y, s.sensor_y_mm);
                    }
                    const int n = adaptiveGridSize(13, (hi_x - lo_x) * (hi_y - lo_y), sensor_area);
                    optics::RayGridOptions options;
                    options.square = probe->square();
                    const auto grid =
                        optics::traceRayGrid(lens, path, theta, phi, kLambdaGreen_nm, n, options);
                    ASSERT_TRUE(grid.has_value());
                    const GhostQuads quads = quadsFromGrid(*grid, mapping);
                    ImageRGB area(w, h), truth(w, h);
                    RasterOptions sixteen;
                    sixteen.supersample = 16;
                    rasterizeReference(area, quads, 1, 1.0f, lens.aperture());
                    rasterizeReference(truth, quads, 1, 1.0f, lens.aperture(), sixteen);
                    if (!(imageSum(truth) > 0.0)) continue;
                    const auto db = psnr(area, truth);
                    ASSERT_TRUE(db.has_value());
                    EXPECT_GE(*db, 50.0);
                    ++drawn;
                }
            }
        }
    }
    EXPECT_GE(drawn, 14);  // most of the 18 cases put light in the image
}

// The light's own power, integrated over the pupil's cells, converges with the grid: a 32 x 32
// grid is within 0.1% of a 96 x 96 one on axis and at the edge of the field, where clear
// apertures cut the beam.
TEST(AreaIntegration, TheLightsPowerConvergesWithTheGrid) {
    for (const char* file : {"heliar-tronnier.csv", "canon-tele-zoom-200.csv"}) {
        const optics::Lens lens = loadLens(file);
        const double limit_deg = fieldLimitDeg(lens);
        for (const double theta_deg : {0.0, 0.3 * limit_deg, 0.7 * limit_deg}) {
            SCOPED_TRACE(std::string(file) + " theta " + std::to_string(theta_deg));
            const double theta = degToRad(theta_deg);
            const auto fine =
                optics::traceRayGrid(lens, optics::GhostPath{}, theta, 0.0, kLambdaGreen_nm, 96);
            const auto coarse =
                optics::traceRayGrid(lens, optics::GhostPath{}, theta, 0.0, kLambdaGreen_nm, 32);
            ASSERT_TRUE(fine.has_value() && coarse.has_value());
            const double reference = imagingPower(*fine, lens.aperture());
            ASSERT_GT(reference, 0.0);
            EXPECT_NEAR(imagingPower(*coarse, lens.aperture()), reference, 1e-3 * reference);
            // Every sample the tracer cut has a ratio above 1, every other one at most 1.
            for (const optics::GridSample& s : coarse->samples)
                if (s.has_position) {
                    EXPECT_EQ(s.valid, s.aperture_ratio <= 1.0f);
                }
        }
    }
}

// A sampling count out of range is an error naming the field, not an abort.
TEST(AreaIntegration, RenderSceneRefusesASupersampleOutOfRange) {
    const optics::Lens lens = loadLens("heliar-tronnier.csv");
    SceneOptions options;
    options.width = 16;
    options.height = 16;
    const Light light{5.0, 0.0, {1.0f, 1.0f, 1.0f}};
    for (const int samples : {-1, 65}) {
        options.raster.supersample = samples;
        const auto image = renderScene(lens, {&light, 1}, options);
        ASSERT_FALSE(image.has_value());
        EXPECT_NE(image.error().message.find("supersample"), std::string::npos);
    }
}

}  // namespace
}  // namespace flarelab::render
