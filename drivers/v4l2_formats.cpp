#include "drivers/v4l2_formats.h"

#include <linux/videodev2.h>

#include <algorithm>
#include <array>

namespace flarelab::drivers {
namespace {

using hdr::RawFormat;
constexpr RawFormat kMono = RawFormat::Mono;
constexpr RawFormat kRggb = RawFormat::BayerRGGB;
constexpr RawFormat kBggr = RawFormat::BayerBGGR;
constexpr RawFormat kGrbg = RawFormat::BayerGRBG;
constexpr RawFormat kGbrg = RawFormat::BayerGBRG;

constexpr const char* kLsb = "LSB-aligned in 16-bit little-endian words";
constexpr const char* kFull =
    "16-bit little-endian words (sensor depth and alignment: bits=, align=)";
constexpr const char* kMipi = "MIPI CSI-2 packed";

V4l2FormatInfo raw(uint32_t fourcc,
                   const char* name,
                   RawFormat format,
                   int bits,
                   V4l2Layout layout,
                   const char* note) {
    V4l2FormatInfo f;
    f.fourcc = fourcc;
    f.name = name;
    f.raw_format = format;
    f.bits = bits;
    f.layout = layout;
    f.layout_note = note;
    return f;
}

V4l2FormatInfo luma422(uint32_t fourcc, const char* name, int offset) {
    V4l2FormatInfo f = raw(fourcc, name, kMono, 8, V4l2Layout::LumaOf422,
                           "luma of interleaved 4:2:2 YUV (gamma-encoded)");
    f.raw = false;
    f.luma_offset = offset;
    return f;
}

V4l2FormatInfo lumaPlane(uint32_t fourcc, const char* name, int num, int den) {
    V4l2FormatInfo f =
        raw(fourcc, name, kMono, 8, V4l2Layout::LumaPlane, "luma plane of YUV (gamma-encoded)");
    f.raw = false;
    f.size_num = num;
    f.size_den = den;
    return f;
}

const std::vector<V4l2FormatInfo>& table() {
    using L = V4l2Layout;
    static const std::vector<V4l2FormatInfo> formats = {
        raw(V4L2_PIX_FMT_Y16, "Y16", kMono, 16, L::Full16, kFull),
        raw(V4L2_PIX_FMT_Y16_BE, "Y16-BE", kMono, 16, L::Full16Be, "16-bit big-endian words"),
        raw(V4L2_PIX_FMT_SRGGB16, "RG16", kRggb, 16, L::Full16, kFull),
        raw(V4L2_PIX_FMT_SBGGR16, "BYR2", kBggr, 16, L::Full16, kFull),
        raw(V4L2_PIX_FMT_SGRBG16, "GR16", kGrbg, 16, L::Full16, kFull),
        raw(V4L2_PIX_FMT_SGBRG16, "GB16", kGbrg, 16, L::Full16, kFull),
        raw(V4L2_PIX_FMT_Y14, "Y14", kMono, 14, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SRGGB14, "RG14", kRggb, 14, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SBGGR14, "BG14", kBggr, 14, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SGRBG14, "GR14", kGrbg, 14, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SGBRG14, "GB14", kGbrg, 14, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SRGGB14P, "pREE", kRggb, 14, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SBGGR14P, "pBEE", kBggr, 14, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SGRBG14P, "pgEE", kGrbg, 14, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SGBRG14P, "pGEE", kGbrg, 14, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_Y12, "Y12", kMono, 12, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SRGGB12, "RG12", kRggb, 12, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SBGGR12, "BG12", kBggr, 12, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SGRBG12, "BA12", kGrbg, 12, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SGBRG12, "GB12", kGbrg, 12, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SRGGB12P, "pRCC", kRggb, 12, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SBGGR12P, "pBCC", kBggr, 12, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SGRBG12P, "pgCC", kGrbg, 12, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SGBRG12P, "pGCC", kGbrg, 12, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_Y10, "Y10", kMono, 10, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_Y10P, "Y10P", kMono, 10, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_Y10BPACK, "Y10B", kMono, 10, L::BitPackedBe,
            "bit-packed, most significant bit first"),
        raw(V4L2_PIX_FMT_SRGGB10, "RG10", kRggb, 10, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SBGGR10, "BG10", kBggr, 10, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SGRBG10, "BA10", kGrbg, 10, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SGBRG10, "GB10", kGbrg, 10, L::Lsb16, kLsb),
        raw(V4L2_PIX_FMT_SRGGB10P, "pRAA", kRggb, 10, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SBGGR10P, "pBAA", kBggr, 10, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SGRBG10P, "pgAA", kGrbg, 10, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_SGBRG10P, "pGAA", kGbrg, 10, L::Mipi, kMipi),
        raw(V4L2_PIX_FMT_GREY, "GREY", kMono, 8, L::Byte, "one byte a sample"),
        raw(V4L2_PIX_FMT_SRGGB8, "RGGB", kRggb, 8, L::Byte, "one byte a sample"),
        raw(V4L2_PIX_FMT_SBGGR8, "BA81", kBggr, 8, L::Byte, "one byte a sample"),
        raw(V4L2_PIX_FMT_SGRBG8, "GRBG", kGrbg, 8, L::Byte, "one byte a sample"),
        raw(V4L2_PIX_FMT_SGBRG8, "GBRG", kGbrg, 8, L::Byte, "one byte a sample"),
        luma422(V4L2_PIX_FMT_YUYV, "YUYV", 0),
        luma422(V4L2_PIX_FMT_YVYU, "YVYU", 0),
        luma422(V4L2_PIX_FMT_UYVY, "UYVY", 1),
        luma422(V4L2_PIX_FMT_VYUY, "VYUY", 1),
        lumaPlane(V4L2_PIX_FMT_NV12, "NV12", 3, 2),
        lumaPlane(V4L2_PIX_FMT_NV21, "NV21", 3, 2),
        lumaPlane(V4L2_PIX_FMT_YUV420, "YU12", 3, 2),
        lumaPlane(V4L2_PIX_FMT_YVU420, "YV12", 3, 2),
        lumaPlane(V4L2_PIX_FMT_NV16, "NV16", 2, 1),
        lumaPlane(V4L2_PIX_FMT_NV61, "NV61", 2, 1),
        lumaPlane(V4L2_PIX_FMT_YUV422P, "422P", 2, 1),
        lumaPlane(V4L2_PIX_FMT_NV24, "NV24", 3, 1),
        lumaPlane(V4L2_PIX_FMT_NV42, "NV42", 3, 1),
    };
    return formats;
}

// MIPI CSI-2 packing: samples per group and bytes per group.
int mipiGroup(int bits) { return bits == 12 ? 2 : 4; }
int mipiGroupBytes(int bits) { return mipiGroup(bits) * bits / 8; }

constexpr int64_t kMaxSide = int64_t{1} << 15;

Error badBuffer(const std::string& what) {
    return makeError(ErrorCode::IoError, "v4l2 frame: " + what);
}

}  // namespace

std::span<const V4l2FormatInfo> v4l2Formats() { return table(); }

const V4l2FormatInfo* findV4l2Format(uint32_t fourcc) {
    for (const V4l2FormatInfo& f : table())
        if (f.fourcc == fourcc) return &f;
    return nullptr;
}

std::string fourccText(uint32_t fourcc) {
    std::string text;
    for (int i = 0; i < 4; ++i) {
        const auto c = static_cast<char>((fourcc >> (8 * i)) & (i == 3 ? 0x7f : 0xff));
        text += (c >= 0x20 && c < 0x7f) ? c : '.';
    }
    while (!text.empty() && text.back() == ' ') text.pop_back();
    if (fourcc & (1u << 31)) text += "-BE";
    return text;
}

std::optional<uint32_t> fourccFromText(std::string_view text) {
    bool big_endian = false;
    if (text.size() > 3 && text.substr(text.size() - 3) == "-BE") {
        big_endian = true;
        text.remove_suffix(3);
    }
    if (text.empty() || text.size() > 4) return std::nullopt;
    uint32_t fourcc = 0;
    for (int i = 0; i < 4; ++i) {
        const char c = i < static_cast<int>(text.size()) ? text[i] : ' ';
        if (c < 0x20 || c >= 0x7f) return std::nullopt;
        fourcc |= static_cast<uint32_t>(static_cast<unsigned char>(c)) << (8 * i);
    }
    if (big_endian) {
        if (fourcc & (1u << 31)) return std::nullopt;
        fourcc |= 1u << 31;
    }
    return fourcc;
}

int64_t minBytesPerLine(const V4l2FormatInfo& format, int64_t width) {
    if (width < 1) return 0;
    switch (format.layout) {
        case V4l2Layout::Byte:
        case V4l2Layout::LumaPlane:
            return width;
        case V4l2Layout::Lsb16:
        case V4l2Layout::Full16:
        case V4l2Layout::Full16Be:
            return 2 * width;
        case V4l2Layout::Mipi: {
            const int group = mipiGroup(format.bits);
            return (width + group - 1) / group * mipiGroupBytes(format.bits);
        }
        case V4l2Layout::BitPackedBe:
            return (width * format.bits + 7) / 8;
        case V4l2Layout::LumaOf422:
            return 2 * ((width + 1) / 2 * 2);
    }
    return 0;
}

int64_t imageBytes(const V4l2FormatInfo& format, int64_t bytes_per_line, int64_t height) {
    return bytes_per_line * height * format.size_num / format.size_den;
}

Result<V4l2Samples> unpackV4l2Samples(const V4l2FormatInfo& format,
                                      std::span<const uint8_t> bytes,
                                      const V4l2Unpacking& u) {
    if (u.width < 1 || u.height < 1 || u.width > kMaxSide || u.height > kMaxSide)
        return badBuffer("width x height = " + std::to_string(u.width) + " x " +
                         std::to_string(u.height) + " is not in 1..32768 a side");
    const int64_t line = minBytesPerLine(format, u.width);
    if (u.bytes_per_line < line)
        return badBuffer("bytes_per_line = " + std::to_string(u.bytes_per_line) + " does not fit " +
                         std::to_string(u.width) + " samples of " + fourccText(format.fourcc) +
                         " (" + std::to_string(line) + " bytes at least)");
    const int64_t needed = u.bytes_per_line * (u.height - 1) + line;
    if (static_cast<int64_t>(bytes.size()) < needed)
        return badBuffer("bytesused = " + std::to_string(bytes.size()) + " is less than the " +
                         std::to_string(needed) + " bytes of a " + std::to_string(u.width) + "x" +
                         std::to_string(u.height) + " " + fourccText(format.fourcc) + " frame");
    const bool full16 =
        format.layout == V4l2Layout::Full16 || format.layout == V4l2Layout::Full16Be;
    const int value_bits = u.value_bits == 0 ? format.bits : u.value_bits;
    if (value_bits < 1 || value_bits > format.bits || (!full16 && value_bits != format.bits) ||
        (u.msb_aligned && !full16))
        return makeError(ErrorCode::InvalidArgument,
                         "v4l2 frame: " + fourccText(format.fourcc) + " carries " +
                             std::to_string(format.bits) + "-bit samples; " +
                             std::to_string(value_bits) + " bits" +
                             (u.msb_aligned ? ", MSB-aligned," : "") + " do not apply to it");
    const int shift = u.msb_aligned ? format.bits - value_bits : 0;
    const uint32_t white = (uint32_t{1} << value_bits) - 1;

    V4l2Samples out;
    out.bit_depth = value_bits;
    out.samples.resize(static_cast<size_t>(u.width * u.height));
    for (int64_t y = 0; y < u.height; ++y) {
        const uint8_t* row = bytes.data() + y * u.bytes_per_line;
        uint16_t* dst = out.samples.data() + y * u.width;
        switch (format.layout) {
            case V4l2Layout::Byte:
            case V4l2Layout::LumaPlane:
                for (int64_t x = 0; x < u.width; ++x) dst[x] = row[x];
                break;
            case V4l2Layout::LumaOf422:
                for (int64_t x = 0; x < u.width; ++x) dst[x] = row[2 * x + format.luma_offset];
                break;
            case V4l2Layout::Lsb16:
            case V4l2Layout::Full16:
                for (int64_t x = 0; x < u.width; ++x)
                    dst[x] = static_cast<uint16_t>(row[2 * x] | (row[2 * x + 1] << 8));
                break;
            case V4l2Layout::Full16Be:
                for (int64_t x = 0; x < u.width; ++x)
                    dst[x] = static_cast<uint16_t>((row[2 * x] << 8) | row[2 * x + 1]);
                break;
            case V4l2Layout::Mipi: {
                // Per group: `group` high bytes, then the low bits of each sample in turn,
                // the first in the lowest bits of the first low byte.
                const int group = mipiGroup(format.bits);
                const int group_bytes = mipiGroupBytes(format.bits);
                const int low_bits = format.bits - 8;
                for (int64_t x0 = 0; x0 < u.width; x0 += group) {
                    const uint8_t* g = row + x0 / group * group_bytes;
                    uint32_t low = 0;
                    for (int b = group; b < group_bytes; ++b)
                        low |= static_cast<uint32_t>(g[b]) << (8 * (b - group));
                    for (int i = 0; i < group && x0 + i < u.width; ++i) {
                        const uint32_t l = (low >> (i * low_bits)) & ((1u << low_bits) - 1);
                        dst[x0 + i] = static_cast<uint16_t>((g[i] << low_bits) | l);
                    }
                }
                break;
            }
            case V4l2Layout::BitPackedBe:
                for (int64_t x = 0; x < u.width; ++x) {
                    uint32_t v = 0;
                    for (int b = 0; b < format.bits; ++b) {
                        const int64_t bit = x * format.bits + b;
                        v = (v << 1) | ((row[bit / 8] >> (7 - bit % 8)) & 1u);
                    }
                    dst[x] = static_cast<uint16_t>(v);
                }
                break;
        }
        for (int64_t x = 0; x < u.width; ++x) {
            const uint32_t v = static_cast<uint32_t>(dst[x]) >> shift;
            if (v > white) ++out.clipped;
            dst[x] = static_cast<uint16_t>(std::min(v, white));
        }
    }
    return out;
}

std::vector<uint8_t> packV4l2Samples(const V4l2FormatInfo& format,
                                     std::span<const uint16_t> samples,
                                     int64_t width,
                                     int64_t height,
                                     int64_t bytes_per_line) {
    std::vector<uint8_t> out(static_cast<size_t>(imageBytes(format, bytes_per_line, height)), 0x80);
    for (int64_t y = 0; y < height; ++y) {
        uint8_t* row = out.data() + y * bytes_per_line;
        const uint16_t* src = samples.data() + y * width;
        switch (format.layout) {
            case V4l2Layout::Byte:
            case V4l2Layout::LumaPlane:
                for (int64_t x = 0; x < width; ++x) row[x] = static_cast<uint8_t>(src[x]);
                break;
            case V4l2Layout::LumaOf422:
                for (int64_t x = 0; x < width; ++x)
                    row[2 * x + format.luma_offset] = static_cast<uint8_t>(src[x]);
                break;
            case V4l2Layout::Lsb16:
            case V4l2Layout::Full16:
                for (int64_t x = 0; x < width; ++x) {
                    row[2 * x] = static_cast<uint8_t>(src[x] & 0xff);
                    row[2 * x + 1] = static_cast<uint8_t>(src[x] >> 8);
                }
                break;
            case V4l2Layout::Full16Be:
                for (int64_t x = 0; x < width; ++x) {
                    row[2 * x] = static_cast<uint8_t>(src[x] >> 8);
                    row[2 * x + 1] = static_cast<uint8_t>(src[x] & 0xff);
                }
                break;
            case V4l2Layout::Mipi: {
                const int group = mipiGroup(format.bits);
                const int group_bytes = mipiGroupBytes(format.bits);
                const int low_bits = format.bits - 8;
                for (int64_t x0 = 0; x0 < width; x0 += group) {
                    uint8_t* g = row + x0 / group * group_bytes;
                    uint32_t low = 0;
                    for (int i = 0; i < group; ++i) {
                        const uint32_t v = x0 + i < width ? src[x0 + i] : 0;
                        g[i] = static_cast<uint8_t>(v >> low_bits);
                        low |= (v & ((1u << low_bits) - 1)) << (i * low_bits);
                    }
                    for (int b = group; b < group_bytes; ++b)
                        g[b] = static_cast<uint8_t>(low >> (8 * (b - group)));
                }
                break;
            }
            case V4l2Layout::BitPackedBe:
                std::fill(row, row + minBytesPerLine(format, width), uint8_t{0});
                for (int64_t x = 0; x < width; ++x)
                    for (int b = 0; b < format.bits; ++b) {
                        const int64_t bit = x * format.bits + b;
                        if ((src[x] >> (format.bits - 1 - b)) & 1u)
                            row[bit / 8] |= static_cast<uint8_t>(0x80u >> (bit % 8));
                    }
                break;
        }
    }
    return out;
}

}  // namespace flarelab::drivers
