// libFuzzer target for the EXR reader (hdr/exr.h).
//
// Any byte string goes to readExrFromMemory, the code readExr runs on a file. A rejection must
// name the input; an acceptance must be an image of the size the limits allow with every value
// finite, since the reader promises to pass on no NaN or infinity. Limits below the defaults keep
// one input's image small, so a valid header with a large data window costs memory only up to
// what libFuzzer allows. Every violation is a trap, so libFuzzer records the input.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include "hdr/exr.h"

namespace {

using namespace flarelab;
using namespace flarelab::hdr;

constexpr char kSource[] = "fuzz-input";

void require(bool condition) {
    if (!condition) __builtin_trap();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    ExrReadOptions options;
    options.max_side = 4096;
    options.max_pixels = 1 << 20;
    const Result<ExrImage> read = readExrFromMemory(std::span(data, size), kSource, options);
    if (!read) {
        require(read.error().message.rfind(std::string(kSource) + ": ", 0) == 0);
        return 0;
    }
    const ImageRGB& image = read->image;
    require(image.width >= 1 && image.height >= 1);
    require(image.width <= options.max_side && image.height <= options.max_side);
    require(image.width * image.height <= options.max_pixels);
    require(image.pixels.size() == static_cast<size_t>(image.width * image.height * 3));
    for (const float v : image.pixels) require(std::isfinite(v));
    for (const double t : read->meta.exposure_times_s) require(std::isfinite(t) && t > 0.0);
    for (const auto* number : {&read->meta.angle_deg, &read->meta.roll_deg, &read->meta.gain})
        require(!number->has_value() || std::isfinite(**number));
    return 0;
}
