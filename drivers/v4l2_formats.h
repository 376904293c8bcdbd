// ============================================================================
//  flarelab drivers: V4l2Layout, V4l2FormatInfo, v4l2Formats, findV4l2Format, fourccText,
//                    fourccFromText, unpackV4l2Samples, packV4l2Samples
// ============================================================================
//
// The V4L2 pixel formats the V4L2 camera (v4l2_camera.h) can turn into 16-bit samples, in the
// order it prefers them, and how each is laid out in memory. Layouts, as the kernel's
// documentation (Documentation/userspace-api/media/v4l/pixfmt-*.rst) defines them:
//
//   Byte       GREY, Bayer 8 (BA81 GBRG GRBG RGGB): one byte a sample.
//   Lsb16      Y10 Y12 Y14, Bayer 10/12/14 expanded (BG10 ... RG14): little-endian 16-bit words,
//              LSB-aligned: a 10-bit sample lies in 0..1023, the high bits are zero.
//   Full16     Y16, Bayer 16 (BYR2 GB16 GR16 RG16): little-endian 16-bit words. V4L2 says the
//              sensor's precision may be lower (LSB-aligned, "values in range 0 to 1023"), but
//              some drivers shift a 10- or 12-bit sensor to the top (MSB-aligned): the camera
//              URI says which (bits=, align=); by default all 16 bits count.
//   Full16Be   Y16-BE: big-endian 16-bit words.
//   Mipi       MIPI CSI-2 packing: Y10P and Bayer pBAA.. (10 bit, 4 samples in 5 bytes), pBCC..
//              (12 bit, 2 in 3), pBEE.. (14 bit, 4 in 7): the 8 high bits of each sample of a
//              group in a byte each, then the low bits of all of them, the first sample's in the
//              lowest bits.
//   BitPackedBe  Y10BPACK: 10-bit samples packed end to end, most significant bit first.
//   LumaOf422  YUYV UYVY YVYU VYUY: the luma byte of interleaved 4:2:2, every other byte.
//   LumaPlane  NV12 NV21 NV16 NV61 NV24 NV42 YU12 YV12 422P: the luma plane that comes first.
//
// Luma of YUV is gamma-encoded by the camera's processor: those formats are not raw (raw is
// false) and come last, after 8-bit raw; a camera that offers only them says its response is
// Unknown. Compressed formats (MJPG, H264) and RGB are not here: the camera refuses them.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"
#include "hdr/raw_frame.h"

namespace flarelab::drivers {

enum class V4l2Layout {
    Byte,
    Lsb16,
    Full16,
    Full16Be,
    Mipi,
    BitPackedBe,
    LumaOf422,
    LumaPlane,
};

struct V4l2FormatInfo {
    uint32_t fourcc = 0;
    const char* name = "";  // as a URI's format= names it: "Y16", "Y16-BE", "RG12", "pRAA"
    hdr::RawFormat raw_format = hdr::RawFormat::Mono;
    int bits = 8;  // of each sample as the format carries it
    V4l2Layout layout = V4l2Layout::Byte;
    bool raw = true;      // false: the luma of a YUV format (not linear)
    int luma_offset = 0;  // LumaOf422: the byte of each pair that holds Y (0 YUYV, 1 UYVY)
    // The whole image is bytes_per_line * height * size_num / size_den bytes (the chroma planes
    // of LumaPlane formats follow the luma plane at the luma plane's bytes per line).
    int size_num = 1;
    int size_den = 1;
    const char* layout_note = "";  // for listings: how samples lie
};

// Every supported format, preferred first: 16, 14, 12, 10 bit (grey before Bayer, unpacked before
// packed at each depth), then 8-bit raw, then the luma of YUV.
std::span<const V4l2FormatInfo> v4l2Formats();
// nullptr when flarelab cannot read the format.
const V4l2FormatInfo* findV4l2Format(uint32_t fourcc);

// "Y16 " -> "Y16", a big-endian fourcc (bit 31) gets "-BE": "Y16-BE"; bytes that are not
// printable as '.'.
std::string fourccText(uint32_t fourcc);
// The inverse for up to four printable characters, padded with spaces, with an optional "-BE";
// nullopt otherwise.
std::optional<uint32_t> fourccFromText(std::string_view text);

// The fewest bytes one line of `width` samples takes (0 when width < 1).
int64_t minBytesPerLine(const V4l2FormatInfo& format, int64_t width);
// The bytes an image of `height` lines at `bytes_per_line` takes, chroma planes included.
int64_t imageBytes(const V4l2FormatInfo& format, int64_t bytes_per_line, int64_t height);

// How to read the samples out of a buffer. For Full16 and Full16Be formats a sensor of fewer
// bits: value_bits < 16 with msb_aligned (samples are shifted right by 16 - value_bits) or not
// (samples are taken as they are and must lie below 2^value_bits). Other formats need
// value_bits = format.bits and msb_aligned false.
struct V4l2Unpacking {
    int64_t width = 0;
    int64_t height = 0;
    int64_t bytes_per_line = 0;
    int value_bits = 0;  // 0: format.bits
    bool msb_aligned = false;
};

struct V4l2Samples {
    std::vector<uint16_t> samples;  // width * height, row-major
    int bit_depth = 0;              // samples lie in 0 .. 2^bit_depth - 1
    // Samples above 2^bit_depth - 1 in the buffer (a driver that fills the high bits of an
    // LSB-aligned format, or a wrong align=): clipped to that, and counted here.
    int64_t clipped = 0;
};

// The samples of one frame. IoError naming the field when the buffer is too small for
// width x height at bytes_per_line, a dimension is not positive or too large (more than 2^15 a
// side), or bytes_per_line is shorter than a line; InvalidArgument when the unpacking does not
// fit the format.
Result<V4l2Samples> unpackV4l2Samples(const V4l2FormatInfo& format,
                                      std::span<const uint8_t> bytes,
                                      const V4l2Unpacking& unpacking);

// The inverse, for the playback device (v4l2_device.h) and tests: samples (each below
// 2^format.bits) laid out as the format lays them, imageBytes() long; padding and chroma bytes
// are filled with 0x80.
std::vector<uint8_t> packV4l2Samples(const V4l2FormatInfo& format,
                                     std::span<const uint16_t> samples,
                                     int64_t width,
                                     int64_t height,
                                     int64_t bytes_per_line);

}  // namespace flarelab::drivers
