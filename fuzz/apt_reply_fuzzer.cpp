// Fuzz target: arbitrary bytes as a stream from a Thorlabs APT controller (drivers/apt_head.h).
// The framer must always make progress within the buffer, every frame it finds must parse and
// encode back to the same bytes, and the decoders must accept or refuse what parses without
// reading past it.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <span>

#include "drivers/apt_head.h"

namespace {

namespace d = flarelab::drivers;

void decode(const d::AptMessage& m) {
    (void)d::aptMessageName(m.id);
    switch (m.id) {
        case d::apt::kHwGetInfo:
            (void)d::decodeAptHwInfo(m);
            break;
        case d::apt::kMotMoveCompleted:
        case d::apt::kMotMoveStopped:
        case d::apt::kMotGetStatusUpdate:
        case d::apt::kMotGetDcStatusUpdate:
            if (auto status = d::decodeAptStatus(m))
                (void)d::describeAptStatusBits(status->status_bits);
            break;
        default:
            break;
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::span<const uint8_t> all(data, size);
    if (auto whole = d::parseAptMessage(all)) {
        if (d::encodeAptMessage(*whole) != std::vector<uint8_t>(all.begin(), all.end()))
            std::abort();
        decode(*whole);
    }
    std::span<const uint8_t> rest = all;
    while (!rest.empty()) {
        const d::AptFraming f = d::findAptFrame(rest);
        if (f.kind == d::AptFraming::Kind::NeedMore) break;
        if (f.length == 0 || f.length > rest.size()) std::abort();
        if (f.kind == d::AptFraming::Kind::Message) {
            const auto frame = rest.first(f.length);
            auto m = d::parseAptMessage(frame);
            if (!m) std::abort();
            if (d::encodeAptMessage(*m) != std::vector<uint8_t>(frame.begin(), frame.end()))
                std::abort();
            decode(*m);
        }
        rest = rest.subspan(f.length);
    }
    return 0;
}
