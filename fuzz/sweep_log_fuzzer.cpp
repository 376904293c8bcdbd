// libFuzzer target for a version 2 sweep's frame log (hdr/sweep.h: frames.log), the file a crash
// may leave torn and that a reader takes from disk as it finds it.
//
// The bytes are parsed as a log. A refusal must be a ParseError naming the file. An accepted log
// must account for every byte (whole records, then at most one torn tail), must not have
// allocated from a declared length, and must read back the same records once written again by
// formatSweepFrameLogRecord (the framing and checksums are the writer's, whatever the payload's
// encoding was). Every violation is a trap, so libFuzzer records the input.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "hdr/sweep.h"

namespace {

using namespace flarelab;
using namespace flarelab::hdr;

void require(bool condition) {
    if (!condition) __builtin_trap();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);
    auto log = parseSweepFrameLog(bytes, "frames.log");
    if (!log) {
        require(log.error().code == ErrorCode::ParseError);
        require(log.error().message.rfind("frames.log: ", 0) == 0);
        return 0;
    }
    require(log->valid_bytes >= 0 && log->torn_bytes >= 0);
    require(log->valid_bytes + log->torn_bytes == static_cast<int64_t>(size));
    require((log->torn_bytes == 0) == log->torn.empty() || size < kSweepFrameLogMagic.size());
    std::string again(kSweepFrameLogMagic);
    for (const auto& record : log->records)
        again += formatSweepFrameLogRecord(record.index, record.frame);
    auto reread = parseSweepFrameLog(again, "again");
    require(reread.has_value());
    require(reread->torn_bytes == 0);
    require(reread->records.size() == log->records.size());
    // Compared as written (a NaN in a fuzzed frame is not equal to itself).
    for (size_t i = 0; i < log->records.size(); ++i)
        require(formatSweepFrameLogRecord(reread->records[i].index, reread->records[i].frame) ==
                formatSweepFrameLogRecord(log->records[i].index, log->records[i].frame));
    return 0;
}
