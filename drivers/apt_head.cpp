#include "drivers/apt_head.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <thread>

#include "drivers/detail/stage_util.h"

namespace flarelab::drivers {
namespace {

using detail::fmt;
using detail::untagged;

// What the manual gives for each message this driver or its simulator sends or receives: its
// data length, or kHeaderOnly. Some controllers send MOVE_COMPLETED and MOVE_STOPPED as a bare
// header (channel in param1), others with the 14-byte status: both are accepted.
constexpr int kHeaderOnly = -1;
constexpr int kNone = -2;

struct Spec {
    uint16_t id;
    const char* name;
    int length;
    int other_length;
};

constexpr Spec kSpecs[] = {
    {apt::kHwDisconnect, "MGMSG_HW_DISCONNECT", kHeaderOnly, kNone},
    {apt::kHwReqInfo, "MGMSG_HW_REQ_INFO", kHeaderOnly, kNone},
    {apt::kHwGetInfo, "MGMSG_HW_GET_INFO", 84, kNone},
    {apt::kHwStartUpdateMsgs, "MGMSG_HW_START_UPDATEMSGS", kHeaderOnly, kNone},
    {apt::kHwStopUpdateMsgs, "MGMSG_HW_STOP_UPDATEMSGS", kHeaderOnly, kNone},
    {apt::kHwResponse, "MGMSG_HW_RESPONSE", kHeaderOnly, kNone},
    {apt::kHwRichResponse, "MGMSG_HW_RICHRESPONSE", 68, kNone},
    {apt::kModSetChanEnableState, "MGMSG_MOD_SET_CHANENABLESTATE", kHeaderOnly, kNone},
    {apt::kModReqChanEnableState, "MGMSG_MOD_REQ_CHANENABLESTATE", kHeaderOnly, kNone},
    {apt::kModGetChanEnableState, "MGMSG_MOD_GET_CHANENABLESTATE", kHeaderOnly, kNone},
    {apt::kModIdentify, "MGMSG_MOD_IDENTIFY", kHeaderOnly, kNone},
    {apt::kMotReqPosCounter, "MGMSG_MOT_REQ_POSCOUNTER", kHeaderOnly, kNone},
    {apt::kMotGetPosCounter, "MGMSG_MOT_GET_POSCOUNTER", 6, kNone},
    {apt::kMotSetVelParams, "MGMSG_MOT_SET_VELPARAMS", 14, kNone},
    {apt::kMotReqVelParams, "MGMSG_MOT_REQ_VELPARAMS", kHeaderOnly, kNone},
    {apt::kMotGetVelParams, "MGMSG_MOT_GET_VELPARAMS", 14, kNone},
    {apt::kMotReqStatusBits, "MGMSG_MOT_REQ_STATUSBITS", kHeaderOnly, kNone},
    {apt::kMotGetStatusBits, "MGMSG_MOT_GET_STATUSBITS", 6, kNone},
    {apt::kMotMoveHome, "MGMSG_MOT_MOVE_HOME", kHeaderOnly, kNone},
    {apt::kMotMoveHomed, "MGMSG_MOT_MOVE_HOMED", kHeaderOnly, kNone},
    {apt::kMotMoveAbsolute, "MGMSG_MOT_MOVE_ABSOLUTE", 6, kNone},
    {apt::kMotMoveCompleted, "MGMSG_MOT_MOVE_COMPLETED", 14, kHeaderOnly},
    {apt::kMotMoveStop, "MGMSG_MOT_MOVE_STOP", kHeaderOnly, kNone},
    {apt::kMotMoveStopped, "MGMSG_MOT_MOVE_STOPPED", 14, kHeaderOnly},
    {apt::kMotReqStatusUpdate, "MGMSG_MOT_REQ_STATUSUPDATE", kHeaderOnly, kNone},
    {apt::kMotGetStatusUpdate, "MGMSG_MOT_GET_STATUSUPDATE", 14, kNone},
    {apt::kMotReqDcStatusUpdate, "MGMSG_MOT_REQ_DCSTATUSUPDATE", kHeaderOnly, kNone},
    {apt::kMotGetDcStatusUpdate, "MGMSG_MOT_GET_DCSTATUSUPDATE", 14, kNone},
    {apt::kMotAckDcStatusUpdate, "MGMSG_MOT_ACK_DCSTATUSUPDATE", kHeaderOnly, kNone},
};

const Spec* specOf(uint16_t id) {
    for (const Spec& s : kSpecs)
        if (s.id == id) return &s;
    return nullptr;
}

bool accepts(const Spec& s, int length) { return s.length == length || s.other_length == length; }

// The addresses an APT unit can have: host, rack motherboard, bays 1-10, stand-alone USB unit.
bool validAddress(uint8_t a) {
    return a == apt::kHost || a == apt::kRack || (a >= 0x21 && a <= 0x2A) || a == apt::kGenericUsb;
}

uint16_t le16(std::span<const uint8_t> b, size_t at) {
    return static_cast<uint16_t>(b[at] | (b[at + 1] << 8));
}

uint32_t le32(std::span<const uint8_t> b, size_t at) {
    return static_cast<uint32_t>(b[at]) | (static_cast<uint32_t>(b[at + 1]) << 8) |
           (static_cast<uint32_t>(b[at + 2]) << 16) | (static_cast<uint32_t>(b[at + 3]) << 24);
}

void put16(std::vector<uint8_t>& out, uint16_t v) {
    out.push_back(static_cast<uint8_t>(v & 0xFF));
    out.push_back(static_cast<uint8_t>(v >> 8));
}

void put32(std::vector<uint8_t>& out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<uint8_t>((v >> (8 * i)) & 0xFF));
}

std::string hex2(unsigned v) {
    char text[8];
    std::snprintf(text, sizeof(text), "0x%02x", v & 0xFFu);
    return text;
}

// The channel a message names: param1 of header-only ones, the leading "chan ident" word of
// long ones; nullopt for messages that name none (HW_GET_INFO, the fault reports).
std::optional<int> channelOf(const AptMessage& m) {
    switch (m.id) {
        case apt::kModGetChanEnableState:
        case apt::kMotMoveHomed:
            return m.param1;
        case apt::kMotMoveCompleted:
        case apt::kMotMoveStopped:
            if (!m.has_data) return m.param1;
            return le16(m.data, 0);
        case apt::kMotGetPosCounter:
        case apt::kMotGetVelParams:
        case apt::kMotGetStatusBits:
        case apt::kMotGetStatusUpdate:
        case apt::kMotGetDcStatusUpdate:
            return le16(m.data, 0);
        default:
            return std::nullopt;
    }
}

bool isEvent(uint16_t id) {
    return id == apt::kMotMoveCompleted || id == apt::kMotMoveStopped || id == apt::kMotMoveHomed;
}

constexpr uint32_t kFaultBits = apt::kMotionError | apt::kOverTemperature | apt::kBusVoltageFault |
                                apt::kCommutationError | apt::kOverload | apt::kEncoderFault |
                                apt::kOverCurrent | apt::kCurrentFault;

}  // namespace

std::string aptMessageName(uint16_t id) {
    char hex[16];
    std::snprintf(hex, sizeof(hex), "0x%04x", static_cast<unsigned>(id));
    if (const Spec* s = specOf(id)) return std::string(s->name) + " (" + hex + ")";
    return std::string("unknown message ") + hex;
}

std::vector<uint8_t> encodeAptMessage(const AptMessage& m) {
    std::vector<uint8_t> out;
    out.reserve(6 + m.data.size());
    put16(out, m.id);
    if (m.has_data) {
        put16(out, static_cast<uint16_t>(m.data.size()));
        out.push_back(static_cast<uint8_t>(m.destination | apt::kDataFlag));
    } else {
        out.push_back(m.param1);
        out.push_back(m.param2);
        out.push_back(static_cast<uint8_t>(m.destination & 0x7F));
    }
    out.push_back(m.source);
    if (m.has_data) out.insert(out.end(), m.data.begin(), m.data.end());
    return out;
}

Result<AptMessage> parseAptMessage(std::span<const uint8_t> bytes) {
    const auto bad = [&](const std::string& why) -> Error {
        return makeError(ErrorCode::ParseError,
                         "apt message '" + quoteBytes(bytes, 48) + "': " + why);
    };
    if (bytes.size() < 6)
        return bad("needs the 6-byte header, has " + std::to_string(bytes.size()) + " bytes");
    AptMessage m;
    m.id = le16(bytes, 0);
    const Spec* spec = specOf(m.id);
    if (!spec) return bad(aptMessageName(m.id));
    m.has_data = (bytes[4] & apt::kDataFlag) != 0;
    m.destination = static_cast<uint8_t>(bytes[4] & 0x7F);
    m.source = bytes[5];
    if (!validAddress(m.destination))
        return bad("destination " + hex2(m.destination) + " is no APT address");
    if (!validAddress(m.source)) return bad("source " + hex2(m.source) + " is no APT address");
    if (m.has_data) {
        const size_t length = le16(bytes, 2);
        if (!accepts(*spec, static_cast<int>(length)))
            return bad(
                std::string(spec->name) + " with " + std::to_string(length) +
                " data bytes; the protocol gives " +
                (spec->length == kHeaderOnly ? std::string("none") : std::to_string(spec->length)));
        if (bytes.size() != 6 + length)
            return bad("the header announces " + std::to_string(length) + " data bytes, " +
                       std::to_string(bytes.size() - 6) + " follow");
        m.data.assign(bytes.begin() + 6, bytes.end());
    } else {
        if (!accepts(*spec, kHeaderOnly))
            return bad(std::string(spec->name) + " without its " + std::to_string(spec->length) +
                       " data bytes (data flag 0x80 not set)");
        if (bytes.size() != 6)
            return bad("a header-only message followed by " + std::to_string(bytes.size() - 6) +
                       " more bytes");
        m.param1 = bytes[2];
        m.param2 = bytes[3];
    }
    return m;
}

AptFraming findAptFrame(std::span<const uint8_t> stream) {
    using Kind = AptFraming::Kind;
    if (stream.size() < 2) return {Kind::NeedMore, 0};
    const Spec* spec = specOf(le16(stream, 0));
    if (!spec) return {Kind::Garbage, 1};
    if (stream.size() < 6) return {Kind::NeedMore, 0};
    const bool has_data = (stream[4] & apt::kDataFlag) != 0;
    if (!validAddress(static_cast<uint8_t>(stream[4] & 0x7F)) || !validAddress(stream[5]))
        return {Kind::Garbage, 1};
    size_t total = 6;
    if (has_data) {
        const int length = le16(stream, 2);
        if (!accepts(*spec, length) || length < 0) return {Kind::Garbage, 1};
        total += static_cast<size_t>(length);
    } else if (!accepts(*spec, kHeaderOnly)) {
        return {Kind::Garbage, 1};
    }
    if (stream.size() < total) return {Kind::NeedMore, 0};
    return {Kind::Message, total};
}

Result<AptStatus> decodeAptStatus(const AptMessage& m) {
    AptStatus status;
    if (!m.has_data) {
        status.channel = m.param1;
        status.full = false;
        return status;
    }
    if (m.data.size() != 14)
        return makeError(ErrorCode::ParseError, aptMessageName(m.id) +
                                                    ": a status needs 14 data "
                                                    "bytes, has " +
                                                    std::to_string(m.data.size()));
    status.channel = le16(m.data, 0);
    status.position = static_cast<int32_t>(le32(m.data, 2));
    status.status_bits = le32(m.data, 10);
    return status;
}

Result<AptHwInfo> decodeAptHwInfo(const AptMessage& m) {
    if (m.id != apt::kHwGetInfo || m.data.size() != 84)
        return makeError(ErrorCode::ParseError,
                         aptMessageName(m.id) + " is not a MGMSG_HW_GET_INFO with 84 data bytes");
    AptHwInfo info;
    info.serial = le32(m.data, 0);
    for (size_t i = 4; i < 12 && m.data[i] != 0; ++i) {
        const uint8_t c = m.data[i];
        if (c < 32 || c > 126)
            return makeError(ErrorCode::ParseError,
                             "MGMSG_HW_GET_INFO: the model name holds byte " + hex2(c));
        info.model += static_cast<char>(c);
    }
    info.type = le16(m.data, 12);
    // Firmware: minor, interim, major, unused.
    info.firmware = std::to_string(m.data[16]) + "." + std::to_string(m.data[15]) + "." +
                    std::to_string(m.data[14]);
    info.hardware_version = le16(m.data, 78);
    info.modification_state = le16(m.data, 80);
    info.channels = le16(m.data, 82);
    return info;
}

std::string describeAptStatusBits(uint32_t bits) {
    struct Named {
        uint32_t bit;
        const char* name;
    };
    constexpr Named kNames[] = {
        {apt::kForwardLimit, "forward limit switch"},
        {apt::kReverseLimit, "reverse limit switch"},
        {apt::kMovingForward, "moving forward"},
        {apt::kMovingReverse, "moving in reverse"},
        {apt::kJoggingForward, "jogging forward"},
        {apt::kJoggingReverse, "jogging in reverse"},
        {apt::kHoming, "homing"},
        {apt::kHomed, "homed"},
        {apt::kMotionError, "motion error (excessive position error)"},
        {apt::kOverTemperature, "over temperature"},
        {apt::kBusVoltageFault, "bus voltage fault"},
        {apt::kCommutationError, "commutation error"},
        {apt::kOverload, "motor overload or current limit"},
        {apt::kEncoderFault, "encoder fault"},
        {apt::kOverCurrent, "over current"},
        {apt::kCurrentFault, "current fault"},
        {apt::kEnabled, "enabled"},
    };
    std::string out;
    for (const Named& n : kNames)
        if (bits & n.bit) out += (out.empty() ? "" : ", ") + std::string(n.name);
    char hex[16];
    std::snprintf(hex, sizeof(hex), "0x%08x", static_cast<unsigned>(bits));
    return (out.empty() ? std::string("no bits set") : out) + " (" + hex + ")";
}

// ---------------------------------------------------------------------------------------------
// Options

Status AptHeadOptions::validate() const {
    const auto bad = [](const std::string& why) -> Error {
        return makeError(ErrorCode::InvalidArgument, "apt head options: " + why);
    };
    if (port.empty()) return bad("no serial port (e.g. apt:/dev/ttyUSB0)");
    if (channel < 1 || channel > 16) return bad("channel must lie in 1..16");
    if (!validAddress(address) || address == apt::kHost)
        return bad("address " + hex2(address) + " is no APT controller address");
    for (auto [key, value] :
         {std::pair<const char*, const std::optional<double>*>{"counts_per_deg", &counts_per_deg},
          {"vel_per_deg_s", &vel_per_deg_s},
          {"acc_per_deg_s2", &acc_per_deg_s2}})
        if (*value && !(std::isfinite(**value) && **value > 0.0))
            return bad(std::string(key) + " must be positive");
    if (!std::isfinite(min_deg) || !std::isfinite(max_deg) || !(min_deg < max_deg))
        return bad("min_deg < max_deg, both finite, is required");
    const double counts = counts_per_deg.value_or(kK10cr1CountsPerDeg);
    if (std::max(std::abs(min_deg), std::abs(max_deg)) * counts > 2.0e9)
        return bad("min_deg/max_deg reach beyond the controller's 32-bit position counter");
    if (!std::isfinite(max_speed_deg_s) || !(max_speed_deg_s > 0.0))
        return bad("max_speed_deg_s must be positive");
    if (!(reply_timeout_s > 0.0 && reply_timeout_s <= 60.0))
        return bad("reply_timeout_s must lie in (0, 60]");
    if (!(poll_s > 0.0 && poll_s <= 10.0)) return bad("poll_s must lie in (0, 10]");
    if (!(init_dwell_s >= 0.0 && init_dwell_s <= 1.0))
        return bad("init_dwell_s must lie in [0, 1]");
    return Ok{};
}

Result<AptHeadOptions> AptHeadOptions::fromUri(const DeviceUri& uri) {
    if (Status ok =
            uri.onlyParams({"channel", "baud", "address", "counts_per_deg", "vel_per_deg_s",
                            "acc_per_deg_s2", "min_deg", "max_deg", "max_speed_deg_s",
                            "reply_timeout_s", "poll_s", "init_dwell_s", "ignore_status_bits"});
        !ok)
        return ok.error();
    AptHeadOptions o;
    o.port = uri.path;
    if (o.port.empty())
        return makeError(ErrorCode::InvalidArgument,
                         "device uri '" + uri.text +
                             "': apt needs the serial port, e.g. apt:/dev/ttyUSB0?channel=1");
    auto channel = detail::uriWhole(uri, "channel", o.channel, 1, 16);
    if (!channel) return channel.error();
    o.channel = static_cast<int>(*channel);
    auto baud = detail::uriWhole(uri, "baud", o.baud, 1, 4000000);
    if (!baud) return baud.error();
    o.baud = static_cast<int>(*baud);
    auto address = detail::uriWhole(uri, "address", o.address, 1, 255);
    if (!address) return address.error();
    o.address = static_cast<uint8_t>(*address);
    auto ignore = detail::uriWhole(uri, "ignore_status_bits", 0, 0, 0xFFFFFFFFLL);
    if (!ignore) return ignore.error();
    o.ignore_status_bits = static_cast<uint32_t>(*ignore);
    for (auto [key, field] :
         {std::pair<const char*, std::optional<double>*>{"counts_per_deg", &o.counts_per_deg},
          {"vel_per_deg_s", &o.vel_per_deg_s},
          {"acc_per_deg_s2", &o.acc_per_deg_s2}}) {
        auto value = detail::uriOptional(uri, key);
        if (!value) return value.error();
        *field = *value;
    }
    for (auto [key, field] :
         {std::pair<const char*, double*>{"min_deg", &o.min_deg}, {"max_deg", &o.max_deg}}) {
        auto value = uri.number(key, *field);
        if (!value) return value.error();
        *field = *value;
    }
    for (auto [key, field] :
         {std::pair<const char*, double*>{"max_speed_deg_s", &o.max_speed_deg_s},
          {"reply_timeout_s", &o.reply_timeout_s},
          {"poll_s", &o.poll_s}}) {
        auto value = detail::uriPositive(uri, key, *field);
        if (!value) return value.error();
        *field = *value;
    }
    auto dwell = uri.number("init_dwell_s", o.init_dwell_s);
    if (!dwell) return dwell.error();
    o.init_dwell_s = *dwell;
    if (Status ok = o.validate(); !ok)
        return ok.error().withContext("device uri '" + uri.text + "'");
    return o;
}

// ---------------------------------------------------------------------------------------------
// The head

AptHead::AptHead(Key, AptHeadOptions options, std::unique_ptr<SerialPort> port)
    : options_(std::move(options)), port_(std::move(port)) {}

std::string AptHead::name() const {
    return "apt " + options_.port + " channel " + std::to_string(options_.channel);
}

Result<std::unique_ptr<AptHead>> AptHead::open(const AptHeadOptions& options) {
    if (Status ok = options.validate(); !ok) return ok.error();
    SerialOptions serial;
    serial.baud = options.baud;
    serial.flow = FlowControl::RtsCts;
    auto port = SerialPort::open(options.port, serial);
    if (!port) return port.error();
    auto head = std::make_unique<AptHead>(Key{}, options, std::move(*port));
    if (Status ok = head->initialise(); !ok) return ok.error();
    return head;
}

AptMessage AptHead::header(uint16_t id, uint8_t param1, uint8_t param2) const {
    AptMessage m;
    m.id = id;
    m.param1 = param1;
    m.param2 = param2;
    m.destination = options_.address;
    m.source = apt::kHost;
    return m;
}

AptMessage AptHead::withData(uint16_t id, std::vector<uint8_t> data) const {
    AptMessage m = header(id);
    m.has_data = true;
    m.data = std::move(data);
    return m;
}

Status AptHead::send(const AptMessage& message) {
    return port_->writeAll(encodeAptMessage(message), deadlineAfter(options_.reply_timeout_s));
}

Status AptHead::checkOrigin(const AptMessage& m) const {
    if (m.source != options_.address || m.destination != apt::kHost)
        return makeError(ErrorCode::IoError, aptMessageName(m.id) + " from address " +
                                                 hex2(m.source) + " to " + hex2(m.destination) +
                                                 ", not from " + hex2(options_.address) +
                                                 " to the host (0x01)");
    if (const auto channel = channelOf(m); channel && *channel != options_.channel)
        return makeError(ErrorCode::IoError, aptMessageName(m.id) + " for channel " +
                                                 std::to_string(*channel) + ", not " +
                                                 std::to_string(options_.channel));
    return Ok{};
}

Result<AptMessage> AptHead::await(uint16_t reply_id,
                                  SerialClock::time_point deadline,
                                  std::string& skipped,
                                  bool& retryable) {
    size_t garbage = 0;
    retryable = true;
    for (;;) {
        for (;;) {
            const AptFraming f = findAptFrame(rx_);
            if (f.kind == AptFraming::Kind::NeedMore) break;
            const auto end = rx_.begin() + static_cast<std::ptrdiff_t>(f.length);
            if (f.kind == AptFraming::Kind::Garbage) {
                garbage += f.length;
                rx_.erase(rx_.begin(), end);
                continue;
            }
            auto parsed = parseAptMessage(std::span<const uint8_t>(rx_.data(), f.length));
            rx_.erase(rx_.begin(), end);
            if (!parsed) return parsed.error();  // the framer and the parser disagree: a bug
            const AptMessage& m = *parsed;
            if (Status ok = checkOrigin(m); !ok) return ok.error();
            retryable = false;  // the controller's own fault reports are answers
            if (m.id == apt::kHwResponse)
                return makeError(ErrorCode::IoError,
                                 name() +
                                     ": the controller reports a fault (MGMSG_HW_RESPONSE); "
                                     "see its front panel or Thorlabs' Kinesis software");
            if (m.id == apt::kHwRichResponse) {
                const uint16_t about = le16(m.data, 0), code = le16(m.data, 2);
                std::string notes;
                for (size_t i = 4; i < m.data.size() && m.data[i] != 0; ++i)
                    notes += static_cast<char>(m.data[i]);
                return makeError(ErrorCode::IoError,
                                 name() + ": the controller reports fault code " +
                                     std::to_string(code) + " about " + aptMessageName(about) +
                                     ": '" + quoteBytes(notes) + "'");
            }
            retryable = true;
            if (isEvent(m.id)) {
                if (m.id == apt::kMotMoveHomed) {
                    events_.homed = true;
                } else {
                    auto status = decodeAptStatus(m);
                    if (!status) return status.error();
                    (m.id == apt::kMotMoveCompleted ? events_.completed : events_.stopped) =
                        *status;
                }
            }
            if (m.id == reply_id) return m;
            if (!isEvent(m.id)) skipped += (skipped.empty() ? "" : ", ") + aptMessageName(m.id);
        }
        std::array<uint8_t, 256> chunk{};
        auto n = port_->readSome(chunk, deadline);
        if (!n) {
            if (deviceFaultOf(n.error()) != DeviceFault::Timeout) {
                retryable = false;
                return n.error();
            }
            std::string detail = "no " + aptMessageName(reply_id);
            if (!rx_.empty())
                detail +=
                    "; a message cut short: '" + quoteBytes(std::span<const uint8_t>(rx_)) + "'";
            if (garbage > 0)
                detail += "; dropped " + std::to_string(garbage) + " bytes that frame no message";
            if (!skipped.empty()) detail += "; other messages: " + skipped;
            return deviceError(DeviceFault::Timeout, name(), detail);
        }
        rx_.insert(rx_.end(), chunk.begin(), chunk.begin() + static_cast<std::ptrdiff_t>(*n));
    }
}

Result<AptMessage> AptHead::request(const AptMessage& message, uint16_t reply_id) {
    std::lock_guard io(io_mutex_);
    std::vector<std::string> problems;
    bool last_timed_out = false;
    for (int attempt = 0; attempt < 2; ++attempt) {
        if (attempt > 0) {
            // Whatever half-message or stale answer is left would be read as this one's.
            rx_.clear();
            if (Status ok = port_->flushInput(); !ok) return ok.error();
        }
        if (Status ok = send(message); !ok) return ok.error();
        std::string skipped;
        bool retryable = false;
        auto reply = await(reply_id, deadlineAfter(options_.reply_timeout_s), skipped, retryable);
        if (reply) return reply;
        const Error& e = reply.error();
        if (!retryable) return e;
        last_timed_out = deviceFaultOf(e) == DeviceFault::Timeout;
        problems.push_back(untagged(e));
    }
    rx_.clear();
    (void)port_->flushInput();
    std::string detail;
    for (size_t i = 0; i < problems.size(); ++i) detail += (i ? "; then " : "") + problems[i];
    const std::string what = aptMessageName(message.id);
    if (last_timed_out)
        return deviceError(DeviceFault::Timeout, name(),
                           "no valid answer to " + what +
                               " within reply_timeout_s = " + fmt(options_.reply_timeout_s) +
                               ", twice: " + detail + " (powered? a Thorlabs APT controller at " +
                               std::to_string(options_.baud) + " baud?)");
    return makeError(ErrorCode::IoError, name() + ": bad answer to " + what + ", twice: " + detail);
}

Result<uint32_t> AptHead::statusBits() {
    auto reply = request(header(apt::kMotReqStatusBits, static_cast<uint8_t>(options_.channel)),
                         apt::kMotGetStatusBits);
    if (!reply) return reply.error();
    return le32(reply->data, 2) & ~options_.ignore_status_bits;
}

Result<int32_t> AptHead::positionCounts() {
    auto reply = request(header(apt::kMotReqPosCounter, static_cast<uint8_t>(options_.channel)),
                         apt::kMotGetPosCounter);
    if (!reply) return reply.error();
    return static_cast<int32_t>(le32(reply->data, 2));
}

Error AptHead::faultFromBits(uint32_t bits, const std::string& doing) {
    const std::string what = doing + ": " + describeAptStatusBits(bits);
    if (bits & apt::kEncoderFault) {
        std::lock_guard lock(state_mutex_);
        homed_ = false;
        return deviceError(DeviceFault::LostPosition, name(), what + "; home before moving again");
    }
    if (bits & (apt::kMotionError | apt::kOverload | apt::kOverCurrent | apt::kCurrentFault))
        return deviceError(DeviceFault::Stalled, name(), what);
    return makeError(ErrorCode::IoError,
                     name() + ": " + what + " (a controller fault: needs a person)");
}

Status AptHead::initialise() {
    // The manual's FTDI start-up: RTS down, pause, purge, pause, RTS up (no RTS on a pty).
    auto lowered = port_->setRts(false);
    if (!lowered) return lowered.error();
    std::this_thread::sleep_for(std::chrono::duration<double>(options_.init_dwell_s));
    if (Status ok = port_->flushInput(); !ok) return ok.error();
    std::this_thread::sleep_for(std::chrono::duration<double>(options_.init_dwell_s));
    auto raised = port_->setRts(true);
    if (!raised) return raised.error();
    rts_applied_ = *raised;

    if (Status ok = send(header(apt::kHwStopUpdateMsgs)); !ok) return ok.error();
    auto info_message = request(header(apt::kHwReqInfo), apt::kHwGetInfo);
    if (!info_message) return info_message.error();
    auto info = decodeAptHwInfo(*info_message);
    if (!info) return info.error().withContext(name());
    if (info->channels > 0 && options_.channel > info->channels)
        return makeError(ErrorCode::InvalidArgument, name() + ": the " + info->model + " has " +
                                                         std::to_string(info->channels) +
                                                         " channel(s); check channel=");
    const bool scaled =
        options_.counts_per_deg || options_.vel_per_deg_s || options_.acc_per_deg_s2;
    if (info->model != "K10CR1" &&
        !(options_.counts_per_deg && options_.vel_per_deg_s && options_.acc_per_deg_s2))
        return makeError(ErrorCode::InvalidArgument,
                         name() + ": the controller is a '" + quoteBytes(info->model) +
                             "', not a K10CR1, so the K10CR1's scale factors do not apply: give "
                             "counts_per_deg, vel_per_deg_s and acc_per_deg_s2 for its stage "
                             "(the APT protocol manual lists them per stage)" +
                             (scaled ? " (all three are needed)" : ""));
    counts_per_deg_ = options_.counts_per_deg.value_or(kK10cr1CountsPerDeg);
    vel_per_deg_s_ = options_.vel_per_deg_s.value_or(kK10cr1VelocityPerDegS);
    acc_per_deg_s2_ = options_.acc_per_deg_s2.value_or(kK10cr1AccelerationPerDegS2);
    identity_.backend = "apt";
    identity_.model = "Thorlabs " + info->model + " (firmware " + info->firmware + ")";
    identity_.serial = std::to_string(info->serial);
    identity_.uri = "apt:" + options_.port + "?channel=" + std::to_string(options_.channel);
    limits_ = HeadLimits{options_.min_deg, options_.max_deg, options_.max_speed_deg_s};

    const auto channel = static_cast<uint8_t>(options_.channel);
    if (Status ok = send(header(apt::kModSetChanEnableState, channel, 0x01)); !ok)
        return ok.error();
    auto enabled =
        request(header(apt::kModReqChanEnableState, channel), apt::kModGetChanEnableState);
    if (!enabled) return enabled.error();
    if (enabled->param2 != 0x01)
        return makeError(ErrorCode::IoError,
                         name() + ": the channel stays disabled (enable state " +
                             hex2(enabled->param2) + " after MGMSG_MOD_SET_CHANENABLESTATE)");

    auto velocity = request(header(apt::kMotReqVelParams, channel), apt::kMotGetVelParams);
    if (!velocity) return velocity.error();
    acceleration_ = static_cast<int32_t>(le32(velocity->data, 6));
    const auto max_velocity = static_cast<int32_t>(le32(velocity->data, 10));
    if (max_velocity <= 0)
        return makeError(ErrorCode::IoError, name() + ": maximum velocity " +
                                                 std::to_string(max_velocity) + " is not positive");
    {
        std::lock_guard lock(state_mutex_);
        speed_deg_s_ = max_velocity / vel_per_deg_s_;
    }
    if (speed_deg_s() > limits_.max_speed_deg_s)
        if (Status ok = setSpeed(limits_.max_speed_deg_s); !ok) return ok.error();

    auto bits = statusBits();
    if (!bits) return bits.error();
    std::lock_guard lock(state_mutex_);
    homed_ = (*bits & apt::kHomed) != 0;
    return Ok{};
}

DeviceIdentity AptHead::identity() const { return identity_; }

HeadLimits AptHead::limits() const { return limits_; }

int32_t AptHead::targetCounts(double angle_deg) const {
    return static_cast<int32_t>(std::llround(angle_deg * counts_per_deg_));
}

double AptHead::speed_deg_s() const {
    std::lock_guard lock(state_mutex_);
    return speed_deg_s_;
}

Status AptHead::setSpeed(double speed_deg_s) {
    if (!std::isfinite(speed_deg_s) || !(speed_deg_s > 0.0) ||
        speed_deg_s > limits_.max_speed_deg_s)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "speed_deg_s = " + fmt(speed_deg_s) + " outside (0, " +
                               fmt(limits_.max_speed_deg_s) + "]");
    const auto velocity = static_cast<int32_t>(std::llround(speed_deg_s * vel_per_deg_s_));
    if (velocity < 1)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "speed_deg_s = " + fmt(speed_deg_s) + " is below one velocity unit");
    std::vector<uint8_t> data;
    put16(data, static_cast<uint16_t>(options_.channel));
    put32(data, 0);  // minimum velocity: always 0, says the manual
    put32(data, static_cast<uint32_t>(acceleration_));
    put32(data, static_cast<uint32_t>(velocity));
    {
        std::lock_guard io(io_mutex_);
        if (Status ok = send(withData(apt::kMotSetVelParams, std::move(data))); !ok)
            return ok.error();
    }
    auto readback = request(header(apt::kMotReqVelParams, static_cast<uint8_t>(options_.channel)),
                            apt::kMotGetVelParams);
    if (!readback) return readback.error();
    const auto applied = static_cast<int32_t>(le32(readback->data, 10));
    if (applied != velocity)
        return makeError(ErrorCode::IoError, name() + ": asked for velocity " +
                                                 std::to_string(velocity) +
                                                 ", the controller "
                                                 "keeps " +
                                                 std::to_string(applied));
    std::lock_guard lock(state_mutex_);
    speed_deg_s_ = applied / vel_per_deg_s_;
    return Ok{};
}

Result<double> AptHead::position() {
    {
        std::lock_guard lock(state_mutex_);
        if (!homed_)
            return deviceError(DeviceFault::NotHomed, name(), "position unknown: home first");
    }
    auto counts = positionCounts();
    if (!counts) return counts.error();
    return *counts / counts_per_deg_;
}

bool AptHead::beginMotion() {
    // Under the state lock, so that a stop() either finds nothing moving or sets its flag after
    // this motion cleared it: never lost in between.
    std::lock_guard lock(state_mutex_);
    if (moving_) return false;
    moving_ = true;
    stop_requested_ = false;
    return true;
}

Status AptHead::stop() {
    {
        std::lock_guard lock(state_mutex_);
        if (!moving_) return Ok{};
        stop_requested_ = true;
        wake_.notify_all();
    }
    std::lock_guard io(io_mutex_);
    // A profiled stop (0x02): the motor brakes along its acceleration ramp.
    return send(header(apt::kMotMoveStop, static_cast<uint8_t>(options_.channel), 0x02));
}

Result<uint32_t> AptHead::waitMotion(Motion kind,
                                     int32_t target,
                                     SerialClock::time_point deadline,
                                     const std::string& doing) {
    const auto halt = [&] {
        std::lock_guard io(io_mutex_);
        (void)send(header(apt::kMotMoveStop, static_cast<uint8_t>(options_.channel), 0x02));
    };
    Events seen;
    int standing = 0;  // polls in a row that found the motor standing away from its target
    bool stop_seen = false;
    bool stop_repeated = false;
    for (;;) {
        auto bits = statusBits();
        if (!bits) {
            if (deviceFaultOf(bits.error()) != DeviceFault::Disconnected) halt();
            return bits.error();
        }
        {
            std::lock_guard io(io_mutex_);
            if (events_.completed) seen.completed = events_.completed;
            if (events_.stopped) seen.stopped = events_.stopped;
            seen.homed = seen.homed || events_.homed;
            events_ = Events{};
        }
        const uint32_t faults = (*bits | (seen.stopped ? seen.stopped->status_bits : 0)) &
                                kFaultBits & ~options_.ignore_status_bits;
        if (faults) {
            halt();
            return faultFromBits(*bits | faults, doing);
        }
        const bool moving = (*bits & apt::kMovingBits) != 0;
        if (moving && stop_requested_ && !stop_repeated) {
            // stop() may have reached the controller before the move did: say it again.
            stop_repeated = true;
            halt();
        }
        if (kind == Motion::Move) {
            // A completion that names another position is a late one of an earlier move.
            if (seen.completed && (!seen.completed->full || seen.completed->position == target))
                return *bits;
            if (!moving) {
                auto at = positionCounts();
                if (!at) return at.error();
                if (*at == target) return *bits;
                if (stop_requested_ || seen.stopped) return *bits;
                if (++standing >= 3)
                    return deviceError(DeviceFault::Stalled, name(),
                                       doing + ": the motor stands at " +
                                           fmt(*at / counts_per_deg_) +
                                           " deg without having announced the end of the move (" +
                                           describeAptStatusBits(*bits) + ")");
            } else {
                standing = 0;
            }
        } else {
            if (seen.homed || ((*bits & apt::kHomed) && !moving)) return *bits;
            if (!moving && (stop_requested_ || seen.stopped)) return *bits;
        }
        if (SerialClock::now() >= deadline) {
            halt();
            return deviceError(DeviceFault::Timeout, name(), doing + " did not finish in time");
        }
        std::unique_lock lock(state_mutex_);
        const auto next = std::min(deadline, deadlineAfter(options_.poll_s));
        wake_.wait_until(lock, next, [&] { return stop_requested_ && !stop_seen; });
        stop_seen = stop_requested_;
    }
}

Result<double> AptHead::moveTo(double angle_deg, double timeout_s) {
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
    const int32_t target = targetCounts(angle_deg);
    const std::string what =
        "move to " + fmt(angle_deg) + " deg (" + std::to_string(target) + " counts)";
    std::vector<uint8_t> data;
    put16(data, static_cast<uint16_t>(options_.channel));
    put32(data, static_cast<uint32_t>(target));
    {
        std::lock_guard io(io_mutex_);
        events_ = Events{};  // announcements of earlier moves are not this one's
        if (Status ok = send(withData(apt::kMotMoveAbsolute, std::move(data))); !ok)
            return ok.error();
    }
    auto bits = waitMotion(Motion::Move, target, deadline, what);
    if (!bits) return bits.error();
    auto at = positionCounts();
    if (!at) return at.error();
    const double at_deg = *at / counts_per_deg_;
    if (stop_requested_)
        return deviceError(DeviceFault::Stopped, name(),
                           what + " stopped at " + fmt(at_deg) + " deg");
    if (*at != target)
        return deviceError(DeviceFault::Stalled, name(),
                           what + " ended at " + fmt(at_deg) + " deg, " +
                               std::to_string(std::llabs(static_cast<long long>(target) - *at)) +
                               " counts short (" + describeAptStatusBits(*bits) + ")");
    return at_deg;
}

Status AptHead::home(double timeout_s) {
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
    {
        std::lock_guard io(io_mutex_);
        events_ = Events{};
        if (Status ok = send(header(apt::kMotMoveHome, static_cast<uint8_t>(options_.channel)));
            !ok)
            return ok.error();
    }
    auto bits = waitMotion(Motion::Home, 0, deadline, "homing");
    if (!bits) return bits.error();
    if (stop_requested_) return deviceError(DeviceFault::Stopped, name(), "homing stopped");
    auto check = statusBits();
    if (!check) return check.error();
    if (!(*check & apt::kHomed))
        return deviceError(DeviceFault::NotHomed, name(),
                           "homing ended but the controller does not report the channel homed (" +
                               describeAptStatusBits(*check) + ")");
    std::lock_guard lock(state_mutex_);
    homed_ = true;
    return Ok{};
}

Status addAptHeadBackend(HeadRegistry& registry) {
    auto open = [](const DeviceUri& uri) -> Result<std::unique_ptr<Head>> {
        auto options = AptHeadOptions::fromUri(uri);
        if (!options) return options.error();
        auto head = AptHead::open(*options);
        if (!head) return head.error().withContext("device uri '" + uri.text + "'");
        return std::unique_ptr<Head>(std::move(*head));
    };
    auto list = [] {
        std::vector<DeviceListing> heads;
        for (DeviceListing& port : listSerialPorts()) {
            if (port.backend != "apt") continue;
            port.kind = "head";
            heads.push_back(std::move(port));
        }
        return heads;
    };
    return registry.addBackend("apt", "Thorlabs rotation mounts (APT protocol, serial)",
                               std::move(open), std::move(list));
}

}  // namespace flarelab::drivers
