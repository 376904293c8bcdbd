// ============================================================================
//  flarelab render: ToneMapOptions, toneMap, writePng, readPng, autoExposureStops
// ============================================================================
//
// 8-bit previews of linear HDR images, for people to look at; the data itself goes to OpenEXR.
// Two curves, applied per channel after scaling by 2^exposure_stops:
//   - Reinhard (the global operator of Reinhard et al. 2002, L / (1 + L)), then the sRGB transfer
//     function: maps [0, inf) onto [0, 1) smoothly and monotonically, keeps mid-tones close to a
//     plain sRGB view and compresses highlights instead of clipping them. Applied per channel, so
//     very bright flare desaturates towards white, as film and sensors do.
//   - Log, for inspecting dynamic range: code value linear in stops, 1 at a scaled value of 1 and
//     0 at log_range_stops below it (clamped at both ends; zero and below map to 0).
// Negative inputs (ringing of a filter, not physical radiance) display as 0. NaN and infinity are
// never written: they are counted and reported as an error.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common/image.h"
#include "common/result.h"

namespace flarelab::render {

enum class ToneCurve { Reinhard, Log };

struct ToneMapOptions {
    double exposure_stops = 0.0;  // -64..64; the image is scaled by 2^exposure_stops
    ToneCurve curve = ToneCurve::Reinhard;
    double log_range_stops = 16.0;  // Log only: stops shown, 1..64
};

// 8-bit sRGB-encoded RGB, interleaved, rows top to bottom.
struct PreviewImage {
    int64_t width = 0;
    int64_t height = 0;
    std::vector<uint8_t> pixels;  // width * height * 3
};

// InvalidArgument naming the field when an option is outside its range.
Status validateToneMapOptions(const ToneMapOptions& options);

// The display value in [0, 1] of one linear channel value (finite), before quantization to
// round(255 * value). Non-decreasing in `linear`, 0 for linear <= 0. The options must be valid.
double toneCurve(double linear, const ToneMapOptions& options);

// The whole image through toneCurve. InvalidArgument for bad options or when the image holds NaN
// or infinity (the message gives their count and the first one's pixel and channel).
Result<PreviewImage> toneMap(const ImageRGB& image, const ToneMapOptions& options);

// Tone-maps `image` and writes it as PNG to `path`. The bytes go to a temporary file in the same
// directory, which is flushed to disk and renamed onto `path`, so `path` holds either its old
// content or the complete new image, never a partial one. Errors name the path: InvalidArgument
// (options, an empty image, non-finite pixels, more than 65535 pixels a side), Internal (the PNG
// encoder failed), IoError (the directory or file cannot be written; no temporary is left).
Status writePng(const ImageRGB& image, const std::string& path, const ToneMapOptions& options);

// Reads a PNG (libpng; any bit depth, converted to 8-bit sRGB, an alpha channel composited onto
// black) back as RGB, for checking previews: NotFound when the file does not exist, ParseError
// naming the path when it cannot be decoded or claims more than 2^28 pixels.
Result<PreviewImage> readPng(const std::string& path);

// The exposure, in stops, that scales the `percentile` (0..1) of the image's lit values (each
// pixel's largest finite channel, over the pixels where it is above 0) to 1, Reinhard's
// mid-grey (display 0.73): in a flare image, where the light's own pixels are thousands of times
// brighter than its ghosts, the ghosts show. Clamped to -64..64; 0 when no pixel is lit.
double autoExposureStops(const ImageRGB& image, double percentile = 0.99);

}  // namespace flarelab::render
