// Instants written the way the predict tests write them.
#pragma once

#include <chrono>
#include <cstdint>

#include "predict/utc_time.h"

namespace flarelab::predict::test_times {

// The instant y-m-d hh:mm:ss.us UTC.
inline UtcInstant at(int y, unsigned m, unsigned d, int hh, int mm, int ss, int64_t us = 0) {
    using namespace std::chrono;
    return sys_days{year{y} / month{m} / day{d}} + hours{hh} + minutes{mm} + seconds{ss} +
           microseconds{us};
}

}  // namespace flarelab::predict::test_times
