#include "hdr/exr.h"

#include <ImfHeader.h>
#include <ImfInputFile.h>
#include <ImfStandardAttributes.h>
#include <ImfThreading.h>
#include <gtest/gtest.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <csignal>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "tests/test_files.h"
#include "tests/test_paths.h"

namespace flarelab::hdr {
namespace {

using flarelab::testing::contains;
using flarelab::testing::readText;
using flarelab::testing::TempDir;
using flarelab::testing::writeText;

namespace fs = std::filesystem;

Result<ExrImage> readBytesAsExr(const std::string& bytes, const std::string& name = "test") {
    return readExrFromMemory(
        std::span(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()), name);
}

// A smooth image with a little seeded noise: compresses like a real frame.
ImageRGB smoothImage(int64_t width, int64_t height, uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<float> noise(0.0f, 0.01f);
    ImageRGB image(width, height);
    for (int64_t y = 0; y < height; ++y)
        for (int64_t x = 0; x < width; ++x)
            for (int c = 0; c < 3; ++c)
                image.at(x, y)[c] = 0.5f + 0.4f * std::sin(0.05f * x + 0.03f * y + c) + noise(rng);
    return image;
}

bool bitwiseEqual(const ImageRGB& a, const ImageRGB& b) {
    return a.width == b.width && a.height == b.height && a.pixels.size() == b.pixels.size() &&
           std::memcmp(a.pixels.data(), b.pixels.data(), a.pixels.size() * sizeof(float)) == 0;
}

ExrMetadata fullMetadata() {
    ExrMetadata meta;
    meta.angle_deg = 12.4;
    meta.roll_deg = -0.0;
    meta.exposure_times_s = {0.25, 1.0, 4.0, 1.0 / 3.0, 1.0 / 8000.0};
    meta.gain = 2.5;
    meta.camera = "sim-cam 36x24 mm, 4000x2667";
    meta.lens = "double-gauss-tronnier-50mm f/2";
    meta.merge_method = "debevec weighted, hat";
    meta.software_version = "flarelab 0.1.0";
    meta.extra["rig"] = "bench 2";
    meta.extra["binary"] = std::string("a\0b", 3);
    meta.extra[std::string(kExrMaxExtraKeyLength, 'k')] = "longest key";
    return meta;
}

// ---------------------------------------------------------------------------------------------
// A hand-made EXR writer, independent of OpenEXR: single-part scan lines, no compression, any
// channels, data window and extra header attributes, so the tests can build files the library's
// writer never makes (UINT or Y channels, NaN pixels, wrong attribute types, absurd windows).

struct RawChannel {
    std::string name;
    int type = 2;  // 0 UINT, 1 HALF, 2 FLOAT
};

struct RawAttribute {
    std::string name;
    std::string type;
    std::string value;
};

void put32(std::string& out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>(v >> (8 * i)));
}
void put64(std::string& out, uint64_t v) {
    for (int i = 0; i < 8; ++i) out.push_back(static_cast<char>(v >> (8 * i)));
}
std::string le32(uint32_t v) {
    std::string out;
    put32(out, v);
    return out;
}
std::string leDouble(double v) {
    std::string out;
    put64(out, std::bit_cast<uint64_t>(v));
    return out;
}
std::string box(int32_t x0, int32_t y0, int32_t x1, int32_t y1) {
    return le32(x0) + le32(y0) + le32(x1) + le32(y1);
}

// `bits(channel index, x, y)` gives each sample's bits (the low 16 for half).
std::string rawExr(int32_t x0,
                   int32_t y0,
                   int32_t x1,
                   int32_t y1,
                   std::vector<RawChannel> channels,
                   const std::vector<RawAttribute>& extra,
                   const std::function<uint32_t(size_t, int32_t, int32_t)>& bits) {
    std::sort(channels.begin(), channels.end(),
              [](const RawChannel& a, const RawChannel& b) { return a.name < b.name; });
    std::string chlist;
    for (const RawChannel& c : channels) {
        chlist += c.name + '\0';
        put32(chlist, c.type);
        chlist += std::string(4, '\0');  // pLinear, reserved
        put32(chlist, 1);
        put32(chlist, 1);
    }
    chlist += '\0';
    std::vector<RawAttribute> attributes = {
        {"channels", "chlist", chlist},
        {"compression", "compression", std::string(1, '\0')},
        {"dataWindow", "box2i", box(x0, y0, x1, y1)},
        {"displayWindow", "box2i", box(x0, y0, x1, y1)},
        {"lineOrder", "lineOrder", std::string(1, '\0')},
        {"pixelAspectRatio", "float", le32(std::bit_cast<uint32_t>(1.0f))},
        {"screenWindowCenter", "v2f", std::string(8, '\0')},
        {"screenWindowWidth", "float", le32(std::bit_cast<uint32_t>(1.0f))},
    };
    attributes.insert(attributes.end(), extra.begin(), extra.end());

    std::string out;
    put32(out, 20000630);
    put32(out, 2);
    for (const RawAttribute& a : attributes) {
        out += a.name + '\0' + a.type + '\0';
        put32(out, static_cast<uint32_t>(a.value.size()));
        out += a.value;
    }
    out += '\0';
    const int64_t height = int64_t{y1} - y0 + 1;
    if (height > 4096 || int64_t{x1} - x0 + 1 > 4096)
        return out;  // a header for the size checks; no pixels behind it
    const size_t table = out.size();
    out += std::string(static_cast<size_t>(height) * 8, '\0');
    for (int32_t y = y0; y <= y1; ++y) {
        const uint64_t offset = out.size();
        std::memcpy(&out[table + static_cast<size_t>(y - y0) * 8], &offset, 8);
        std::string line;
        for (size_t c = 0; c < channels.size(); ++c)
            for (int32_t x = x0; x <= x1; ++x) {
                const uint32_t v = bits(c, x, y);
                line.push_back(static_cast<char>(v));
                line.push_back(static_cast<char>(v >> 8));
                if (channels[c].type != 1) {
                    line.push_back(static_cast<char>(v >> 16));
                    line.push_back(static_cast<char>(v >> 24));
                }
            }
        put32(out, static_cast<uint32_t>(y));
        put32(out, static_cast<uint32_t>(line.size()));
        out += line;
    }
    return out;
}

constexpr uint32_t kHalfOne = 0x3c00;
constexpr uint32_t kHalfTwo = 0x4000;
constexpr uint32_t kHalfNaN = 0x7e00;
uint32_t floatBits(float v) { return std::bit_cast<uint32_t>(v); }

std::string rgbFloatExr(const std::vector<RawAttribute>& extra) {
    return rawExr(0, 0, 3, 2, {{"R"}, {"G"}, {"B"}}, extra,
                  [](size_t c, int32_t x, int32_t y) { return floatBits(c + x + 10.0f * y); });
}

// ---------------------------------------------------------------------------------------------
// Writing and reading back.

TEST(WriteExr, FloatRoundTripIsBitwiseIdentical) {
    TempDir dir;
    std::mt19937_64 rng(1);
    std::uniform_real_distribution<double> exponent(-44.0, 38.0);
    std::bernoulli_distribution negative(0.3);
    ImageRGB image(37, 23);
    for (float& v : image.pixels) {
        v = static_cast<float>(std::pow(10.0, exponent(rng)));
        if (negative(rng)) v = -v;
    }
    image.pixels[0] = 0.0f;
    image.pixels[1] = -0.0f;
    image.pixels[2] = std::numeric_limits<float>::denorm_min();
    image.pixels[3] = std::numeric_limits<float>::max();
    const std::string path = dir.file("frame.exr");
    const auto report = writeExr(path, image, {});
    ASSERT_TRUE(report) << report.error().message;
    EXPECT_FALSE(report->half);
    EXPECT_TRUE(report->note.empty());
    const auto read = readExr(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_TRUE(bitwiseEqual(read->image, image));
    EXPECT_EQ(read->origin_x, 0);
    EXPECT_EQ(read->origin_y, 0);
    EXPECT_EQ(dir.entries(), std::vector<std::string>{"frame.exr"});
}

TEST(WriteExr, HalfRoundTripIsWithinHalfPrecision) {
    TempDir dir;
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> log2_value(-14.0, std::log2(kHalfMax));
    std::bernoulli_distribution negative(0.3);
    ImageRGB image(31, 17);
    for (float& v : image.pixels) {
        v = static_cast<float>(std::exp2(log2_value(rng)));
        if (negative(rng)) v = -v;
    }
    image.pixels[0] = 0.0f;
    image.pixels[1] = static_cast<float>(kHalfMax);
    image.pixels[2] = static_cast<float>(kHalfMinNormal);
    for (const ExrPixelType type : {ExrPixelType::Half, ExrPixelType::HalfWhereFits}) {
        const std::string path = dir.file("half.exr");
        ExrWriteOptions options;
        options.pixel_type = type;
        const auto report = writeExr(path, image, {}, options);
        ASSERT_TRUE(report) << report.error().message;
        EXPECT_TRUE(report->half);
        EXPECT_TRUE(report->note.empty());
        const auto read = readExr(path);
        ASSERT_TRUE(read) << read.error().message;
        ASSERT_EQ(read->image.pixels.size(), image.pixels.size());
        for (size_t i = 0; i < image.pixels.size(); ++i)
            EXPECT_LE(std::abs(read->image.pixels[i] - image.pixels[i]),
                      std::abs(image.pixels[i]) * std::exp2(-11.0))
                << "value " << i << ": " << image.pixels[i];
        EXPECT_EQ(read->image.pixels[1], static_cast<float>(kHalfMax));
        // Half takes two bytes a value instead of four.
        EXPECT_LT(fs::file_size(path), 31 * 17 * 3 * 4);
    }
}

TEST(WriteExr, HalfRefusesAValueBeyondHalfRange) {
    TempDir dir;
    ImageRGB image = smoothImage(5, 4, 3);
    image.at(2, 1)[1] = 70000.0f;
    ExrWriteOptions options;
    options.pixel_type = ExrPixelType::Half;
    const std::string path = dir.file("half.exr");
    const auto report = writeExr(path, image, {}, options);
    ASSERT_FALSE(report);
    EXPECT_EQ(report.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(contains(report.error().message, path)) << report.error().message;
    EXPECT_TRUE(contains(report.error().message, "pixel (2, 1) channel G"))
        << report.error().message;
    EXPECT_TRUE(dir.entries().empty());
}

TEST(WriteExr, HalfWhereFitsFallsBackToFloatAndSaysWhy) {
    TempDir dir;
    ImageRGB image = smoothImage(5, 4, 4);
    image.at(2, 1)[1] = 70000.0f;
    ExrWriteOptions options;
    options.pixel_type = ExrPixelType::HalfWhereFits;
    const std::string path = dir.file("half.exr");
    const auto report = writeExr(path, image, {}, options);
    ASSERT_TRUE(report) << report.error().message;
    EXPECT_FALSE(report->half);
    EXPECT_TRUE(contains(report->note, "pixel (2, 1) channel G")) << report->note;
    const auto read = readExr(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_TRUE(bitwiseEqual(read->image, image));
}

TEST(WriteExr, TinyValuesKeepFloatUnlessPrecisionLossIsAccepted) {
    TempDir dir;
    ImageRGB image = smoothImage(3, 3, 5);
    image.at(1, 2)[2] = 1e-6f;
    ExrWriteOptions options;
    options.pixel_type = ExrPixelType::HalfWhereFits;
    const auto kept = writeExr(dir.file("a.exr"), image, {}, options);
    ASSERT_TRUE(kept) << kept.error().message;
    EXPECT_FALSE(kept->half);
    EXPECT_TRUE(contains(kept->note, "pixel (1, 2) channel B")) << kept->note;

    options.half_min_abs = 0.0;
    const auto half = writeExr(dir.file("b.exr"), image, {}, options);
    ASSERT_TRUE(half) << half.error().message;
    EXPECT_TRUE(half->half);
    const auto read = readExr(dir.file("b.exr"));
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_NEAR(read->image.at(1, 2)[2], 1e-6f, 6e-8f);  // a half denormal step
}

TEST(WriteExr, MetadataRoundTrips) {
    TempDir dir;
    const ExrMetadata meta = fullMetadata();
    const std::string path = dir.file("meta.exr");
    ASSERT_TRUE(writeExr(path, smoothImage(4, 4, 6), meta));
    const auto read = readExr(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->meta, meta);
    EXPECT_EQ(read->meta.exposure_times_s[3], 1.0 / 3.0);  // exactly, not rounded through float

    ASSERT_TRUE(writeExr(path, smoothImage(4, 4, 6), {}));
    const auto empty = readExr(path);
    ASSERT_TRUE(empty) << empty.error().message;
    EXPECT_EQ(empty->meta, ExrMetadata{});
}

// Every standard attribute set, each value a float exactly.
ExrStandardAttributes standardAttributes() {
    ExrStandardAttributes standard;
    standard.cap_date = "2026:11:29 08:04:02";
    standard.utc_offset_s = -3600.0;
    standard.exp_time_s = 1.0;
    standard.aperture = 11.0;
    standard.iso_speed = 100.0;
    standard.chromaticities = ExrChromaticities{{0.640000045f, 0.330000013f},
                                                {0.300000012f, 0.600000024f},
                                                {0.150000006f, 0.0599999987f},
                                                {0.312700003f, 0.328999996f}};
    return standard;
}

TEST(WriteExr, OpenExrStandardAttributesRoundTripAndOpenExrReadsThem) {
    TempDir dir;
    ExrMetadata meta = fullMetadata();
    meta.standard = standardAttributes();
    const std::string path = dir.file("standard.exr");
    ASSERT_TRUE(writeExr(path, smoothImage(4, 4, 6), meta));
    const auto read = readExr(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->meta, meta);

    // OpenEXR's own accessors (what other tools call) see them.
    Imf::InputFile file(path.c_str());
    const Imf::Header& header = file.header();
    ASSERT_TRUE(Imf::hasCapDate(header) && Imf::hasUtcOffset(header) && Imf::hasExpTime(header) &&
                Imf::hasAperture(header) && Imf::hasIsoSpeed(header) &&
                Imf::hasChromaticities(header));
    EXPECT_EQ(Imf::capDate(header), "2026:11:29 08:04:02");
    EXPECT_EQ(Imf::utcOffset(header), -3600.0f);
    EXPECT_EQ(Imf::expTime(header), 1.0f);
    EXPECT_EQ(Imf::aperture(header), 11.0f);
    EXPECT_EQ(Imf::isoSpeed(header), 100.0f);
    EXPECT_EQ(Imf::chromaticities(header).white, Imath::V2f(0.3127f, 0.329f));

    // A value that is not a float exactly reads back as the nearest float.
    meta.standard = {};
    meta.standard.aperture = 5.6;
    ASSERT_TRUE(writeExr(path, smoothImage(4, 4, 6), meta));
    const auto rounded = readExr(path);
    ASSERT_TRUE(rounded);
    EXPECT_EQ(*rounded->meta.standard.aperture, static_cast<double>(5.6f));
    EXPECT_FALSE(rounded->meta.standard.exp_time_s);
    EXPECT_TRUE(rounded->meta.standard.cap_date.empty());
}

TEST(WriteExr, RefusesStandardAttributesOpenExrCannotHold) {
    TempDir dir;
    const std::vector<std::pair<std::function<void(ExrStandardAttributes&)>, std::string>> cases = {
        {[](ExrStandardAttributes& s) { s.cap_date = "2026-11-29 08:04:02"; }, "capDate"},
        {[](ExrStandardAttributes& s) { s.cap_date = "2026:13:29 08:04:02"; }, "capDate"},
        {[](ExrStandardAttributes& s) { s.exp_time_s = 0.0; }, "expTime"},
        {[](ExrStandardAttributes& s) { s.exp_time_s = 1e-50; }, "expTime"},
        {[](ExrStandardAttributes& s) { s.aperture = 1e40; }, "aperture"},
        {[](ExrStandardAttributes& s) { s.iso_speed = std::nan(""); }, "isoSpeed"},
        {[](ExrStandardAttributes& s) { s.utc_offset_s = 1e6; }, "utcOffset"},
        {[](ExrStandardAttributes& s) { s.chromaticities->red[0] = 1.5; }, "chromaticities"}};
    for (const auto& [edit, attribute] : cases) {
        ExrMetadata meta;
        meta.standard = standardAttributes();
        edit(meta.standard);
        const auto written = writeExr(dir.file("bad.exr"), smoothImage(2, 2, 1), meta);
        ASSERT_FALSE(written) << attribute;
        EXPECT_EQ(written.error().code, ErrorCode::InvalidArgument);
        EXPECT_TRUE(contains(written.error().message, attribute)) << written.error().message;
    }
    EXPECT_TRUE(dir.entries().empty());
}

TEST(WriteExr, EveryCompressionRoundTrips) {
    TempDir dir;
    const ImageRGB image = smoothImage(64, 40, 7);
    for (const ExrCompression compression :
         {ExrCompression::None, ExrCompression::Zip, ExrCompression::Piz}) {
        for (const ExrPixelType type : {ExrPixelType::Float, ExrPixelType::Half}) {
            SCOPED_TRACE(static_cast<int>(compression) * 10 + static_cast<int>(type));
            ExrWriteOptions options;
            options.compression = compression;
            options.pixel_type = type;
            const std::string path = dir.file("c.exr");
            ASSERT_TRUE(writeExr(path, image, fullMetadata(), options));
            const auto read = readExr(path);
            ASSERT_TRUE(read) << read.error().message;
            EXPECT_EQ(read->meta, fullMetadata());
            if (type == ExrPixelType::Float) {
                EXPECT_TRUE(bitwiseEqual(read->image, image));
            } else {
                for (size_t i = 0; i < image.pixels.size(); ++i)
                    ASSERT_NEAR(read->image.pixels[i], image.pixels[i], 1e-3f);
            }
        }
    }
}

TEST(WriteExr, OnePixelRoundTrips) {
    TempDir dir;
    ImageRGB image(1, 1);
    image.pixels = {1.0f, 2.0f, 3.0f};
    ASSERT_TRUE(writeExr(dir.file("one.exr"), image, {}));
    const auto read = readExr(dir.file("one.exr"));
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_TRUE(bitwiseEqual(read->image, image));
}

TEST(WriteExr, LargeImageRoundTrips) {
    TempDir dir;
    const ImageRGB image = smoothImage(2000, 1000, 8);
    ASSERT_TRUE(writeExr(dir.file("large.exr"), image, fullMetadata()));
    const auto read = readExr(dir.file("large.exr"));
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_TRUE(bitwiseEqual(read->image, image));
}

// With useExrThreads OpenEXR compresses line blocks on its thread pool: the file's bytes and what
// is read back may not depend on how many threads there are, or whether there are any. The pool
// is given back afterwards: the death tests of this binary fork, and a child cannot use it.
TEST(WriteExr, AnyNumberOfThreadsWritesAndReadsTheSameBytes) {
    TempDir dir;
    const ImageRGB image = smoothImage(640, 300, 9);
    const int before = Imf::globalThreadCount();
    const int pool = useExrThreads();
    EXPECT_GE(pool, 1);
    EXPECT_EQ(useExrThreads(3), 3);
    for (const ExrCompression compression : {ExrCompression::Zip, ExrCompression::Piz}) {
        SCOPED_TRACE(static_cast<int>(compression));
        ExrWriteOptions options;
        options.compression = compression;
        std::vector<std::string> bytes;
        for (const int threads : {pool, 0, 3}) {
            Imf::setGlobalThreadCount(threads);
            const std::string path = dir.file("t" + std::to_string(threads) + ".exr");
            ASSERT_TRUE(writeExr(path, image, fullMetadata(), options));
            bytes.push_back(readText(path));
            const auto read = readExr(path);
            ASSERT_TRUE(read) << read.error().message;
            EXPECT_TRUE(bitwiseEqual(read->image, image)) << threads << " threads";
        }
        EXPECT_GT(bytes[0].size(), 1000u);
        EXPECT_EQ(bytes[1], bytes[0]) << "no threads";
        EXPECT_EQ(bytes[2], bytes[0]) << "3 threads";
    }
    Imf::setGlobalThreadCount(before);
}

TEST(WriteExr, RefusesNonFinitePixelsAndKeepsTheOldFile) {
    TempDir dir;
    const std::string path = dir.file("frame.exr");
    ASSERT_TRUE(writeExr(path, smoothImage(6, 5, 9), {}));
    const std::string before = readText(path);
    for (const float bad :
         {std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity(),
          -std::numeric_limits<float>::infinity()}) {
        ImageRGB image = smoothImage(6, 5, 10);
        image.at(4, 3)[2] = bad;
        image.at(5, 4)[0] = bad;  // later in the image; the first one is named
        const auto report = writeExr(path, image, {});
        ASSERT_FALSE(report);
        EXPECT_EQ(report.error().code, ErrorCode::InvalidArgument);
        EXPECT_TRUE(contains(report.error().message, path)) << report.error().message;
        EXPECT_TRUE(contains(report.error().message, "pixel (4, 3) channel B"))
            << report.error().message;
        EXPECT_EQ(readText(path), before);
        EXPECT_EQ(dir.entries(), std::vector<std::string>{"frame.exr"});
    }
}

TEST(WriteExr, RefusesInvalidImagesAndMetadata) {
    TempDir dir;
    const std::string path = dir.file("x.exr");
    EXPECT_FALSE(writeExr(path, ImageRGB(0, 5), {}));
    EXPECT_FALSE(writeExr(path, ImageRGB(int64_t{1} << 16, 1), {}));
    ImageRGB short_pixels(2, 2);
    short_pixels.pixels.pop_back();
    EXPECT_FALSE(writeExr(path, short_pixels, {}));

    const ImageRGB image = smoothImage(2, 2, 11);
    ExrMetadata meta;
    meta.angle_deg = std::numeric_limits<double>::quiet_NaN();
    auto report = writeExr(path, image, meta);
    ASSERT_FALSE(report);
    EXPECT_TRUE(contains(report.error().message, kExrAttrAngle)) << report.error().message;
    meta = {};
    meta.exposure_times_s = {1.0, 0.0};
    report = writeExr(path, image, meta);
    ASSERT_FALSE(report);
    EXPECT_TRUE(contains(report.error().message, kExrAttrExposureTimes)) << report.error().message;
    meta = {};
    meta.extra[""] = "x";
    EXPECT_FALSE(writeExr(path, image, meta));
    meta = {};
    meta.extra[std::string(kExrMaxExtraKeyLength + 1, 'k')] = "x";
    EXPECT_FALSE(writeExr(path, image, meta));
    EXPECT_TRUE(dir.entries().empty());
}

// ---------------------------------------------------------------------------------------------
// Interrupted writes.

TEST(WriteExr, FailedRenameLeavesNoTemporaryFile) {
    TempDir dir;
    // A directory where the file should go: everything is written, and the rename fails.
    const std::string path = dir.file("taken");
    fs::create_directory(path);
    writeText(dir.file("taken/inside"), "keep");
    const auto report = writeExr(path, smoothImage(8, 8, 12), {});
    ASSERT_FALSE(report);
    EXPECT_EQ(report.error().code, ErrorCode::IoError);
    EXPECT_TRUE(contains(report.error().message, "rename")) << report.error().message;
    EXPECT_EQ(dir.entries(), std::vector<std::string>{"taken"});
    EXPECT_EQ(readText(dir.file("taken/inside")), "keep");
}

TEST(WriteExr, WriteFailingMidwayKeepsTheOldFile) {
    TempDir dir;
    const std::string path = dir.file("frame.exr");
    ASSERT_TRUE(writeExr(path, smoothImage(4, 4, 13), fullMetadata()));
    const std::string before = readText(path);

    // A file size limit makes the disk "full" after 16 KiB of a 48 KiB file. The signal it
    // raises is ignored, so write() reports EFBIG as a full disk reports ENOSPC.
    std::mt19937_64 rng(14);
    std::uniform_real_distribution<float> noise(0.0f, 1.0f);
    ImageRGB image(64, 64);
    for (float& v : image.pixels) v = noise(rng);
    ExrWriteOptions options;
    options.compression = ExrCompression::None;
    rlimit old_limit{};
    ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &old_limit), 0);
    rlimit limit = old_limit;
    limit.rlim_cur = 16 * 1024;
    const auto old_handler = std::signal(SIGXFSZ, SIG_IGN);
    ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limit), 0);
    const auto report = writeExr(path, image, {}, options);
    ::setrlimit(RLIMIT_FSIZE, &old_limit);
    std::signal(SIGXFSZ, old_handler);

    ASSERT_FALSE(report);
    EXPECT_EQ(report.error().code, ErrorCode::IoError);
    EXPECT_TRUE(contains(report.error().message, path)) << report.error().message;
    EXPECT_EQ(readText(path), before);
    EXPECT_EQ(dir.entries(), std::vector<std::string>{"frame.exr"});
    const auto read = readExr(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->meta, fullMetadata());
}

TEST(WriteExr, MissingDirectoryIsAnError) {
    TempDir dir;
    const auto report = writeExr(dir.file("no/such/dir.exr"), smoothImage(2, 2, 15), {});
    ASSERT_FALSE(report);
    EXPECT_EQ(report.error().code, ErrorCode::IoError);
    EXPECT_TRUE(dir.entries().empty());
}

// ---------------------------------------------------------------------------------------------
// Reading what other programs write, and what no program should.

TEST(ReadExr, MemoryAndFileReadersAgree) {
    TempDir dir;
    const std::string path = dir.file("frame.exr");
    ASSERT_TRUE(writeExr(path, smoothImage(9, 7, 16), fullMetadata()));
    const auto from_file = readExr(path);
    const auto from_memory = readBytesAsExr(readText(path));
    ASSERT_TRUE(from_file) << from_file.error().message;
    ASSERT_TRUE(from_memory) << from_memory.error().message;
    EXPECT_TRUE(bitwiseEqual(from_file->image, from_memory->image));
    EXPECT_EQ(from_file->meta, from_memory->meta);
}

TEST(ReadExr, HandMadeFloatFileReads) {
    const auto read = readBytesAsExr(rgbFloatExr({}));
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->image.width, 4);
    EXPECT_EQ(read->image.height, 3);
    // rawExr numbers channels in name order: B 0, G 1, R 2.
    EXPECT_EQ(read->image.at(3, 2)[0], 2 + 3 + 20.0f);
    EXPECT_EQ(read->image.at(3, 2)[2], 0 + 3 + 20.0f);
    EXPECT_EQ(read->meta, ExrMetadata{});
}

TEST(ReadExr, DataWindowAwayFromTheOriginIsKept) {
    const std::string bytes = rawExr(
        -3, 20, 1, 22, {{"R", 1}, {"G", 1}, {"B", 1}}, {},
        [](size_t c, int32_t x, int32_t) { return c == 0 && x == -3 ? kHalfTwo : kHalfOne; });
    const auto read = readBytesAsExr(bytes);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->origin_x, -3);
    EXPECT_EQ(read->origin_y, 20);
    EXPECT_EQ(read->image.width, 5);
    EXPECT_EQ(read->image.height, 3);
    EXPECT_EQ(read->image.at(0, 0)[2], 2.0f);  // channel 0 in name order is B
    EXPECT_EQ(read->image.at(0, 0)[0], 1.0f);
    EXPECT_EQ(read->image.at(4, 2)[2], 1.0f);
}

TEST(ReadExr, LuminanceBecomesGray) {
    const std::string bytes = rawExr(0, 0, 2, 1, {{"Y", 2}}, {}, [](size_t, int32_t x, int32_t y) {
        return floatBits(0.5f * x + y);
    });
    const auto read = readBytesAsExr(bytes);
    ASSERT_TRUE(read) << read.error().message;
    for (int64_t y = 0; y < 2; ++y)
        for (int64_t x = 0; x < 3; ++x)
            for (int c = 0; c < 3; ++c) EXPECT_EQ(read->image.at(x, y)[c], 0.5f * x + y);
}

TEST(ReadExr, AlphaIsIgnored) {
    const std::string bytes =
        rawExr(0, 0, 1, 1, {{"R", 1}, {"G", 1}, {"B", 1}, {"A", 1}}, {},
               [](size_t c, int32_t, int32_t) { return c == 0 ? kHalfNaN : kHalfOne; });
    // Channels are stored by name: A first. Its NaN must not matter.
    const auto read = readBytesAsExr(bytes);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->image.pixels, std::vector<float>(12, 1.0f));
}

TEST(ReadExr, NonFinitePixelIsNamed) {
    const std::string bytes = rawExr(10, 5, 13, 7, {{"R", 1}, {"G", 1}, {"B", 1}}, {},
                                     [](size_t c, int32_t x, int32_t y) {
                                         return c == 1 && x == 12 && y == 6 ? kHalfNaN : kHalfOne;
                                     });
    // Channel index 1 in name order (B, G, R) is G.
    const auto read = readBytesAsExr(bytes, "nan.exr");
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(read.error().message, "nan.exr: pixel (12, 6) channel G"))
        << read.error().message;
}

TEST(ReadExr, UintChannelIsUnsupported) {
    const std::string bytes = rawExr(0, 0, 1, 1, {{"R", 0}, {"G", 2}, {"B", 2}}, {},
                                     [](size_t, int32_t, int32_t) { return 1u; });
    const auto read = readBytesAsExr(bytes);
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
    EXPECT_TRUE(contains(read.error().message, "channel R is UINT")) << read.error().message;
}

TEST(ReadExr, MissingChannelIsNamed) {
    const std::string bytes = rawExr(0, 0, 1, 1, {{"R"}, {"G"}}, {},
                                     [](size_t, int32_t, int32_t) { return floatBits(1.0f); });
    const auto read = readBytesAsExr(bytes);
    ASSERT_FALSE(read);
    EXPECT_TRUE(contains(read.error().message, "no channel B")) << read.error().message;

    const std::string none =
        rawExr(0, 0, 1, 1, {{"Z"}}, {}, [](size_t, int32_t, int32_t) { return floatBits(1.0f); });
    const auto read_none = readBytesAsExr(none);
    ASSERT_FALSE(read_none);
    EXPECT_TRUE(contains(read_none.error().message, "neither R, G, B nor Y"))
        << read_none.error().message;
}

TEST(ReadExr, HugeDataWindowIsRefusedBeforeAllocating) {
    const auto fill = [](size_t, int32_t, int32_t) { return 0u; };
    for (const auto& [x0, y0, x1, y1] :
         {std::array<int32_t, 4>{-(1 << 30), 0, 1 << 30, 0},
          std::array<int32_t, 4>{0, std::numeric_limits<int32_t>::min(), 0,
                                 std::numeric_limits<int32_t>::max()},
          std::array<int32_t, 4>{0, 0, (1 << 15), 0},
          std::array<int32_t, 4>{0, 0, (1 << 15) - 1, (1 << 14)}}) {
        const auto read = readBytesAsExr(rawExr(x0, y0, x1, y1, {{"R"}, {"G"}, {"B"}}, {}, fill));
        ASSERT_FALSE(read);
        EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
        EXPECT_TRUE(contains(read.error().message, "exceeds the limit")) << read.error().message;
    }
    const auto inverted = readBytesAsExr(rawExr(5, 0, 4, 0, {{"R"}, {"G"}, {"B"}}, {}, fill));
    ASSERT_FALSE(inverted);
    EXPECT_TRUE(contains(inverted.error().message, "empty data window"))
        << inverted.error().message;
}

TEST(ReadExr, FlarelabAttributesAreChecked) {
    const RawAttribute version{kExrAttrVersion, "int", le32(1)};
    struct Case {
        std::vector<RawAttribute> attributes;
        std::string expected;
    };
    const Case cases[] = {
        {{version, {kExrAttrAngle, "float", le32(floatBits(1.0f))}},
         "'flarelab.angle_deg' is not of type double"},
        {{version, {kExrAttrCamera, "double", leDouble(1.0)}},
         "'flarelab.camera' is not of type string"},
        {{version, {kExrAttrGain, "double", leDouble(std::numeric_limits<double>::infinity())}},
         "'flarelab.gain' is not finite"},
        {{version, {kExrAttrExposureTimes, "string", "0.25  1"}}, "'flarelab.exposure_times_s'"},
        {{version, {kExrAttrExposureTimes, "string", "0.25 -1"}}, "'flarelab.exposure_times_s'"},
        {{version, {kExrAttrExposureTimes, "string", ""}}, "'flarelab.exposure_times_s'"},
        {{version, {"flarelab.colour", "string", "red"}}, "'flarelab.colour' is not a flarelab"},
        {{version, {"flarelab.extra.", "string", "x"}}, "'flarelab.extra.' is not a flarelab"},
        {{{kExrAttrAngle, "double", leDouble(1.0)}}, "flarelab.version is not"},
        {{{kExrAttrVersion, "string", "1"}}, "'flarelab.version' is not of type int"},
        {{{kExrAttrVersion, "int", le32(2)}}, "flarelab.version is 2"},
    };
    for (const Case& c : cases) {
        const auto read = readBytesAsExr(rgbFloatExr(c.attributes), "attr.exr");
        ASSERT_FALSE(read) << c.expected;
        EXPECT_TRUE(contains(read.error().message, "attr.exr")) << read.error().message;
        EXPECT_TRUE(contains(read.error().message, c.expected)) << read.error().message;
    }
    const auto good = readBytesAsExr(rgbFloatExr(
        {version, {kExrAttrExposureTimes, "string", "0.25 1e-3 4"}, {"other", "string", "x"}}));
    ASSERT_TRUE(good) << good.error().message;
    EXPECT_EQ(good->meta.exposure_times_s, (std::vector<double>{0.25, 1e-3, 4.0}));
}

TEST(ReadExr, OpenExrStandardAttributesAreChecked) {
    const auto chromaticities = [](float v) {
        std::string bytes;
        for (int i = 0; i < 8; ++i) bytes += le32(floatBits(v));
        return bytes;
    };
    struct Case {
        RawAttribute attribute;
        std::string expected;
    };
    const Case cases[] = {
        {{"capDate", "int", le32(3)}, "'capDate' is not of type string"},
        {{"capDate", "string", "yesterday"}, "'capDate' is not YYYY:MM:DD hh:mm:ss"},
        {{"expTime", "double", leDouble(1.0)}, "'expTime' is not of type float"},
        {{"expTime", "float", le32(floatBits(-1.0f))}, "'expTime' = -1 is not positive"},
        {{"aperture", "float", le32(floatBits(std::numeric_limits<float>::infinity()))},
         "'aperture'"},
        {{"isoSpeed", "float", le32(floatBits(0.0f))}, "'isoSpeed' = 0 is not positive"},
        {{"utcOffset", "float", le32(floatBits(1e7f))}, "'utcOffset'"},
        {{"chromaticities", "chromaticities", chromaticities(2.0f)}, "'chromaticities' holds 2"},
        {{"chromaticities", "string", "sRGB"}, "'chromaticities' is not of type chromaticities"},
    };
    for (const Case& c : cases) {
        const auto read = readBytesAsExr(rgbFloatExr({c.attribute}), "std.exr");
        ASSERT_FALSE(read) << c.expected;
        EXPECT_EQ(read.error().code, ErrorCode::ParseError);
        EXPECT_TRUE(contains(read.error().message, "std.exr: header attribute " + c.expected))
            << read.error().message;
    }
    // Another program's file with standard attributes and no flarelab ones reads with them.
    const auto good =
        readBytesAsExr(rgbFloatExr({{"capDate", "string", "2003:01:02 03:04:05"},
                                    {"aperture", "float", le32(floatBits(4.0f))},
                                    {"chromaticities", "chromaticities", chromaticities(0.25f)}}));
    ASSERT_TRUE(good) << good.error().message;
    EXPECT_EQ(good->meta.standard.cap_date, "2003:01:02 03:04:05");
    EXPECT_EQ(good->meta.standard.aperture, 4.0);
    EXPECT_EQ(good->meta.standard.chromaticities->green[1], 0.25);
    ExrMetadata only_standard;
    only_standard.standard = good->meta.standard;
    EXPECT_EQ(good->meta, only_standard);
}

TEST(ExrCaptureTime, GivesLocalTimeAndTheOffsetBackToUtc) {
    const char* old_tz = std::getenv("TZ");
    const std::string saved = old_tz ? old_tz : "";
    // 2026-11-28 07:04:02 UTC.
    const int64_t moment_ns = int64_t{1795849442} * 1000000000 + 123;
    ::setenv("TZ", "UTC0", 1);
    ::tzset();
    auto utc = exrCaptureTime(moment_ns);
    // Two hours east of Greenwich: local time 09:04:02, UTC == local - 7200 s.
    ::setenv("TZ", "EET-2", 1);
    ::tzset();
    auto east = exrCaptureTime(moment_ns);
    if (old_tz)
        ::setenv("TZ", saved.c_str(), 1);
    else
        ::unsetenv("TZ");
    ::tzset();
    ASSERT_TRUE(utc && east);
    EXPECT_EQ(utc->cap_date, "2026:11:28 07:04:02");
    EXPECT_EQ(utc->utc_offset_s, 0.0);
    EXPECT_EQ(east->cap_date, "2026:11:28 09:04:02");
    EXPECT_EQ(east->utc_offset_s, -7200.0);
    EXPECT_FALSE(exrCaptureTime(0));
    EXPECT_FALSE(exrCaptureTime(-5));
}

TEST(ReadExr, MalformedHeadersAreParseErrors) {
    const std::vector<RawAttribute> cases[] = {
        {{"odd", "box2i", box(0, 0, 0, 0).substr(0, 8)}},  // OpenEXR would read past it
        {{"odd", "double", le32(0)}},
        {{"odd", "stringvector", le32(10) + "abc"}},
        {{"odd", "chlist", std::string("R\0", 2)}},
        {{"odd", "preview", le32(100) + le32(100) + "abcd"}},
        {{"odd", "preview", le32(0xffffffff) + le32(0xffffffff) + "abcd"}},
        {{"type", "string", "tiledimage"}},
        {{"chunkCount", "int", le32(7)}},
    };
    for (const auto& attributes : cases) {
        const auto read = readBytesAsExr(rgbFloatExr(attributes), "bad.exr");
        ASSERT_FALSE(read) << attributes[0].type;
        EXPECT_TRUE(contains(read.error().message, "bad.exr: ")) << read.error().message;
    }
}

TEST(ReadExr, MissingFileIsNotFound) {
    TempDir dir;
    const auto read = readExr(dir.file("absent.exr"));
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(contains(read.error().message, dir.file("absent.exr"))) << read.error().message;

    const auto directory = readExr(dir.file(""));
    ASSERT_FALSE(directory);
    EXPECT_EQ(directory.error().code, ErrorCode::IoError);
}

TEST(ReadExr, GarbageIsNotAnExr) {
    TempDir dir;
    std::mt19937_64 rng(17);
    std::string garbage(1000, '\0');
    for (char& c : garbage) c = static_cast<char>(rng());
    for (const std::string& bytes : {std::string(), std::string("P6\n1 1\n255\n\1\2\3"), garbage}) {
        writeText(dir.file("garbage.exr"), bytes);
        const auto read = readExr(dir.file("garbage.exr"));
        ASSERT_FALSE(read);
        EXPECT_EQ(read.error().code, ErrorCode::ParseError);
        EXPECT_TRUE(contains(read.error().message, "not an OpenEXR file")) << read.error().message;
    }
    // Flip bytes of a good file's header, one at a time: errors or images, never a crash.
    const std::string good = rgbFloatExr({});
    for (size_t i = 8; i < 200; ++i) {
        std::string bytes = good;
        bytes[i] = static_cast<char>(bytes[i] ^ 0x5a);
        const auto read = readBytesAsExr(bytes);
        if (!read) {
            EXPECT_FALSE(read.error().message.empty());
        }
    }
}

TEST(ReadExr, EveryTruncationIsAnError) {
    TempDir dir;
    for (const ExrCompression compression :
         {ExrCompression::None, ExrCompression::Zip, ExrCompression::Piz}) {
        ExrWriteOptions options;
        options.compression = compression;
        ASSERT_TRUE(writeExr(dir.file("t.exr"), smoothImage(7, 40, 18), fullMetadata(), options));
        const std::string bytes = readText(dir.file("t.exr"));
        for (size_t length = 0; length < bytes.size(); ++length) {
            const auto read = readBytesAsExr(bytes.substr(0, length), "cut.exr");
            ASSERT_FALSE(read) << "length " << length;
            EXPECT_TRUE(contains(read.error().message, "cut.exr: ")) << read.error().message;
        }
        // The same through the file reader, at a few lengths.
        for (const size_t length : {size_t{5}, size_t{100}, bytes.size() / 2, bytes.size() - 1}) {
            writeText(dir.file("cut.exr"), bytes.substr(0, length));
            const auto read = readExr(dir.file("cut.exr"));
            ASSERT_FALSE(read) << "length " << length;
            EXPECT_EQ(read.error().code, ErrorCode::ParseError);
        }
    }
}

TEST(ReadExr, LimitsAreOptions) {
    const std::string bytes = rgbFloatExr({});
    ExrReadOptions options;
    options.max_pixels = 11;
    const auto read = readExrFromMemory(
        std::span(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()), "x", options);
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
    options = {};
    options.max_channels = 2;
    EXPECT_FALSE(readExrFromMemory(
        std::span(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()), "x", options));
}

TEST(WriteExr, TheLowerBoundChannelRoundTripsAndIsCheckedOnWrite) {
    TempDir dir;
    ImageRGB image(5, 3);
    for (size_t i = 0; i < image.pixels.size(); ++i) image.pixels[i] = static_cast<float>(i);
    std::vector<uint8_t> bounds(15, 0);
    bounds[3] = 7;
    bounds[7] = 4;
    bounds[14] = 1;
    const std::string path = dir.file("bounds.exr");
    for (const auto type : {ExrPixelType::Float, ExrPixelType::Half}) {
        ExrWriteOptions options;
        options.pixel_type = type;
        ASSERT_TRUE(writeExr(path, image, {}, options, bounds));
        const auto read = readExr(path);
        ASSERT_TRUE(read) << read.error().message;
        EXPECT_EQ(read->lower_bound, bounds);
        EXPECT_EQ(read->image.pixels, image.pixels);
    }
    // Without it, the file has no such channel and says nothing.
    ASSERT_TRUE(writeExr(path, image, {}));
    const auto plain = readExr(path);
    ASSERT_TRUE(plain) << plain.error().message;
    EXPECT_TRUE(plain->lower_bound.empty());
    // The writer refuses another size and bits beyond R, G, B, and leaves the file as it was.
    bounds.pop_back();
    auto refused = writeExr(path, image, {}, {}, bounds);
    ASSERT_FALSE(refused);
    EXPECT_TRUE(contains(refused.error().message, "lower_bound holds 14 values"))
        << refused.error().message;
    bounds.push_back(8);
    refused = writeExr(path, image, {}, {}, bounds);
    ASSERT_FALSE(refused);
    EXPECT_TRUE(contains(refused.error().message, "lower_bound at x 4, y 2 is 8"))
        << refused.error().message;
    EXPECT_TRUE(readExr(path)->lower_bound.empty());
}

TEST(ReadExr, ALowerBoundThatIsNotBitsOfRgbIsNamed) {
    // Channel index 3 in name order (B, G, R, flarelab.lower_bound).
    constexpr uint32_t kHalfHalf = 0x3800, kHalfEight = 0x4800;
    for (const uint32_t bad : {kHalfHalf, kHalfEight, kHalfNaN}) {
        const std::string bytes =
            rawExr(0, 0, 2, 1, {{"R", 1}, {"G", 1}, {"B", 1}, {"flarelab.lower_bound", 1}}, {},
                   [&](size_t c, int32_t x, int32_t y) {
                       return c == 3 ? (x == 1 && y == 1 ? bad : kHalfOne) : kHalfTwo;
                   });
        const auto read = readBytesAsExr(bytes, "bounds.exr");
        ASSERT_FALSE(read);
        EXPECT_EQ(read.error().code, ErrorCode::ParseError);
        EXPECT_TRUE(
            contains(read.error().message, "bounds.exr: pixel (1, 1) channel flarelab.lower_bound"))
            << read.error().message;
    }
    const std::string uint_bounds =
        rawExr(0, 0, 0, 0, {{"R", 1}, {"G", 1}, {"B", 1}, {"flarelab.lower_bound", 0}}, {},
               [](size_t, int32_t, int32_t) { return 1u; });
    const auto read = readBytesAsExr(uint_bounds);
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
}

TEST(ReadExr, EverySeedOfTheFuzzCorpusReads) {
    const fs::path corpus = testing::sourcePath("fuzz/corpus/exr");
    int files = 0;
    for (const auto& entry : fs::directory_iterator(corpus)) {
        // Seeds are *.exr; regression inputs the fuzzer found are kept beside them unnamed.
        if (entry.path().extension() != ".exr") continue;
        const auto read = readExr(entry.path().string());
        EXPECT_TRUE(read) << read.error().message;
        ++files;
    }
    EXPECT_GE(files, 5);
}

}  // namespace
}  // namespace flarelab::hdr
