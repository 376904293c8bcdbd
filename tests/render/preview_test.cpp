#include "render/preview.h"

#include <gtest/gtest.h>
#include <stdlib.h>
#include <sys/stat.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>

#include "tests/test_files.h"

namespace flarelab::render {
namespace {

namespace fs = std::filesystem;

using flarelab::testing::TempDir;

ImageRGB gradient(int64_t w, int64_t h) {
    ImageRGB image(w, h);
    for (int64_t y = 0; y < h; ++y) {
        for (int64_t x = 0; x < w; ++x) {
            float* p = image.at(x, y);
            p[0] = static_cast<float>(x) / static_cast<float>(w - 1) * 4.0f;
            p[1] = static_cast<float>(y) / static_cast<float>(h - 1);
            p[2] = 0.25f;
        }
    }
    return image;
}

TEST(WritePng, RoundTripsThroughLibpng) {
    TempDir dir;
    const std::string path = dir.file("gradient.png");
    const ImageRGB image = gradient(16, 8);
    const ToneMapOptions options;
    ASSERT_TRUE(writePng(image, path, options));
    // The file is a PNG: it opens with the 8-byte signature.
    std::ifstream file(path, std::ios::binary);
    char signature[8] = {};
    file.read(signature, 8);
    EXPECT_EQ(std::string(signature, 8), std::string("\x89PNG\r\n\x1a\n", 8));
    const Result<PreviewImage> read = readPng(path);
    ASSERT_TRUE(read) << read.error().message;
    ASSERT_EQ(read->width, 16);
    ASSERT_EQ(read->height, 8);
    const Result<PreviewImage> expected = toneMap(image, options);
    ASSERT_TRUE(expected);
    EXPECT_EQ(read->pixels, expected->pixels);
    for (int y = 0; y < 8; ++y) {
        for (int x = 0; x < 16; ++x) {
            const uint8_t* rgb = read->pixels.data() + (y * 16 + x) * 3;
            for (int c = 0; c < 3; ++c)
                EXPECT_EQ(rgb[c], std::lround(toneCurve(image.at(x, y)[c], options) * 255.0));
        }
    }
    // Left to right the red ramp never gets darker.
    for (int x = 1; x < 16; ++x) EXPECT_GE(read->pixels[x * 3], read->pixels[(x - 1) * 3]);
    EXPECT_EQ(dir.entries().size(), 1u);  // no temporary left beside it
}

TEST(WritePng, ReplacesAnExistingFileWhole) {
    TempDir dir;
    const std::string path = dir.file("out.png");
    ASSERT_TRUE(writePng(gradient(4, 4), path, {}));
    ASSERT_TRUE(writePng(gradient(9, 3), path, {}));
    const Result<PreviewImage> read = readPng(path);
    ASSERT_TRUE(read);
    EXPECT_EQ(read->width, 9);
    EXPECT_EQ(read->height, 3);
    EXPECT_EQ(dir.entries().size(), 1u);
}

TEST(WritePng, UnwritablePathIsAnErrorNamingIt) {
    TempDir dir;
    const std::string missing = dir.file("no/such/dir/x.png");
    const Status s = writePng(gradient(4, 4), missing, {});
    ASSERT_FALSE(s);
    EXPECT_EQ(s.error().code, ErrorCode::IoError);
    EXPECT_NE(s.error().message.find(missing), std::string::npos) << s.error().message;
    // A directory where the file should go: the rename fails, the temporary is cleaned up.
    const fs::path occupied = dir.file("occupied.png");
    fs::create_directory(occupied);
    fs::create_directory(occupied / "child");
    const Status t = writePng(gradient(4, 4), occupied.string(), {});
    ASSERT_FALSE(t);
    EXPECT_NE(t.error().message.find(occupied.string()), std::string::npos);
    EXPECT_EQ(dir.entries().size(), 1u);
    EXPECT_FALSE(writePng(gradient(4, 4), "", {}));
}

TEST(WritePng, RejectsNonFinitePixelsWithACount) {
    TempDir dir;
    const std::string path = dir.file("bad.png");
    ImageRGB image = gradient(8, 8);
    image.at(3, 5)[1] = std::numeric_limits<float>::quiet_NaN();
    image.at(7, 7)[2] = std::numeric_limits<float>::infinity();
    const Status s = writePng(image, path, {});
    ASSERT_FALSE(s);
    EXPECT_EQ(s.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(s.error().message.find("2 non-finite"), std::string::npos) << s.error().message;
    EXPECT_NE(s.error().message.find("x=3 y=5 channel 1"), std::string::npos);
    EXPECT_NE(s.error().message.find(path), std::string::npos);
    EXPECT_FALSE(fs::exists(path));
    EXPECT_EQ(dir.entries().size(), 0u);
}

TEST(WritePng, RejectsEmptyImagesAndBadOptions) {
    TempDir dir;
    const std::string path = dir.file("x.png");
    EXPECT_FALSE(writePng(ImageRGB(), path, {}));
    EXPECT_FALSE(writePng(ImageRGB(0, 5), path, {}));
    ToneMapOptions bad;
    bad.exposure_stops = std::numeric_limits<double>::quiet_NaN();
    const Status s = writePng(gradient(2, 2), path, bad);
    ASSERT_FALSE(s);
    EXPECT_NE(s.error().message.find("exposure_stops"), std::string::npos);
    bad = {};
    bad.log_range_stops = 0.0;
    EXPECT_FALSE(validateToneMapOptions(bad));
    EXPECT_EQ(dir.entries().size(), 0u);
}

TEST(WritePng, WritesAOneByOneImage) {
    TempDir dir;
    const std::string path = dir.file("one.png");
    ImageRGB one(1, 1);
    one.at(0, 0)[0] = 1.0f;
    ASSERT_TRUE(writePng(one, path, {}));
    const Result<PreviewImage> read = readPng(path);
    ASSERT_TRUE(read);
    ASSERT_EQ(read->width, 1);
    EXPECT_EQ(read->pixels[0], std::lround(toneCurve(1.0, {}) * 255.0));
    EXPECT_EQ(read->pixels[2], 0);
}

TEST(ReadPng, ReportsMissingAndBrokenFiles) {
    TempDir dir;
    const std::string missing = dir.file("missing.png");
    const Result<PreviewImage> a = readPng(missing);
    ASSERT_FALSE(a);
    EXPECT_EQ(a.error().code, ErrorCode::NotFound);
    const std::string broken = dir.file("broken.png");
    std::ofstream(broken) << "not a png";
    const Result<PreviewImage> b = readPng(broken);
    ASSERT_FALSE(b);
    EXPECT_EQ(b.error().code, ErrorCode::ParseError);
    EXPECT_NE(b.error().message.find(broken), std::string::npos);
}

// The 99th percentile (or any other) of the lit pixels' largest channel goes to 1; dark,
// negative and non-finite values do not count; an image with nothing lit keeps 0 stops.
TEST(AutoExposure, ScalesAPercentileOfTheLitPixelsToOne) {
    ImageRGB image(101, 2);  // row 0: 0.001 .. 0.101 in green; row 1: dark, negative, NaN, inf
    for (int64_t x = 0; x < 101; ++x) image.at(x, 0)[1] = 0.001f * static_cast<float>(x + 1);
    image.at(0, 1)[0] = -5.0f;
    image.at(1, 1)[2] = std::numeric_limits<float>::quiet_NaN();
    image.at(2, 1)[0] = std::numeric_limits<float>::infinity();
    EXPECT_NEAR(autoExposureStops(image, 0.5), -std::log2(0.051), 1e-6);
    EXPECT_NEAR(autoExposureStops(image, 1.0), -std::log2(0.101), 1e-6);
    EXPECT_NEAR(autoExposureStops(image), -std::log2(0.100), 1e-6);  // the 99th of 101
    // A light a million times brighter than its ghosts moves the percentile by one pixel only.
    image.at(50, 1)[0] = 1e6f;
    EXPECT_NEAR(autoExposureStops(image, 0.5), -std::log2(0.052), 1e-6);
    EXPECT_EQ(autoExposureStops(ImageRGB(8, 8)), 0.0);
    ImageRGB faint(1, 1);
    faint.at(0, 0)[0] = 1e-30f;
    EXPECT_EQ(autoExposureStops(faint), 64.0);  // clamped to what ToneMapOptions accepts
}

TEST(ToneCurve, IsMonotonicAndMapsZeroToZero) {
    for (const ToneCurve curve : {ToneCurve::Reinhard, ToneCurve::Log}) {
        for (const double exposure : {-10.0, 0.0, 3.5}) {
            ToneMapOptions o;
            o.curve = curve;
            o.exposure_stops = exposure;
            EXPECT_EQ(toneCurve(0.0, o), 0.0);
            EXPECT_EQ(toneCurve(-5.0, o), 0.0);
            double previous = 0.0;
            for (double stops = -40.0; stops <= 40.0; stops += 0.01) {
                const double y = toneCurve(std::exp2(stops), o);
                ASSERT_GE(y, previous) << stops;
                ASSERT_LE(y, 1.0);
                previous = y;
            }
        }
    }
}

TEST(ToneCurve, ReinhardKeepsMidTonesAndCompressesHighlights) {
    const ToneMapOptions o;
    // L / (1 + L) at 1 is 0.5, sRGB-encoded 0.7354.
    EXPECT_NEAR(toneCurve(1.0, o), 0.7354, 1e-4);
    EXPECT_LT(toneCurve(1e3, o), 1.0);
    EXPECT_GT(toneCurve(1e3, o), 0.999);
    ToneMapOptions brighter;
    brighter.exposure_stops = 1.0;
    EXPECT_DOUBLE_EQ(toneCurve(0.5, brighter), toneCurve(1.0, o));
}

TEST(ToneCurve, LogModeIsLinearInStops) {
    ToneMapOptions o;
    o.curve = ToneCurve::Log;
    o.log_range_stops = 16.0;
    EXPECT_DOUBLE_EQ(toneCurve(1.0, o), 1.0);
    EXPECT_DOUBLE_EQ(toneCurve(std::exp2(-8.0), o), 0.5);
    EXPECT_DOUBLE_EQ(toneCurve(std::exp2(-16.0), o), 0.0);
    EXPECT_DOUBLE_EQ(toneCurve(std::exp2(-30.0), o), 0.0);
    EXPECT_DOUBLE_EQ(toneCurve(1e30, o), 1.0);
}

TEST(ToneMap, HugeValuesSaturateWithoutOverflow) {
    ImageRGB image(3, 1);
    for (float& v : image.pixels) v = std::numeric_limits<float>::max();
    image.at(1, 0)[0] = std::numeric_limits<float>::denorm_min();
    for (const ToneCurve curve : {ToneCurve::Reinhard, ToneCurve::Log}) {
        ToneMapOptions o;
        o.curve = curve;
        o.exposure_stops = 64.0;
        const Result<PreviewImage> p = toneMap(image, o);
        ASSERT_TRUE(p);
        EXPECT_EQ(p->pixels[0], 255);
        EXPECT_EQ(p->pixels[8], 255);
        o.exposure_stops = -64.0;
        const Result<PreviewImage> dark = toneMap(image, o);
        ASSERT_TRUE(dark);
        EXPECT_EQ(dark->pixels[3], 0);
    }
}

}  // namespace
}  // namespace flarelab::render
