// ============================================================================
//  flarelab drivers: AptMessage, AptFraming, AptStatus, AptHwInfo, AptHeadOptions, AptHead,
//                    addAptHeadBackend
// ============================================================================
//
// Thorlabs motion controllers through the APT binary protocol (Thorlabs, "APT Controllers
// Host-Controller Communications Protocol"; the Kinesis controllers speak the same), aimed at the
// K10CR1 motorised rotation mount: a stepper controller behind an FTDI USB serial chip.
//
// The protocol. Every message starts with a 6-byte header, little-endian:
//
//     bytes 0-1  message id                        (0x0453 MGMSG_MOT_MOVE_ABSOLUTE, ...)
//     bytes 2-3  param1, param2                    (a header-only message)
//             or the length of the data that follows (when the destination has bit 0x80 set)
//     byte  4    destination | 0x80 when data follows
//     byte  5    source
//
// Addresses: 0x01 the host, 0x11 a rack's motherboard, 0x21.. its bays, 0x50 a stand-alone USB
// unit such as the K10CR1. The channel is param1 of a header-only message or the first data word
// ("chan ident") of a long one. There is no checksum; a message is checked by its id (known),
// its length (the one the manual gives for that id), its addresses and its channel. The stream
// is framed by those same rules: findAptFrame resynchronises after garbage by dropping bytes
// until a known id with plausible addresses and length starts the buffer.
//
// The head. A move is MOT_MOVE_ABSOLUTE to round(angle_deg * counts_per_deg), computed afresh
// from the requested angle (a sweep of i * 0.2 deg lands on the same count at step i whatever came
// before). The controller answers MOT_MOVE_COMPLETED when it arrives; meanwhile the driver polls
// MOT_REQ_STATUSBITS every poll_s: an error bit (motion error, overload, over-temperature, bus
// voltage, encoder fault) stops the motor and fails the move ([stalled] or [lost-position]), and a
// status that shows the motor standing at the target ends the move even when MOVE_COMPLETED was
// lost. MGMSG_HW_RESPONSE and MGMSG_HW_RICHRESPONSE (the controller reporting a fault) fail
// whatever is under way with the controller's code and text. Homing is MOT_MOVE_HOME, finished by
// MOT_MOVE_HOMED or the "homed" status bit; stop() sends MOT_MOVE_STOP (profiled), answered by
// MOT_MOVE_STOPPED. A request without a valid answer is sent once more (every request this driver
// makes can be repeated without harm), so it takes at most 2 x reply_timeout_s, and home() and
// moveTo() return within their timeout_s plus a few reply_timeout_s (the poll under way, the
// stop).
//
// Opening follows the manual's initialisation of the FTDI chip, transposed to termios: 115200
// baud, 8N1, RTS/CTS flow control; RTS lowered, 50 ms, purge, 50 ms, RTS raised. A pty has no RTS
// (ENOTTY): that step is then skipped. Then MGMSG_HW_STOP_UPDATEMSGS (no unsolicited status
// stream), MGMSG_HW_REQ_INFO (model, serial, firmware, channels),
// MGMSG_MOD_SET_CHANENABLESTATE (enable the channel; checked with REQ), MOT_REQ_VELPARAMS and
// MOT_REQ_STATUSBITS (homed or not).
//
// URI: apt:/dev/ttyUSB0?channel=1 and, optional, counts_per_deg, vel_per_deg_s, acc_per_deg_s2,
// min_deg, max_deg, max_speed_deg_s, address, baud, reply_timeout_s, poll_s, init_dwell_s,
// ignore_status_bits.
//   - counts_per_deg 409600/3 = 136533.33 (the manual's K10CR1 figure: 200 full steps per motor
//     turn x 2048 microsteps x 120:1 worm gear / 360), vel_per_deg_s 7329109 and acc_per_deg_s2
//     1502 (the manual's K10CR1 velocity and acceleration scale factors); a controller that does
//     not identify as a K10CR1 must be given all three.
//   - min_deg, max_deg -180, 180: the mount turns endlessly, but one turn either way from home
//     reaches every direction without winding the camera's cables.
//   - max_speed_deg_s 10: the K10CR1's specified top speed.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/result.h"
#include "drivers/head.h"
#include "drivers/serial_port.h"

namespace flarelab::drivers {

// Message ids and addresses of the APT protocol used here.
namespace apt {
inline constexpr uint16_t kHwDisconnect = 0x0002;
inline constexpr uint16_t kHwReqInfo = 0x0005;
inline constexpr uint16_t kHwGetInfo = 0x0006;
inline constexpr uint16_t kHwStartUpdateMsgs = 0x0011;
inline constexpr uint16_t kHwStopUpdateMsgs = 0x0012;
inline constexpr uint16_t kHwResponse = 0x0080;
inline constexpr uint16_t kHwRichResponse = 0x0081;
inline constexpr uint16_t kModSetChanEnableState = 0x0210;
inline constexpr uint16_t kModReqChanEnableState = 0x0211;
inline constexpr uint16_t kModGetChanEnableState = 0x0212;
inline constexpr uint16_t kModIdentify = 0x0223;
inline constexpr uint16_t kMotReqPosCounter = 0x0411;
inline constexpr uint16_t kMotGetPosCounter = 0x0412;
inline constexpr uint16_t kMotSetVelParams = 0x0413;
inline constexpr uint16_t kMotReqVelParams = 0x0414;
inline constexpr uint16_t kMotGetVelParams = 0x0415;
inline constexpr uint16_t kMotReqStatusBits = 0x0429;
inline constexpr uint16_t kMotGetStatusBits = 0x042A;
inline constexpr uint16_t kMotMoveHome = 0x0443;
inline constexpr uint16_t kMotMoveHomed = 0x0444;
inline constexpr uint16_t kMotMoveAbsolute = 0x0453;
inline constexpr uint16_t kMotMoveCompleted = 0x0464;
inline constexpr uint16_t kMotMoveStop = 0x0465;
inline constexpr uint16_t kMotMoveStopped = 0x0466;
inline constexpr uint16_t kMotReqStatusUpdate = 0x0480;
inline constexpr uint16_t kMotGetStatusUpdate = 0x0481;
inline constexpr uint16_t kMotReqDcStatusUpdate = 0x0490;
inline constexpr uint16_t kMotGetDcStatusUpdate = 0x0491;
inline constexpr uint16_t kMotAckDcStatusUpdate = 0x0492;

inline constexpr uint8_t kHost = 0x01;
inline constexpr uint8_t kRack = 0x11;
inline constexpr uint8_t kGenericUsb = 0x50;
inline constexpr uint8_t kDataFlag = 0x80;

// Status bits (MOT_GET_STATUSBITS, and the status word of MOVE_COMPLETED and status updates).
inline constexpr uint32_t kForwardLimit = 0x00000001;
inline constexpr uint32_t kReverseLimit = 0x00000002;
inline constexpr uint32_t kMovingForward = 0x00000010;
inline constexpr uint32_t kMovingReverse = 0x00000020;
inline constexpr uint32_t kJoggingForward = 0x00000040;
inline constexpr uint32_t kJoggingReverse = 0x00000080;
inline constexpr uint32_t kHoming = 0x00000200;
inline constexpr uint32_t kHomed = 0x00000400;
inline constexpr uint32_t kMotionError = 0x00004000;  // excessive position error
inline constexpr uint32_t kOverTemperature = 0x00020000;
inline constexpr uint32_t kBusVoltageFault = 0x00040000;
inline constexpr uint32_t kCommutationError = 0x00080000;
inline constexpr uint32_t kOverload = 0x01000000;  // motor overload or current limit
inline constexpr uint32_t kEncoderFault = 0x02000000;
inline constexpr uint32_t kOverCurrent = 0x04000000;
inline constexpr uint32_t kCurrentFault = 0x08000000;
inline constexpr uint32_t kEnabled = 0x80000000;
inline constexpr uint32_t kMovingBits =
    kMovingForward | kMovingReverse | kJoggingForward | kJoggingReverse | kHoming;
}  // namespace apt

struct AptMessage {
    uint16_t id = 0;
    uint8_t param1 = 0;       // header-only messages
    uint8_t param2 = 0;       // header-only messages
    uint8_t destination = 0;  // without the data flag
    uint8_t source = 0;
    bool has_data = false;
    std::vector<uint8_t> data;
    bool operator==(const AptMessage&) const = default;
};

// The bytes of a message (the data flag and length are set from has_data and data).
std::vector<uint8_t> encodeAptMessage(const AptMessage& message);

// "MGMSG_MOT_MOVE_COMPLETED (0x0464)", or "unknown message 0x1234".
std::string aptMessageName(uint16_t id);

// Parses exactly one message: ParseError naming what is wrong (too short, unknown id, data flag
// or length not the ones the manual gives for the id, bytes left over, an address that no APT
// unit has).
Result<AptMessage> parseAptMessage(std::span<const uint8_t> bytes);

// Where the next message ends in a byte stream. Message: the first `length` bytes are one
// (parseAptMessage accepts them). Garbage: the first `length` bytes cannot start a message (drop
// them and call again). NeedMore: the buffer starts a message that has not fully arrived.
struct AptFraming {
    enum class Kind { NeedMore, Message, Garbage };
    Kind kind = Kind::NeedMore;
    size_t length = 0;
};
AptFraming findAptFrame(std::span<const uint8_t> stream);

// The 14-byte status of MOVE_COMPLETED, MOVE_STOPPED and the status updates: channel, position
// (counts), a word this driver does not use (encoder count, or velocity and reserved), status bits.
// A header-only MOVE_COMPLETED or MOVE_STOPPED (older controllers) carries the channel alone.
struct AptStatus {
    int channel = 0;
    int32_t position = 0;
    uint32_t status_bits = 0;
    bool full = true;  // false: channel only
};
Result<AptStatus> decodeAptStatus(const AptMessage& message);

// MGMSG_HW_GET_INFO.
struct AptHwInfo {
    uint32_t serial = 0;
    std::string model;  // "K10CR1"
    uint16_t type = 0;
    std::string firmware;  // "major.interim.minor"
    uint16_t hardware_version = 0;
    uint16_t modification_state = 0;
    uint16_t channels = 0;
};
Result<AptHwInfo> decodeAptHwInfo(const AptMessage& message);

// The set status bits in words ("moving forward, homed, enabled").
std::string describeAptStatusBits(uint32_t bits);

// The K10CR1's scale factors from the protocol manual (see the top of this file).
inline constexpr double kK10cr1CountsPerDeg = 409600.0 / 3.0;
inline constexpr double kK10cr1VelocityPerDegS = 7329109.0;
inline constexpr double kK10cr1AccelerationPerDegS2 = 1502.0;

struct AptHeadOptions {
    std::string port;  // "/dev/ttyUSB0"
    int channel = 1;   // 1..16
    int baud = 115200;
    uint8_t address = apt::kGenericUsb;
    // None: the K10CR1's factors, accepted only from a controller that identifies as a K10CR1.
    std::optional<double> counts_per_deg;
    std::optional<double> vel_per_deg_s;
    std::optional<double> acc_per_deg_s2;
    double min_deg = -180.0;
    double max_deg = 180.0;
    double max_speed_deg_s = 10.0;
    double reply_timeout_s = 0.5;  // (0, 60]
    double poll_s = 0.05;          // (0, 10]
    double init_dwell_s = 0.05;    // [0, 1]: the two pauses of the FTDI initialisation
    // Status bits not to read as faults: an escape hatch for a controller that sets one of the
    // error bits in normal running (never seen here: no controller has been tried).
    uint32_t ignore_status_bits = 0;

    // The options of an "apt:" URI; InvalidArgument naming the parameter.
    static Result<AptHeadOptions> fromUri(const DeviceUri& uri);
    Status validate() const;
};

class AptHead final : public Head {
public:
    // Opens the port, runs the initialisation above and reads identity, speed and homed state.
    // Errors of the port (serial_port.h), [timeout] when the controller does not answer,
    // InvalidArgument when it is not a K10CR1 and the URI gives no scale factors, or has no such
    // channel.
    static Result<std::unique_ptr<AptHead>> open(const AptHeadOptions& options);

    DeviceIdentity identity() const override;
    HeadLimits limits() const override;
    Status home(double timeout_s) override;
    Result<double> moveTo(double angle_deg, double timeout_s) override;
    Result<double> position() override;
    double speed_deg_s() const override;
    Status setSpeed(double speed_deg_s) override;
    Status stop() override;

    double countsPerDeg() const { return counts_per_deg_; }
    // The count a move to angle_deg goes to: round(angle_deg * counts_per_deg).
    int32_t targetCounts(double angle_deg) const;
    // True when opening could raise RTS (false on a pseudo-terminal).
    bool rtsApplied() const { return rts_applied_; }

    // For open() only (a passkey keeps the constructor out of reach).
    struct Key {
        explicit Key() = default;
    };
    AptHead(Key, AptHeadOptions options, std::unique_ptr<SerialPort> port);

private:
    // What the controller announced while we waited for something else.
    struct Events {
        std::optional<AptStatus> completed;
        std::optional<AptStatus> stopped;
        bool homed = false;
        std::optional<Error> fault;  // HW_RESPONSE, HW_RICHRESPONSE
    };
    Status send(const AptMessage& message);
    // Sends `request` and waits for a message `reply_id` from our controller on our channel;
    // retried once when nothing valid came.
    Result<AptMessage> request(const AptMessage& request, uint16_t reply_id);
    // Reads and checks messages until one with reply_id arrives or the deadline; everything else
    // is recorded in events_ or skipped (noted in `skipped`). On failure `retryable` says whether
    // asking again may help (nothing valid came) or not (a fault report, a port that is gone).
    Result<AptMessage> await(uint16_t reply_id,
                             SerialClock::time_point deadline,
                             std::string& skipped,
                             bool& retryable);
    Status checkOrigin(const AptMessage& message) const;
    AptMessage header(uint16_t id, uint8_t param1 = 0, uint8_t param2 = 0) const;
    AptMessage withData(uint16_t id, std::vector<uint8_t> data) const;
    Result<uint32_t> statusBits();
    Result<int32_t> positionCounts();
    // Polls until `finished` says so, a fault, stop(), or the deadline (then the motor is
    // stopped); returns the last status bits.
    enum class Motion { Move, Home };
    Result<uint32_t> waitMotion(Motion kind,
                                int32_t target,
                                SerialClock::time_point deadline,
                                const std::string& doing);
    Error faultFromBits(uint32_t bits, const std::string& doing);
    Status initialise();
    std::string name() const;
    // Marks a move or homing as under way: false when one already is.
    bool beginMotion();

    const AptHeadOptions options_;
    std::mutex io_mutex_;
    std::unique_ptr<SerialPort> port_;
    std::vector<uint8_t> rx_;  // received bytes not yet framed
    Events events_;

    DeviceIdentity identity_;
    double counts_per_deg_ = kK10cr1CountsPerDeg;
    double vel_per_deg_s_ = kK10cr1VelocityPerDegS;
    double acc_per_deg_s2_ = kK10cr1AccelerationPerDegS2;
    HeadLimits limits_;
    int32_t acceleration_ = 0;  // the controller's, kept when the speed changes
    bool rts_applied_ = false;

    mutable std::mutex state_mutex_;
    std::condition_variable wake_;
    double speed_deg_s_ = 0.0;
    bool homed_ = false;
    std::atomic<bool> moving_{false};
    std::atomic<bool> stop_requested_{false};
};

// Adds the "apt" scheme: opens an AptHead from its URI; lists the serial ports whose USB identity
// suggests a Thorlabs controller (serial_port.h) as kind "head".
Status addAptHeadBackend(HeadRegistry& registry);

}  // namespace flarelab::drivers
