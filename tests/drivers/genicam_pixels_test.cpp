#include "drivers/genicam_pixels.h"

#include <gtest/gtest.h>

#include <random>

namespace flarelab::drivers {
namespace {

std::vector<uint8_t> bytes(std::initializer_list<int> values) {
    std::vector<uint8_t> out;
    for (int v : values) out.push_back(static_cast<uint8_t>(v));
    return out;
}

// Packs samples as the PFNC "p" formats do: one stream of bits, least significant first.
std::vector<uint8_t> packLsb(const std::vector<uint16_t>& samples, int bits) {
    std::vector<uint8_t> out((samples.size() * bits + 7) / 8, 0);
    uint64_t bit = 0;
    for (uint16_t s : samples)
        for (int b = 0; b < bits; ++b, ++bit)
            if (s >> b & 1) out[bit / 8] |= static_cast<uint8_t>(1 << (bit % 8));
    return out;
}

TEST(GenicamPixelFormat, ReadsPfncNamesAndRefusesColourFormats) {
    const auto mono12p = genicamPixelFormat("Mono12p");
    ASSERT_TRUE(mono12p);
    EXPECT_EQ(mono12p->layout, hdr::RawFormat::Mono);
    EXPECT_EQ(mono12p->bits, 12);
    EXPECT_EQ(mono12p->packing, PixelPacking::Lsb);
    const auto bayer = genicamPixelFormat("BayerGB10Packed");
    ASSERT_TRUE(bayer);
    EXPECT_EQ(bayer->layout, hdr::RawFormat::BayerGBRG);
    EXPECT_EQ(bayer->bits, 10);
    EXPECT_EQ(bayer->packing, PixelPacking::GigEPacked);
    EXPECT_EQ(genicamPixelFormat("BayerBG16")->layout, hdr::RawFormat::BayerBGGR);
    EXPECT_EQ(genicamPixelFormat("BayerGR8")->layout, hdr::RawFormat::BayerGRBG);
    for (const char* name : {"RGB8", "YUV422_8", "Mono", "Mono9", "Mono16p", "BayerXY8", "Bayer",
                             "BayerRG", "Coord3D_C16", "mono16", ""})
        EXPECT_FALSE(genicamPixelFormat(name)) << name;
}

TEST(RankGenicamPixelFormats, PutsDeepGreyFirstAndEightBitsLast) {
    const auto ranked =
        rankGenicamPixelFormats({"Mono8", "BayerRG8", "RGB8", "BayerRG12p", "Mono12Packed",
                                 "Mono12", "BayerRG16", "Mono16", "Mono10p"});
    std::vector<std::string> names;
    for (const auto& f : ranked) names.push_back(f.name);
    EXPECT_EQ(names, (std::vector<std::string>{"Mono16", "Mono12", "Mono12Packed", "Mono10p",
                                               "BayerRG16", "BayerRG12p", "Mono8", "BayerRG8"}));
    EXPECT_EQ(
        chooseGenicamPixelFormat({"Mono8", "BayerRG8", "BayerRG12"}, hdr::RawFormat::BayerRGGB)
            ->name,
        "BayerRG12");
    EXPECT_FALSE(chooseGenicamPixelFormat({"Mono8", "BayerRG8"}, hdr::RawFormat::BayerBGGR));
    EXPECT_EQ(bayerOrderName(hdr::RawFormat::BayerGBRG), "GB");
}

TEST(UnpackGenicamPixels, ReadsLittleEndianWordsAndBytes) {
    const auto mono16 = *genicamPixelFormat("Mono16");
    const auto data = bytes({0x34, 0x12, 0xff, 0xff, 0x00, 0x80, 0x01, 0x00});
    const auto samples = unpackGenicamPixels(mono16, data, 2, 2);
    ASSERT_TRUE(samples) << samples.error().message;
    EXPECT_EQ(*samples, (std::vector<uint16_t>{0x1234, 0xffff, 0x8000, 0x0001}));
    const auto mono8 = *genicamPixelFormat("Mono8");
    EXPECT_EQ(*unpackGenicamPixels(mono8, bytes({0, 7, 255}), 3, 1),
              (std::vector<uint16_t>{0, 7, 255}));
}

TEST(UnpackGenicamPixels, ReadsGigEVisionPackedLayouts) {
    // Mono12Packed: B0 = p0[11:4], B1 = p1[3:0] << 4 | p0[3:0], B2 = p1[11:4].
    const auto mono12 = *genicamPixelFormat("Mono12Packed");
    const auto s12 = unpackGenicamPixels(mono12, bytes({0xab, 0x4c, 0x12, 0xff, 0x0f}), 3, 1);
    ASSERT_TRUE(s12) << s12.error().message;
    EXPECT_EQ(*s12, (std::vector<uint16_t>{0xabc, 0x124, 0xfff}));
    // Mono10Packed: B0 = p0[9:2], B1 = p1[1:0] << 4 | p0[1:0], B2 = p1[9:2].
    const auto mono10 = *genicamPixelFormat("Mono10Packed");
    const auto s10 = unpackGenicamPixels(mono10, bytes({0xff, 0x23, 0x80, 0x12, 0x01}), 3, 1);
    ASSERT_TRUE(s10) << s10.error().message;
    EXPECT_EQ(*s10, (std::vector<uint16_t>{0x3ff, 0x202, 0x049}));
    // Three bytes for every two samples, two for an odd last one.
    EXPECT_EQ(genicamPayloadBytes(mono10, 3), 5);
    EXPECT_EQ(genicamPayloadBytes(mono12, 4), 6);
    EXPECT_FALSE(unpackGenicamPixels(mono10, bytes({0xff, 0x23, 0x80, 0x12}), 4, 1));
}

TEST(UnpackGenicamPixels, ReadsLsbPackedStreamsOfEveryDepth) {
    std::mt19937_64 rng(11);
    for (const char* name : {"Mono10p", "Mono12p", "Mono14p", "BayerRG12p", "BayerGB10p"}) {
        const auto format = *genicamPixelFormat(name);
        for (int64_t width : {1, 3, 5, 8, 17}) {
            const int64_t height = 3;
            std::vector<uint16_t> samples(static_cast<size_t>(width * height));
            for (auto& s : samples) s = static_cast<uint16_t>(rng() & ((1u << format.bits) - 1));
            const auto packed = packLsb(samples, format.bits);
            const auto unpacked = unpackGenicamPixels(format, packed, width, height);
            ASSERT_TRUE(unpacked) << name << ": " << unpacked.error().message;
            EXPECT_EQ(*unpacked, samples) << name << " width " << width;
        }
    }
    // Mono12p by hand: p0 = 0xabc, p1 = 0x123 -> bc 3a 12.
    EXPECT_EQ(*unpackGenicamPixels(*genicamPixelFormat("Mono12p"), bytes({0xbc, 0x3a, 0x12}), 2, 1),
              (std::vector<uint16_t>{0xabc, 0x123}));
}

TEST(UnpackGenicamPixels, SkipsRowPaddingAndStartsPaddedRowsOnAByte) {
    const auto mono16 = *genicamPixelFormat("Mono16");
    const auto s =
        unpackGenicamPixels(mono16, bytes({1, 0, 2, 0, 9, 9, 3, 0, 4, 0, 9, 9}), 2, 2, 2);
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_EQ(*s, (std::vector<uint16_t>{1, 2, 3, 4}));
    // 3 samples of Mono12p take 4.5 bytes: a padded row holds 5 bytes, then its padding.
    const auto p12 = *genicamPixelFormat("Mono12p");
    auto row = packLsb({0x111, 0x222, 0x333}, 12);
    ASSERT_EQ(row.size(), 5u);
    std::vector<uint8_t> image = row;
    image.push_back(0xee);
    auto second = packLsb({0x444, 0x555, 0x666}, 12);
    image.insert(image.end(), second.begin(), second.end());
    image.push_back(0xee);
    const auto padded = unpackGenicamPixels(p12, image, 3, 2, 1);
    ASSERT_TRUE(padded) << padded.error().message;
    EXPECT_EQ(*padded, (std::vector<uint16_t>{0x111, 0x222, 0x333, 0x444, 0x555, 0x666}));
}

TEST(UnpackGenicamPixels, RefusesShortDataBadSizesAndSamplesBeyondTheirBits) {
    const auto mono16 = *genicamPixelFormat("Mono16");
    const auto short_data = unpackGenicamPixels(mono16, bytes({1, 2, 3}), 2, 1);
    ASSERT_FALSE(short_data);
    EXPECT_EQ(short_data.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(short_data.error().message.find("Mono16: 3 bytes for a 2 x 1 image that needs 4"),
              std::string::npos)
        << short_data.error().message;
    EXPECT_FALSE(unpackGenicamPixels(mono16, bytes({1, 2}), 0, 1));
    EXPECT_FALSE(unpackGenicamPixels(mono16, bytes({1, 2}), 1, -1));
    EXPECT_FALSE(unpackGenicamPixels(mono16, bytes({1, 2}), int64_t{1} << 40, int64_t{1} << 40));
    EXPECT_FALSE(unpackGenicamPixels(mono16, bytes({1, 2}), 1, 1, -3));
    // Mono12 in 16-bit words: 0x1000 needs 13 bits (a camera sending left-aligned data).
    const auto left = unpackGenicamPixels(*genicamPixelFormat("Mono12"), bytes({0x00, 0x10}), 1, 1);
    ASSERT_FALSE(left);
    EXPECT_NE(left.error().message.find("exceeds 12 bits"), std::string::npos);
}

TEST(UnpackGenicamPixels, NeverReadsPastTheDataForAnySize) {
    // Every format at random sizes, with exactly the bytes it needs or fewer: a result or a
    // clear error (ASan checks the reads).
    std::mt19937_64 rng(5);
    const char* names[] = {"Mono8",   "Mono10", "Mono10p",      "Mono10Packed", "Mono12",
                           "Mono12p", "Mono14", "Mono12Packed", "Mono16",       "BayerRG12p"};
    for (int i = 0; i < 2000; ++i) {
        const auto format = *genicamPixelFormat(names[rng() % std::size(names)]);
        const int64_t width = 1 + static_cast<int64_t>(rng() % 13);
        const int64_t height = 1 + static_cast<int64_t>(rng() % 5);
        const int64_t padding = (rng() % 3 == 0) ? static_cast<int64_t>(rng() % 4) : 0;
        const int64_t needed = padding > 0 ? (genicamPayloadBytes(format, width) + padding) * height
                                           : genicamPayloadBytes(format, width * height);
        const int64_t size = needed - static_cast<int64_t>(rng() % 2);
        std::vector<uint8_t> data(static_cast<size_t>(size));
        // Unpacked deep samples stay within their bits when every byte does.
        const bool words = format.packing == PixelPacking::None && format.bits > 8;
        const unsigned byte_mask = words ? (1u << (format.bits - 8)) - 1 : 0xffu;
        for (uint8_t& b : data) b = static_cast<uint8_t>(rng() & byte_mask);
        const auto out = unpackGenicamPixels(format, data, width, height, padding);
        EXPECT_EQ(out.has_value(), size >= needed) << format.name;
        if (out) {
            EXPECT_EQ(static_cast<int64_t>(out->size()), width * height);
            for (uint16_t s : *out) EXPECT_LT(s, 1u << format.bits);
        }
    }
}

}  // namespace
}  // namespace flarelab::drivers
