// ============================================================================
//  flarelab drivers: SimHead, SimHeadOptions, SimHeadFaults, addSimHeadBackend
// ============================================================================
//
// A simulated panorama head for the simulated rig and the daemon's tests.
//
// Motion. A move of distance d runs a trapezoid velocity profile: it accelerates at
// acceleration_deg_s2 up to speed_deg_s, cruises, and brakes at the same rate (a triangle when d
// is too short to reach the speed; acceleration 0 means the speed is reached at once). Then the
// head settles for settle_s before moveTo returns. moveDuration_s gives the total.
//
// Reported and true angle. Like an open-loop stepper the head reports the angle it commanded,
// while the camera points where the gears put it (trueAngle_deg, what SimCamera renders):
//   - backlash: a dead band of backlash_deg between motor and camera. After a move up the camera
//     lags backlash_deg / 2 below the reported angle, after a move down as far above it, so the
//     two approach directions differ by backlash_deg;
//   - position noise: each move ends position_noise_deg (standard deviation, Gaussian, drawn
//     from `seed`) off.
// home() drives to the home switch, which sits at true angle 0: afterwards both angles are 0.
//
// Faults, injected at construction or with setFaults, for the daemon's tests:
//   - stall_at_deg: an obstacle; a move that would reach or cross it stops 0.001 deg short of
//     it: [stalled], the head stays homed and knows where it is;
//   - hang_moves: the next n moves or homings never arrive: they wait out their timeout and
//     answer [timeout], the head where it was;
//   - lose_position_in_moves: the n-th next move loses steps (it stops 30 % short of the target)
//     and notices: [lost-position], and the head is not homed until home();
//   - disconnected: every call answers [disconnected].
// A move whose profile takes longer than its timeout stops where the timeout finds it: [timeout].
//
// Time runs on a SimClock (sim_clock.h): fast mode does not sleep (a move is over when moveTo
// returns, so there is nothing for stop() to interrupt); real-time mode sleeps in slices, so
// stop() from another thread interrupts a move within a few milliseconds (the head stops at
// once, without braking).
#pragma once

#include <atomic>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <string>

#include "drivers/head.h"
#include "drivers/sim_clock.h"

namespace flarelab::drivers {

struct SimHeadFaults {
    std::optional<double> stall_at_deg;
    int hang_moves = 0;              // >= 0
    int lose_position_in_moves = 0;  // 0: never; 1: the next move
    bool disconnected = false;
};

struct SimHeadOptions {
    std::string serial = "SIMHEAD-0";
    double min_deg = -90.0;
    double max_deg = 90.0;
    double speed_deg_s = 20.0;  // in (0, max_speed_deg_s]
    double max_speed_deg_s = 90.0;
    double acceleration_deg_s2 = 100.0;  // >= 0; 0: no ramp
    double settle_s = 0.1;               // >= 0
    double backlash_deg = 0.0;           // >= 0
    double position_noise_deg = 0.0;     // >= 0, standard deviation per move
    uint64_t seed = 1;
    double start_deg = 0.0;  // true angle before homing, in [min_deg, max_deg]
    bool homed = false;      // true: starts homed at start_deg (tests that skip homing)
    SimHeadFaults faults;

    // InvalidArgument naming the first field out of range.
    Status validate() const;
};

class SimHead final : public Head {
public:
    // InvalidArgument for bad options. Without a clock the head gets its own fast one.
    static Result<std::unique_ptr<SimHead>> make(const SimHeadOptions& options,
                                                 std::shared_ptr<SimClock> clock = nullptr);
    // The options must be valid (checked).
    SimHead(const SimHeadOptions& options, std::shared_ptr<SimClock> clock);

    DeviceIdentity identity() const override;
    HeadLimits limits() const override;
    Status home(double timeout_s) override;
    Result<double> moveTo(double angle_deg, double timeout_s) override;
    Result<double> position() override;
    double speed_deg_s() const override;
    Status setSpeed(double speed_deg_s) override;
    Status stop() override;

    // Where the camera really points (deg), whether homed or not; during a move, now.
    double trueAngle_deg() const;
    bool homed() const;
    void setFaults(const SimHeadFaults& faults);
    const std::shared_ptr<SimClock>& clock() const { return clock_; }
    // Simulated seconds the last move or homing took, settling included.
    double lastMoveDuration_s() const;

    // Time of a trapezoid move over distance_deg >= 0, without settling.
    static double moveDuration_s(double distance_deg,
                                 double speed_deg_s,
                                 double acceleration_deg_s2);
    // Distance covered after t_s of such a move (distance_deg once it is over).
    static double moveDistance_deg(double t_s,
                                   double distance_deg,
                                   double speed_deg_s,
                                   double acceleration_deg_s2);

private:
    struct Motion {
        int64_t start_ns = 0;
        double from_deg = 0.0;      // reported angle at the start
        double distance_deg = 0.0;  // >= 0, along direction
        double direction = 1.0;
        double true_from_deg = 0.0;
        double speed_deg_s = 0.0;
    };
    // Reported and true angle `elapsed_s` into a motion.
    std::pair<double, double> along(const Motion& m, double elapsed_s) const;
    std::string name() const;
    Error disconnectedError() const;
    // Runs a motion to its end, an interruption, or the timeout (unlocks while waiting).
    // Returns the seconds it ran and whether it was interrupted by stop().
    struct Ran {
        double elapsed_s = 0.0;
        bool stopped = false;
        bool timed_out = false;
    };
    Ran run(std::unique_lock<std::mutex>& lock,
            const Motion& m,
            double duration_s,
            double timeout_s);

    SimHeadOptions options_;
    std::shared_ptr<SimClock> clock_;
    mutable std::mutex mutex_;
    double speed_deg_s_;
    double reported_deg_;
    double true_deg_;
    bool homed_;
    SimHeadFaults faults_;
    std::optional<Motion> moving_;
    std::atomic<bool> stop_requested_{false};
    double last_move_s_ = 0.0;
    std::mt19937_64 rng_;
};

// Adds the "sim" scheme to a head registry: "sim:" opens a SimHead with `defaults` on `clock`
// (a new fast clock per head when null). URI parameters override: speed_deg_s,
// acceleration_deg_s2, settle_s, backlash_deg, position_noise_deg, seed, and time=fast|real (a
// clock of its own in that mode). InvalidArgument naming the parameter when one is unknown or
// out of range.
Status addSimHeadBackend(HeadRegistry& registry,
                         const SimHeadOptions& defaults = {},
                         std::shared_ptr<SimClock> clock = nullptr);

}  // namespace flarelab::drivers
