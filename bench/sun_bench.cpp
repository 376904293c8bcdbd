// sun_bench: the sun's position (predict/sun.h) on one core.
//
//   BM_SunPosition        one sunPosition: the whole SPA (about 200 periodic terms and 63
//                         nutation terms) at one instant.
//   BM_SunTimeline/<n>    sunTimeline over n seconds at 1 s steps (n + 1 positions): the geocentric
//                         part hourly and interpolated, the rotation, parallax and refraction at
//                         every step. 10800 is the broadcast case: 3 hours at 1 s.
//   BM_SunPositionLoop/<n> the same positions by n + 1 sunPosition calls, the baseline.
//
// Items are positions. The site and day are the SPA paper's example (Golden, Colorado).
#include <benchmark/benchmark.h>

#include <chrono>
#include <cstdint>

#include "predict/sun.h"

namespace flarelab::bench {
namespace {

using namespace flarelab::predict;
using std::chrono::seconds;

SunSite golden() {
    SunSite s;
    s.latitude_deg = 39.742476;
    s.longitude_deg = -105.1786;
    s.elevation_m = 1830.14;
    s.pressure_mbar = 820.0;
    s.temperature_c = 11.0;
    return s;
}

UtcInstant start() { return *parseIso8601("2003-10-17T09:00:00-07:00"); }

void BM_SunPosition(benchmark::State& state) {
    const SunSite site = golden();
    UtcInstant t = start();
    for (auto _ : state) {
        auto p = sunPosition(site, t);
        benchmark::DoNotOptimize(p);
        t += seconds{1};
    }
    state.SetItemsProcessed(state.iterations());
}
BENCHMARK(BM_SunPosition);

void BM_SunTimeline(benchmark::State& state) {
    const SunSite site = golden();
    const seconds span{state.range(0)};
    for (auto _ : state) {
        auto timeline = sunTimeline(site, start(), start() + span, seconds{1});
        benchmark::DoNotOptimize(timeline);
    }
    state.SetItemsProcessed(state.iterations() * (state.range(0) + 1));
}
BENCHMARK(BM_SunTimeline)->Arg(600)->Arg(10800)->Unit(benchmark::kMillisecond);

void BM_SunPositionLoop(benchmark::State& state) {
    const SunSite site = golden();
    for (auto _ : state) {
        for (int64_t i = 0; i <= state.range(0); ++i) {
            auto p = sunPosition(site, start() + seconds{i});
            benchmark::DoNotOptimize(p);
        }
    }
    state.SetItemsProcessed(state.iterations() * (state.range(0) + 1));
}
BENCHMARK(BM_SunPositionLoop)->Arg(10800)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace flarelab::bench

BENCHMARK_MAIN();
