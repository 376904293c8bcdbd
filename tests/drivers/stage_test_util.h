// Helpers of the serial stage tests (zaber_head_test, apt_head_test).
#pragma once

#include <chrono>
#include <functional>
#include <string>
#include <thread>

#include "common/result.h"
#include "drivers/device.h"

namespace flarelab::drivers::stage_testing {

// Polls `ready` until it holds or timeout_s passed; whether it held. Tests wait on conditions
// with this, never on a fixed sleep.
inline bool waitUntil(const std::function<bool()>& ready, double timeout_s) {
    const auto deadline = std::chrono::steady_clock::now() +
                          std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                              std::chrono::duration<double>(timeout_s));
    while (!ready()) {
        if (std::chrono::steady_clock::now() >= deadline) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return true;
}

// The fault an outcome carries, for EXPECT_EQ; nullopt for success or an untagged error.
template <typename T>
std::optional<DeviceFault> faultOf(const Result<T>& result) {
    if (result) return std::nullopt;
    return deviceFaultOf(result.error());
}

template <typename T>
std::string messageOf(const Result<T>& result) {
    return result ? std::string("(success)") : result.error().message;
}

}  // namespace flarelab::drivers::stage_testing
