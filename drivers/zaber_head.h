// ============================================================================
//  flarelab drivers: ZaberReply, ZaberCommand, ZaberHeadOptions, ZaberHead, addZaberHeadBackend
// ============================================================================
//
// Zaber rotation stages through Zaber's ASCII protocol (the "ASCII Protocol Manual", firmware 6.06
// and later), on a serial port (serial_port.h).
//
// The protocol. A command is one line: '/', device address, axis number, an optional message id
// (0-99), the command text, an optional checksum ":XX", and a newline:
//
//     /1 1 12 move abs 853333:75
//
// The device answers with a reply line:
//
//     @01 1 12 OK BUSY -- 0:E4
//      |  | |  |  |    |  `- data ("0" when there is nothing to say), then the optional checksum
//      |  | |  |  |    `---- the most urgent warning flag, "--" for none (FS stalled, WR no
//      |  | |  |  |          reference position, NI movement interrupted, ...)
//      |  | |  |  `--------- BUSY while the axis moves, IDLE otherwise
//      |  | |  `------------ OK, or RJ with the reason as data (BADDATA, BADCOMMAND, ...)
//      |  | `--------------- the command's message id, when it had one
//      |  `----------------- axis (0: the whole device)
//      `-------------------- device address, two digits
//
// besides info lines ('#', the rest of a long answer) and alerts ('!', spontaneous; off by
// default). The checksum is the two's complement of the byte sum of everything between the
// leading character and the ':' (so that the sum including it is 0 modulo 256), as two
// upper-case hex digits; devices add it to replies when their comm.checksum setting is 1.
//
// The head. Positions are the axis's own position in microsteps ("pos"), and angle_deg =
// pos / units_per_deg, so 0 deg is where home puts the axis. A move to angle_deg goes to
// round(angle_deg * units_per_deg), computed afresh from the requested angle: a sweep that asks
// for i * 0.2 deg lands on the same count at step i however many steps came before (no error
// accumulates from adding up steps that are not whole microsteps). A move is "move abs N",
// then the axis is polled with "get pos" (status and position in one reply) every poll_s until
// it reports IDLE, and the final reply is checked: its warning flag (FS -> [stalled], WR/WH ->
// [not-homed], WL/WM/FQ/FI/FA -> [lost-position], NI -> [stopped], driver faults -> errors), and
// the position against the target. Every reply is checked: device and axis, message id (a reply
// with an older id is a late answer to an earlier command and is skipped), checksum when
// present, reply flag, warning flag. A bad reply (garbled, bad checksum, wrong address) or no
// reply is retried once, since every command this driver sends can be repeated without harm
// (absolute moves, queries, stop). So an exchange takes at most 2 x reply_timeout_s, and home()
// and moveTo() return within their timeout_s plus a few reply_timeout_s (the poll under way, the
// stop).
//
// URI: zaber:/dev/ttyUSB0?device=1&axis=1&baud=115200&units_per_deg=4266.67 and, optional,
// min_deg, max_deg, max_speed_deg_s, checksum=0|1, message_ids=0|1, reply_timeout_s, poll_s.
//   - baud 115200: the factory default of Zaber devices speaking the ASCII protocol.
//   - units_per_deg: microsteps per degree. The default, 1 / 0.000234375 deg = 4266.67, is the
//     default microstep size Zaber gives for its X-RSW and T-RS rotary stages (200 full steps per
//     motor turn, 64 microsteps per step, a 120:1 worm gear), scaled by the resolution the axis
//     reports ("get resolution") over 64. Any other stage needs its own value from its product
//     page ("microstep size": units_per_deg = 1 / microstep size in degrees).
//   - min_deg / max_deg: default the axis's own limit.min and limit.max; given values must lie
//     inside them.
//   - max_speed_deg_s: default the speed the axis was set up with (its maxspeed at open), which
//     the lab chose as safe for its load; maxspeed is in (microsteps/s) x 1.6384.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>

#include "common/result.h"
#include "drivers/head.h"
#include "drivers/serial_port.h"

namespace flarelab::drivers {

// The default microsteps per degree (see the top of this file), at resolution
// kZaberDefaultResolution.
inline constexpr double kZaberDefaultUnitsPerDeg = 1.0 / 0.000234375;
inline constexpr int kZaberDefaultResolution = 64;
// maxspeed counts per microstep/s (the ASCII protocol's speed unit).
inline constexpr double kZaberSpeedUnitsPerStepPerS = 1.6384;

struct ZaberReply {
    enum class Kind { Reply, Info, Alert };
    Kind kind = Kind::Reply;
    int device = 0;                 // 1..99
    int axis = 0;                   // 0..99
    std::optional<int> message_id;  // 0..99
    bool rejected = false;          // RJ (replies only)
    bool busy = false;              // BUSY (replies and alerts)
    std::string warning = "--";     // "--" or two upper-case letters (replies and alerts)
    std::string data;               // may hold spaces; no checksum
    bool has_checksum = false;      // a checksum was present (and matched)
    bool continues = false;         // the data ends in '\': info lines follow
    bool operator==(const ZaberReply&) const = default;
};

// Parses one line as the device sends it (a trailing "\r" or "\r\n" is allowed). ParseError
// quoting the line and naming the field when it does not follow the format above, or when its
// checksum does not match.
Result<ZaberReply> parseZaberReply(std::string_view line);

struct ZaberCommand {
    int device = 0;  // 0: every device
    int axis = 0;    // 0: the device as a whole
    std::optional<int> message_id;
    std::string text;  // "move abs 100", "" for a bare status request
    bool had_checksum = false;
    bool operator==(const ZaberCommand&) const = default;
};

// Parses a command line as a device reads it (what the simulator serves). ParseError as above.
Result<ZaberCommand> parseZaberCommand(std::string_view line);

// The checksum of a message body (the text between the leading character and the ':').
uint8_t zaberChecksum(std::string_view body);
// "/1 1 12 move abs 100:XX\n"; no id when message_id is empty, no ":XX" unless with_checksum.
std::string formatZaberCommand(const ZaberCommand& command, bool with_checksum);
// The reply line for a reply (with "\r\n"), checksummed when reply.has_checksum.
std::string formatZaberReply(const ZaberReply& reply);

// What a warning flag means, in a few words ("stalled and stopped"); "unknown warning flag"
// for flags this driver does not know.
std::string zaberWarningMeaning(std::string_view flag);
// The flag's precedence (0 the most urgent, as the manual orders them); a reply shows the most
// urgent flag standing. Unknown flags rank after every known one.
int zaberWarningRank(std::string_view flag);

struct ZaberHeadOptions {
    std::string port;  // "/dev/ttyUSB0"
    int device = 1;    // 1..99
    int axis = 1;      // 1..9
    int baud = 115200;
    std::optional<double> units_per_deg;  // > 0; none: the default scaled by the resolution
    std::optional<double> min_deg;
    std::optional<double> max_deg;
    std::optional<double> max_speed_deg_s;
    bool checksums = true;         // send ":XX" with every command
    bool message_ids = true;       // send a message id with every command
    double reply_timeout_s = 0.5;  // (0, 60]: how long one reply may take
    double poll_s = 0.05;          // (0, 10]: the status poll interval during a move

    // The options of a "zaber:" URI; InvalidArgument naming the parameter.
    static Result<ZaberHeadOptions> fromUri(const DeviceUri& uri);
    Status validate() const;
};

class ZaberHead final : public Head {
public:
    // Opens the port, reads the axis's identity, resolution, limits, speed and whether it is
    // homed. Errors of the port (serial_port.h), a device that does not answer ([timeout]),
    // InvalidArgument for options that contradict the device (limits outside its own).
    static Result<std::unique_ptr<ZaberHead>> open(const ZaberHeadOptions& options);

    DeviceIdentity identity() const override;
    HeadLimits limits() const override;
    Status home(double timeout_s) override;
    Result<double> moveTo(double angle_deg, double timeout_s) override;
    Result<double> position() override;
    double speed_deg_s() const override;
    Status setSpeed(double speed_deg_s) override;
    Status stop() override;

    double unitsPerDeg() const { return units_per_deg_; }
    // The microstep count a move to angle_deg goes to: round(angle_deg * units_per_deg).
    int64_t targetSteps(double angle_deg) const;

    // For open() only (a passkey keeps the constructor out of reach).
    struct Key {
        explicit Key() = default;
    };
    ZaberHead(Key, ZaberHeadOptions options, std::unique_ptr<SerialPort> port);

private:
    // Sends one command to the axis (axis 0: the device) and returns its checked reply (right
    // address and id, valid checksum); retried once on a bad or missing reply.
    Result<ZaberReply> exchange(const std::string& text, bool device_scope = false);
    // exchange(), then an RJ becomes an error (BADDATA -> [out-of-range] when out_of_range).
    Result<ZaberReply> command(const std::string& text,
                               bool device_scope = false,
                               bool out_of_range_on_baddata = false);
    // The error a rejected reply stands for.
    Error rejection(const ZaberReply& reply,
                    const std::string& text,
                    bool out_of_range_on_baddata) const;
    Result<int64_t> readInteger(const std::string& setting, bool device_scope = false);
    // The fault a warning flag stands for, or nullopt for a harmless flag.
    std::optional<Error> warningError(const std::string& flag, const std::string& doing);
    // Polls until the axis is IDLE or the deadline; the last reply. Stops the axis on timeout.
    Result<ZaberReply> waitIdle(SerialClock::time_point deadline, const std::string& doing);
    Status initialise();
    std::string name() const;
    // Marks a move or homing as under way: false when one already is.
    bool beginMotion();

    const ZaberHeadOptions options_;
    std::mutex io_mutex_;  // the line: one exchange at a time
    std::unique_ptr<SerialPort> port_;
    int next_id_ = 0;

    DeviceIdentity identity_;
    double units_per_deg_ = kZaberDefaultUnitsPerDeg;
    HeadLimits limits_;

    mutable std::mutex state_mutex_;
    std::condition_variable wake_;  // stop() wakes a waiting move
    double speed_deg_s_ = 0.0;
    bool homed_ = false;
    std::atomic<bool> moving_{false};
    std::atomic<bool> stop_requested_{false};
};

// Adds the "zaber" scheme: opens a ZaberHead from its URI; lists the serial ports whose USB
// identity suggests a Zaber device (serial_port.h) as kind "head".
Status addZaberHeadBackend(HeadRegistry& registry);

}  // namespace flarelab::drivers
