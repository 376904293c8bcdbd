#include "render/scene.h"

#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <cmath>
#include <limits>

#include "render/metrics.h"
#include "tests/test_paths.h"

namespace flarelab::render {
namespace {

optics::Lens heliar() {
    return *optics::Lens::make(
        *optics::loadPrescription(flarelab::testing::lensPath("heliar-tronnier.csv")),
        optics::CameraDescription{});
}

SceneOptions small() {
    SceneOptions o;
    o.width = 96;
    o.height = 64;
    o.base_grid = 24;
    o.probe_grid = 6;
    o.starburst_options.mask_size = 32;
    o.starburst_options.fft_size = 128;
    return o;
}

double sum(const ImageRGB& image) {
    double total = 0.0;
    for (float v : image.pixels) {
        EXPECT_TRUE(std::isfinite(v));
        EXPECT_GE(v, 0.0f);
        total += v;
    }
    return total;
}

TEST(RenderScene, NoLightsGiveABlackImage) {
    const auto image = renderScene(heliar(), {}, small());
    ASSERT_TRUE(image);
    EXPECT_EQ(sum(*image), 0.0);
}

TEST(RenderScene, OnAxisAndOffAxisLightsGiveFiniteFlare) {
    for (double theta : {0.0, 3.0, 30.0}) {
        const Light light{theta, 15.0, {1.0f, 0.5f, 0.25f}};
        SceneStats stats;
        const auto image = renderScene(heliar(), std::span(&light, 1), small(), &stats);
        ASSERT_TRUE(image) << theta;
        EXPECT_GT(sum(*image), 0.0) << theta;
        EXPECT_GT(stats.ghosts_drawn, 0) << theta;
    }
}

TEST(RenderScene, TiledAndReferenceAgreeAlsoWhenDrawingInBatches) {
    const Light lights[] = {{4.0, 30.0, {1.0f, 0.8f, 0.6f}}, {12.0, -100.0, {0.5f, 0.5f, 1.0f}}};
    SceneOptions o = small();
    o.starburst = false;
    o.tiled = false;
    const auto reference = renderScene(heliar(), lights, o);
    o.tiled = true;
    o.max_pending_primitives = 500;  // many batches
    SceneStats stats;
    const auto batched = renderScene(heliar(), lights, o, &stats);
    ASSERT_TRUE(reference && batched);
    EXPECT_GT(stats.tiles.primitives, 5000);
    for (size_t i = 0; i < reference->pixels.size(); ++i)
        ASSERT_NEAR(batched->pixels[i], reference->pixels[i],
                    1e-5f * std::abs(reference->pixels[i]) + 1e-30f)
            << i;
}

TEST(RenderScene, TheTiledImageDoesNotDependOnTheNumberOfThreads) {
    const Light light{7.0, 20.0, {1.0f, 1.0f, 1.0f}};
    SceneOptions o = small();
    o.merge = kLightMerge;
    const auto many = renderScene(heliar(), std::span(&light, 1), o);
    ImageRGB one_thread;
    {
        tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
        auto image = renderScene(heliar(), std::span(&light, 1), o);
        ASSERT_TRUE(image);
        one_thread = std::move(*image);
    }
    ASSERT_TRUE(many);
    EXPECT_EQ(many->pixels, one_thread.pixels);
}

TEST(RenderScene, MergedPrimitivesStayCloseToTheReferenceAndKeepTheEnergy) {
    const Light light{5.0, 30.0, {1.0f, 1.0f, 1.0f}};
    SceneOptions o = small();
    o.width = 240;
    o.height = 160;
    o.base_grid = 64;
    o.starburst = false;
    o.tiled = false;
    const auto reference = renderScene(heliar(), std::span(&light, 1), o);
    ASSERT_TRUE(reference);
    o.tiled = true;
    for (const MergeOptions merge : {kLightMerge, kHeavyMerge}) {
        o.merge = merge;
        SceneStats merged_stats;
        const auto merged = renderScene(heliar(), std::span(&light, 1), o, &merged_stats);
        ASSERT_TRUE(merged);
        const auto quality = psnr(*merged, *reference);
        ASSERT_TRUE(quality);
        EXPECT_GT(*quality, merge.gamma < 0.01 ? 55.0 : 40.0) << merge.gamma;
        EXPECT_NEAR(imageSum(*merged), imageSum(*reference), 0.01 * imageSum(*reference));
    }
    o.merge = kLightMerge;
    o.merge.steps = 8;
    EXPECT_FALSE(renderScene(heliar(), std::span(&light, 1), o));
    o.merge.steps = 2;
    o.merge.gamma = std::nan("");
    EXPECT_FALSE(renderScene(heliar(), std::span(&light, 1), o));
}

// The image window (SceneOptions::image_window) traces only the part of each entry square whose
// rays can reach the image. Its image must be the whole grid's up to the interpolation error of
// another ray lattice: measured against the whole grid, it may be no farther than a whole grid
// one ray coarser is (less 3 dB). On six lenses, on axis, off axis, at the field's edge, on images
// small enough that most ghosts are larger than they are. (On the nine shipped lenses, once, with
// 10 cases: the window was from 1.6 dB to 70 dB closer to the whole grid than the coarser grid,
// or the same image.)
TEST(RenderScene, TheImageWindowDrawsWhatTheWholeGridDraws) {
    struct Case {
        const char* lens;
        double theta, phi;
        int64_t width, height;
    };
    const Case cases[] = {
        {"heliar-tronnier.csv", 5.0, 30.0, 192, 108},
        {"heliar-tronnier.csv", 0.0, 0.0, 96, 64},
        {"canon-tele-zoom-200.csv", 4.0, 200.0, 192, 108},
        {"itoh-wide-zoom.csv", 30.0, 45.0, 192, 108},
        {"nikon-28-75mm.csv", 12.0, -20.0, 120, 80},
        {"double-gauss-tronnier-50mm.csv", 8.0, 135.0, 192, 108},
    };
    int64_t windowed = 0;
    for (const Case& c : cases) {
        SCOPED_TRACE(std::string(c.lens) + " at " + std::to_string(c.theta));
        const auto lens =
            optics::Lens::make(*optics::loadPrescription(flarelab::testing::lensPath(c.lens)),
                               optics::CameraDescription{});
        ASSERT_TRUE(lens);
        const Light light{c.theta, c.phi, {1.0f, 1.0f, 1.0f}};
        SceneOptions o;
        o.width = c.width;
        o.height = c.height;
        o.base_grid = 48;
        o.starburst = false;
        o.cull_relative_l2 = 0.0;
        o.merge = kNoMerge;
        o.image_window = false;
        const auto whole = renderScene(*lens, std::span(&light, 1), o);
        ASSERT_TRUE(whole);
        o.base_grid = 47;
        const auto coarser = renderScene(*lens, std::span(&light, 1), o);
        ASSERT_TRUE(coarser);
        o.base_grid = 48;
        o.image_window = true;
        SceneStats stats;
        const auto window = renderScene(*lens, std::span(&light, 1), o, &stats);
        ASSERT_TRUE(window);
        windowed += stats.grids_windowed;
        const double lattice = *psnr(*coarser, *whole);
        const double drawn = *psnr(*window, *whole);
        EXPECT_GT(drawn, lattice - 3.0);
        EXPECT_NEAR(imageSum(*window), imageSum(*whole), 0.01 * imageSum(*whole));
    }
    EXPECT_GT(windowed, 20);
}

TEST(RenderScene, LightBehindTheCameraIsSkippedNotAnError) {
    const Light lights[] = {{90.0, 0.0, {1, 1, 1}}, {135.0, 40.0, {1, 1, 1}}};
    SceneStats stats;
    const auto image = renderScene(heliar(), lights, small(), &stats);
    ASSERT_TRUE(image);
    EXPECT_EQ(stats.lights_behind, 2);
    EXPECT_EQ(sum(*image), 0.0);
}

TEST(RenderScene, OnePixelImageStaysFinite) {
    SceneOptions o = small();
    o.width = 1;
    o.height = 1;
    const Light light{0.0, 0.0, {1, 1, 1}};
    const auto image = renderScene(heliar(), std::span(&light, 1), o);
    ASSERT_TRUE(image);
    EXPECT_GT(sum(*image), 0.0);  // the light's own image lands on the only pixel
}

TEST(RenderScene, RejectsBadLightsAndOptionsNamingThem) {
    const Light nan_light{std::nan(""), 0.0, {1, 1, 1}};
    const auto a = renderScene(heliar(), std::span(&nan_light, 1), small());
    ASSERT_FALSE(a);
    EXPECT_NE(a.error().message.find("light 1"), std::string::npos);
    const Light negative{5.0, 0.0, {1, -1, 1}};
    EXPECT_FALSE(renderScene(heliar(), std::span(&negative, 1), small()));
    SceneOptions o = small();
    o.width = 0;
    EXPECT_FALSE(renderScene(heliar(), {}, o));
    o = small();
    o.base_grid = 1;
    EXPECT_FALSE(renderScene(heliar(), {}, o));
}

TEST(RenderScene, MaxGridCapsTheSmoothGridsAndLeavesTheImage) {
    // The Heliar at 5 deg: its large ghosts get eq. 13 grids of up to base_grid a side, the
    // small ones a few tens.
    const Light light{5.0, 30.0, {1.0f, 1.0f, 1.0f}};
    SceneOptions o;
    o.width = 240;
    o.height = 135;
    o.base_grid = 128;
    o.starburst = false;
    o.cull_relative_l2 = 0.0;
    o.merge = kLightMerge;
    o.max_grid = 0;
    SceneStats whole_stats;
    const auto whole = renderScene(heliar(), std::span(&light, 1), o, &whole_stats);
    ASSERT_TRUE(whole);
    o.max_grid = 128;  // no grid is larger than the base: nothing changes
    const auto same = renderScene(heliar(), std::span(&light, 1), o);
    ASSERT_TRUE(same);
    EXPECT_EQ(same->pixels, whole->pixels);
    // Against the uncapped grids without merge.
    o.max_grid = 0;
    o.merge = kNoMerge;
    const auto truth = renderScene(heliar(), std::span(&light, 1), o);
    ASSERT_TRUE(truth);
    o.merge = kLightMerge;
    const double merged = *psnr(*whole, *truth);
    // A cap whatever the grid's bend: every grid at most 32 a side.
    o.max_grid = 32;
    o.grid_bend_px = 1e9;
    SceneStats blunt_stats;
    const auto blunt = renderScene(heliar(), std::span(&light, 1), o, &blunt_stats);
    ASSERT_TRUE(blunt);
    EXPECT_EQ(blunt_stats.ghosts_drawn, whole_stats.ghosts_drawn);
    EXPECT_LE(blunt_stats.rays, blunt_stats.ghosts_drawn * 32 * 32);
    EXPECT_LT(blunt_stats.rays, whole_stats.rays / 4);
    // With the bend test (the default tolerance) grids that bend keep more rays, and the image
    // may not move farther from the uncapped grids than the merge already is, less 1 dB.
    o.grid_bend_px = SceneOptions{}.grid_bend_px;
    SceneStats stats;
    const auto capped = renderScene(heliar(), std::span(&light, 1), o, &stats);
    ASSERT_TRUE(capped);
    EXPECT_GE(stats.rays, blunt_stats.rays);
    EXPECT_LT(stats.rays, whole_stats.rays);
    const double cut = *psnr(*capped, *truth);
    EXPECT_GT(cut, merged - 1.0) << "merged " << merged << " dB, capped " << cut << " dB";
    EXPECT_NEAR(imageSum(*capped), imageSum(*truth), 0.01 * imageSum(*truth));
    // The double Gauss's ghosts bend (caustics, near-focused ghosts): the same blunt cap moves
    // its image well away from the uncapped grids, and the bend test keeps what they draw.
    {
        const auto gauss = optics::Lens::make(*optics::loadPrescription(flarelab::testing::lensPath(
                                                  "double-gauss-tronnier-50mm.csv")),
                                              optics::CameraDescription{});
        ASSERT_TRUE(gauss);
        SceneOptions g = o;
        g.max_grid = 0;
        g.merge = kNoMerge;
        const auto g_truth = renderScene(*gauss, std::span(&light, 1), g);
        ASSERT_TRUE(g_truth);
        g.merge = kLightMerge;
        const auto g_whole = renderScene(*gauss, std::span(&light, 1), g);
        ASSERT_TRUE(g_whole);
        g.max_grid = 32;
        g.grid_bend_px = 1e9;
        const auto g_blunt = renderScene(*gauss, std::span(&light, 1), g);
        ASSERT_TRUE(g_blunt);
        g.grid_bend_px = SceneOptions{}.grid_bend_px;
        const auto g_bend = renderScene(*gauss, std::span(&light, 1), g);
        ASSERT_TRUE(g_bend);
        const double g_merged = *psnr(*g_whole, *g_truth);
        const double g_blunt_db = *psnr(*g_blunt, *g_truth);
        const double g_bend_db = *psnr(*g_bend, *g_truth);
        EXPECT_LT(g_blunt_db, g_merged - 10.0) << "blunt cap " << g_blunt_db << " dB";
        EXPECT_GT(g_bend_db, g_merged - 3.0)
            << "merged " << g_merged << " dB, capped with the bend test " << g_bend_db << " dB";
    }
    // A cap of 2 (one quad a ghost) still draws finite light; bad caps and tolerances are
    // refused by name.
    o.max_grid = 2;
    o.grid_bend_px = 1e9;
    const auto tiny = renderScene(heliar(), std::span(&light, 1), o);
    ASSERT_TRUE(tiny);
    EXPECT_TRUE(std::isfinite(imageSum(*tiny)));
    o.grid_bend_px = SceneOptions{}.grid_bend_px;
    for (const int bad : {1, -1, 4096}) {
        o.max_grid = bad;
        const auto refused = renderScene(heliar(), std::span(&light, 1), o);
        ASSERT_FALSE(refused) << bad;
        EXPECT_NE(refused.error().message.find("max_grid"), std::string::npos)
            << refused.error().message;
    }
    o.max_grid = 64;
    for (const double bad : {0.0, -1.0, std::nan(""), std::numeric_limits<double>::infinity()}) {
        o.grid_bend_px = bad;
        const auto refused = renderScene(heliar(), std::span(&light, 1), o);
        ASSERT_FALSE(refused) << bad;
        EXPECT_NE(refused.error().message.find("grid_bend_px"), std::string::npos)
            << refused.error().message;
    }
}

double relativeL2(const ImageRGB& test, const ImageRGB& truth) {
    double diff = 0.0, norm = 0.0;
    for (size_t i = 0; i < truth.pixels.size(); ++i) {
        const double d = double{test.pixels[i]} - truth.pixels[i];
        diff += d * d;
        norm += double{truth.pixels[i]} * truth.pixels[i];
    }
    return std::sqrt(diff / norm);
}

TEST(RenderScene, CullingDropsTheFaintestGhostsWithinItsL2Budget) {
    for (const char* file : {"heliar-tronnier.csv", "nikon-tele-zoom.csv"}) {
        SCOPED_TRACE(file);
        const optics::Lens lens =
            *optics::Lens::make(*optics::loadPrescription(flarelab::testing::lensPath(file)),
                                optics::CameraDescription{});
        SceneOptions o = small();
        o.width = 192;
        o.height = 128;
        o.base_grid = 32;
        o.starburst = false;
        o.cull_relative_l2 = 0.0;
        const Light light{8.0, 30.0, {1, 1, 1}};
        SceneStats all;
        const auto truth = renderScene(lens, std::span(&light, 1), o, &all);
        ASSERT_TRUE(truth);
        EXPECT_EQ(all.ghosts_culled, 0);
        int64_t culled_before = 0;
        for (const double budget : {1e-3, 1e-2, 5e-2}) {
            o.cull_relative_l2 = budget;
            SceneStats stats;
            const auto culled = renderScene(lens, std::span(&light, 1), o, &stats);
            ASSERT_TRUE(culled);
            EXPECT_GE(stats.ghosts_culled, culled_before);
            culled_before = stats.ghosts_culled;
            // A culled grid might have drawn nothing anyway (its probe touched the image, its
            // quads did not), so the counts bound each other.
            EXPECT_LE(stats.ghosts_drawn, all.ghosts_drawn);
            EXPECT_GE(stats.ghosts_drawn + stats.ghosts_culled, all.ghosts_drawn);
            EXPECT_LE(stats.culled_relative_l2, budget);
            // The estimate ignores overlaps and shapes; the image stays within twice the budget.
            EXPECT_LE(relativeL2(*culled, *truth), 2.0 * budget) << "budget " << budget;
        }
        EXPECT_GT(culled_before, 0);
    }
}

TEST(RenderScene, AGhostBelowTheMeanFloorIsNotDrawn) {
    SceneOptions o = small();
    o.starburst = false;
    o.cull_mean_below = 1e30;  // above any ghost
    const Light light{8.0, 30.0, {1, 1, 1}};
    SceneStats stats;
    const auto image = renderScene(heliar(), std::span(&light, 1), o, &stats);
    ASSERT_TRUE(image);
    EXPECT_EQ(sum(*image), 0.0);
    EXPECT_EQ(stats.ghosts_drawn, 0);
    EXPECT_GT(stats.ghosts_culled, 0);
}

TEST(RenderScene, RejectsBadCullingNamingIt) {
    for (const double bad : {-1e-3, 1.5, std::nan("")}) {
        SceneOptions o = small();
        o.cull_relative_l2 = bad;
        const auto r = renderScene(heliar(), {}, o);
        ASSERT_FALSE(r);
        EXPECT_NE(r.error().message.find("cull_relative_l2"), std::string::npos);
        o = small();
        o.cull_mean_below = bad < 1.0 ? bad : std::numeric_limits<double>::infinity();
        const auto m = renderScene(heliar(), {}, o);
        ASSERT_FALSE(m);
        EXPECT_NE(m.error().message.find("cull_mean_below"), std::string::npos);
    }
}

// One path at a time: the images of the paths drawn alone add up to the image of all of them
// (no culling, no starburst, so nothing depends on which paths are drawn together), and a path
// the lens does not have is refused by name.
TEST(RenderScene, PathsDrawnAloneAddUpToAllOfThem) {
    const optics::Lens lens = heliar();
    SceneOptions options = small();
    options.starburst = false;
    options.cull_relative_l2 = 0.0;
    const Light light{6.0, 20.0, {1.0f, 1.0f, 1.0f}};
    const auto all = renderScene(lens, std::span(&light, 1), options);
    ASSERT_TRUE(all) << all.error().message;
    auto enumeration = optics::enumerateGhosts(lens, options.ghosts);
    ASSERT_TRUE(enumeration);
    ASSERT_GT(enumeration->ghosts.size(), 3u);
    ImageRGB summed(options.width, options.height);
    int lit = 0;
    for (const optics::GhostPath& path : enumeration->ghosts) {
        SceneOptions one = options;
        one.only_paths = {path, path};  // a repeat is drawn once
        const auto image = renderScene(lens, std::span(&light, 1), one);
        ASSERT_TRUE(image) << optics::pathLabel(path) << ": " << image.error().message;
        lit += sum(*image) > 0.0;
        for (size_t i = 0; i < summed.pixels.size(); ++i) summed.pixels[i] += image->pixels[i];
    }
    EXPECT_GT(lit, 3);
    double diff = 0.0, norm = 0.0;
    for (size_t i = 0; i < summed.pixels.size(); ++i) {
        const double d = static_cast<double>(summed.pixels[i]) - all->pixels[i];
        diff += d * d;
        norm += static_cast<double>(all->pixels[i]) * all->pixels[i];
    }
    EXPECT_LT(std::sqrt(diff / norm), 1e-5);

    SceneOptions foreign = options;
    foreign.only_paths = {optics::GhostPath{0, 99}};
    const auto refused = renderScene(lens, std::span(&light, 1), foreign);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("only_paths"), std::string::npos)
        << refused.error().message;
}

}  // namespace
}  // namespace flarelab::render
