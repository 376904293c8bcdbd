#include "predict/lab_figures.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <vector>

#include "common/units.h"
#include "fit/model_eval.h"
#include "fit/sweep_fit.h"
#include "render/ghost_shape.h"
#include "tests/predict/moving_disc_model.h"

namespace flarelab::predict {
namespace {

// One ghost, a disc of radius 200 mm on the axis with the same value v inside at every angle
// from 0 to `to_deg`: the frame is evenly lit by v DN/s per pixel whatever the light's angle, so
// every lab figure has a closed form. 36 x 24 mm, 72 x 48 pixels, 50 mm, f/8.
fit::FlareModel evenVeilModel(double v, double to_deg, double light_power) {
    fit::FlareModel shell = testing::movingDiscModel(0);
    shell.capture.to_deg = shell.valid_to_deg = to_deg;
    shell.capture.light_power_dn_s = light_power;
    fit::SweepFitResult tracks;
    const int frames = static_cast<int>(std::lround(to_deg / 0.5)) + 1;
    tracks.frame_count = frames;
    fit::GhostTrack track;
    track.id = 1;
    for (int i = 0; i < frames; ++i) {
        fit::GhostState disc;
        disc.shape = render::circleGhostShape(0.0, 0.0, 200.0);
        disc.shading.border_rgb = {v, v, v};
        disc.shading.inner_rgb = {v, v, v};
        disc.shading.inner_falloff_mm = 0.5;
        disc.shading.outer_falloff_mm = 0.05;
        track.samples.push_back({0.5 * i, disc, 0.0});
    }
    tracks.tracks.push_back(track);
    auto built = fit::buildModel(tracks, shell, fit::SweepFitOptions{});
    EXPECT_TRUE(built) << built.error().message;
    return built ? *built : shell;
}

TEST(ArcInsideFrame, MatchesCountingPointsOnTheCircle) {
    const double w = 36.0, h = 24.0;
    EXPECT_DOUBLE_EQ(arcInsideFrame(0.0, w, h), 2.0 * std::numbers::pi);
    EXPECT_DOUBLE_EQ(arcInsideFrame(11.9, w, h), 2.0 * std::numbers::pi);
    EXPECT_DOUBLE_EQ(arcInsideFrame(21.7, w, h), 0.0);  // beyond the corner (21.63 mm)
    for (double r : {12.5, 15.0, 18.0, 19.0, 21.0, 21.6}) {
        const int n = 200000;
        int inside = 0;
        for (int k = 0; k < n; ++k) {
            const double phi = 2.0 * std::numbers::pi * (k + 0.5) / n;
            inside += std::abs(r * std::cos(phi)) <= w / 2 && std::abs(r * std::sin(phi)) <= h / 2;
        }
        EXPECT_NEAR(arcInsideFrame(r, w, h), 2.0 * std::numbers::pi * inside / n, 1e-4) << r;
    }
}

TEST(LabFigures, AnEvenVeilHasTheClosedForms) {
    const double v = 3.0, power = 4.0e6, to = 30.0;
    const fit::FlareModel model = evenVeilModel(v, to, power);
    auto table = FlareFigureTable::build(model, tableOptions(0.5, 30.0, 72));
    ASSERT_TRUE(table) << table.error().message;
    auto lab = labFigures(model, *table, LabFigureOptions{2.0});
    ASSERT_TRUE(lab) << lab.error().message;
    ASSERT_TRUE(lab->scaled) << lab->missing;
    ASSERT_EQ(lab->centre_flare.size(), lab->theta_deg.size());
    for (double c : lab->centre_flare) EXPECT_NEAR(c, v, 1e-3 * v);

    const double f = 50.0, pixel_area = (36.0 / 72) * (24.0 / 48);
    const double pupil_area = std::numbers::pi * (f / 8.0) * (f / 8.0) / 4.0;
    for (double pst : lab->pst) EXPECT_NEAR(pst, v / pixel_area * pupil_area / power, 1e-3 * pst);

    // VGI: f^2 / (A_pix P) v 2 pi (cos 1 deg - cos 30 deg).
    const double scale = f * f / (pixel_area * power);
    EXPECT_EQ(lab->vgi_from_deg, 1.0);
    EXPECT_EQ(lab->vgi_to_deg, to);
    const double vgi =
        scale * v * 2.0 * std::numbers::pi * (std::cos(degToRad(1.0)) - std::cos(degToRad(to)));
    EXPECT_NEAR(lab->vgi, vgi, 1e-3 * vgi);

    // Image flare: the same veil from the directions inside the 36 x 24 frame (field 23.4 deg),
    // summed here by counting the frame's points in a fine grid of directions.
    EXPECT_NEAR(lab->frame_field_deg, radToDeg(std::atan(std::hypot(18.0, 12.0) / f)), 1e-12);
    EXPECT_TRUE(lab->image_flare_complete);
    double solid = 0.0;
    const int n = 2000;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            const double x = -18.0 + 36.0 * (i + 0.5) / n, y = -12.0 + 24.0 * (j + 0.5) / n;
            const double r = std::hypot(x, y);
            if (std::atan(r / f) < degToRad(1.0)) continue;  // the black patch
            // dOmega of a sensor cell seen from the lens: dA cos^3 / f^2.
            const double c = f / std::sqrt(f * f + r * r);
            solid += (36.0 / n) * (24.0 / n) * c * c * c / (f * f);
        }
    EXPECT_NEAR(lab->image_flare, scale * v * solid, 2e-3 * scale * v * solid);
    EXPECT_LT(lab->image_flare, lab->vgi);  // a chart is the part of the field in the frame
}

TEST(LabFigures, OffAxisAnEvenVeilIsTheFieldsSolidAngleOverCos4) {
    // At image heights 0.5 and 0.7 the veil is v everywhere; the white there falls as cos^4.
    const double v = 2.0, power = 3.0e6, to = 30.0, f = 50.0;
    const fit::FlareModel model = evenVeilModel(v, to, power);
    FigureTableOptions options = tableOptions(0.5, 5.0, 96);
    options.field_points = {0.5, 0.7};
    auto table = FlareFigureTable::build(model, options);
    ASSERT_TRUE(table) << table.error().message;
    auto lab = labFigures(model, *table, LabFigureOptions{1.0});
    ASSERT_TRUE(lab) << lab.error().message;
    ASSERT_EQ(lab->field.size(), 2u);
    const double pixel_area = (36.0 / 72) * (24.0 / 48);
    const double scale = f * f / (pixel_area * power);
    for (const LabFieldPoint& p : lab->field) {
        const double x = p.height * 18.0, y = p.height * 12.0;
        const double cos_p = f / std::sqrt(x * x + y * y + f * f);
        EXPECT_NEAR(p.field_deg, radToDeg(std::acos(cos_p)), 1e-9);
        const double whole = 2.0 * std::numbers::pi * (1.0 - std::cos(degToRad(to)));
        const double white = std::pow(cos_p, 4.0);
        EXPECT_NEAR(p.vgi, scale * v * whole / white, 5e-3 * p.vgi) << p.height;
        // The chart: the frame's solid angle (the spot's is a thousandth of it).
        double solid = 0.0;
        const int n = 1000;
        for (int i = 0; i < n; ++i)
            for (int j = 0; j < n; ++j) {
                const double sx = -18.0 + 36.0 * (i + 0.5) / n, sy = -12.0 + 24.0 * (j + 0.5) / n;
                const double c = f / std::sqrt(f * f + sx * sx + sy * sy);
                solid += (36.0 / n) * (24.0 / n) * c * c * c / (f * f);
            }
        EXPECT_NEAR(p.image_flare, scale * v * solid / white, 0.02 * p.image_flare) << p.height;
    }
    // Further out, the same veil is a larger share of a dimmer white.
    EXPECT_GT(lab->field[1].vgi, lab->field[0].vgi);
    EXPECT_GT(lab->field[0].vgi, lab->vgi);
}

TEST(LabFigures, OffAxisAGhostCountsWhereItLies) {
    // The moving disc (radius 3 mm) lies 1.5 mm per degree of the light on the far side of it:
    // at 3 deg it covers the point at height 0.2 along the diagonal (3.6 mm right, 2.4 mm down)
    // only for some rolls; the table's samples there follow the drawing at every roll.
    fit::FlareModel model = testing::movingDiscModel();
    FigureTableOptions options = tableOptions(0.5, 10.0, 144);
    options.field_points = {0.2};
    auto table = FlareFigureTable::build(model, options);
    ASSERT_TRUE(table) << table.error().message;
    ASSERT_EQ(table->fieldPoints().size(), 1u);
    const int64_t i = 6;  // 3 deg: the disc's centre at 4.5 mm from the image centre
    int covered = 0, clear = 0;
    ASSERT_DOUBLE_EQ(table->thetaAt(i), 3.0);
    for (int64_t j = 0; j < table->phiCount(); ++j) {
        const double phi = table->phiAt(j);
        auto image = fit::renderModel(model, 3.0, phi, 144, 96);
        ASSERT_TRUE(image);
        // The point 3.6 mm right of and 2.4 mm below the centre: pixel (72 + 14.4, 48 + 9.6) of
        // the 4 px/mm drawing.
        const double drawn = image->at(86, 57)[1];
        EXPECT_NEAR(table->fieldFlare(0, i, j), drawn, 0.35 * std::max(1.0, drawn)) << phi;
        covered += drawn > 1.0;
        clear += drawn == 0.0;
    }
    EXPECT_GT(covered, 0);  // the disc passes over the point at some rolls, not at others
    EXPECT_GT(clear, 0);
    auto lab = labFigures(model, *table);
    ASSERT_TRUE(lab);
    EXPECT_TRUE(lab->field.empty());  // no light power: no figures
}

TEST(LabFigures, TheCentreFlareFollowsTheGhostOffTheCentre) {
    // The moving disc (radius 3 mm, centre -1.5 mm per degree) covers the centre up to 2 deg.
    fit::FlareModel model = testing::movingDiscModel();
    auto table = FlareFigureTable::build(model, tableOptions(0.5, 30.0, 144));
    ASSERT_TRUE(table) << table.error().message;
    auto lab = labFigures(model, *table);
    ASSERT_TRUE(lab) << lab.error().message;
    for (size_t i = 0; i < lab->theta_deg.size(); ++i) {
        const double t = lab->theta_deg[i];
        if (t <= 1.0) {
            EXPECT_GT(lab->centre_flare[i], 2.0) << t;
        }
        if (t >= 2.5) {
            EXPECT_EQ(lab->centre_flare[i], 0.0) << t;
        }
    }
    // Drawn by itself at the capture's size: the four pixels around the centre agree.
    auto image = fit::renderModel(model, 0.0, 0.0, 72, 48);
    ASSERT_TRUE(image);
    double centre = 0.0;
    for (int64_t y : {23, 24})
        for (int64_t x : {35, 36}) centre += image->at(x, y)[1] / 4.0;
    EXPECT_NEAR(lab->centre_flare[0], centre, 0.02 * centre);
}

TEST(LabFigures, AModelWithoutItsScaleSaysWhatItLacks) {
    fit::FlareModel model = testing::movingDiscModel();
    model.lens.f_number.reset();
    auto table = FlareFigureTable::build(model, tableOptions(1.0, 30.0, 48));
    ASSERT_TRUE(table) << table.error().message;
    auto lab = labFigures(model, *table);
    ASSERT_TRUE(lab) << lab.error().message;
    EXPECT_FALSE(lab->scaled);
    EXPECT_EQ(lab->missing, "capture.light_power_dn_s, lens.f_number");
    EXPECT_TRUE(lab->pst.empty());
    EXPECT_FALSE(lab->centre_flare.empty());
}

TEST(LabFigures, RefusesABlackSpotOutOfRangeAndStopsWhereTheModelStops) {
    {
        fit::FlareModel m = evenVeilModel(1.0, 10.0, 1.0e6);
        for (const std::vector<double>& points :
             {std::vector<double>{0.0}, std::vector<double>{1.5}, std::vector<double>(9, 0.5)}) {
            FigureTableOptions o = tableOptions(0.5, 30.0, 48);
            o.field_points = points;
            EXPECT_FALSE(FlareFigureTable::build(m, o)) << points.size();
        }
    }
    const fit::FlareModel model = evenVeilModel(1.0, 10.0, 1.0e6);
    auto table = FlareFigureTable::build(model, tableOptions(0.5, 30.0, 48));
    ASSERT_TRUE(table) << table.error().message;
    for (double spot : {0.0, -1.0, 20.5, std::nan("")}) {
        auto lab = labFigures(model, *table, LabFigureOptions{spot});
        ASSERT_FALSE(lab) << spot;
        EXPECT_NE(lab.error().message.find("black_spot_deg"), std::string::npos);
    }
    // 10 deg is short of the frame's corner (23.4 deg): the chart's figure is partial.
    auto lab = labFigures(model, *table);
    ASSERT_TRUE(lab) << lab.error().message;
    EXPECT_FALSE(lab->image_flare_complete);
    EXPECT_EQ(lab->vgi_to_deg, 10.0);
    EXPECT_GT(lab->image_flare, 0.0);
    EXPECT_LE(lab->image_flare, lab->vgi);
    EXPECT_TRUE(std::isfinite(lab->vgi));
}

TEST(LabFigures, AModelWithoutGhostsHasNoVeil) {
    fit::FlareModel empty = testing::movingDiscModel(0);
    empty.capture.light_power_dn_s = 1.0e6;
    auto table = FlareFigureTable::build(empty, tableOptions(1.0, 30.0, 48));
    ASSERT_TRUE(table) << table.error().message;
    auto lab = labFigures(empty, *table);
    ASSERT_TRUE(lab) << lab.error().message;
    ASSERT_TRUE(lab->scaled);
    EXPECT_EQ(lab->vgi, 0.0);
    EXPECT_EQ(lab->image_flare, 0.0);
    for (double p : lab->pst) EXPECT_EQ(p, 0.0);
}

TEST(LabFigures, ACentreFlareFromElsewhereIsCheckedFirst) {
    const fit::FlareModel model = evenVeilModel(1.0, 10.0, 1.0e6);
    const double nan = std::nan("");
    const std::pair<std::vector<double>, std::vector<double>> bad[] = {
        {{0.0}, {1.0}},                // one angle
        {{0.0, 1.0}, {1.0}},           // a value short
        {{-1.0, 1.0}, {1.0, 1.0}},     // below 0
        {{0.0, 2.0, 2.0}, {1, 1, 1}},  // not increasing
        {{0.0, 1.0}, {1.0, nan}},      // not finite
        {{0.0, 1.0}, {1.0, -1.0}}};    // negative
    for (const auto& [theta, centre] : bad)
        EXPECT_FALSE(labFiguresOfCentre(model, theta, centre)) << theta.size();
    // The same values as the table's give the same index.
    auto table = FlareFigureTable::build(model, tableOptions(0.5, 30.0, 48));
    ASSERT_TRUE(table);
    auto from_table = labFigures(model, *table);
    ASSERT_TRUE(from_table);
    auto given = labFiguresOfCentre(model, from_table->theta_deg, from_table->centre_flare);
    ASSERT_TRUE(given) << given.error().message;
    EXPECT_EQ(given->vgi, from_table->vgi);
    EXPECT_TRUE(given->pst.empty());
}

}  // namespace
}  // namespace flarelab::predict
