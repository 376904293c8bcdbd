// Fuzz target: arbitrary bytes as lines from a Zaber device (drivers/zaber_head.h), read both as
// replies and as commands (what the simulator parses). Whatever parses must survive formatting
// and parsing again unchanged; nothing may crash, hang or read out of bounds.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string_view>

#include "drivers/zaber_head.h"

namespace {

using flarelab::drivers::formatZaberCommand;
using flarelab::drivers::formatZaberReply;
using flarelab::drivers::parseZaberCommand;
using flarelab::drivers::parseZaberReply;
using flarelab::drivers::zaberWarningMeaning;

// Formatting may lengthen a line by a digit or two (ids are written with two); near the length
// limit the second parse may then refuse it, which is no bug.
constexpr size_t kRoundTripBelow = 480;

void checkLine(std::string_view line) {
    if (auto reply = parseZaberReply(line)) {
        (void)zaberWarningMeaning(reply->warning);
        if (line.size() < kRoundTripBelow) {
            auto again = parseZaberReply(formatZaberReply(*reply));
            if (!again || !(*again == *reply)) std::abort();
        }
    }
    if (auto command = parseZaberCommand(line)) {
        if (line.size() < kRoundTripBelow) {
            auto again = parseZaberCommand(formatZaberCommand(*command, command->had_checksum));
            if (!again || !(*again == *command)) std::abort();
        }
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    checkLine(text);
    // Also line by line, as the serial reader hands them over.
    size_t start = 0;
    while (start < text.size()) {
        const size_t end = text.find('\n', start);
        checkLine(text.substr(start, end == std::string_view::npos ? end : end - start));
        if (end == std::string_view::npos) break;
        start = end + 1;
    }
    return 0;
}
