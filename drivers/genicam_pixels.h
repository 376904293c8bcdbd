// ============================================================================
//  flarelab drivers: GenicamPixelFormat, PixelPacking, unpackGenicamPixels
// ============================================================================
//
// The raw pixel formats of GenICam cameras (GigE Vision, USB3 Vision) that flarelab takes, by
// their PFNC names as a camera's PixelFormat feature lists them, and the unpacking of their
// payload into 16-bit samples (hdr/raw_frame.h). Kept apart from the Aravis backend so that it
// builds and is tested without Aravis.
//
// Which formats: single-channel grey (Mono8..Mono16) and raw Bayer mosaics (BayerRG8..16 and
// the BG, GR, GB orders), unpacked (one sample per byte or per little-endian 16-bit word) or
// packed. Colour, YUV and 3-D formats are not raw sensor data and are not taken.
//
// Packed layouts (a row starts on a byte only when the camera pads rows, see
// unpackGenicamPixels):
//   GigE Vision "Packed" (Mono10Packed, Mono12Packed, BayerRG12Packed, ...): two samples in
//     three bytes whatever the depth (an odd last sample in two); byte 0 holds the high 8 bits
//     of sample 0, byte 2 those of sample 1, byte 1 their low bits (sample 0's in the low
//     nibble, sample 1's in the high one; for 10 bits, bits 0-1 and 4-5). As in the GigE Vision
//     1.2 pixel format tables and the cameras' manuals.
//   PFNC "p" (Mono10p, Mono12p, BayerRG12p, ...): the samples follow each other as one stream
//     of bits, least significant bit first, with no padding: n samples take
//     ceil(n * bits / 8) bytes.
//
// Preference (chooseGenicamPixelFormat): more than 8 bits before 8 bits; among those, grey
// before Bayer, more bits before fewer, unpacked before packed. 8-bit formats only when the
// camera offers nothing deeper, and the backend then warns: 8 bits cannot hold the range of a
// flare measurement.
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

enum class PixelPacking {
    None,        // 8-bit: one byte a sample; deeper: one little-endian 16-bit word a sample
    GigEPacked,  // GigE Vision's Mono10Packed, Mono12Packed: two samples in three bytes
    Lsb,         // PFNC's Mono10p, Mono12p: a stream of bits, least significant first
};

struct GenicamPixelFormat {
    std::string name;  // PFNC name, as the camera's PixelFormat feature lists it
    hdr::RawFormat layout = hdr::RawFormat::Mono;
    int bits = 8;  // per sample, 8..16: samples lie in 0 .. 2^bits - 1
    PixelPacking packing = PixelPacking::None;
    bool operator==(const GenicamPixelFormat&) const = default;
};

// The format of a PFNC name; nullopt for a name flarelab does not take (RGB8, YUV422_8, ...).
std::optional<GenicamPixelFormat> genicamPixelFormat(std::string_view name);

// The names flarelab takes, best first by the preference above, from a camera's list (names it
// does not take are left out; the order of equals is kept).
std::vector<GenicamPixelFormat> rankGenicamPixelFormats(const std::vector<std::string>& names);

// The best of `names` with the given layout; nullopt when there is none.
std::optional<GenicamPixelFormat> chooseGenicamPixelFormat(const std::vector<std::string>& names,
                                                           hdr::RawFormat layout);

// PFNC's Bayer order word for a layout ("RG" for BayerRGGB); "" for Mono.
std::string_view bayerOrderName(hdr::RawFormat layout);

// Bytes that `count` samples take.
int64_t genicamPayloadBytes(const GenicamPixelFormat& format, int64_t count);

// Unpacks a width x height image, rows top first. Without row padding the rows follow each other
// with no gap (packed formats pack across rows); with row_padding_bytes > 0 (GVSP's x padding)
// every row starts on a byte and is followed by that many bytes. Bytes beyond the image (chunk
// data) are ignored. InvalidArgument, naming the format and sizes, when the sizes are not
// positive, the data are shorter than the image, or a sample of an unpacked format deeper than 8
// bits does not fit its bits (a camera that sends its samples left-aligned).
Result<std::vector<uint16_t>> unpackGenicamPixels(const GenicamPixelFormat& format,
                                                  std::span<const uint8_t> data,
                                                  int64_t width,
                                                  int64_t height,
                                                  int64_t row_padding_bytes = 0);

}  // namespace flarelab::drivers
