#include "drivers/v4l2_formats.h"

#include <gtest/gtest.h>
#include <linux/videodev2.h>

#include <random>
#include <set>

namespace flarelab::drivers {
namespace {

const V4l2FormatInfo& format(uint32_t fourcc) {
    const V4l2FormatInfo* f = findV4l2Format(fourcc);
    EXPECT_NE(f, nullptr) << fourccText(fourcc);
    return *f;
}

std::vector<uint16_t> unpack(uint32_t fourcc,
                             const std::vector<uint8_t>& bytes,
                             int64_t width,
                             int64_t height,
                             int64_t bytes_per_line,
                             int value_bits = 0,
                             bool msb = false) {
    auto s = unpackV4l2Samples(format(fourcc), bytes,
                               V4l2Unpacking{width, height, bytes_per_line, value_bits, msb});
    EXPECT_TRUE(s) << (s ? "" : s.error().message);
    return s ? s->samples : std::vector<uint16_t>{};
}

TEST(FourccText, TrimsSpacesAndMarksBigEndian) {
    EXPECT_EQ(fourccText(V4L2_PIX_FMT_Y16), "Y16");
    EXPECT_EQ(fourccText(V4L2_PIX_FMT_Y16_BE), "Y16-BE");
    EXPECT_EQ(fourccText(V4L2_PIX_FMT_SRGGB10P), "pRAA");
    EXPECT_EQ(fourccText(0x01020304), "....");
    EXPECT_EQ(fourccFromText("Y16"), V4L2_PIX_FMT_Y16);
    EXPECT_EQ(fourccFromText("Y16-BE"), V4L2_PIX_FMT_Y16_BE);
    EXPECT_EQ(fourccFromText("GREY"), V4L2_PIX_FMT_GREY);
    for (const char* bad : {"", "Y16XX", "\x01", "ABCDE-BE"})
        EXPECT_FALSE(fourccFromText(bad)) << bad;
}

TEST(V4l2Formats, AreUniqueNamedAndPreferDeeperRawFirst) {
    std::set<uint32_t> seen;
    int previous_bits = 16;
    bool luma_seen = false;
    for (const V4l2FormatInfo& f : v4l2Formats()) {
        EXPECT_TRUE(seen.insert(f.fourcc).second) << f.name;
        EXPECT_EQ(fourccFromText(f.name), f.fourcc) << f.name;
        EXPECT_EQ(fourccText(f.fourcc), f.name);
        if (!f.raw) {
            luma_seen = true;
            continue;
        }
        EXPECT_FALSE(luma_seen) << f.name << ": raw after a luma format";
        EXPECT_LE(f.bits, previous_bits) << f.name;
        previous_bits = f.bits;
    }
    EXPECT_TRUE(luma_seen);
    EXPECT_EQ(v4l2Formats().front().fourcc, V4L2_PIX_FMT_Y16);
}

// Byte layouts written out by hand from the kernel's pixfmt documentation, independent of
// packV4l2Samples.
TEST(UnpackV4l2Samples, ReadsLsbAlignedWords) {
    EXPECT_EQ(unpack(V4L2_PIX_FMT_Y10, {0xff, 0x03, 0x00, 0x02}, 2, 1, 4),
              (std::vector<uint16_t>{1023, 512}));
    EXPECT_EQ(unpack(V4L2_PIX_FMT_SBGGR12, {0xff, 0x0f, 0x01, 0x00}, 2, 1, 4),
              (std::vector<uint16_t>{4095, 1}));
}

TEST(UnpackV4l2Samples, ClipsAndCountsHighBitsOfAnLsbFormat) {
    auto s =
        unpackV4l2Samples(format(V4L2_PIX_FMT_Y10), std::vector<uint8_t>{0x00, 0x04, 0x05, 0x00},
                          V4l2Unpacking{2, 1, 4});
    ASSERT_TRUE(s);
    EXPECT_EQ(s->samples, (std::vector<uint16_t>{1023, 5}));
    EXPECT_EQ(s->clipped, 1);
    EXPECT_EQ(s->bit_depth, 10);
}

TEST(UnpackV4l2Samples, ReadsBigEndianWords) {
    EXPECT_EQ(unpack(V4L2_PIX_FMT_Y16_BE, {0x12, 0x34, 0xff, 0x00}, 2, 1, 4),
              (std::vector<uint16_t>{0x1234, 0xff00}));
    EXPECT_EQ(unpack(V4L2_PIX_FMT_Y16, {0x12, 0x34}, 1, 1, 2), (std::vector<uint16_t>{0x3412}));
}

TEST(UnpackV4l2Samples, ShiftsMsbAlignedSensorDataBack) {
    // A 12-bit sensor in the top of 16-bit words: 0xfff0 is 0xfff.
    auto msb =
        unpackV4l2Samples(format(V4L2_PIX_FMT_Y16), std::vector<uint8_t>{0xf0, 0xff, 0x10, 0x00},
                          V4l2Unpacking{2, 1, 4, 12, true});
    ASSERT_TRUE(msb);
    EXPECT_EQ(msb->samples, (std::vector<uint16_t>{0xfff, 0x001}));
    EXPECT_EQ(msb->bit_depth, 12);
    // The same words read LSB-aligned: 0xfff0 is beyond 12 bits, clipped and counted.
    auto lsb =
        unpackV4l2Samples(format(V4L2_PIX_FMT_Y16), std::vector<uint8_t>{0xf0, 0xff, 0x10, 0x00},
                          V4l2Unpacking{2, 1, 4, 12, false});
    ASSERT_TRUE(lsb);
    EXPECT_EQ(lsb->samples, (std::vector<uint16_t>{0xfff, 0x010}));
    EXPECT_EQ(lsb->clipped, 1);
}

TEST(UnpackV4l2Samples, ReadsMipiRaw10) {
    // 0x3ff 0x000 0x155 0x2aa: high bytes ff 00 55 aa, low bits 11 00 01 10 from bit 0 up.
    EXPECT_EQ(unpack(V4L2_PIX_FMT_SRGGB10P, {0xff, 0x00, 0x55, 0xaa, 0x93}, 4, 1, 5),
              (std::vector<uint16_t>{0x3ff, 0x000, 0x155, 0x2aa}));
    // A width that does not fill the last group.
    EXPECT_EQ(unpack(V4L2_PIX_FMT_Y10P, {0xff, 0x00, 0x55, 0xaa, 0x93}, 3, 1, 5),
              (std::vector<uint16_t>{0x3ff, 0x000, 0x155}));
}

TEST(UnpackV4l2Samples, ReadsMipiRaw12And14) {
    // 0xabc 0x123: high bytes ab 12, low nibbles c then 3.
    EXPECT_EQ(unpack(V4L2_PIX_FMT_SBGGR12P, {0xab, 0x12, 0x3c}, 2, 1, 3),
              (std::vector<uint16_t>{0xabc, 0x123}));
    // 0x3fff 0x0001 0x2000 0x1555: high bytes ff 00 80 55, then six low bits each from bit 0:
    // 63 | 1 << 6 | 0 << 12 | 21 << 18 = 0x54007f, little-endian.
    EXPECT_EQ(unpack(V4L2_PIX_FMT_SGBRG14P, {0xff, 0x00, 0x80, 0x55, 0x7f, 0x00, 0x54}, 4, 1, 7),
              (std::vector<uint16_t>{0x3fff, 0x0001, 0x2000, 0x1555}));
}

TEST(UnpackV4l2Samples, ReadsBitPackedBigEndian) {
    // 1111111111 0000000001 -> 11111111 11000000 0001....
    EXPECT_EQ(unpack(V4L2_PIX_FMT_Y10BPACK, {0xff, 0xc0, 0x10}, 2, 1, 3),
              (std::vector<uint16_t>{0x3ff, 0x001}));
}

TEST(UnpackV4l2Samples, TakesLumaOfYuvAndSkipsLinePadding) {
    EXPECT_EQ(unpack(V4L2_PIX_FMT_YUYV, {10, 128, 20, 129}, 2, 1, 4),
              (std::vector<uint16_t>{10, 20}));
    EXPECT_EQ(unpack(V4L2_PIX_FMT_UYVY, {128, 10, 129, 20}, 2, 1, 4),
              (std::vector<uint16_t>{10, 20}));
    // NV12, 2x2 with 4 bytes a line: luma lines 1 2 _ _ / 3 4 _ _, then chroma.
    EXPECT_EQ(unpack(V4L2_PIX_FMT_NV12, {1, 2, 9, 9, 3, 4, 9, 9, 128, 128, 0, 0}, 2, 2, 4),
              (std::vector<uint16_t>{1, 2, 3, 4}));
}

TEST(PackV4l2Samples, RoundTripsEveryFormatAtOddSizes) {
    std::mt19937_64 rng(17);
    for (const V4l2FormatInfo& f : v4l2Formats()) {
        for (const auto& [w, h] : {std::pair<int64_t, int64_t>{7, 3}, {1, 1}, {16, 2}}) {
            const int64_t line = minBytesPerLine(f, w) + 5;  // padded
            std::vector<uint16_t> samples(static_cast<size_t>(w * h));
            for (uint16_t& v : samples) v = static_cast<uint16_t>(rng() & ((1u << f.bits) - 1));
            const auto bytes = packV4l2Samples(f, samples, w, h, line);
            EXPECT_EQ(static_cast<int64_t>(bytes.size()), imageBytes(f, line, h)) << f.name;
            auto back = unpackV4l2Samples(f, bytes, V4l2Unpacking{w, h, line});
            ASSERT_TRUE(back) << f.name << ": " << back.error().message;
            EXPECT_EQ(back->samples, samples) << f.name << " " << w << "x" << h;
            EXPECT_EQ(back->bit_depth, f.bits);
            EXPECT_EQ(back->clipped, 0);
        }
    }
}

TEST(UnpackV4l2Samples, NamesWhatDoesNotFit) {
    const V4l2FormatInfo& y16 = format(V4L2_PIX_FMT_Y16);
    const std::vector<uint8_t> bytes(100, 0);
    auto short_buffer = unpackV4l2Samples(y16, bytes, V4l2Unpacking{10, 10, 20});
    ASSERT_FALSE(short_buffer);
    EXPECT_NE(short_buffer.error().message.find("bytesused = 100"), std::string::npos)
        << short_buffer.error().message;
    auto short_line = unpackV4l2Samples(y16, bytes, V4l2Unpacking{10, 1, 19});
    ASSERT_FALSE(short_line);
    EXPECT_NE(short_line.error().message.find("bytes_per_line = 19"), std::string::npos);
    for (const auto& [w, h] : {std::pair<int64_t, int64_t>{0, 1}, {1, -1}, {40000, 1}}) {
        auto bad = unpackV4l2Samples(y16, bytes, V4l2Unpacking{w, h, 2 * w});
        ASSERT_FALSE(bad);
        EXPECT_NE(bad.error().message.find("width x height"), std::string::npos);
    }
    // Sensor bits apply to 16-bit words only.
    auto bits = unpackV4l2Samples(format(V4L2_PIX_FMT_Y10), bytes, V4l2Unpacking{2, 1, 4, 8, true});
    ASSERT_FALSE(bits);
    EXPECT_EQ(bits.error().code, ErrorCode::InvalidArgument);
}

}  // namespace
}  // namespace flarelab::drivers
