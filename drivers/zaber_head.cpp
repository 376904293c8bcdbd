#include "drivers/zaber_head.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <vector>

#include "drivers/detail/stage_util.h"

namespace flarelab::drivers {
namespace {

using detail::fmt;
using detail::untagged;

// Longer lines are not Zaber replies (long answers are split into info lines of about 80).
constexpr size_t kMaxLine = 512;

bool isDigit(char c) { return c >= '0' && c <= '9'; }

bool allDigits(std::string_view s) {
    return !s.empty() && std::all_of(s.begin(), s.end(), isDigit);
}

// A whole number of at most max_digits digits.
std::optional<int> smallNumber(std::string_view s, size_t max_digits) {
    if (!allDigits(s) || s.size() > max_digits) return std::nullopt;
    int value = 0;
    for (char c : s) value = value * 10 + (c - '0');
    return value;
}

int hexValue(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    return -1;
}

// A signed 64-bit integer, the whole string.
std::optional<int64_t> parseInteger(std::string_view s) {
    int64_t value = 0;
    const char* begin = s.data();
    const char* end = s.data() + s.size();
    if (begin != end && *begin == '+') ++begin;
    const auto [ptr, ec] = std::from_chars(begin, end, value);
    if (ec != std::errc() || ptr != end || begin == end) return std::nullopt;
    return value;
}

std::vector<std::string_view> splitSpaces(std::string_view s) {
    std::vector<std::string_view> tokens;
    size_t start = 0;
    for (;;) {
        const size_t space = s.find(' ', start);
        tokens.push_back(s.substr(start, space == std::string_view::npos ? space : space - start));
        if (space == std::string_view::npos) break;
        start = space + 1;
    }
    return tokens;
}

std::string joined(const std::vector<std::string_view>& tokens, size_t from) {
    std::string out;
    for (size_t i = from; i < tokens.size(); ++i) {
        if (i > from) out += ' ';
        out += tokens[i];
    }
    return out;
}

struct Framed {
    std::string_view body;  // between the type character and ':'
    bool has_checksum = false;
};

// Checks the characters and the checksum of a line common to commands and replies.
Result<Framed> frame(std::string_view line, const char* what, const std::string& quoted) {
    const auto bad = [&](const std::string& why) -> Error {
        return makeError(ErrorCode::ParseError, std::string(what) + " '" + quoted + "': " + why);
    };
    if (line.size() > kMaxLine) return bad("longer than " + std::to_string(kMaxLine) + " bytes");
    if (line.empty()) return bad("empty line");
    for (size_t i = 0; i < line.size(); ++i) {
        const auto c = static_cast<unsigned char>(line[i]);
        if (c < 32 || c > 126) {
            char hex[8];
            std::snprintf(hex, sizeof(hex), "0x%02x", static_cast<unsigned>(c));
            return bad(std::string("byte ") + hex + " at column " + std::to_string(i + 1) +
                       " is not printable ASCII");
        }
    }
    Framed f;
    f.body = line.substr(1);
    const size_t colon = line.find(':');
    if (colon != std::string_view::npos) {
        if (colon + 3 != line.size())
            return bad("':' must start a two-digit checksum at the end of the line");
        const int hi = hexValue(line[colon + 1]), lo = hexValue(line[colon + 2]);
        if (hi < 0 || lo < 0)
            return bad("checksum ':" + std::string(line.substr(colon + 1)) +
                       "' is not two hex digits");
        f.body = line.substr(1, colon - 1);
        const int sent = hi * 16 + lo;
        const int computed = zaberChecksum(f.body);
        if (sent != computed) {
            char text[64];
            std::snprintf(text, sizeof(text), "checksum :%02X does not match the message (:%02X)",
                          static_cast<unsigned>(sent), static_cast<unsigned>(computed));
            return bad(text);
        }
        f.has_checksum = true;
    }
    return f;
}

std::string_view withoutLineEnd(std::string_view line) {
    while (!line.empty() && (line.back() == '\n' || line.back() == '\r')) line.remove_suffix(1);
    return line;
}

bool isWarningFlag(std::string_view s) {
    return s == "--" || (s.size() == 2 && s[0] >= 'A' && s[0] <= 'Z' && s[1] >= 'A' && s[1] <= 'Z');
}

struct FlagMeaning {
    const char* flag;
    const char* meaning;
};

// The warning flags of the ASCII protocol manual, most urgent first.
constexpr FlagMeaning kFlags[] = {
    {"FF", "critical system error"},
    {"FN", "peripheral not supported"},
    {"FZ", "peripheral inactive"},
    {"FH", "driver disabled by the hardware emergency stop"},
    {"FV", "driver disabled: supply over- or under-voltage"},
    {"FO", "driver disabled at start-up or by command"},
    {"FC", "current inrush error"},
    {"FM", "motor temperature error"},
    {"FD", "driver disabled (overheating)"},
    {"FQ", "encoder error"},
    {"FI", "index error"},
    {"FA", "analog encoder sync error"},
    {"FR", "overdrive limit exceeded"},
    {"FS", "stalled and stopped"},
    {"FB", "stream bounds error"},
    {"FP", "interpolated path deviation"},
    {"FE", "limit error: a limit sensor was not found or is faulty"},
    {"FT", "excessive twist"},
    {"WL", "unexpected limit trigger"},
    {"WV", "voltage out of range"},
    {"WT", "controller temperature high"},
    {"WS", "stalled, recovering"},
    {"WM", "displaced when stationary"},
    {"WP", "invalid calibration type"},
    {"WR", "no reference position (not homed)"},
    {"WH", "device not homed"},
    {"NC", "manual control (knob) in use"},
    {"NI", "movement interrupted"},
    {"ND", "stream discontinuity"},
    {"NR", "value rounded"},
    {"NT", "value truncated"},
    {"NU", "setting update pending"},
    {"NJ", "joystick calibrating"},
    {"NB", "firmware update mode"},
};

}  // namespace

uint8_t zaberChecksum(std::string_view body) {
    unsigned sum = 0;
    for (char c : body) sum += static_cast<unsigned char>(c);
    return static_cast<uint8_t>((256u - (sum & 0xFFu)) & 0xFFu);
}

Result<ZaberReply> parseZaberReply(std::string_view raw) {
    const std::string_view line = withoutLineEnd(raw);
    const std::string quoted = quoteBytes(line);
    auto framed = frame(line, "zaber reply", quoted);
    if (!framed) return framed.error();
    const auto bad = [&](const std::string& why) -> Error {
        return makeError(ErrorCode::ParseError, "zaber reply '" + quoted + "': " + why);
    };
    ZaberReply reply;
    switch (line[0]) {
        case '@':
            reply.kind = ZaberReply::Kind::Reply;
            break;
        case '#':
            reply.kind = ZaberReply::Kind::Info;
            break;
        case '!':
            reply.kind = ZaberReply::Kind::Alert;
            break;
        default:
            return bad("starts with '" + quoteBytes(line.substr(0, 1)) +
                       "', not '@' (reply), '#' (info) or '!' (alert)");
    }
    reply.has_checksum = framed->has_checksum;
    const std::vector<std::string_view> t = splitSpaces(framed->body);
    for (size_t i = 0; i < t.size(); ++i)
        if (t[i].empty() && !(i + 1 == t.size() && reply.kind == ZaberReply::Kind::Info))
            return bad("empty field " + std::to_string(i + 1) + " (extra space?)");
    if (t.size() < 2) return bad("no axis after the device address");
    const auto device = smallNumber(t[0], 2);
    if (!device || t[0].size() != 2 || *device < 1)
        return bad("device address '" + std::string(t[0]) + "' is not two digits 01..99");
    reply.device = *device;
    const auto axis = smallNumber(t[1], 2);
    if (!axis) return bad("axis '" + std::string(t[1]) + "' is not a number 0..99");
    reply.axis = *axis;
    size_t i = 2;
    if (reply.kind != ZaberReply::Kind::Alert && i < t.size() && allDigits(t[i])) {
        const auto id = smallNumber(t[i], 2);
        if (!id) return bad("message id '" + std::string(t[i]) + "' is not a number 0..99");
        reply.message_id = *id;
        ++i;
    }
    if (reply.kind == ZaberReply::Kind::Reply) {
        if (i + 4 > t.size())
            return bad("needs reply flag, status, warning flag and data after the address");
        if (t[i] == "OK")
            reply.rejected = false;
        else if (t[i] == "RJ")
            reply.rejected = true;
        else
            return bad("reply flag '" + std::string(t[i]) + "' is not OK or RJ");
        ++i;
    }
    if (reply.kind != ZaberReply::Kind::Info) {
        if (i + 2 > t.size()) return bad("needs status and warning flag");
        if (t[i] == "BUSY")
            reply.busy = true;
        else if (t[i] == "IDLE")
            reply.busy = false;
        else
            return bad("status '" + std::string(t[i]) + "' is not BUSY or IDLE");
        ++i;
        if (!isWarningFlag(t[i]))
            return bad("warning flag '" + std::string(t[i]) + "' is not '--' or two capitals");
        reply.warning = std::string(t[i]);
        ++i;
    }
    reply.data = joined(t, i);
    if (!reply.data.empty() && reply.data.back() == '\\') {
        reply.continues = true;
        reply.data.pop_back();
        while (!reply.data.empty() && reply.data.back() == ' ') reply.data.pop_back();
    }
    return reply;
}

Result<ZaberCommand> parseZaberCommand(std::string_view raw) {
    const std::string_view line = withoutLineEnd(raw);
    const std::string quoted = quoteBytes(line);
    auto framed = frame(line, "zaber command", quoted);
    if (!framed) return framed.error();
    const auto bad = [&](const std::string& why) -> Error {
        return makeError(ErrorCode::ParseError, "zaber command '" + quoted + "': " + why);
    };
    if (line[0] != '/') return bad("does not start with '/'");
    ZaberCommand command;
    command.had_checksum = framed->has_checksum;
    // Devices accept runs of spaces between words; so does this parser.
    std::vector<std::string_view> t;
    for (std::string_view w : splitSpaces(framed->body))
        if (!w.empty()) t.push_back(w);
    size_t i = 0;
    if (i < t.size() && allDigits(t[i])) {
        const auto device = smallNumber(t[i], 2);
        if (!device) return bad("device address '" + std::string(t[i]) + "' is not 0..99");
        command.device = *device;
        ++i;
        if (i < t.size() && allDigits(t[i])) {
            const auto axis = smallNumber(t[i], 2);
            if (!axis) return bad("axis '" + std::string(t[i]) + "' is not 0..99");
            command.axis = *axis;
            ++i;
            if (i < t.size() && allDigits(t[i])) {
                const auto id = smallNumber(t[i], 2);
                if (!id) return bad("message id '" + std::string(t[i]) + "' is not 0..99");
                command.message_id = *id;
                ++i;
            }
        }
    }
    command.text = joined(t, i);
    return command;
}

std::string formatZaberCommand(const ZaberCommand& command, bool with_checksum) {
    std::string body = std::to_string(command.device) + " " + std::to_string(command.axis);
    if (command.message_id) body += " " + std::to_string(*command.message_id);
    if (!command.text.empty()) body += " " + command.text;
    std::string line = "/" + body;
    if (with_checksum) {
        char sum[8];
        std::snprintf(sum, sizeof(sum), ":%02X", static_cast<unsigned>(zaberChecksum(body)));
        line += sum;
    }
    return line + "\n";
}

std::string formatZaberReply(const ZaberReply& reply) {
    char address[16];
    std::snprintf(address, sizeof(address), "%02d %d", reply.device, reply.axis);
    std::string body = address;
    if (reply.message_id) {
        char id[8];
        std::snprintf(id, sizeof(id), " %02d", *reply.message_id);
        body += id;
    }
    if (reply.kind == ZaberReply::Kind::Reply) body += reply.rejected ? " RJ" : " OK";
    if (reply.kind != ZaberReply::Kind::Info) {
        body += reply.busy ? " BUSY " : " IDLE ";
        body += reply.warning;
    }
    // A reply always has a data field; the '\' of a continued message is a word of its own.
    if (!reply.data.empty() || reply.kind == ZaberReply::Kind::Reply || reply.continues)
        body += " " + reply.data;
    if (reply.continues) body += "\\";
    const char type = reply.kind == ZaberReply::Kind::Reply  ? '@'
                      : reply.kind == ZaberReply::Kind::Info ? '#'
                                                             : '!';
    std::string line = std::string(1, type) + body;
    if (reply.has_checksum) {
        char sum[8];
        std::snprintf(sum, sizeof(sum), ":%02X", static_cast<unsigned>(zaberChecksum(body)));
        line += sum;
    }
    return line + "\r\n";
}

std::string zaberWarningMeaning(std::string_view flag) {
    if (flag == "--") return "no warning";
    for (const FlagMeaning& f : kFlags)
        if (flag == f.flag) return f.meaning;
    return "unknown warning flag";
}

int zaberWarningRank(std::string_view flag) {
    int rank = 0;
    for (const FlagMeaning& f : kFlags) {
        if (flag == f.flag) return rank;
        ++rank;
    }
    return rank;
}

// ---------------------------------------------------------------------------------------------
// Options

Status ZaberHeadOptions::validate() const {
    const auto bad = [](const std::string& why) -> Error {
        return makeError(ErrorCode::InvalidArgument, "zaber head options: " + why);
    };
    if (port.empty()) return bad("no serial port (e.g. zaber:/dev/ttyUSB0)");
    if (device < 1 || device > 99) return bad("device must lie in 1..99");
    if (axis < 1 || axis > 9) return bad("axis must lie in 1..9");
    if (units_per_deg && !(std::isfinite(*units_per_deg) && *units_per_deg > 0.0))
        return bad("units_per_deg must be positive");
    if (min_deg && !std::isfinite(*min_deg)) return bad("min_deg must be finite");
    if (max_deg && !std::isfinite(*max_deg)) return bad("max_deg must be finite");
    if (min_deg && max_deg && !(*min_deg < *max_deg)) return bad("min_deg must be below max_deg");
    if (max_speed_deg_s && !(std::isfinite(*max_speed_deg_s) && *max_speed_deg_s > 0.0))
        return bad("max_speed_deg_s must be positive");
    if (!(reply_timeout_s > 0.0 && reply_timeout_s <= 60.0))
        return bad("reply_timeout_s must lie in (0, 60]");
    if (!(poll_s > 0.0 && poll_s <= 10.0)) return bad("poll_s must lie in (0, 10]");
    return Ok{};
}

Result<ZaberHeadOptions> ZaberHeadOptions::fromUri(const DeviceUri& uri) {
    if (Status ok = uri.onlyParams({"device", "axis", "baud", "units_per_deg", "min_deg", "max_deg",
                                    "max_speed_deg_s", "checksum", "message_ids", "reply_timeout_s",
                                    "poll_s"});
        !ok)
        return ok.error();
    ZaberHeadOptions o;
    o.port = uri.path;
    if (o.port.empty())
        return makeError(ErrorCode::InvalidArgument,
                         "device uri '" + uri.text +
                             "': zaber needs the serial port, e.g. zaber:/dev/ttyUSB0?axis=1");
    auto device = detail::uriWhole(uri, "device", o.device, 1, 99);
    if (!device) return device.error();
    o.device = static_cast<int>(*device);
    auto axis = detail::uriWhole(uri, "axis", o.axis, 1, 9);
    if (!axis) return axis.error();
    o.axis = static_cast<int>(*axis);
    auto baud = detail::uriWhole(uri, "baud", o.baud, 1, 4000000);
    if (!baud) return baud.error();
    o.baud = static_cast<int>(*baud);
    auto checksum = detail::uriWhole(uri, "checksum", 1, 0, 1);
    if (!checksum) return checksum.error();
    o.checksums = *checksum == 1;
    auto ids = detail::uriWhole(uri, "message_ids", 1, 0, 1);
    if (!ids) return ids.error();
    o.message_ids = *ids == 1;
    for (auto [key, field] :
         {std::pair<const char*, std::optional<double>*>{"units_per_deg", &o.units_per_deg},
          {"min_deg", &o.min_deg},
          {"max_deg", &o.max_deg},
          {"max_speed_deg_s", &o.max_speed_deg_s}}) {
        auto value = detail::uriOptional(uri, key);
        if (!value) return value.error();
        *field = *value;
    }
    auto reply_timeout = detail::uriPositive(uri, "reply_timeout_s", o.reply_timeout_s);
    if (!reply_timeout) return reply_timeout.error();
    o.reply_timeout_s = *reply_timeout;
    auto poll = detail::uriPositive(uri, "poll_s", o.poll_s);
    if (!poll) return poll.error();
    o.poll_s = *poll;
    if (Status ok = o.validate(); !ok)
        return ok.error().withContext("device uri '" + uri.text + "'");
    return o;
}

// ---------------------------------------------------------------------------------------------
// The head

ZaberHead::ZaberHead(Key, ZaberHeadOptions options, std::unique_ptr<SerialPort> port)
    : options_(std::move(options)), port_(std::move(port)) {}

std::string ZaberHead::name() const {
    return "zaber " + options_.port + " device " + std::to_string(options_.device) + " axis " +
           std::to_string(options_.axis);
}

Result<std::unique_ptr<ZaberHead>> ZaberHead::open(const ZaberHeadOptions& options) {
    if (Status ok = options.validate(); !ok) return ok.error();
    SerialOptions serial;
    serial.baud = options.baud;
    serial.flow = FlowControl::None;
    auto port = SerialPort::open(options.port, serial);
    if (!port) return port.error();
    auto head = std::make_unique<ZaberHead>(Key{}, options, std::move(*port));
    if (Status ok = head->initialise(); !ok) return ok.error();
    return head;
}

Result<ZaberReply> ZaberHead::exchange(const std::string& text, bool device_scope) {
    std::lock_guard io(io_mutex_);
    const int axis = device_scope ? 0 : options_.axis;
    std::vector<std::string> problems;
    bool last_timed_out = false;
    for (int attempt = 0; attempt < 2; ++attempt) {
        // Whatever sits in the input now is stale: an answer that came after its deadline.
        if (Status ok = port_->flushInput(); !ok) return ok.error();
        ZaberCommand command;
        command.device = options_.device;
        command.axis = axis;
        command.text = text;
        if (options_.message_ids) {
            command.message_id = next_id_;
            next_id_ = (next_id_ + 1) % 100;
        }
        const auto deadline = deadlineAfter(options_.reply_timeout_s);
        if (Status ok = port_->writeAll(formatZaberCommand(command, options_.checksums), deadline);
            !ok)
            return ok.error();
        std::string skipped;
        for (;;) {
            auto line = port_->readLine(deadline, kMaxLine);
            if (!line) {
                if (deviceFaultOf(line.error()) != DeviceFault::Timeout) return line.error();
                last_timed_out = true;
                problems.push_back(untagged(line.error()) + skipped);
                break;
            }
            auto reply = parseZaberReply(*line);
            if (!reply) {
                last_timed_out = false;
                problems.push_back(reply.error().message);
                break;
            }
            if (reply->kind != ZaberReply::Kind::Reply) continue;  // alerts, info lines
            if (reply->device != options_.device || reply->axis != axis) {
                last_timed_out = false;
                problems.push_back("reply '" + quoteBytes(*line) + "' comes from device " +
                                   std::to_string(reply->device) + " axis " +
                                   std::to_string(reply->axis));
                break;
            }
            if (command.message_id) {
                if (!reply->message_id) {
                    last_timed_out = false;
                    problems.push_back("reply '" + quoteBytes(*line) +
                                       "' has no message id (firmware before 6.06? try "
                                       "message_ids=0)");
                    break;
                }
                if (*reply->message_id != *command.message_id) {
                    // A late answer to an earlier command: skip it, keep waiting for ours.
                    skipped += " (skipped '" + quoteBytes(*line) + "': message id " +
                               std::to_string(*reply->message_id) + ", not " +
                               std::to_string(*command.message_id) + ")";
                    continue;
                }
            }
            if (reply->continues) {
                last_timed_out = false;
                problems.push_back("reply '" + quoteBytes(*line) +
                                   "' continues on info lines, which no command of this driver "
                                   "asks for");
                break;
            }
            return *reply;
        }
    }
    std::string detail;
    for (size_t i = 0; i < problems.size(); ++i) detail += (i ? "; then " : "") + problems[i];
    if (last_timed_out)
        return deviceError(DeviceFault::Timeout, name(),
                           "no valid reply to '" + text + "' within reply_timeout_s = " +
                               fmt(options_.reply_timeout_s) + ", twice: " + detail +
                               " (powered? at " + std::to_string(options_.baud) +
                               " baud? speaking the ASCII protocol?)");
    return makeError(ErrorCode::IoError,
                     name() + ": bad reply to '" + text + "', twice: " + detail);
}

Result<ZaberReply> ZaberHead::command(const std::string& text,
                                      bool device_scope,
                                      bool out_of_range_on_baddata) {
    auto reply = exchange(text, device_scope);
    if (!reply) return reply.error();
    if (!reply->rejected) return reply;
    return rejection(*reply, text, out_of_range_on_baddata);
}

Error ZaberHead::rejection(const ZaberReply& reply,
                           const std::string& text,
                           bool out_of_range_on_baddata) const {
    const std::string& reason = reply.data;
    const std::string what = "device rejected '" + text + "': " + reason;
    if (reason == "BADDATA" && out_of_range_on_baddata)
        return deviceError(DeviceFault::OutOfRange, name(),
                           what + " (the value lies outside what the axis allows)");
    if (reason == "STATUSBUSY" || reason == "AGAIN")
        return deviceError(DeviceFault::Busy, name(), what + " (the axis is busy)");
    if (reason == "BADCOMMAND")
        return makeError(ErrorCode::Unsupported,
                         name() + ": " + what + " (a command this device does not know)");
    if (reason == "BADAXIS" || reason == "DEVICEONLY" || reason == "AXISONLY")
        return makeError(ErrorCode::InvalidArgument,
                         name() + ": " + what + " (check the axis number in the URI)");
    if (reason == "PARKED")
        return makeError(ErrorCode::IoError,
                         name() + ": " + what + " (the axis is parked: 'tools parking unpark')");
    if (reason == "DRIVERDISABLED")
        return makeError(ErrorCode::IoError,
                         name() + ": " + what + " (the motor driver is off: warning flag " +
                             reply.warning + ", " + zaberWarningMeaning(reply.warning) + ")");
    return makeError(ErrorCode::IoError, name() + ": " + what);
}

Result<int64_t> ZaberHead::readInteger(const std::string& setting, bool device_scope) {
    auto reply = command("get " + setting, device_scope);
    if (!reply) return reply.error();
    const auto value = parseInteger(reply->data);
    if (!value)
        return makeError(ErrorCode::IoError, name() + ": 'get " + setting + "' answered '" +
                                                 quoteBytes(reply->data) + "', not a whole number");
    return *value;
}

std::optional<Error> ZaberHead::warningError(const std::string& flag, const std::string& doing) {
    if (flag == "--") return std::nullopt;
    const std::string what =
        doing + ": warning flag " + flag + " (" + zaberWarningMeaning(flag) + ")";
    const auto lost = [&](DeviceFault fault, const std::string& advice) {
        std::lock_guard lock(state_mutex_);
        homed_ = false;
        return deviceError(fault, name(), what + advice);
    };
    if (flag == "FS" || flag == "FR") return deviceError(DeviceFault::Stalled, name(), what);
    if (flag == "FQ" || flag == "FI" || flag == "FA" || flag == "WL" || flag == "WM")
        return lost(DeviceFault::LostPosition, "; home before the next move");
    if (flag == "WR" || flag == "WH") return lost(DeviceFault::NotHomed, "; home first");
    if (flag == "NI")
        return deviceError(DeviceFault::Stopped, name(),
                           what + ": another command or the knob interrupted it");
    if (flag == "NC")
        return deviceError(DeviceFault::Busy, name(), what + ": someone turns the knob");
    if (flag[0] == 'F' || flag == "NB")
        return makeError(ErrorCode::IoError,
                         name() + ": " + what + " (needs a person: see the device's manual)");
    return std::nullopt;  // WV, WT, WS, WP, ND, NR, NT, NU, NJ: no reason to fail the move
}

Status ZaberHead::initialise() {
    auto device_id = readInteger("deviceid", true);
    if (!device_id) return device_id.error();
    std::string serial = "unknown";
    if (auto s = exchange("get system.serial", true); s && !s->rejected)
        serial = s->data;
    else if (!s)
        return s.error();
    std::string version = "?";
    if (auto v = exchange("get version", true); v && !v->rejected)
        version = v->data;
    else if (!v)
        return v.error();
    identity_.backend = "zaber";
    identity_.model = "Zaber device id " + std::to_string(*device_id) + " axis " +
                      std::to_string(options_.axis) + " (firmware " + version + ")";
    identity_.serial = serial;
    identity_.uri = "zaber:" + options_.port + "?device=" + std::to_string(options_.device) +
                    "&axis=" + std::to_string(options_.axis);

    // Microsteps per degree: given, or Zaber's rotary default at the axis's resolution.
    auto resolution = exchange("get resolution");
    if (!resolution) return resolution.error();
    // Devices without microsteps (direct drives) do not know the setting; other refusals (a
    // wrong axis) are errors.
    if (resolution->rejected && resolution->data != "BADCOMMAND")
        return rejection(*resolution, "get resolution", false);
    if (options_.units_per_deg) {
        units_per_deg_ = *options_.units_per_deg;
    } else {
        const auto steps = resolution->rejected ? std::nullopt : parseInteger(resolution->data);
        if (!steps || *steps < 1 || *steps > 4096)
            return makeError(ErrorCode::InvalidArgument,
                             name() + ": the axis reports no microstep resolution ('" +
                                 quoteBytes(resolution->data) +
                                 "'), so the default units_per_deg does not apply: give "
                                 "units_per_deg in the URI (1 / the stage's microstep size in "
                                 "degrees)");
        units_per_deg_ = kZaberDefaultUnitsPerDeg * static_cast<double>(*steps) /
                         static_cast<double>(kZaberDefaultResolution);
    }

    auto lo = readInteger("limit.min");
    if (!lo) return lo.error();
    auto hi = readInteger("limit.max");
    if (!hi) return hi.error();
    const double device_min = static_cast<double>(*lo) / units_per_deg_;
    const double device_max = static_cast<double>(*hi) / units_per_deg_;
    if (!(device_min < device_max))
        return makeError(ErrorCode::IoError,
                         name() + ": limit.min = " + std::to_string(*lo) +
                             " is not below limit.max = " + std::to_string(*hi));
    limits_.min_deg = options_.min_deg.value_or(device_min);
    limits_.max_deg = options_.max_deg.value_or(device_max);
    if (limits_.min_deg < device_min || limits_.max_deg > device_max)
        return makeError(ErrorCode::InvalidArgument,
                         name() + ": min_deg/max_deg [" + fmt(limits_.min_deg) + ", " +
                             fmt(limits_.max_deg) + "] reach outside the axis's limits [" +
                             fmt(device_min) + ", " + fmt(device_max) +
                             "] deg (limit.min, limit.max)");
    if (!(limits_.min_deg < limits_.max_deg))
        return makeError(ErrorCode::InvalidArgument, name() + ": min_deg must be below max_deg");

    auto maxspeed = readInteger("maxspeed");
    if (!maxspeed) return maxspeed.error();
    const double speed =
        static_cast<double>(*maxspeed) / kZaberSpeedUnitsPerStepPerS / units_per_deg_;
    if (!(speed > 0.0))
        return makeError(ErrorCode::IoError,
                         name() + ": maxspeed = " + std::to_string(*maxspeed) + " is not positive");
    limits_.max_speed_deg_s = options_.max_speed_deg_s.value_or(speed);
    {
        std::lock_guard lock(state_mutex_);
        speed_deg_s_ = speed;
    }
    if (speed > limits_.max_speed_deg_s)
        if (Status ok = setSpeed(limits_.max_speed_deg_s); !ok) return ok.error();

    auto warnings = command("warnings");
    if (!warnings) return warnings.error();
    bool referenced = true;
    for (std::string_view flag : splitSpaces(warnings->data))
        if (flag == "WR" || flag == "WH") referenced = false;
    std::lock_guard lock(state_mutex_);
    homed_ = referenced;
    return Ok{};
}

DeviceIdentity ZaberHead::identity() const { return identity_; }

HeadLimits ZaberHead::limits() const { return limits_; }

int64_t ZaberHead::targetSteps(double angle_deg) const {
    return std::llround(angle_deg * units_per_deg_);
}

double ZaberHead::speed_deg_s() const {
    std::lock_guard lock(state_mutex_);
    return speed_deg_s_;
}

Status ZaberHead::setSpeed(double speed_deg_s) {
    if (!std::isfinite(speed_deg_s) || !(speed_deg_s > 0.0) ||
        speed_deg_s > limits_.max_speed_deg_s)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "speed_deg_s = " + fmt(speed_deg_s) + " outside (0, " +
                               fmt(limits_.max_speed_deg_s) + "]");
    const int64_t value = std::llround(speed_deg_s * units_per_deg_ * kZaberSpeedUnitsPerStepPerS);
    if (value < 1)
        return deviceError(
            DeviceFault::OutOfRange, name(),
            "speed_deg_s = " + fmt(speed_deg_s) + " is below the axis's smallest speed step");
    auto set = command("set maxspeed " + std::to_string(value), false, true);
    if (!set) return set.error();
    auto readback = readInteger("maxspeed");
    if (!readback) return readback.error();
    std::lock_guard lock(state_mutex_);
    speed_deg_s_ = static_cast<double>(*readback) / kZaberSpeedUnitsPerStepPerS / units_per_deg_;
    return Ok{};
}

Result<double> ZaberHead::position() {
    {
        std::lock_guard lock(state_mutex_);
        if (!homed_)
            return deviceError(DeviceFault::NotHomed, name(), "position unknown: home first");
    }
    auto reply = command("get pos");
    if (!reply) return reply.error();
    if (reply->warning == "WR" || reply->warning == "WH" || reply->warning == "WL" ||
        reply->warning == "WM" || reply->warning == "FQ" || reply->warning == "FI" ||
        reply->warning == "FA")
        return *warningError(reply->warning, "position");
    const auto steps = parseInteger(reply->data);
    if (!steps)
        return makeError(ErrorCode::IoError, name() + ": 'get pos' answered '" +
                                                 quoteBytes(reply->data) + "', not a count");
    return static_cast<double>(*steps) / units_per_deg_;
}

bool ZaberHead::beginMotion() {
    // Under the state lock, so that a stop() either finds nothing moving or sets its flag after
    // this motion cleared it: never lost in between.
    std::lock_guard lock(state_mutex_);
    if (moving_) return false;
    moving_ = true;
    stop_requested_ = false;
    return true;
}

Status ZaberHead::stop() {
    {
        std::lock_guard lock(state_mutex_);
        if (!moving_) return Ok{};
        stop_requested_ = true;
        wake_.notify_all();
    }
    auto reply = command("stop");
    if (!reply) return reply.error();
    return Ok{};
}

Result<ZaberReply> ZaberHead::waitIdle(SerialClock::time_point deadline, const std::string& doing) {
    bool stop_seen = false;
    bool stop_repeated = false;
    for (;;) {
        auto reply = command("get pos");
        if (!reply) return reply.error();
        if (!reply->busy) return reply;
        if (stop_requested_ && !stop_repeated) {
            // stop() may have reached the device before the move command did: say it again.
            stop_repeated = true;
            if (auto stopped = command("stop"); !stopped) return stopped.error();
        }
        if (SerialClock::now() >= deadline) {
            // Do not leave the axis running past its caller's patience.
            (void)command("stop");
            const auto steps = parseInteger(reply->data);
            return deviceError(
                DeviceFault::Timeout, name(),
                doing + " did not finish in time" +
                    (steps ? "; stopped near " + fmt(static_cast<double>(*steps) / units_per_deg_) +
                                 " deg"
                           : std::string()));
        }
        std::unique_lock lock(state_mutex_);
        const auto next = std::min(deadline, deadlineAfter(options_.poll_s));
        wake_.wait_until(lock, next, [&] { return stop_requested_ && !stop_seen; });
        stop_seen = stop_requested_;
    }
}

Result<double> ZaberHead::moveTo(double angle_deg, double timeout_s) {
    if (!std::isfinite(angle_deg) || angle_deg < limits_.min_deg || angle_deg > limits_.max_deg)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "angle_deg = " + fmt(angle_deg) + " outside the limits [" +
                               fmt(limits_.min_deg) + ", " + fmt(limits_.max_deg) + "]");
    if (!std::isfinite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, name(), "timeout_s must be positive");
    {
        std::lock_guard lock(state_mutex_);
        if (!homed_) return deviceError(DeviceFault::NotHomed, name(), "cannot move: home first");
    }
    if (!beginMotion()) return deviceError(DeviceFault::Busy, name(), "another move is running");
    struct Done {
        std::atomic<bool>& flag;
        ~Done() { flag = false; }
    } done{moving_};
    const auto deadline = deadlineAfter(timeout_s);
    const int64_t target = targetSteps(angle_deg);
    const std::string what =
        "move to " + fmt(angle_deg) + " deg (" + std::to_string(target) + " microsteps)";

    // Flags left from an earlier move (NI after a stop) would be read as this move's.
    if (auto cleared = command("warnings clear"); !cleared) return cleared.error();
    auto started = command("move abs " + std::to_string(target), false, true);
    if (!started) return started.error();
    // A fault already standing (a driver shut down) fails the move now; any other flag is read
    // when the move has ended.
    if (started->warning[0] == 'F')
        if (auto e = warningError(started->warning, what)) return *e;

    auto last = waitIdle(deadline, what);
    if (!last) return last.error();
    const auto steps = parseInteger(last->data);
    if (!steps)
        return makeError(ErrorCode::IoError, name() + ": 'get pos' answered '" +
                                                 quoteBytes(last->data) + "', not a count");
    const double at_deg = static_cast<double>(*steps) / units_per_deg_;
    if (stop_requested_)
        return deviceError(DeviceFault::Stopped, name(),
                           what + " stopped at " + fmt(at_deg) + " deg");
    if (auto e = warningError(last->warning, what)) return *e;
    if (*steps != target)
        return deviceError(DeviceFault::Stalled, name(),
                           what + " ended at " + fmt(at_deg) + " deg, " +
                               std::to_string(std::llabs(target - *steps)) +
                               " microsteps short, without a warning flag");
    return at_deg;
}

Status ZaberHead::home(double timeout_s) {
    if (!std::isfinite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, name(), "timeout_s must be positive");
    if (!beginMotion()) return deviceError(DeviceFault::Busy, name(), "another move is running");
    struct Done {
        std::atomic<bool>& flag;
        ~Done() { flag = false; }
    } done{moving_};
    {
        std::lock_guard lock(state_mutex_);
        homed_ = false;
    }
    const auto deadline = deadlineAfter(timeout_s);
    if (auto cleared = command("warnings clear"); !cleared) return cleared.error();
    if (auto started = command("home"); !started) return started.error();
    auto last = waitIdle(deadline, "homing");
    if (!last) return last.error();
    if (stop_requested_) return deviceError(DeviceFault::Stopped, name(), "homing stopped");
    if (last->warning != "WR" && last->warning != "WH")
        if (auto e = warningError(last->warning, "homing")) return *e;
    auto warnings = command("warnings");
    if (!warnings) return warnings.error();
    for (std::string_view flag : splitSpaces(warnings->data))
        if (flag == "WR" || flag == "WH")
            return deviceError(DeviceFault::NotHomed, name(),
                               "homing ended but the axis still has no reference position (" +
                                   std::string(flag) + "): check the home sensor");
    std::lock_guard lock(state_mutex_);
    homed_ = true;
    return Ok{};
}

Status addZaberHeadBackend(HeadRegistry& registry) {
    auto open = [](const DeviceUri& uri) -> Result<std::unique_ptr<Head>> {
        auto options = ZaberHeadOptions::fromUri(uri);
        if (!options) return options.error();
        auto head = ZaberHead::open(*options);
        if (!head) return head.error().withContext("device uri '" + uri.text + "'");
        return std::unique_ptr<Head>(std::move(*head));
    };
    auto list = [] {
        std::vector<DeviceListing> heads;
        for (DeviceListing& port : listSerialPorts()) {
            if (port.backend != "zaber") continue;
            port.kind = "head";
            heads.push_back(std::move(port));
        }
        return heads;
    };
    return registry.addBackend("zaber", "Zaber rotation stages (ASCII protocol, serial)",
                               std::move(open), std::move(list));
}

}  // namespace flarelab::drivers
