// ============================================================================
//  flarelab drivers: SimClock, SimTime
// ============================================================================
//
// The clock the simulated rig shares (SimHead, SimCamera), so that head moves and exposures add
// up on one time line and frame timestamps are consistent with the moves between them. In fast
// mode time is simulated: waiting only advances the clock, nothing sleeps, and a sweep of many
// minutes of rig time runs as fast as the renderer allows while still reporting the rig time it
// would have taken. In real-time mode the clock is the steady clock and waiting sleeps.
// Thread-safe.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>

namespace flarelab::drivers {

enum class SimTime { Fast, RealTime };

class SimClock {
public:
    explicit SimClock(SimTime mode = SimTime::Fast);

    SimTime mode() const { return mode_; }

    // Nanoseconds since the clock was made.
    int64_t now_ns() const;

    // Waits until now_ns() >= t_ns. Real time sleeps in slices of at most 5 ms and gives up when
    // `cancel` (if given) becomes true, returning false; fast mode moves the clock forward
    // (never back) and returns true.
    bool waitUntil(int64_t t_ns, const std::atomic<bool>* cancel = nullptr);

    // waitUntil(now + duration_s); duration_s >= 0.
    bool wait(double duration_s, const std::atomic<bool>* cancel = nullptr);

private:
    SimTime mode_;
    std::chrono::steady_clock::time_point start_;
    std::atomic<int64_t> simulated_ns_{0};
};

inline int64_t secondsToNs(double s) { return static_cast<int64_t>(s * 1e9 + 0.5); }

}  // namespace flarelab::drivers
