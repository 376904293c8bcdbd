// ============================================================================
//  flarelab hdr: ExrMetadata, ExrStandardAttributes, ExrChromaticities, ExrWriteOptions,
//                ExrReadOptions, ExrImage, exrCaptureTime, writeExr, readExr,
//                readExrFromMemory, useExrThreads
// ============================================================================
//
// HDR frames on disk (DESIGN.md, "Formats"): single-part scanline OpenEXR files with channels R,
// G, B in float32 (or half where every value fits half), plus flarelab's own header attributes.
// The writer refuses NaN and infinity, writes to a temporary file beside the target and renames
// it into place, so an existing file survives any failure. The reader validates the header
// before OpenEXR allocates anything for it, and refuses non-finite pixels, so whatever it returns
// is finite. No OpenEXR exception leaves this module: each becomes an Error naming the file.
//
// flarelab's header attributes (format version 1). Every name starts with "flarelab.", and a
// file that carries any of them must carry "flarelab.version"; a file with none of them (written
// by another program) reads with empty metadata.
//
//   flarelab.version           int     format version, 1
//   flarelab.angle_deg         double  θ, the angle between the optical axis and the light
//   flarelab.roll_deg          double  φ, the light's roll around the axis
//   flarelab.exposure_times_s  string  the bracket's exposure times in seconds, separated by one
//                                      space, each as the shortest decimal that reads back to the
//                                      same double ("0.25 1 4"); OpenEXR has no double-vector
//                                      attribute, and its float vector would round the times
//   flarelab.gain              double  sensor gain (linear factor)
//   flarelab.camera            string  camera description
//   flarelab.lens              string  lens description
//   flarelab.merge_method      string  how the bracket was merged
//   flarelab.software_version  string  the program that wrote the file
//   flarelab.extra.<key>       string  free attributes, ExrMetadata::extra[<key>]
//
// flarelab's own channel (optional; other programs show it as layer "flarelab"):
//
//   flarelab.lower_bound       half    per pixel, which of R, G, B are only lower bounds (bits
//                                      1, 2, 4: hdr/merge.h, lowerBounds): a value 0 to 7. A
//                                      file without it says nothing about clipping.
//
// An absent optional field, empty string or empty vector is not written. The reader refuses an
// attribute of the wrong type, a non-finite number, a non-positive exposure time, an unknown
// "flarelab.*" name and any version other than 1, naming the attribute.
//
// OpenEXR's standard attributes (ImfStandardAttributes.h), written where known so that other
// tools read them (ExrMetadata::standard; they are OpenEXR's, not part of flarelab's version):
//
//   capDate         string          when the image was captured, local time, "YYYY:MM:DD hh:mm:ss"
//   utcOffset       float           seconds: UTC == local time + utcOffset
//   expTime         float           exposure time, s. A merged frame's values are DN per second at
//                                   unity gain (hdr/merge.h), what a 1 s exposure would read: 1.
//   aperture        float           the lens's f-number
//   isoSpeed        float           ISO speed of the sensor at the frame's values' gain
//   chromaticities  chromaticities  CIE xy of the red, green and blue primaries and white
//
// The numbers are floats in the file, as OpenEXR defines them: a value reads back as the float
// nearest to what was written. The reader refuses one of the wrong type, one that is not finite,
// an expTime, aperture or isoSpeed that is not positive, a utcOffset beyond a day, a capDate not
// in the form above and chromaticities outside [0, 1], naming the attribute; a file without them
// reads with them absent.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/image.h"
#include "common/result.h"

namespace flarelab::hdr {

inline constexpr int kExrFormatVersion = 1;

inline constexpr char kExrAttrVersion[] = "flarelab.version";
inline constexpr char kExrAttrAngle[] = "flarelab.angle_deg";
inline constexpr char kExrAttrRoll[] = "flarelab.roll_deg";
inline constexpr char kExrAttrExposureTimes[] = "flarelab.exposure_times_s";
inline constexpr char kExrAttrGain[] = "flarelab.gain";
inline constexpr char kExrAttrCamera[] = "flarelab.camera";
inline constexpr char kExrAttrLens[] = "flarelab.lens";
inline constexpr char kExrAttrMergeMethod[] = "flarelab.merge_method";
inline constexpr char kExrAttrSoftwareVersion[] = "flarelab.software_version";
inline constexpr char kExrAttrExtraPrefix[] = "flarelab.extra.";

// Longest key of ExrMetadata::extra: OpenEXR attribute names hold at most 255 characters.
inline constexpr size_t kExrMaxExtraKeyLength = 255 - (sizeof(kExrAttrExtraPrefix) - 1);

// Largest finite half, and the smallest positive half that still has full (11-bit) precision;
// below it, half values are denormal and then zero.
inline constexpr double kHalfMax = 65504.0;
inline constexpr double kHalfMinNormal = 6.103515625e-05;  // 2^-14

inline constexpr char kExrStdCapDate[] = "capDate";
inline constexpr char kExrStdUtcOffset[] = "utcOffset";
inline constexpr char kExrStdExpTime[] = "expTime";
inline constexpr char kExrStdAperture[] = "aperture";
inline constexpr char kExrStdIsoSpeed[] = "isoSpeed";
inline constexpr char kExrStdChromaticities[] = "chromaticities";

// CIE 1931 xy chromaticities of an RGB image's primaries and white point.
struct ExrChromaticities {
    std::array<double, 2> red{};
    std::array<double, 2> green{};
    std::array<double, 2> blue{};
    std::array<double, 2> white{};
    bool operator==(const ExrChromaticities&) const = default;
};

// Rec. ITU-R BT.709 primaries with a D65 white point: linear sRGB.
inline constexpr ExrChromaticities kRec709Chromaticities{
    {0.64, 0.33}, {0.30, 0.60}, {0.15, 0.06}, {0.3127, 0.3290}};

// OpenEXR's standard attributes (see the top of this file); each absent when not known.
struct ExrStandardAttributes {
    std::string cap_date;  // "YYYY:MM:DD hh:mm:ss", local time; empty: not known
    std::optional<double> utc_offset_s;
    std::optional<double> exp_time_s;
    std::optional<double> aperture;  // f-number
    std::optional<double> iso_speed;
    std::optional<ExrChromaticities> chromaticities;
    bool operator==(const ExrStandardAttributes&) const = default;
};

// capDate and utcOffset of a moment (ns since the Unix epoch, UTC: RawFrame::host_timestamp_ns)
// in the host's time zone. InvalidArgument when the moment is not positive or the year does not
// have four digits.
Result<ExrStandardAttributes> exrCaptureTime(int64_t unix_time_ns);

struct ExrMetadata {
    std::optional<double> angle_deg;
    std::optional<double> roll_deg;
    std::vector<double> exposure_times_s;  // each finite and > 0
    std::optional<double> gain;
    std::string camera;
    std::string lens;
    std::string merge_method;
    std::string software_version;
    // Keys are 1 to kExrMaxExtraKeyLength characters without NUL; values are any bytes.
    std::map<std::string, std::string> extra;
    ExrStandardAttributes standard;
    bool operator==(const ExrMetadata&) const = default;
};

enum class ExrPixelType {
    Float,          // float32: every value exactly
    Half,           // half, or an error when a value does not fit half (see ExrWriteOptions)
    HalfWhereFits,  // half when every value fits half, else float32 and a note saying why
};

enum class ExrCompression { None, Zip, Piz };

struct ExrWriteOptions {
    ExrPixelType pixel_type = ExrPixelType::Float;
    ExrCompression compression = ExrCompression::Zip;
    // A value fits half when |v| <= kHalfMax and v is 0 or |v| >= half_min_abs. The default keeps
    // half's full relative precision (2^-11) for every nonzero value; 0 accepts that tiny values
    // lose precision or become 0.
    double half_min_abs = kHalfMinNormal;
};

// What writeExr wrote.
struct ExrWriteReport {
    bool half = false;  // the channels are half (else float32)
    // Why float32 was written although HalfWhereFits asked for half (the first value that does
    // not fit); empty otherwise.
    std::string note;
};

// Limits a reader checks on the header before anything is allocated for the image.
struct ExrReadOptions {
    int64_t max_side = int64_t{1} << 15;    // data window width and height, pixels
    int64_t max_pixels = int64_t{1} << 28;  // width * height; the image takes 12 bytes per pixel
    int max_channels = 64;                  // channels in the file, read or not
    // The size the caller knows the image has (a sweep's frame size, hdr/sweep.h); 0 = any. A
    // data window of another size is refused (ParseError) before the image is allocated, so a
    // small file that declares a huge image costs nothing.
    int64_t expected_width_px = 0;
    int64_t expected_height_px = 0;
};

struct ExrImage {
    // The file's data window, with the data window's top-left pixel at (0, 0). A channel Y alone
    // is copied to R, G and B; channel A and others are ignored.
    ImageRGB image;
    ExrMetadata meta;
    // Where the data window starts in the file's pixel space (OpenEXR lets it start anywhere,
    // also at negative coordinates); pixel (x, y) of `image` is (origin_x + x, origin_y + y) there.
    int64_t origin_x = 0;
    int64_t origin_y = 0;
    // Per pixel (row-major), the channel flarelab.lower_bound: bits 1, 2, 4 for R, G, B being
    // only lower bounds. Empty when the file has no such channel.
    std::vector<uint8_t> lower_bound;
};

// Writes `image` (at least 1x1, at most 2^15 pixels per side, every value finite) with `meta` to
// `path` as a single-part scanline EXR with channels R, G, B and data and display window
// [0, width - 1] x [0, height - 1]. The file is written to "<path>.tmp-<pid>" in the same
// directory, flushed to disk and renamed onto `path`, and the directory flushed; on any failure
// before the rename the temporary file is removed and whatever was at `path` is left as it was.
// When only the directory's flush fails, the error says that the file was renamed into place.
// Errors name the path and what failed: the first non-finite pixel (x, y, channel), the first value
// that does not fit half when Half was asked for, an invalid metadata field, or the operating
// system's or OpenEXR's complaint.
// `lower_bound`, when not empty (width * height values, each 0 to 7), is written as the channel
// flarelab.lower_bound; InvalidArgument for another size or value.
Result<ExrWriteReport> writeExr(const std::string& path,
                                const ImageRGB& image,
                                const ExrMetadata& meta,
                                const ExrWriteOptions& options = {},
                                std::span<const uint8_t> lower_bound = {});

// Reads a single-part scanline EXR whose channels R, G, B (A and others ignored) or Y alone are
// half or float32. Refused, with an Error naming the file: a missing or unreadable file
// (NotFound, IoError), anything not an EXR or truncated or corrupt (ParseError), tiled, deep or
// multi-part files, UINT or subsampled channels, luminance-chroma files, ID manifests and data
// windows beyond `options` (Unsupported), a missing channel, a NaN or infinite pixel (named by its
// x, y in the file's pixel space and its channel), a flarelab.lower_bound value that is not a
// whole number 0 to 7 and invalid flarelab attributes (ParseError).
Result<ExrImage> readExr(const std::string& path, const ExrReadOptions& options = {});

// The same reader over bytes in memory; `name` stands for the file in error messages.
Result<ExrImage> readExrFromMemory(std::span<const uint8_t> bytes,
                                   const std::string& name = "<memory>",
                                   const ExrReadOptions& options = {});

// Lets OpenEXR compress and decompress a file's line blocks on a pool of `threads` threads (0:
// as many as the machine has cores) in every read and write from here on; without it each runs
// in the calling thread, and zlib then takes most of a frame's time (a 1920x1080 float frame
// with ZIP: about 0.7 s written on one core). The bytes written do not depend on the pool. The
// pool is OpenEXR's own and process-wide, so this is the program's choice, made once in main():
// a process that forks and goes on without exec must not make it, since the pool's threads do
// not exist in the child and an EXR read or written there would wait for them forever. Returns
// the pool's size.
int useExrThreads(int threads = 0);

}  // namespace flarelab::hdr
