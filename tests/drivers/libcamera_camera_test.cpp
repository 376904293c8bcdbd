// The libcamera backend up to the camera: formats and their unpacking, the choice of format,
// controls, metadata, the settling of new settings, URIs (libcamera_mapping.h, built
// everywhere); and, where libcamera is built in, that it lists no camera and refuses to open a
// missing one, quietly, on a machine without cameras. No test here has met a camera.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <limits>
#include <random>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "drivers/libcamera_mapping.h"
#include "hdr/raw_io.h"

#if FLARELAB_HAVE_LIBCAMERA
#include "drivers/libcamera_camera.h"
#endif

namespace flarelab::drivers {
namespace {

bool mentions(const Error& error, const std::string& text) {
    return error.message.find(text) != std::string::npos;
}

const LibcameraRawFormat& format(std::string_view name) {
    const LibcameraRawFormat* f = findLibcameraRawFormat(name);
    EXPECT_NE(f, nullptr) << name;
    return f ? *f : libcameraRawFormats().front();
}

// Reference packers, written from the layouts' descriptions as bit streams (unlike the
// unpacker's per-group arithmetic), for round trips.
std::vector<uint8_t> packLine(const std::vector<uint16_t>& samples, const LibcameraRawFormat& f) {
    std::vector<uint8_t> out;
    const size_t n = samples.size();
    switch (f.packing) {
        case RawPacking::None:
            for (uint16_t s : samples) {
                out.push_back(static_cast<uint8_t>(s & 0xff));
                if (f.bit_depth > 8) out.push_back(static_cast<uint8_t>(s >> 8));
            }
            break;
        case RawPacking::Csi2: {
            // Groups of 4 (RAW10) or 2 (RAW12) samples: first the high 8 bits of each, then one
            // byte of their low bits, the first sample's in the least significant bits.
            const size_t group = f.bit_depth == 10 ? 4 : 2;
            const int low_bits = f.bit_depth - 8;
            for (size_t g = 0; g < n; g += group) {
                uint8_t low = 0;
                for (size_t i = 0; i < group; ++i) {
                    // A partial group is padded with ones: the unpacker must not read them.
                    const uint16_t s = g + i < n ? samples[g + i] : 0xffff;
                    out.push_back(static_cast<uint8_t>(s >> low_bits));
                    low |= static_cast<uint8_t>((s & ((1 << low_bits) - 1)) << (low_bits * i));
                }
                out.push_back(low);
            }
            break;
        }
        case RawPacking::Ipu3: {
            // 25 samples a 32-byte block, a little-endian bit stream.
            for (size_t b = 0; b < n; b += 25) {
                // The 6 padding bits and the samples past the line's end are ones.
                std::vector<uint8_t> block(32, 0);
                block[31] = 0xfc;
                for (size_t i = 0; i < 25; ++i)
                    for (int bit = 0; bit < 10; ++bit)
                        if (b + i >= n || samples[b + i] >> bit & 1) {
                            const size_t at = 10 * i + static_cast<size_t>(bit);
                            block[at / 8] |= static_cast<uint8_t>(1 << (at % 8));
                        }
                out.insert(out.end(), block.begin(), block.end());
            }
            break;
        }
    }
    return out;
}

TEST(LibcameraRawFormats, EveryBayerOrderAndDepthIsReadableOnce) {
    std::set<std::pair<uint32_t, uint64_t>> codes;
    std::set<std::string_view> names;
    for (const LibcameraRawFormat& f : libcameraRawFormats()) {
        EXPECT_TRUE(codes.insert({f.fourcc, f.modifier}).second) << f.name;
        EXPECT_TRUE(names.insert(f.name).second) << f.name;
        EXPECT_EQ(findLibcameraRawFormat(f.fourcc, f.modifier), &f);
        EXPECT_EQ(findLibcameraRawFormat(f.name), &f);
    }
    const std::pair<const char*, hdr::RawFormat> orders[] = {{"RGGB", hdr::RawFormat::BayerRGGB},
                                                             {"GRBG", hdr::RawFormat::BayerGRBG},
                                                             {"GBRG", hdr::RawFormat::BayerGBRG},
                                                             {"BGGR", hdr::RawFormat::BayerBGGR}};
    for (const auto& [order, layout] : orders) {
        for (const char* suffix : {"8", "10", "12", "16", "10_CSI2P", "12_CSI2P", "10_IPU3"}) {
            const std::string name = std::string("S") + order + suffix;
            const LibcameraRawFormat* f = findLibcameraRawFormat(name);
            ASSERT_NE(f, nullptr) << name;
            EXPECT_EQ(f->layout, layout) << name;
            EXPECT_EQ(f->bit_depth, std::stoi(suffix)) << name;
        }
    }
    for (const char* mono : {"R8", "R10", "R12", "R10_CSI2P"})
        EXPECT_EQ(format(mono).layout, hdr::RawFormat::Mono) << mono;
    // Not in libcamera 0.0.3, nor formats flarelab reads.
    EXPECT_EQ(findLibcameraRawFormat("R16"), nullptr);
    EXPECT_EQ(findLibcameraRawFormat("YUYV"), nullptr);
    EXPECT_EQ(findLibcameraRawFormat(libcameraFourcc('Y', 'U', 'Y', 'V'), 0), nullptr);
}

TEST(UnpackLibcameraRaw, ReadsCsi2Raw10AsTheSpecificationLaysItOut) {
    // 0x3ff, 0x000, 0x155, 0x2aa: high bytes ff 00 55 aa; low bits 3, 0, 1, 2 from bit 0 up.
    const std::vector<uint8_t> line = {0xff, 0x00, 0x55, 0xaa, 0x93};
    const auto out = unpackLibcameraRaw(line, format("SRGGB10_CSI2P"), 4, 1, 5);
    ASSERT_TRUE(out) << out.error().message;
    EXPECT_EQ(*out, (std::vector<uint16_t>{0x3ff, 0x000, 0x155, 0x2aa}));
}

TEST(UnpackLibcameraRaw, ReadsCsi2Raw12AsTheSpecificationLaysItOut) {
    // 0xabc, 0x123: high bytes ab 12, then 0x3 (low bits of the second) over 0xc (the first's).
    const std::vector<uint8_t> line = {0xab, 0x12, 0x3c};
    const auto out = unpackLibcameraRaw(line, format("SBGGR12_CSI2P"), 2, 1, 3);
    ASSERT_TRUE(out) << out.error().message;
    EXPECT_EQ(*out, (std::vector<uint16_t>{0xabc, 0x123}));
}

TEST(UnpackLibcameraRaw, ReadsIpu3BitStreamAcrossByteBoundaries) {
    std::vector<uint8_t> block(32, 0);
    block[0] = 0xff;   // sample 0 = 0x3ff: bits 0..9
    block[1] = 0x07;   // ... bits 8, 9; sample 1 = 1: bit 10
    block[31] = 0x03;  // sample 24 = 0x300: bits 248, 249
    const auto out = unpackLibcameraRaw(block, format("SGRBG10_IPU3"), 25, 1, 32);
    ASSERT_TRUE(out) << out.error().message;
    EXPECT_EQ((*out)[0], 0x3ff);
    EXPECT_EQ((*out)[1], 1);
    for (int i = 2; i < 24; ++i) EXPECT_EQ((*out)[i], 0) << i;
    EXPECT_EQ((*out)[24], 0x300);
}

TEST(UnpackLibcameraRaw, RoundTripsEveryFormatAtOddWidthsAndPaddedStrides) {
    std::mt19937_64 rng(17);
    for (const LibcameraRawFormat& f : libcameraRawFormats()) {
        std::uniform_int_distribution<int> sample(0, (1 << f.bit_depth) - 1);
        for (int64_t width : {1, 2, 3, 5, 7, 13, 24, 25, 26, 51}) {
            const int64_t height = 3;
            const int64_t line = libcameraLineBytes(f, width);
            for (int64_t pad : {0, 1, 3, 64}) {
                const int64_t stride = line + pad;
                // Padding holds garbage the unpacker must not read as samples.
                std::vector<uint8_t> buffer(static_cast<size_t>(stride * height), 0xee);
                std::vector<uint16_t> want;
                for (int64_t y = 0; y < height; ++y) {
                    std::vector<uint16_t> row(static_cast<size_t>(width));
                    for (uint16_t& s : row) s = static_cast<uint16_t>(sample(rng));
                    const std::vector<uint8_t> packed = packLine(row, f);
                    ASSERT_GE(static_cast<int64_t>(packed.size()), line) << f.name;
                    std::copy_n(packed.begin(), line, buffer.begin() + y * stride);
                    want.insert(want.end(), row.begin(), row.end());
                }
                // The last line needs no padding after it.
                buffer.resize(static_cast<size_t>(stride * (height - 1) + line));
                const auto out = unpackLibcameraRaw(buffer, f, width, height, stride);
                ASSERT_TRUE(out) << f.name << " " << width << ": " << out.error().message;
                EXPECT_EQ(*out, want) << f.name << " width " << width << " stride " << stride;
            }
        }
    }
}

TEST(UnpackLibcameraRaw, LineBytesPadPartialGroups) {
    EXPECT_EQ(libcameraLineBytes(format("SRGGB10_CSI2P"), 1), 5);
    EXPECT_EQ(libcameraLineBytes(format("SRGGB10_CSI2P"), 4), 5);
    EXPECT_EQ(libcameraLineBytes(format("SRGGB10_CSI2P"), 5), 10);
    EXPECT_EQ(libcameraLineBytes(format("SRGGB12_CSI2P"), 3), 6);
    EXPECT_EQ(libcameraLineBytes(format("SRGGB10_IPU3"), 26), 64);
    EXPECT_EQ(libcameraLineBytes(format("R8"), 7), 7);
    EXPECT_EQ(libcameraLineBytes(format("SRGGB16"), 7), 14);
    EXPECT_EQ(libcameraLineBytes(format("R8"), 0), 0);
}

TEST(UnpackLibcameraRaw, RefusesShortStridesAndBuffersNamingThem) {
    const LibcameraRawFormat& f = format("SGBRG12_CSI2P");
    const std::vector<uint8_t> buffer(100, 0);
    const auto short_stride = unpackLibcameraRaw(buffer, f, 5, 2, 8);  // a line takes 9
    ASSERT_FALSE(short_stride);
    EXPECT_EQ(short_stride.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(mentions(short_stride.error(), "stride = 8"));
    // 10 lines of stride 10 need 9 * 10 + 9 = 99 bytes: 98 is one too few.
    const std::vector<uint8_t> almost(98, 0);
    const auto truncated = unpackLibcameraRaw(almost, f, 5, 10, 10);
    ASSERT_FALSE(truncated);
    EXPECT_EQ(truncated.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(mentions(truncated.error(), "size = 98"));
    EXPECT_TRUE(unpackLibcameraRaw(std::vector<uint8_t>(99, 0), f, 5, 10, 10));
    for (auto [w, h, field] :
         {std::tuple{0, 1, "width"}, std::tuple{1, 0, "height"}, std::tuple{32769, 1, "width"}}) {
        const auto bad = unpackLibcameraRaw(buffer, f, w, h, 9);
        ASSERT_FALSE(bad);
        EXPECT_TRUE(mentions(bad.error(), field)) << bad.error().message;
    }
    // Unpacked 10-bit containers with bits above the 10th: not the format they claim.
    const std::vector<uint8_t> left_justified = {0x00, 0x00, 0xc0, 0xff};
    const auto high = unpackLibcameraRaw(left_justified, format("SRGGB10"), 2, 1, 4);
    ASSERT_FALSE(high);
    EXPECT_EQ(high.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(mentions(high.error(), "sample (1, 0) = 65472 exceeds 10 bits"));
    // A huge stride must not overflow the size check.
    EXPECT_FALSE(unpackLibcameraRaw(buffer, f, 5, 3, int64_t{1} << 62));
}

LibcameraFormatOffer offer(std::string_view name, std::vector<PixelSize> sizes) {
    const LibcameraRawFormat* f = findLibcameraRawFormat(name);
    LibcameraFormatOffer o;
    o.name = std::string(name);
    o.fourcc = f ? f->fourcc : libcameraFourcc('Y', 'U', 'Y', 'V');
    o.modifier = f ? f->modifier : 0;
    o.sizes = std::move(sizes);
    return o;
}

TEST(ChooseLibcameraFormat, TakesTheDeepestUnpackedFormatAtItsLargestSize) {
    const std::vector<LibcameraFormatOffer> offers = {
        offer("YUYV", {{640, 480}}),
        offer("SBGGR10_CSI2P", {{640, 480}, {3280, 2464}}),
        offer("SBGGR12_CSI2P", {{1332, 990}, {4056, 3040}, {2028, 1520}}),
        offer("SBGGR12", {{2028, 1520}, {4056, 3040}}),
    };
    const auto choice = chooseLibcameraFormat(offers, {}, "cam");
    ASSERT_TRUE(choice) << choice.error().message;
    EXPECT_EQ(choice->format.name, "SBGGR12");
    EXPECT_EQ(choice->size, (PixelSize{4056, 3040}));
    EXPECT_EQ(choice->format.layout, hdr::RawFormat::BayerBGGR);
    // Packed CSI-2 before IPU3 at the same depth.
    const std::vector<LibcameraFormatOffer> packed = {offer("SRGGB10_IPU3", {{64, 48}}),
                                                      offer("SRGGB10_CSI2P", {{64, 48}})};
    EXPECT_EQ(chooseLibcameraFormat(packed, {}, "cam")->format.name, "SRGGB10_CSI2P");
}

TEST(ChooseLibcameraFormat, KeepsWhatTheUriAsksForOrSaysWhatIsOffered) {
    const std::vector<LibcameraFormatOffer> offers = {
        offer("SRGGB10_CSI2P", {{640, 480}, {1640, 1232}, {3280, 2464}}),
        offer("SRGGB8", {{640, 480}}),
    };
    const auto asked = chooseLibcameraFormat(offers, {"SRGGB10_CSI2P", 1640, 0}, "cam");
    ASSERT_TRUE(asked) << asked.error().message;
    EXPECT_EQ(asked->size, (PixelSize{1640, 1232}));
    const auto eight = chooseLibcameraFormat(offers, {"SRGGB8", 0, 0}, "cam");
    ASSERT_TRUE(eight);
    EXPECT_EQ(eight->format.bit_depth, 8);

    const auto missing = chooseLibcameraFormat(offers, {"SRGGB12", 0, 0}, "cam");
    ASSERT_FALSE(missing);
    EXPECT_EQ(deviceFaultOf(missing.error()), DeviceFault::OutOfRange);
    EXPECT_TRUE(mentions(missing.error(), "format = SRGGB12"));
    EXPECT_TRUE(mentions(missing.error(), "SRGGB10_CSI2P (640x480 1640x1232 3280x2464)"));

    const auto no_width = chooseLibcameraFormat(offers, {"", 1920, 0}, "cam");
    ASSERT_FALSE(no_width);
    EXPECT_EQ(deviceFaultOf(no_width.error()), DeviceFault::OutOfRange);
    EXPECT_TRUE(mentions(no_width.error(), "width = 1920"));
    const auto no_size = chooseLibcameraFormat(offers, {"", 640, 481}, "cam");
    ASSERT_FALSE(no_size);
    EXPECT_TRUE(mentions(no_size.error(), "width x height = 640x481"));
}

TEST(ChooseLibcameraFormat, RefusesACameraWithoutReadableRawFormats) {
    const std::vector<LibcameraFormatOffer> offers = {offer("YUYV", {{640, 480}}),
                                                      offer("SRGGB10", {})};
    const auto choice = chooseLibcameraFormat(offers, {}, "cam");
    ASSERT_FALSE(choice);
    EXPECT_EQ(choice.error().code, ErrorCode::Unsupported);
    EXPECT_TRUE(mentions(choice.error(), "YUYV (640x480)"));
    EXPECT_TRUE(mentions(choice.error(), "SRGGB10 (no size)"));
    EXPECT_FALSE(chooseLibcameraFormat({}, {}, "cam"));
}

TEST(AcceptValidatedFormat, TakesAFlippedBayerOrderUnlessTheUriNamedTheFormat) {
    const LibcameraRawFormat& flipped = format("SGRBG10_CSI2P");
    const auto taken = acceptValidatedFormat(flipped.fourcc, flipped.modifier, flipped.name,
                                             {3280, 2464}, {}, "cam");
    ASSERT_TRUE(taken) << taken.error().message;
    EXPECT_EQ(taken->format.layout, hdr::RawFormat::BayerGRBG);
    EXPECT_EQ(taken->size, (PixelSize{3280, 2464}));

    const auto named = acceptValidatedFormat(flipped.fourcc, flipped.modifier, flipped.name,
                                             {3280, 2464}, {"SRGGB10_CSI2P", 0, 0}, "cam");
    ASSERT_FALSE(named);
    EXPECT_EQ(deviceFaultOf(named.error()), DeviceFault::OutOfRange);
    EXPECT_TRUE(mentions(named.error(), "format = SRGGB10_CSI2P"));
    EXPECT_TRUE(mentions(named.error(), "SGRBG10_CSI2P 3280x2464"));

    const auto resized = acceptValidatedFormat(flipped.fourcc, flipped.modifier, flipped.name,
                                               {3280, 2464}, {"", 0, 2000}, "cam");
    ASSERT_FALSE(resized);
    EXPECT_TRUE(mentions(resized.error(), "height = 2000"));

    const auto yuyv =
        acceptValidatedFormat(libcameraFourcc('Y', 'U', 'Y', 'V'), 0, "YUYV", {64, 48}, {}, "cam");
    ASSERT_FALSE(yuyv);
    EXPECT_TRUE(mentions(yuyv.error(), "format: the camera adjusted its raw stream to YUYV"));
    EXPECT_FALSE(
        acceptValidatedFormat(flipped.fourcc, flipped.modifier, flipped.name, {0, 0}, {}, "cam"));
}

TEST(LibcameraLimits, RefusesACameraWithoutManualExposureNamingTheControl) {
    const LibcameraControlRange exposure{29, 6'700'000}, gain{1.0, 22.26};
    const auto none = libcameraLimits(std::nullopt, gain, "cam");
    ASSERT_FALSE(none);
    EXPECT_EQ(none.error().code, ErrorCode::Unsupported);
    EXPECT_TRUE(mentions(none.error(), "ExposureTime"));
    const auto no_gain = libcameraLimits(exposure, std::nullopt, "cam");
    ASSERT_FALSE(no_gain);
    EXPECT_TRUE(mentions(no_gain.error(), "AnalogueGain"));

    const auto limits = libcameraLimits(exposure, gain, "cam");
    ASSERT_TRUE(limits);
    EXPECT_EQ(limits->min_exposure_us, 29);
    EXPECT_EQ(limits->max_exposure_us, 6'700'000);
    EXPECT_DOUBLE_EQ(limits->max_gain, 22.26);
    // The Raspberry Pi IPA's static range starts at 0; a range past int32 is cut to it.
    const auto wide = libcameraLimits(LibcameraControlRange{0, 1e12}, gain, "cam");
    ASSERT_TRUE(wide);
    EXPECT_EQ(wide->min_exposure_us, 1);
    EXPECT_EQ(wide->max_exposure_us, 2147483647);

    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    for (const LibcameraControlRange& bad :
         {LibcameraControlRange{10, 5}, LibcameraControlRange{0, 0.5},
          LibcameraControlRange{kNaN, kNaN}, LibcameraControlRange{0.2, 0.8}}) {
        const auto refused = libcameraLimits(bad, gain, "cam");
        ASSERT_FALSE(refused) << bad.min << " " << bad.max;
        EXPECT_EQ(refused.error().code, ErrorCode::IoError);
        EXPECT_TRUE(mentions(refused.error(), "ExposureTime range"));
    }
    for (const LibcameraControlRange& bad :
         {LibcameraControlRange{0, 16}, LibcameraControlRange{4, 2},
          LibcameraControlRange{1, std::numeric_limits<double>::infinity()}})
        EXPECT_FALSE(libcameraLimits(exposure, bad, "cam")) << bad.min << " " << bad.max;
}

TEST(ExposureToMicroseconds, RoundsToWholeMicrosecondsAndNeverClamps) {
    const LibcameraLimits limits{29, 6'700'000, 1.0, 16.0};
    EXPECT_EQ(*exposureToMicroseconds(0.25, limits, "cam"), 250000);
    EXPECT_EQ(*exposureToMicroseconds(4.0, limits, "cam"), 4000000);
    EXPECT_EQ(*exposureToMicroseconds(29.4e-6, limits, "cam"), 29);
    EXPECT_EQ(*exposureToMicroseconds(6.7, limits, "cam"), 6700000);
    for (double bad : {28.4e-6, 6.7000006, 0.0, -1.0, 1e300, std::nan(""),
                       std::numeric_limits<double>::infinity()}) {
        const auto refused = exposureToMicroseconds(bad, limits, "cam");
        ASSERT_FALSE(refused) << bad;
        EXPECT_EQ(deviceFaultOf(refused.error()), DeviceFault::OutOfRange);
        EXPECT_TRUE(mentions(refused.error(), "exposure_s = "));
        EXPECT_TRUE(mentions(refused.error(), "[2.9e-05, 6.7]")) << refused.error().message;
    }
    EXPECT_FLOAT_EQ(*gainToControl(2.5, limits, "cam"), 2.5f);
    EXPECT_FLOAT_EQ(*gainToControl(16.0, limits, "cam"), 16.0f);
    for (double bad : {0.99, 16.01, std::nan(""), -std::numeric_limits<double>::infinity()}) {
        const auto refused = gainToControl(bad, limits, "cam");
        ASSERT_FALSE(refused) << bad;
        EXPECT_EQ(deviceFaultOf(refused.error()), DeviceFault::OutOfRange);
        EXPECT_TRUE(mentions(refused.error(), "gain = "));
    }
}

LibcameraFormatChoice choice(std::string_view name, int64_t w, int64_t h) {
    return LibcameraFormatChoice{format(name), PixelSize{w, h}};
}

TEST(RawFrameFromLibcamera, CarriesWhatTheMetadataSaysTheSensorDid) {
    LibcameraFrameMetadata m;
    m.exposure_us = 249'987;  // rounded to a line time
    m.analogue_gain = 2.0117;
    m.sensor_timestamp_ns = 1'234'567'890'123;
    m.black_levels = std::array<int64_t, 4>{4096, 4096, 4096, 4160};  // on a 16-bit scale
    m.sequence = 42;
    m.host_timestamp_ns = 1'700'000'000'000'000'000;
    const auto frame = rawFrameFromLibcamera(m, {250'000, 2.0f}, choice("SGBRG10_CSI2P", 3, 2),
                                             {1, 2, 3, 4, 5, 6}, "imx477 /base/i2c@1");
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_DOUBLE_EQ(frame->exposure_s, 0.249987);
    EXPECT_DOUBLE_EQ(frame->gain, 2.0117);
    EXPECT_EQ(frame->timestamp_ns, 1'234'567'890'123);
    EXPECT_EQ(frame->timestamp_marks, hdr::TimestampMark::ExposureStart);
    EXPECT_EQ(frame->host_timestamp_ns, 1'700'000'000'000'000'000);
    EXPECT_EQ(frame->sequence, 42);
    EXPECT_EQ(frame->bit_depth, 10);
    EXPECT_DOUBLE_EQ(frame->white_level_dn, 1023.0);
    EXPECT_DOUBLE_EQ(frame->black_level_dn, 4112.0 / 64.0);  // mean, 16 bits to 10
    EXPECT_EQ(frame->format, hdr::RawFormat::BayerGBRG);
    EXPECT_EQ(frame->width, 3);
    EXPECT_EQ(frame->height, 2);
    EXPECT_EQ(frame->samples, (std::vector<uint16_t>{1, 2, 3, 4, 5, 6}));
    EXPECT_EQ(frame->camera, "imx477 /base/i2c@1");
    EXPECT_TRUE(hdr::validateRawFrame(*frame));
}

TEST(RawFrameFromLibcamera, FallsBackToTheRequestWhereThePipelineSaysNothing) {
    LibcameraFrameMetadata m;  // uvcvideo in 0.0.3 reports only SensorTimestamp
    const auto frame = rawFrameFromLibcamera(m, {10'000, 1.5f}, choice("R12", 2, 1), {7, 8}, "cam");
    ASSERT_TRUE(frame);
    EXPECT_DOUBLE_EQ(frame->exposure_s, 0.01);
    EXPECT_DOUBLE_EQ(frame->gain, 1.5);
    EXPECT_EQ(frame->timestamp_marks, hdr::TimestampMark::Unknown);
    EXPECT_DOUBLE_EQ(frame->black_level_dn, 0.0);
    EXPECT_DOUBLE_EQ(frame->white_level_dn, 4095.0);
    EXPECT_TRUE(hdr::validateRawFrame(*frame));
}

TEST(RawFrameFromLibcamera, RefusesImpossibleMetadataNamingTheControl) {
    const auto with = [](auto change) {
        LibcameraFrameMetadata m;
        change(m);
        return rawFrameFromLibcamera(m, {1000, 1.0f}, choice("R8", 1, 1), {0}, "cam");
    };
    const std::pair<Result<hdr::RawFrame>, const char*> cases[] = {
        {with([](LibcameraFrameMetadata& m) { m.exposure_us = 0; }), "ExposureTime"},
        {with([](LibcameraFrameMetadata& m) { m.exposure_us = -5; }), "ExposureTime"},
        {with([](LibcameraFrameMetadata& m) { m.analogue_gain = std::nan(""); }), "AnalogueGain"},
        {with([](LibcameraFrameMetadata& m) { m.analogue_gain = 0.0; }), "AnalogueGain"},
        {with([](LibcameraFrameMetadata& m) { m.sensor_timestamp_ns = -1; }), "SensorTimestamp"},
        // 8-bit black at 65280 / 256 = 255: not below white.
        {with([](LibcameraFrameMetadata& m) {
             m.black_levels = std::array<int64_t, 4>{65280, 65280, 65280, 65280};
         }),
         "SensorBlackLevels"},
        {with([](LibcameraFrameMetadata& m) {
             m.black_levels = std::array<int64_t, 4>{0, 0, 0, 70000};
         }),
         "SensorBlackLevels"},
    };
    for (const auto& [result, control] : cases) {
        ASSERT_FALSE(result) << control;
        EXPECT_EQ(result.error().code, ErrorCode::IoError);
        EXPECT_TRUE(mentions(result.error(), control)) << result.error().message;
    }
    const auto short_samples =
        rawFrameFromLibcamera({}, {1000, 1.0f}, choice("R8", 2, 2), {1, 2, 3}, "cam");
    ASSERT_FALSE(short_samples);
    EXPECT_TRUE(mentions(short_samples.error(), "samples: 3"));
}

LibcameraFrameMetadata shows(int64_t exposure_us, double gain) {
    LibcameraFrameMetadata m;
    m.exposure_us = exposure_us;
    m.analogue_gain = gain;
    return m;
}

using Verdict = LibcameraSettleTracker::Verdict;

TEST(LibcameraSettleTracker, DropsFramesStillShowingTheOldExposure) {
    LibcameraSettleTracker tracker(30);
    tracker.request({1'000'000, 1.0f});
    EXPECT_EQ(tracker.judge(shows(999'990, 1.0), "cam").verdict, Verdict::Accept);
    // A Raspberry Pi sensor: the new exposure shows two frames after it was asked for, rounded
    // to a line time.
    tracker.request({250'000, 1.0f});
    EXPECT_EQ(tracker.judge(shows(999'990, 1.0), "cam").verdict, Verdict::Discard);
    EXPECT_EQ(tracker.judge(shows(999'990, 1.0), "cam").verdict, Verdict::Discard);
    EXPECT_EQ(tracker.judge(shows(249'981, 1.0), "cam").verdict, Verdict::Accept);
    // Unchanged settings keep their count: the next frame is judged on its own.
    tracker.request({250'000, 1.0f});
    EXPECT_EQ(tracker.framesSinceChange(), 3);
    EXPECT_EQ(tracker.judge(shows(249'981, 1.0), "cam").verdict, Verdict::Accept);
    // A gain change alone, to a gain code near the one asked for.
    tracker.request({250'000, 4.0f});
    EXPECT_EQ(tracker.judge(shows(249'981, 1.0), "cam").verdict, Verdict::Discard);
    EXPECT_EQ(tracker.judge(shows(249'981, 3.93), "cam").verdict, Verdict::Accept);
}

TEST(LibcameraSettleTracker, ToleratesOneLineTimeAtShortExposures) {
    LibcameraSettleTracker tracker(30);  // the camera's shortest exposure: about a line
    tracker.request({100, 1.0f});
    EXPECT_EQ(tracker.judge(shows(250'000, 1.0), "cam").verdict, Verdict::Discard);
    EXPECT_EQ(tracker.judge(shows(90, 1.0), "cam").verdict, Verdict::Accept);
    tracker.request({100, 1.0f});
    EXPECT_EQ(tracker.judge(shows(131, 1.0), "cam").verdict, Verdict::Discard);
}

TEST(LibcameraSettleTracker, DropsBlindFramesWhenThePipelineCannotSay) {
    LibcameraSettleTracker tracker;
    tracker.request({20'000, 1.0f});
    for (int i = 0; i < LibcameraSettleTracker::kBlindFrames; ++i)
        EXPECT_EQ(tracker.judge({}, "cam").verdict, Verdict::Discard) << i;
    EXPECT_EQ(tracker.judge({}, "cam").verdict, Verdict::Accept);
    EXPECT_EQ(tracker.judge({}, "cam").verdict, Verdict::Accept);
}

TEST(LibcameraSettleTracker, RefusesSettingsTheCameraNeverApplies) {
    LibcameraSettleTracker tracker(30);
    tracker.request({4'000'000, 1.0f});
    for (int i = 1; i < LibcameraSettleTracker::kMaxFrames; ++i)
        EXPECT_EQ(tracker.judge(shows(66'666, 1.0), "cam").verdict, Verdict::Discard) << i;
    const auto refused = tracker.judge(shows(66'666, 1.0), "cam");
    ASSERT_EQ(refused.verdict, Verdict::Refuse);
    ASSERT_TRUE(refused.error);
    EXPECT_EQ(deviceFaultOf(*refused.error), DeviceFault::OutOfRange);
    EXPECT_TRUE(mentions(*refused.error, "exposure_s = 4 "));
    EXPECT_TRUE(mentions(*refused.error, "reports 0.066666 s"));

    LibcameraSettleTracker gains(30);
    gains.request({1000, 16.0f});
    LibcameraSettleTracker::Decision last;
    for (int i = 0; i < LibcameraSettleTracker::kMaxFrames; ++i)
        last = gains.judge(shows(1000, 10.67), "cam");
    ASSERT_EQ(last.verdict, Verdict::Refuse);
    EXPECT_TRUE(mentions(*last.error, "gain = 16"));
}

TEST(LibcameraOptionsFromUri, ReadsNameSizeAndFormatAndRefusesUnknownParametersByName) {
    const auto uri = parseDeviceUri(
        "libcamera:/base/soc/i2c0mux/i2c@1/imx477@1a?width=2028&height=1520&format=SBGGR12_CSI2P");
    ASSERT_TRUE(uri);
    const auto options = libcameraOptionsFromUri(*uri);
    ASSERT_TRUE(options) << options.error().message;
    EXPECT_EQ(options->name, "/base/soc/i2c0mux/i2c@1/imx477@1a");
    EXPECT_EQ(options->format.width, 2028);
    EXPECT_EQ(options->format.height, 1520);
    EXPECT_EQ(options->format.format, "SBGGR12_CSI2P");

    const auto bare = libcameraOptionsFromUri(*parseDeviceUri("libcamera:"));
    ASSERT_TRUE(bare);
    EXPECT_EQ(bare->name, "");
    EXPECT_EQ(bare->format.width, 0);

    const std::pair<const char*, const char*> bad[] = {
        {"libcamera:x?exposure=1", "'exposure'"},     {"libcamera:x?width=0", "width"},
        {"libcamera:x?height=12.5", "height"},        {"libcamera:x?width=wide", "width"},
        {"libcamera:x?format=YUYV", "format='YUYV'"},
    };
    for (const auto& [text, field] : bad) {
        const auto refused = libcameraOptionsFromUri(*parseDeviceUri(text));
        ASSERT_FALSE(refused) << text;
        EXPECT_EQ(refused.error().code, ErrorCode::InvalidArgument);
        EXPECT_TRUE(mentions(refused.error(), field)) << refused.error().message;
    }
}

TEST(PickLibcameraCamera, TakesAnIdOrAUniquePartOfOne) {
    const std::vector<std::string> ids = {"/base/soc/i2c0mux/i2c@1/imx477@1a",
                                          "/base/soc/i2c0mux/i2c@0/imx219@10",
                                          "\\_SB_.PCI0.XHC_.RHUB.HS05-5:1.0-04f2:b6dd"};
    EXPECT_EQ(*pickLibcameraCamera(ids, ids[1]), ids[1]);
    EXPECT_EQ(*pickLibcameraCamera(ids, "imx477"), ids[0]);
    EXPECT_EQ(*pickLibcameraCamera(ids, "04f2:b6dd"), ids[2]);
    const auto ambiguous = pickLibcameraCamera(ids, "i2c0mux");
    ASSERT_FALSE(ambiguous);
    EXPECT_EQ(ambiguous.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(mentions(ambiguous.error(), "2 cameras match"));
    const auto missing = pickLibcameraCamera(ids, "ov5647");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(mentions(missing.error(), "'ov5647'"));
    EXPECT_TRUE(mentions(missing.error(), "imx219@10"));
    EXPECT_FALSE(pickLibcameraCamera(ids, ""));  // several: name one
    const std::vector<std::string> one = {ids[0]};
    EXPECT_EQ(*pickLibcameraCamera(one, ""), ids[0]);
    const auto none = pickLibcameraCamera({}, "");
    ASSERT_FALSE(none);
    EXPECT_EQ(none.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(mentions(none.error(), "libcamera sees no camera"));
}

#if FLARELAB_HAVE_LIBCAMERA

// libcamera needs a media controller device (/dev/mediaN) for every pipeline it has; without
// one it can see no camera.
bool machineHasMediaDevices() {
    std::error_code ec;
    for (const auto& entry : std::filesystem::directory_iterator("/dev", ec))
        if (entry.path().filename().string().rfind("media", 0) == 0) return true;
    return false;
}

// The backend keeps libcamera's log off stderr unless a lab asked for it (libcamera_camera.h).
bool libcameraLogRequested() {
    return std::getenv("LIBCAMERA_LOG_FILE") || std::getenv("LIBCAMERA_LOG_LEVELS");
}

TEST(LibcameraBackend, NamesEveryFormatAsLibcameraPrintsIt) {
    for (const LibcameraRawFormat& f : libcameraRawFormats())
        EXPECT_EQ(libcameraFormatName(f.fourcc, f.modifier), f.name);
    EXPECT_EQ(libcameraFormatName(libcameraFourcc('Y', 'U', 'Y', 'V'), 0), "YUYV");
}

TEST(LibcameraBackend, ListsNoCameraOnAMachineWithoutOneAndStaysQuiet) {
    testing::internal::CaptureStderr();
    const std::vector<DeviceListing> found = listLibcameraCameras();
    const std::string logged = testing::internal::GetCapturedStderr();
    if (!libcameraLogRequested()) {
        EXPECT_EQ(logged, "") << "libcamera's log reached stderr";
    }
    for (const DeviceListing& d : found) {
        EXPECT_EQ(d.backend, "libcamera");
        EXPECT_EQ(d.uri.rfind("libcamera:", 0), 0u) << d.uri;
        EXPECT_TRUE(d.details.empty() || d.details.front().rfind("error:", 0) != 0)
            << "libcamera did not start: " << d.details.front();
    }
    if (machineHasMediaDevices())
        GTEST_SKIP() << "this machine has /dev/media*: it may have cameras";
    EXPECT_TRUE(found.empty());
    EXPECT_EQ(libcameraVersion().rfind("v0.", 0), 0u) << libcameraVersion();
}

TEST(LibcameraBackend, OpeningACameraThatIsNotThereNamesIt) {
    CameraRegistry registry;
    ASSERT_TRUE(addLibcameraCameraBackend(registry));
    testing::internal::CaptureStderr();
    const auto camera = registry.open("libcamera:flarelab-no-such-camera?width=64");
    const std::string logged = testing::internal::GetCapturedStderr();
    ASSERT_FALSE(camera);
    EXPECT_EQ(camera.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(mentions(camera.error(), "libcamera camera 'flarelab-no-such-camera': not found"))
        << camera.error().message;
    if (!libcameraLogRequested()) {
        EXPECT_EQ(logged, "");
    }
    // Twice in a row: the shared CameraManager is made again after the last user let go
    // (libcamera 0.0.3 aborts on a second one alive at once).
    const auto again = registry.open("libcamera:flarelab-no-such-camera");
    ASSERT_FALSE(again);
    EXPECT_EQ(again.error().code, ErrorCode::NotFound);
    // A bad URI is refused before libcamera is asked.
    const auto bad = registry.open("libcamera:x?shutter=1");
    ASSERT_FALSE(bad);
    EXPECT_EQ(bad.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(mentions(bad.error(), "'shutter'"));
    if (!machineHasMediaDevices()) {
        const auto any = registry.open("libcamera:");
        ASSERT_FALSE(any);
        EXPECT_EQ(any.error().code, ErrorCode::NotFound);
        EXPECT_TRUE(mentions(any.error(), "libcamera sees no camera"));
    }
    EXPECT_TRUE(registry.enumerate().empty() || machineHasMediaDevices());
}

#endif  // FLARELAB_HAVE_LIBCAMERA

}  // namespace
}  // namespace flarelab::drivers
