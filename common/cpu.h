// ============================================================================
//  flarelab common: what the processor can do
// ============================================================================
//
// The SIMD kernels (the row tracer, the renderer's row loops, model playback) are built twice,
// for AVX2 and without, and pick one at run time: this is the one place that asks the processor.
#pragma once

namespace flarelab {

// True where the processor runs AVX2 (asked once). False on other architectures and compilers.
inline bool processorHasAvx2() {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    static const bool has = [] {
        __builtin_cpu_init();
        return __builtin_cpu_supports("avx2") != 0;
    }();
    return has;
#else
    return false;
#endif
}

}  // namespace flarelab
