#include "render/tiles.h"

#include <gtest/gtest.h>

#include <cmath>

#include "common/units.h"
#include "optics/ghosts.h"
#include "render/metrics.h"
#include "tests/test_paths.h"

namespace flarelab::render {
namespace {

// All ghosts of a lens under one light, as primitives for a width x height image, with the
// reference image drawn from the same quads.
struct Scene {
    std::vector<Primitive> primitives;
    ImageRGB reference;
    optics::ApertureShape aperture;
};

Scene makeScene(const char* lens_file,
                double theta_deg,
                int64_t width,
                int64_t height,
                int n,
                const optics::CameraDescription& camera = {},
                const MergeOptions& merge = {}) {
    const optics::Lens lens = *optics::Lens::make(
        *optics::loadPrescription(flarelab::testing::lensPath(lens_file)), camera);
    const auto ghosts = optics::enumerateGhosts(lens);
    const SensorToImage mapping = sensorToImage(lens.camera(), width, height);
    Scene scene;
    scene.aperture = lens.aperture();
    scene.reference = ImageRGB(width, height);
    const double lambda[3] = {650.0, 550.0, 450.0};
    for (const optics::GhostPath& path : ghosts->ghosts) {
        for (int c = 0; c < 3; ++c) {
            const auto grid =
                optics::traceRayGrid(lens, path, degToRad(theta_deg), 0.4, lambda[c], n);
            const GhostQuads quads = quadsFromGrid(*grid, mapping, merge);
            rasterizeReference(scene.reference, quads, c, 1000.0f, lens.aperture());
            for (size_t i = 0; i < quads.quads.size(); ++i)
                if (auto p = preparePrimitive(quads.quads[i], quads.cellArea(i), c, 1000.0f, width,
                                              height))
                    scene.primitives.push_back(*p);
        }
    }
    return scene;
}

TEST(RenderTiled, MatchesTheReferenceRasterizerBitForBit) {
    const Scene scene = makeScene("heliar-tronnier.csv", 6.0, 200, 150, 33);
    ASSERT_GT(scene.primitives.size(), 10000u);
    for (const TileOptions options :
         {TileOptions{}, TileOptions{128, 8, false}, TileOptions{128, 16, true},
          TileOptions{32, 16, true}, TileOptions{1, 1, true}, TileOptions{4096, 256, true}}) {
        ImageRGB tiled(200, 150);
        TileStats stats;
        ASSERT_TRUE(renderTiled(tiled, scene.primitives, optics::ApertureShape{}, options, &stats));
        EXPECT_EQ(tiled.pixels, scene.reference.pixels)
            << options.coarse_tile_px << "/" << options.dense_tile_px;
        EXPECT_EQ(stats.primitives, static_cast<int64_t>(scene.primitives.size()));
        EXPECT_GE(stats.dense_entries, stats.primitives);
        EXPECT_GT(stats.memory_bytes, 0);
    }
}

// Quads tens of pixels across, merged or not, cut by a round stop, by blades and by vignetting:
// the tiled renderer draws most of their pixels a row at a time (addPrimitiveRow), the reference
// pixel by pixel, and the two agree bit for bit.
TEST(RenderTiled, RowsOfLargeQuadsMatchTheReferenceBitForBit) {
    optics::CameraDescription hexagon;
    hexagon.aperture_blades = 6;
    hexagon.aperture_rotation_deg = 10.0;
    struct Case {
        const char* lens;
        double theta_deg;
        int n;
        optics::CameraDescription camera;
        MergeOptions merge;
    };
    for (const Case& c : {Case{"heliar-tronnier.csv", 4.0, 9, {}, kNoMerge},
                          Case{"heliar-tronnier.csv", 4.0, 33, hexagon, kHeavyMerge},
                          Case{"double-gauss-tronnier-50mm.csv", 18.0, 17, {}, kLightMerge},
                          Case{"lensbaby-toy.csv", 0.0, 17, {}, kNoMerge}}) {
        const Scene scene = makeScene(c.lens, c.theta_deg, 240, 180, c.n, c.camera, c.merge);
        ImageRGB tiled(240, 180);
        ASSERT_TRUE(renderTiled(tiled, scene.primitives, scene.aperture, TileOptions{}));
        EXPECT_EQ(tiled.pixels, scene.reference.pixels) << c.lens << " n " << c.n;
        EXPECT_GT(imageSum(tiled), 0.0) << c.lens;
    }
}

TEST(RenderTiled, CoarseLevelDoesNotChangeTheDenseLists) {
    const Scene scene = makeScene("itoh-wide-zoom.csv", 3.0, 160, 100, 9);
    TileStats with, without;
    ImageRGB a(160, 100), b(160, 100);
    ASSERT_TRUE(renderTiled(a, scene.primitives, optics::ApertureShape{}, {64, 8, true}, &with));
    ASSERT_TRUE(
        renderTiled(b, scene.primitives, optics::ApertureShape{}, {64, 8, false}, &without));
    EXPECT_EQ(with.dense_entries, without.dense_entries);
    EXPECT_GT(with.coarse_entries, 0);
    EXPECT_EQ(without.coarse_entries, 0);
    EXPECT_EQ(a.pixels, b.pixels);
}

TEST(RenderTiled, RejectsBadTilesAndPrimitivesOutsideTheImage) {
    ImageRGB image(16, 16);
    EXPECT_FALSE(renderTiled(image, {}, {}, {128, 0, true}));
    EXPECT_FALSE(renderTiled(image, {}, {}, {12, 8, true}));
    EXPECT_FALSE(renderTiled(image, {}, {}, {8192, 8, true}));
    Primitive p;
    p.x0 = 0;
    p.y0 = 0;
    p.x1 = 16;  // one past the last column
    p.y1 = 3;
    EXPECT_FALSE(renderTiled(image, std::span(&p, 1), {}));
    p.x1 = 3;
    p.channel = 3;
    const auto error = renderTiled(image, std::span(&p, 1), {});
    ASSERT_FALSE(error);
    EXPECT_NE(error.error().message.find("primitive 0"), std::string::npos);
}

TEST(RenderTiled, EmptyInputsAndOnePixelImages) {
    ImageRGB empty;
    EXPECT_TRUE(renderTiled(empty, {}, {}));
    const Scene scene = makeScene("lensbaby-toy.csv", 0.0, 1, 1, 5);
    ImageRGB one(1, 1);
    ASSERT_TRUE(renderTiled(one, scene.primitives, {}));
    EXPECT_EQ(one.pixels, scene.reference.pixels);
    for (float v : one.pixels) EXPECT_TRUE(std::isfinite(v));
}

}  // namespace
}  // namespace flarelab::render
