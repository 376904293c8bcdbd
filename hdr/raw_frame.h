// ============================================================================
//  flarelab hdr: RawFrame, RawFormat
// ============================================================================
//
// One raw exposure as a camera delivers it (DESIGN.md, "Formats"): 16-bit samples, single
// channel or a Bayer mosaic, with everything the bracket merge needs to turn digital numbers back
// into radiance. Cameras (drivers/) produce it, the merge (hdr/merge.h) consumes it, replay
// stores it. Values are the converter's digital numbers (DN) as read out, black level included;
// a converter of b bits puts them in 0 .. 2^b - 1 (left-justified sensors are shifted back by the
// driver).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace flarelab::hdr {

enum class RawFormat {
    Mono,       // one channel
    BayerRGGB,  // 2x2 mosaic, red at (0, 0)
    BayerBGGR,
    BayerGRBG,
    BayerGBRG,
};

// The format's name in raw files and sweep manifests: mono, bayer-rggb, bayer-bggr, bayer-grbg,
// bayer-gbrg; and back (nullopt for any other text).
std::string_view rawFormatName(RawFormat format);
std::optional<RawFormat> parseRawFormat(std::string_view name);
// A colour mosaic (any Bayer pattern), not a single channel.
inline bool isBayer(RawFormat format) { return format != RawFormat::Mono; }

// What RawFrame::timestamp_ns marks on the camera's clock.
enum class TimestampMark {
    Unknown,        // the camera does not say
    ExposureStart,  // the start of the exposure (the simulated camera; GigE Vision's default)
    ExposureEnd,    // the end of the exposure
    FrameArrival,   // when the frame reached the host's driver (V4L2's buffer timestamp)
};

struct RawFrame {
    int64_t width = 0;
    int64_t height = 0;
    RawFormat format = RawFormat::Mono;
    std::vector<uint16_t> samples;  // width * height, row-major, top row first

    // What the camera applied, read back from it where it can say (a camera rounds a requested
    // exposure to its line time, a gain to its steps), else what was set.
    double exposure_s = 0.0;  // > 0
    double gain = 1.0;        // linear, > 0 (1: the sensor's unity setting)
    int bit_depth = 16;       // of the converter, 8..16
    double black_level_dn = 0.0;
    double white_level_dn = 65535.0;  // the largest DN the sensor reports unclipped
    // Noise of one sample, for weighting: read noise in DN (at this gain), and the conversion
    // gain in electrons per DN (at this gain); 0 when the camera does not say.
    double read_noise_dn = 0.0;
    double electrons_per_dn = 0.0;

    double angle_deg = 0.0;    // head angle when the frame was taken
    int64_t timestamp_ns = 0;  // camera clock, monotonic within a sweep
    TimestampMark timestamp_marks = TimestampMark::Unknown;  // what timestamp_ns marks
    // The host's clock (CLOCK_REALTIME, ns since the Unix epoch) when the host had the frame;
    // 0 when unknown. Beside the camera's clock it dates a frame and shows transfer delays.
    int64_t host_timestamp_ns = 0;
    int64_t sequence = 0;  // frame counter of the camera
    std::string camera;    // model and serial, free text

    bool operator==(const RawFrame&) const = default;
};

}  // namespace flarelab::hdr
