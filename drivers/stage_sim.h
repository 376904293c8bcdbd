// ============================================================================
//  flarelab drivers: StageSim, StageSimFaults, ZaberSim, ZaberSimOptions, AptSim, AptSimOptions
// ============================================================================
//
// Simulated rotation stages on a pseudo-terminal, for testing the serial drivers (zaber_head.h,
// apt_head.h) through the real termios path and for trying the rig by hand (flarelab-stage-sim).
// Each simulator opens a pty pair, keeps the slave open (so the line never hangs up between
// clients) and serves the master from a thread: the driver opens slavePath() like any serial
// port. These imitate the protocols as the manuals describe them; they are not the devices, and
// passing against them says nothing about firmware quirks (docs/lab.md says how to test those).
//
// Motion takes time: a move runs a trapezoid profile (SimHead::moveDistance_deg, in device
// units) at the stage's speed and acceleration; a stop halts the axis at once (real stages
// brake along their ramp). Homing drives to count 0. Limits are enforced the way each protocol
// does it (Zaber: RJ BADDATA; APT: the head's own limits, the controller has none for a rotator).
//
// Faults (setFaults, or in the options): the counters apply to the next n replies to requests
// (not to the motion announcements of APT), and are used up in this order: dropped (no reply at
// all), wrong address, wrong message id, wrong channel, then bad checksum, truncated (the first
// half of the bytes, no line end), garbled (bytes replaced by non-ASCII or random ones). The
// rest: an obstacle at a position where moves stall; a reason to reject every move with (Zaber
// RJ); a warning flag to raise when the next move ends (Zaber); a controller fault report
// instead of the next move (APT HW_RICHRESPONSE); lost motion announcements (APT); unsolicited
// status messages (APT); and vanish_after_s, which closes the pty master that long after the
// next move starts, as when a USB cable is pulled mid-move.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <set>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "common/result.h"
#include "drivers/apt_head.h"
#include "drivers/zaber_head.h"

namespace flarelab::drivers {

struct StageSimFaults {
    int drop_replies = 0;
    int wrong_address_replies = 0;
    int wrong_id_replies = 0;
    int wrong_channel_replies = 0;  // APT
    int bad_checksum_replies = 0;   // Zaber
    int truncate_replies = 0;
    int garble_replies = 0;
    std::optional<int64_t> stall_at;       // device units
    std::string reject_moves;              // Zaber: the RJ reason ("DRIVERDISABLED"); "" accepts
    std::string flag_after_move;           // Zaber: raised when the next move ends ("WL", "FQ")
    std::optional<uint16_t> fault_code;    // APT: HW_RICHRESPONSE instead of the next move
    bool drop_announcements = false;       // APT: no MOVE_COMPLETED / MOVE_HOMED
    double unsolicited_status_s = 0.0;     // APT: send GET_STATUSUPDATE this often (0: never)
    std::optional<double> vanish_after_s;  // the next move: close the master this long after
};

class StageSim {
public:
    virtual ~StageSim();
    StageSim(const StageSim&) = delete;
    StageSim& operator=(const StageSim&) = delete;

    // The slave's path ("/dev/pts/7"), for the driver's URI.
    const std::string& slavePath() const { return slave_path_; }

    void setFaults(const StageSimFaults& faults);
    StageSimFaults faults() const;  // what is left of them
    // Closes the master now: the driver's next read or write sees the line hang up.
    void vanish();
    bool vanished() const;

    // The axis, in device units.
    int64_t position() const;
    bool moving() const;
    bool homed() const;
    // Requests (complete commands or messages) received so far.
    size_t requests() const;

protected:
    using Clock = std::chrono::steady_clock;
    struct Motion {
        int64_t from = 0;
        int64_t to = 0;
        double speed = 1.0;  // device units per second, > 0
        double accel = 0.0;  // device units per second squared; 0: none
        Clock::time_point start;
        bool homing = false;
        bool stalls = false;  // ends at an obstacle
    };

    explicit StageSim(uint64_t seed);
    // Opens the pty (raw mode); the subclass's start() calls it, then startThread().
    // A new pty pair, or `tty` (raw) when not empty; then slavePath() is empty.
    Status openLine(const std::string& tty);
    void startThread();
    // Subclasses' destructors call this first: the thread calls their virtual functions.
    void stopThread();

    // Called on the thread with mutex_ held.
    virtual void onBytes(std::span<const uint8_t> bytes, Clock::time_point now) = 0;
    virtual void onMotionEnd(const Motion& motion, Clock::time_point now) = 0;
    virtual void onTick(Clock::time_point now) { (void)now; }

    // With mutex_ held:
    void write(std::span<const uint8_t> bytes);
    void write(std::string_view text);
    int64_t positionAt(Clock::time_point now) const;
    // Starts a motion from where the axis is now; an obstacle on the way shortens it.
    void startMotion(int64_t to, double speed, double accel, bool homing, Clock::time_point now);
    // Stops at once; the motion that was running, if any.
    std::optional<Motion> halt(Clock::time_point now);
    // Takes one count from a fault counter: true when it was positive.
    static bool take(int& counter);
    void garble(std::vector<uint8_t>& bytes, bool non_ascii);

    mutable std::mutex mutex_;
    StageSimFaults faults_;
    std::optional<Motion> motion_;
    int64_t position_ = 0;
    bool homed_ = false;
    size_t requests_ = 0;
    std::mt19937_64 rng_;

private:
    void serve(std::stop_token stop);
    void closeMaster();

    std::string slave_path_;
    int master_ = -1;
    int slave_ = -1;
    bool vanished_ = false;
    std::optional<Clock::time_point> vanish_at_;
    std::jthread thread_;
};

struct ZaberSimOptions {
    int device = 1;  // 1..99
    int axes = 1;    // 1..9
    // A rotary stage at the driver's default 4266.67 microsteps/deg: +-180 deg.
    int64_t limit_min = -768000;
    int64_t limit_max = 768000;
    int resolution = 64;
    int64_t maxspeed = 209715;           // 30 deg/s, in (microsteps/s) x 1.6384
    int64_t max_maxspeed = 20 * 209715;  // set maxspeed above this: RJ BADDATA
    double accel_steps_s2 = 1.28e6;      // 300 deg/s^2
    bool homed = false;                  // false: WR until homed
    int64_t start_position = 0;
    bool checksums = true;  // comm.checksum: replies carry ":XX"
    int device_id = 50081;
    std::string serial = "SIM0001";
    std::string version = "7.38";
    uint64_t seed = 1;
    StageSimFaults faults;
    // Serve on this terminal instead of a new pty (the device side of a USB serial gadget,
    // /dev/ttyGS0, so that the driver reaches the simulator through the kernel's USB stack).
    std::string serve_tty;
};

class ZaberSim final : public StageSim {
public:
    static Result<std::unique_ptr<ZaberSim>> start(const ZaberSimOptions& options);
    ~ZaberSim() override;
    // The warning flags standing now, most urgent first.
    std::vector<std::string> flags() const;
    int64_t maxspeed() const;

    struct Key {
        explicit Key() = default;
    };
    ZaberSim(Key, const ZaberSimOptions& options);

private:
    void onBytes(std::span<const uint8_t> bytes, Clock::time_point now) override;
    void onMotionEnd(const Motion& motion, Clock::time_point now) override;
    void handle(std::string_view line, Clock::time_point now);
    void reply(ZaberReply reply);
    std::string topFlag() const;
    double speed() const;

    ZaberSimOptions options_;
    std::string line_;
    std::set<std::string> flags_;  // besides WR, which stands while not homed
    int64_t maxspeed_;
    bool checksums_;
};

struct AptSimOptions {
    uint8_t address = apt::kGenericUsb;
    int channels = 1;
    std::string model = "K10CR1";  // at most 8 characters
    uint32_t serial = 55000001;
    double counts_per_deg = kK10cr1CountsPerDeg;
    double vel_per_deg_s = kK10cr1VelocityPerDegS;
    double acc_per_deg_s2 = kK10cr1AccelerationPerDegS2;
    double speed_deg_s = 10.0;   // the velocity parameters at power-up
    double accel_deg_s2 = 10.0;  // > 0
    bool homed = false;
    int32_t start_position = 0;
    std::string serve_tty;  // as ZaberSimOptions::serve_tty
    bool enabled = true;    // the channel at power-up
    uint64_t seed = 1;
    StageSimFaults faults;
};

class AptSim final : public StageSim {
public:
    static Result<std::unique_ptr<AptSim>> start(const AptSimOptions& options);
    ~AptSim() override;
    uint32_t statusBits() const;
    bool enabled() const;
    // The velocity parameters' maximum velocity, in APT units.
    int32_t maxVelocity() const;

    struct Key {
        explicit Key() = default;
    };
    AptSim(Key, const AptSimOptions& options);

private:
    void onBytes(std::span<const uint8_t> bytes, Clock::time_point now) override;
    void onMotionEnd(const Motion& motion, Clock::time_point now) override;
    void onTick(Clock::time_point now) override;
    void handle(const AptMessage& message, Clock::time_point now);
    // A reply to a request, with the reply faults applied.
    void reply(AptMessage message);
    // A motion announcement (MOVE_COMPLETED, MOVE_HOMED, MOVE_STOPPED): no reply faults.
    void announce(const AptMessage& message);
    AptMessage status(uint16_t id, Clock::time_point now) const;
    AptMessage header(uint16_t id, uint8_t param1 = 0, uint8_t param2 = 0) const;
    uint32_t bitsAt(Clock::time_point now) const;
    double countsPerS() const;
    double countsPerS2() const;

    AptSimOptions options_;
    std::vector<uint8_t> rx_;
    bool enabled_;
    int32_t min_velocity_ = 0;
    int32_t acceleration_;
    int32_t max_velocity_;
    uint32_t error_bits_ = 0;  // set by a stall until the next move
    Clock::time_point last_unsolicited_;
};

}  // namespace flarelab::drivers
