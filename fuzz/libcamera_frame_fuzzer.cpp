// Fuzz target: what a libcamera camera hands over (drivers/libcamera_mapping.h), from arbitrary
// bytes. The first byte chooses what is read:
//   even: a raw buffer and its request's metadata. Header bytes choose the format, size, stride
//         and the metadata's fields; the rest is the buffer. Whatever unpacks must be
//         width * height samples within the format's bit depth, a frame made from them must pass
//         hdr::validateRawFrame, and the settle tracker must give a refusal its error;
//   odd:  a stream's offered formats and sizes and a request; a choice must be a readable format
//         among the offers, at an offered size.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <span>
#include <string>
#include <vector>

#include "drivers/libcamera_mapping.h"
#include "hdr/raw_io.h"

namespace {

using namespace flarelab::drivers;

// Reads little-endian numbers off the front of the input; zeros past its end.
struct Reader {
    const uint8_t* data;
    size_t size;
    size_t at = 0;

    uint64_t bytes(int n) {
        uint64_t value = 0;
        for (int i = 0; i < n; ++i, ++at)
            if (at < size) value |= static_cast<uint64_t>(data[at]) << (8 * i);
        return value;
    }
    uint8_t u8() { return static_cast<uint8_t>(bytes(1)); }
    uint16_t u16() { return static_cast<uint16_t>(bytes(2)); }
    int64_t i64() { return static_cast<int64_t>(bytes(8)); }
    double f64() {
        const uint64_t bits = bytes(8);
        double value = 0.0;
        std::memcpy(&value, &bits, sizeof value);
        return value;
    }
    std::span<const uint8_t> rest() const {
        return at < size ? std::span<const uint8_t>(data + at, size - at)
                         : std::span<const uint8_t>();
    }
};

void frameCase(Reader& in) {
    const std::span<const LibcameraRawFormat> formats = libcameraRawFormats();
    const LibcameraRawFormat& format = formats[in.u8() % formats.size()];
    const int64_t width = 1 + in.u16() % 300;
    const int64_t height = 1 + in.u8() % 40;
    const int64_t stride = in.u16();
    const uint8_t present = in.u8();
    LibcameraFrameMetadata metadata;
    if (present & 1) metadata.exposure_us = in.i64();
    if (present & 2) metadata.analogue_gain = in.f64();
    if (present & 4) metadata.sensor_timestamp_ns = in.i64();
    if (present & 8) {
        std::array<int64_t, 4> levels{};
        for (int64_t& level : levels) level = static_cast<int16_t>(in.u16()) * 4;
        metadata.black_levels = levels;
    }
    metadata.sequence = in.u16();
    LibcameraSettings requested{static_cast<int32_t>(in.bytes(4)),
                                static_cast<float>(1.0 + in.u8() / 16.0)};

    LibcameraSettleTracker tracker(static_cast<int32_t>(in.u8()));
    tracker.request(requested);
    for (int i = 0; i < LibcameraSettleTracker::kMaxFrames + 2; ++i) {
        const auto decision = tracker.judge(metadata, "fuzz");
        if ((decision.verdict == LibcameraSettleTracker::Verdict::Refuse) !=
            decision.error.has_value())
            std::abort();
    }

    auto samples = unpackLibcameraRaw(in.rest(), format, width, height, stride);
    if (!samples) return;
    if (static_cast<int64_t>(samples->size()) != width * height) std::abort();
    for (uint16_t s : *samples)
        if (s > (1 << format.bit_depth) - 1) std::abort();
    if (requested.exposure_us <= 0) requested.exposure_us = 1;
    const auto frame =
        rawFrameFromLibcamera(metadata, requested, LibcameraFormatChoice{format, {width, height}},
                              std::move(*samples), "fuzz camera");
    if (frame && !flarelab::hdr::validateRawFrame(*frame)) std::abort();
}

void choiceCase(Reader& in) {
    const std::span<const LibcameraRawFormat> formats = libcameraRawFormats();
    std::vector<LibcameraFormatOffer> offers(in.u8() % 6);
    for (LibcameraFormatOffer& offer : offers) {
        const uint8_t pick = in.u8();
        if (pick < 2 * formats.size()) {
            const LibcameraRawFormat& f = formats[pick % formats.size()];
            offer.name = std::string(f.name);
            offer.fourcc = f.fourcc;
            offer.modifier = pick < formats.size() ? f.modifier : in.i64();
        } else {
            offer.name = "other";
            offer.fourcc = static_cast<uint32_t>(in.bytes(4));
        }
        offer.sizes.resize(in.u8() % 5);
        for (PixelSize& size : offer.sizes) size = {in.u16() % 5000, in.u16() % 5000};
    }
    LibcameraFormatRequest request;
    if (const uint8_t named = in.u8(); named < formats.size())
        request.format = std::string(formats[named].name);
    // Mostly "any size", as most URIs ask.
    request.width = in.u8() < 192 ? 0 : in.u16() % 5000;
    request.height = in.u8() < 192 ? 0 : in.u16() % 5000;
    const auto choice = chooseLibcameraFormat(offers, request, "fuzz");
    if (!choice) return;
    if (!findLibcameraRawFormat(choice->format.fourcc, choice->format.modifier)) std::abort();
    bool offered = false;
    for (const LibcameraFormatOffer& offer : offers)
        if (offer.fourcc == choice->format.fourcc && offer.modifier == choice->format.modifier)
            for (const PixelSize& size : offer.sizes) offered = offered || size == choice->size;
    if (!offered || choice->size.width < 1 || choice->size.height < 1) std::abort();
    if (!request.format.empty() && choice->format.name != request.format) std::abort();
    (void)acceptValidatedFormat(choice->format.fourcc, choice->format.modifier, choice->format.name,
                                choice->size, request, "fuzz");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    Reader in{data, size};
    if (in.u8() % 2 == 0)
        frameCase(in);
    else
        choiceCase(in);
    return 0;
}
