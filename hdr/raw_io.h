// ============================================================================
//  flarelab hdr: writeRaw, readRaw, readRawFromMemory (raw frames on disk)
// ============================================================================
//
// Raw brackets are kept on disk as binary PGM (Netpbm P5), 16-bit, so any image viewer shows
// them, with flarelab's metadata in header comments. Format version 2:
//
//   P5
//   # flarelab-raw 2
//   # format mono | bayer-rggb | bayer-bggr | bayer-grbg | bayer-gbrg
//   # exposure_s 0.25
//   # gain 1
//   # bit_depth 12
//   # black_level_dn 256
//   # white_level_dn 4095
//   # read_noise_dn 2.5
//   # electrons_per_dn 0.8
//   # angle_deg 1.4
//   # timestamp_ns 123456789
//   # timestamp_marks exposure-start | exposure-end | frame-arrival | unknown
//   # host_timestamp_ns 1764625473000000000
//   # sequence 42
//   # camera sim camera, serial 0     (the rest of the line; no line breaks)
//   WIDTH HEIGHT
//   MAXVAL                            (2^bit_depth - 1)
//   <width x height samples, 2 bytes each, most significant byte first, rows top to bottom>
//
// Version 1 files (written before 2026-12) lack the two timestamp keys and read with
// TimestampMark::Unknown and host_timestamp_ns 0; the writer writes version 2.
//
// Every key appears exactly once, in any order, before the size line; numbers are written so
// that they read back to the same double. The reader refuses, naming the file and the key or
// byte: another magic or version, an unknown, missing or repeated key, a value that does not
// parse or is out of range (as RawFrame documents), a size over the limits, a MAXVAL that does
// not match bit_depth, a sample above MAXVAL, and a file shorter or longer than its samples.
// The writer writes to a temporary file beside the target, flushes it to disk and renames it
// into place, so the target holds the old or the new frame, never a partial one.
#pragma once

#include <cstdint>
#include <span>
#include <string>

#include "common/result.h"
#include "hdr/raw_frame.h"

namespace flarelab::hdr {

inline constexpr int kRawFormatVersion = 2;

struct RawReadOptions {
    int64_t max_side = int64_t{1} << 15;    // width and height, pixels
    int64_t max_pixels = int64_t{1} << 28;  // width * height
};

// InvalidArgument for a frame RawFrame's rules refuse (sizes, metadata ranges, a sample above
// 2^bit_depth - 1, a camera text with a line break); IoError naming the path otherwise.
Status writeRaw(const std::string& path, const RawFrame& frame);

// NotFound, IoError or ParseError naming the path (and the key or byte offset).
Result<RawFrame> readRaw(const std::string& path, const RawReadOptions& options = {});

// The same from bytes in memory; `name` stands for the file in messages.
Result<RawFrame> readRawFromMemory(std::span<const uint8_t> bytes,
                                   const std::string& name,
                                   const RawReadOptions& options = {});

// The rules of RawFrame (raw_frame.h) a frame must meet to be written or merged: InvalidArgument
// naming the field.
Status validateRawFrame(const RawFrame& frame);

}  // namespace flarelab::hdr
