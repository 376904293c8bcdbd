// ============================================================================
//  flarelab drivers: LibcameraRawFormat, RawPacking, LibcameraFormatOffer, LibcameraFormatRequest,
//                    LibcameraFormatChoice, LibcameraLimits, LibcameraSettings,
//                    LibcameraFrameMetadata, LibcameraSettleTracker, LibcameraCameraOptions
// ============================================================================
//
// The parts of the libcamera camera backend (libcamera_camera.h) that need no camera and no
// libcamera: which raw pixel formats it reads and how they are laid out in memory, the choice of
// format and size from what a camera offers, the mapping of exposure and gain to libcamera's
// controls, a completed request's metadata to a RawFrame, the decision whether a frame already
// shows the settings that were asked for, and the "libcamera:NAME?..." URI. They are built in
// every build of flarelab (with or without libcamera installed), so that they are unit-tested
// everywhere; libcamera_camera.cpp checks at compile time that the format table below matches
// libcamera's own (include/libcamera/formats.h of 0.0.3).
//
// Pixel formats. libcamera names a format by a DRM fourcc and a modifier. The raw formats of
// libcamera 0.0.3 that flarelab reads:
//   R8, R10, R12                       mono, one sample per 8 or 16 bit little-endian container
//   R10_CSI2P                          mono, MIPI CSI-2 packed
//   S{RGGB,GRBG,GBRG,BGGR}{8,10,12,16} Bayer, unpacked (10/12 bits in 16-bit containers, low bits)
//   S....{10,12}_CSI2P                 Bayer, MIPI CSI-2 packed
//   S....10_IPU3                       Bayer, Intel IPU3 packed (25 samples in 32 bytes)
// 0.0.3 has no R16 and no R12_CSI2P (later libcamera adds them).
//
// Packed layouts (MIPI CSI-2 specification, "RAW10" and "RAW12" data types, as V4L2 documents
// them for V4L2_PIX_FMT_SRGGB10P and _SRGGB12P):
//   RAW10: 4 samples in 5 bytes. Bytes 0..3 hold bits 9..2 of samples 0..3; byte 4 holds their
//          bits 1..0, sample 0 in bits 1..0, sample 3 in bits 7..6.
//   RAW12: 2 samples in 3 bytes. Bytes 0, 1 hold bits 11..4 of samples 0, 1; byte 2 holds their
//          bits 3..0, sample 0 in bits 3..0, sample 1 in bits 7..4.
//   IPU3:  25 samples in 32 bytes, a little-endian bit stream: sample i takes bits 10i..10i+9 of
//          the block (bit k is bit k % 8 of byte k / 8); the last 6 bits are padding.
// A line of an odd width ends in a partial group, padded to a whole one; lines are `stride`
// bytes apart, the stride may be larger than the line (alignment padding).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"
#include "drivers/device.h"
#include "hdr/raw_frame.h"

namespace flarelab::drivers {

enum class RawPacking {
    None,  // one sample per byte (8 bits) or per little-endian 16-bit word (10..16 bits)
    Csi2,  // MIPI CSI-2 RAW10 / RAW12
    Ipu3,  // Intel IPU3 10-bit
};

struct LibcameraRawFormat {
    std::string_view name;  // as libcamera prints it: "SRGGB10_CSI2P"
    uint32_t fourcc = 0;
    uint64_t modifier = 0;
    hdr::RawFormat layout = hdr::RawFormat::Mono;
    int bit_depth = 8;  // of the samples: 8, 10, 12 or 16
    RawPacking packing = RawPacking::None;
};

inline constexpr uint32_t libcameraFourcc(char a, char b, char c, char d) {
    return static_cast<uint32_t>(static_cast<unsigned char>(a)) |
           static_cast<uint32_t>(static_cast<unsigned char>(b)) << 8 |
           static_cast<uint32_t>(static_cast<unsigned char>(c)) << 16 |
           static_cast<uint32_t>(static_cast<unsigned char>(d)) << 24;
}

// A DRM fourcc, as libcamera's formats.h builds it, and the DRM format modifiers as libcamera's
// formats.h builds them: vendor << 56 | code.
inline constexpr uint64_t kLibcameraLinear = 0;
inline constexpr uint64_t kLibcameraCsi2Packed =
    (uint64_t{11} << 56) | 1;  // MIPI vendor, CSI-2 packed
inline constexpr uint64_t kLibcameraIpu3Packed =
    (uint64_t{1} << 56) | 13;  // Intel vendor, IPU3 packed

inline constexpr std::array<LibcameraRawFormat, 32> kLibcameraRawFormats = {{
    {"R8", libcameraFourcc('R', '8', ' ', ' '), kLibcameraLinear, hdr::RawFormat::Mono, 8,
     RawPacking::None},
    {"R10", libcameraFourcc('R', '1', '0', ' '), kLibcameraLinear, hdr::RawFormat::Mono, 10,
     RawPacking::None},
    {"R12", libcameraFourcc('R', '1', '2', ' '), kLibcameraLinear, hdr::RawFormat::Mono, 12,
     RawPacking::None},
    {"R10_CSI2P", libcameraFourcc('R', '1', '0', ' '), kLibcameraCsi2Packed, hdr::RawFormat::Mono,
     10, RawPacking::Csi2},
    {"SRGGB8", libcameraFourcc('R', 'G', 'G', 'B'), kLibcameraLinear, hdr::RawFormat::BayerRGGB, 8,
     RawPacking::None},
    {"SGRBG8", libcameraFourcc('G', 'R', 'B', 'G'), kLibcameraLinear, hdr::RawFormat::BayerGRBG, 8,
     RawPacking::None},
    {"SGBRG8", libcameraFourcc('G', 'B', 'R', 'G'), kLibcameraLinear, hdr::RawFormat::BayerGBRG, 8,
     RawPacking::None},
    {"SBGGR8", libcameraFourcc('B', 'A', '8', '1'), kLibcameraLinear, hdr::RawFormat::BayerBGGR, 8,
     RawPacking::None},
    {"SRGGB10", libcameraFourcc('R', 'G', '1', '0'), kLibcameraLinear, hdr::RawFormat::BayerRGGB,
     10, RawPacking::None},
    {"SGRBG10", libcameraFourcc('B', 'A', '1', '0'), kLibcameraLinear, hdr::RawFormat::BayerGRBG,
     10, RawPacking::None},
    {"SGBRG10", libcameraFourcc('G', 'B', '1', '0'), kLibcameraLinear, hdr::RawFormat::BayerGBRG,
     10, RawPacking::None},
    {"SBGGR10", libcameraFourcc('B', 'G', '1', '0'), kLibcameraLinear, hdr::RawFormat::BayerBGGR,
     10, RawPacking::None},
    {"SRGGB12", libcameraFourcc('R', 'G', '1', '2'), kLibcameraLinear, hdr::RawFormat::BayerRGGB,
     12, RawPacking::None},
    {"SGRBG12", libcameraFourcc('B', 'A', '1', '2'), kLibcameraLinear, hdr::RawFormat::BayerGRBG,
     12, RawPacking::None},
    {"SGBRG12", libcameraFourcc('G', 'B', '1', '2'), kLibcameraLinear, hdr::RawFormat::BayerGBRG,
     12, RawPacking::None},
    {"SBGGR12", libcameraFourcc('B', 'G', '1', '2'), kLibcameraLinear, hdr::RawFormat::BayerBGGR,
     12, RawPacking::None},
    {"SRGGB16", libcameraFourcc('R', 'G', 'B', '6'), kLibcameraLinear, hdr::RawFormat::BayerRGGB,
     16, RawPacking::None},
    {"SGRBG16", libcameraFourcc('G', 'R', '1', '6'), kLibcameraLinear, hdr::RawFormat::BayerGRBG,
     16, RawPacking::None},
    {"SGBRG16", libcameraFourcc('G', 'B', '1', '6'), kLibcameraLinear, hdr::RawFormat::BayerGBRG,
     16, RawPacking::None},
    {"SBGGR16", libcameraFourcc('B', 'Y', 'R', '2'), kLibcameraLinear, hdr::RawFormat::BayerBGGR,
     16, RawPacking::None},
    {"SRGGB10_CSI2P", libcameraFourcc('R', 'G', '1', '0'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerRGGB, 10, RawPacking::Csi2},
    {"SGRBG10_CSI2P", libcameraFourcc('B', 'A', '1', '0'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerGRBG, 10, RawPacking::Csi2},
    {"SGBRG10_CSI2P", libcameraFourcc('G', 'B', '1', '0'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerGBRG, 10, RawPacking::Csi2},
    {"SBGGR10_CSI2P", libcameraFourcc('B', 'G', '1', '0'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerBGGR, 10, RawPacking::Csi2},
    {"SRGGB12_CSI2P", libcameraFourcc('R', 'G', '1', '2'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerRGGB, 12, RawPacking::Csi2},
    {"SGRBG12_CSI2P", libcameraFourcc('B', 'A', '1', '2'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerGRBG, 12, RawPacking::Csi2},
    {"SGBRG12_CSI2P", libcameraFourcc('G', 'B', '1', '2'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerGBRG, 12, RawPacking::Csi2},
    {"SBGGR12_CSI2P", libcameraFourcc('B', 'G', '1', '2'), kLibcameraCsi2Packed,
     hdr::RawFormat::BayerBGGR, 12, RawPacking::Csi2},
    {"SRGGB10_IPU3", libcameraFourcc('R', 'G', '1', '0'), kLibcameraIpu3Packed,
     hdr::RawFormat::BayerRGGB, 10, RawPacking::Ipu3},
    {"SGRBG10_IPU3", libcameraFourcc('B', 'A', '1', '0'), kLibcameraIpu3Packed,
     hdr::RawFormat::BayerGRBG, 10, RawPacking::Ipu3},
    {"SGBRG10_IPU3", libcameraFourcc('G', 'B', '1', '0'), kLibcameraIpu3Packed,
     hdr::RawFormat::BayerGBRG, 10, RawPacking::Ipu3},
    {"SBGGR10_IPU3", libcameraFourcc('B', 'G', '1', '0'), kLibcameraIpu3Packed,
     hdr::RawFormat::BayerBGGR, 10, RawPacking::Ipu3},
}};

// Every raw format flarelab reads (the list above).
std::span<const LibcameraRawFormat> libcameraRawFormats();
// nullptr when flarelab does not read the format.
const LibcameraRawFormat* findLibcameraRawFormat(uint32_t fourcc, uint64_t modifier);
const LibcameraRawFormat* findLibcameraRawFormat(std::string_view name);

// The bytes one line of `width` samples takes, partial groups padded (the smallest stride);
// 0 when width < 1.
int64_t libcameraLineBytes(const LibcameraRawFormat& format, int64_t width);

// The image of a raw buffer as 16-bit samples (width * height, row-major), each in
// 0 .. 2^bit_depth - 1. InvalidArgument naming width, height or stride when width or height lies
// outside 1..32768 (RawFrame's limit) or the stride is shorter than a line; ParseError naming the
// buffer's size when it ends before the last line, and naming the sample when an unpacked 10- or
// 12-bit container holds more bits (a buffer that is not right-justified as the format says).
Result<std::vector<uint16_t>> unpackLibcameraRaw(std::span<const uint8_t> data,
                                                 const LibcameraRawFormat& format,
                                                 int64_t width,
                                                 int64_t height,
                                                 int64_t stride_bytes);

struct PixelSize {
    int64_t width = 0;
    int64_t height = 0;
    bool operator==(const PixelSize&) const = default;
};

// One pixel format a camera's stream offers (StreamFormats::pixelformats() with its sizes()).
struct LibcameraFormatOffer {
    std::string name;  // PixelFormat::toString()
    uint32_t fourcc = 0;
    uint64_t modifier = 0;
    std::vector<PixelSize> sizes;
};

// What the URI asks for; empty and 0 leave the choice to chooseLibcameraFormat.
struct LibcameraFormatRequest {
    std::string format;  // a name of libcameraRawFormats()
    int64_t width = 0;
    int64_t height = 0;
};

struct LibcameraFormatChoice {
    LibcameraRawFormat format;
    PixelSize size;
};

// The format and size to ask the camera for. Without a requested format: the readable raw format
// with the most bits, unpacked before CSI-2 packed before IPU3 packed (no unpacking work when the
// camera can do it), then the first offered. Without a requested size: the largest offered
// size of that format (the full sensor, unbinned where the sensor offers it). A requested width
// or height must be offered exactly (with the other, when given). Sizes outside 1..32768 (what a
// RawFrame may hold) are not offers.
// Unsupported when the camera offers no raw format flarelab reads (the message lists what it
// offers); [out-of-range] naming format when the requested one is unknown or not offered, naming
// width / height when no offered size matches (the messages list what is offered).
Result<LibcameraFormatChoice> chooseLibcameraFormat(std::span<const LibcameraFormatOffer> offers,
                                                    const LibcameraFormatRequest& request,
                                                    std::string_view device);

// CameraConfiguration::validate() may adjust a stream (the Raspberry Pi pipeline changes the
// Bayer order when the sensor is flipped, and snaps the size to a sensor mode). What it returned
// is accepted when flarelab reads the format and whatever the URI asked for explicitly is kept:
// [out-of-range] naming format (an unreadable format, or another than the URI's format=), width
// or height (another than the URI's), saying what the camera made of the request.
Result<LibcameraFormatChoice> acceptValidatedFormat(uint32_t fourcc,
                                                    uint64_t modifier,
                                                    std::string_view name,
                                                    const PixelSize& size,
                                                    const LibcameraFormatRequest& request,
                                                    std::string_view device);

// A ControlInfo's range as numbers (libcamera gives int32, int64 or float values).
struct LibcameraControlRange {
    double min = 0.0;
    double max = 0.0;
};

// The ranges flarelab uses: controls::ExposureTime in integer microseconds, controls::
// AnalogueGain linear.
struct LibcameraLimits {
    int32_t min_exposure_us = 1;
    int32_t max_exposure_us = 1;
    double min_gain = 1.0;
    double max_gain = 1.0;
};

// From the camera's ControlInfoMap (after configure(), when pipelines set the ranges of the
// chosen sensor mode). Unsupported naming the control when the camera has no ExposureTime or no
// AnalogueGain (it cannot be exposed manually); IoError naming it when its range is not finite,
// empty (max < min), has no positive exposure or a gain <= 0. An exposure minimum of 0 (the
// Raspberry Pi IPA's static range) becomes 1 us; a maximum past int32 is cut to int32's.
Result<LibcameraLimits> libcameraLimits(const std::optional<LibcameraControlRange>& exposure_us,
                                        const std::optional<LibcameraControlRange>& gain,
                                        std::string_view device);

// exposure_s as controls::ExposureTime: rounded to whole microseconds. [out-of-range] naming
// exposure_s (with the range in seconds) when it is not finite or the rounded value lies outside
// the limits: the camera's range is never silently clamped to.
Result<int32_t> exposureToMicroseconds(double exposure_s,
                                       const LibcameraLimits& limits,
                                       std::string_view device);
// gain as controls::AnalogueGain; [out-of-range] naming gain when not finite or outside the limits.
Result<float> gainToControl(double gain, const LibcameraLimits& limits, std::string_view device);

// What a request asks the sensor for.
struct LibcameraSettings {
    int32_t exposure_us = 0;
    float gain = 1.0f;
    bool operator==(const LibcameraSettings&) const = default;
};

// What a completed request says about its frame: controls in Request::metadata(), the rest from
// the stream's FrameBuffer::metadata() and the host's clock.
struct LibcameraFrameMetadata {
    std::optional<int64_t> exposure_us;          // controls::ExposureTime
    std::optional<double> analogue_gain;         // controls::AnalogueGain
    std::optional<int64_t> sensor_timestamp_ns;  // controls::SensorTimestamp
    // controls::SensorBlackLevels: R, Gr, Gb, B on a 16-bit scale (as if samples ran to 65535).
    std::optional<std::array<int64_t, 4>> black_levels;
    int64_t sequence = 0;           // FrameMetadata::sequence: the sensor's frame counter
    int64_t host_timestamp_ns = 0;  // CLOCK_REALTIME when requestCompleted was emitted
};

// A frame from its metadata and samples. exposure_s and gain are the ones the metadata reports,
// else the ones requested (uvcvideo reports neither); timestamp_ns is SensorTimestamp, which
// libcamera defines as the start of the exposure of the sensor's first row on CLOCK_BOOTTIME
// (control_ids.yaml), hence TimestampMark::ExposureStart (Unknown without it); the black level is
// the mean of SensorBlackLevels scaled to bit_depth (0 without it: `flarelab calibrate` measures
// it); white is 2^bit_depth - 1. IoError naming the control when the metadata holds an exposure
// <= 0, a gain not finite or <= 0, a negative timestamp or a black level outside 0..65535 (a
// device reply flarelab will not pass on) or black levels not below white, and naming samples
// when their count is not width * height. A frame it returns passes hdr::validateRawFrame.
Result<hdr::RawFrame> rawFrameFromLibcamera(const LibcameraFrameMetadata& metadata,
                                            const LibcameraSettings& requested,
                                            const LibcameraFormatChoice& format,
                                            std::vector<uint16_t> samples,
                                            const std::string& camera);

// Sensors apply a new exposure or gain a few frames after it was asked for (the Raspberry Pi
// pipeline's DelayedControls: two frames for most sensors), and a pipeline reports in each
// request's metadata what its frame was really exposed with. The tracker decides, frame by frame
// after a change of settings, whether a frame shows them:
//   Accept   the metadata's exposure is within max(1 %, 2 us, the camera's minimum exposure) of
//            the request (sensors round to a line time) and its gain within 5 % (gain codes);
//   Discard  it does not yet (an old frame), or the metadata says nothing and fewer than
//            kBlindFrames frames have passed since the change (the pipeline cannot say, so the
//            frames that may have been exposed before it are dropped);
//   Refuse   kMaxFrames frames after the change it still does not: the camera applies other
//            settings than asked (a frame-duration limit, a gain it rounds far): [out-of-range]
//            naming exposure_s or gain, with the values asked for and applied.
class LibcameraSettleTracker {
public:
    static constexpr int kBlindFrames = 2;
    static constexpr int kMaxFrames = 8;
    enum class Verdict { Accept, Discard, Refuse };
    struct Decision {
        Verdict verdict = Verdict::Discard;
        std::optional<Error> error;  // with Refuse
    };

    explicit LibcameraSettleTracker(int32_t min_exposure_us = 1)
        : min_exposure_us_(min_exposure_us) {}
    // The settings every request from now on carries; a change starts the count again.
    void request(const LibcameraSettings& settings);
    Decision judge(const LibcameraFrameMetadata& metadata, std::string_view device);
    int framesSinceChange() const { return frames_; }

private:
    std::optional<LibcameraSettings> settings_;
    int32_t min_exposure_us_;
    int frames_ = 0;
};

// A "libcamera:NAME?width=W&height=H&format=F" URI. NAME is a camera id or a unique part of one;
// empty takes the only camera there is. InvalidArgument naming the URI and the parameter when a
// parameter is unknown, width / height is not a positive integer, or format is not a raw format
// flarelab reads (the message lists them).
struct LibcameraCameraOptions {
    std::string name;
    LibcameraFormatRequest format;
};
Result<LibcameraCameraOptions> libcameraOptionsFromUri(const DeviceUri& uri);

// The id of the camera NAME selects among `ids` (CameraManager::cameras()): an exact id, else the
// only id containing NAME, else with an empty NAME the only camera. NotFound naming NAME and
// listing the ids when none matches (or there is no camera), InvalidArgument listing the
// candidates when several do.
Result<std::string> pickLibcameraCamera(std::span<const std::string> ids, std::string_view name);

}  // namespace flarelab::drivers
