#include "drivers/sim_clock.h"

#include <algorithm>
#include <thread>

#include "common/check.h"

namespace flarelab::drivers {

SimClock::SimClock(SimTime mode) : mode_(mode), start_(std::chrono::steady_clock::now()) {}

int64_t SimClock::now_ns() const {
    if (mode_ == SimTime::Fast) return simulated_ns_.load();
    return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() -
                                                                start_)
        .count();
}

bool SimClock::waitUntil(int64_t t_ns, const std::atomic<bool>* cancel) {
    if (mode_ == SimTime::Fast) {
        int64_t now = simulated_ns_.load();
        while (now < t_ns && !simulated_ns_.compare_exchange_weak(now, t_ns)) {
        }
        return true;
    }
    constexpr int64_t kSlice_ns = 5'000'000;
    for (;;) {
        if (cancel && cancel->load()) return false;
        const int64_t now = now_ns();
        if (now >= t_ns) return true;
        std::this_thread::sleep_for(std::chrono::nanoseconds(std::min(kSlice_ns, t_ns - now)));
    }
}

bool SimClock::wait(double duration_s, const std::atomic<bool>* cancel) {
    FLARELAB_CHECK_GE(duration_s, 0.0);
    return waitUntil(now_ns() + secondsToNs(duration_s), cancel);
}

}  // namespace flarelab::drivers
