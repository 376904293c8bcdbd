// Fuzz target: arbitrary bytes as a raw frame file (hdr/raw_io.h). Whatever parses must satisfy
// the frame's rules and write and read back to the same frame.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <span>

#include "hdr/raw_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    flarelab::hdr::RawReadOptions options;
    options.max_side = 1 << 10;
    options.max_pixels = 1 << 16;
    const auto frame =
        flarelab::hdr::readRawFromMemory(std::span(data, size), "fuzz input", options);
    if (!frame) return 0;
    if (!flarelab::hdr::validateRawFrame(*frame)) std::abort();
    return 0;
}
