#include "hdr/merge.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <numeric>
#include <sstream>
#include <utility>

#include "common/check.h"

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace flarelab::hdr {
namespace {

// Quantization noise of a converter, in DN^2: a uniform error of one step.
constexpr double kQuantizationVarianceDn2 = 1.0 / 12.0;
// Caps on the variance terms of one bracket (see BracketPlan): far beyond any real sensor, they
// keep every variance below 1e34 and so every weight a normal float.
constexpr double kMaxShotCoefficient = 1e20;
constexpr double kMaxFloorVariance = 1e30;
// A dark sample bounds its pixel's signal from above by its threshold plus this many read-noise
// sigmas (the reading is noisy: a dim pixel's sample may fall under the threshold).
constexpr double kDarkCeilingSigmas = 4.0;
// Floors that keep divisions finite where a select would break vectorization: sum_rel is 0 or at
// least 1 / kMaxExposureRatio, a sum of weights 0 or at least 1 / (1e20 * 6.6e13 + 1e30).
constexpr float kMinRel = 1e-12f;
constexpr float kMinWeight = 1e-36f;
// Samples one thread handles in one go; the per-sample sums of a run stay in L1.
constexpr int64_t kRun = 1024;

std::string describe(double v) {
    std::ostringstream s;
    s.precision(17);
    s << v;
    return s.str();
}

Error bracketError(size_t index, const std::string& what) {
    return makeError(ErrorCode::InvalidArgument,
                     "mergeBrackets: bracket " + std::to_string(index) + ": " + what);
}

Error optionError(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "mergeBrackets: MergeOptions::" + what);
}

const char* formatName(RawFormat format) {
    switch (format) {
        case RawFormat::Mono:
            return "Mono";
        case RawFormat::BayerRGGB:
            return "BayerRGGB";
        case RawFormat::BayerBGGR:
            return "BayerBGGR";
        case RawFormat::BayerGRBG:
            return "BayerGRBG";
        case RawFormat::BayerGBRG:
            return "BayerGBRG";
    }
    return "unknown";
}

Status checkOptions(const MergeOptions& o) {
    if (!(o.saturation_margin_fraction >= 0.0 && o.saturation_margin_fraction < 1.0))
        return optionError("saturation_margin_fraction is " +
                           describe(o.saturation_margin_fraction) + " (must lie in [0, 1))");
    if (!(std::isfinite(o.min_signal_dn) && o.min_signal_dn >= 0.0))
        return optionError("min_signal_dn is " + describe(o.min_signal_dn) +
                           " (must be finite and >= 0)");
    if (!(std::isfinite(o.fallback_electrons_per_dn) && o.fallback_electrons_per_dn > 0.0))
        return optionError("fallback_electrons_per_dn is " + describe(o.fallback_electrons_per_dn) +
                           " (must be finite and > 0)");
    if (!(std::isfinite(o.fallback_read_noise_dn) && o.fallback_read_noise_dn > 0.0))
        return optionError("fallback_read_noise_dn is " + describe(o.fallback_read_noise_dn) +
                           " (must be finite and > 0)");
    if (!(std::isfinite(o.max_angle_spread_deg) && o.max_angle_spread_deg >= 0.0))
        return optionError("max_angle_spread_deg is " + describe(o.max_angle_spread_deg) +
                           " (must be finite and >= 0)");
    return Ok{};
}

// Everything about one bracket on its own (the fields that must agree between brackets are
// compared in mergeBrackets).
Status checkBracket(const RawFrame& f, size_t i) {
    if (f.width < 1 || f.height < 1)
        return bracketError(i, "width x height is " + std::to_string(f.width) + " x " +
                                   std::to_string(f.height) + " (both must be >= 1)");
    if (f.width > std::numeric_limits<int64_t>::max() / f.height ||
        f.width * f.height > static_cast<int64_t>(std::vector<uint16_t>().max_size()))
        return bracketError(i, "width x height " + std::to_string(f.width) + " x " +
                                   std::to_string(f.height) + " is too large");
    if (static_cast<int64_t>(f.samples.size()) != f.width * f.height)
        return bracketError(i, "samples.size() is " + std::to_string(f.samples.size()) +
                                   ", width * height is " + std::to_string(f.width * f.height));
    if (f.bit_depth < 8 || f.bit_depth > 16)
        return bracketError(i,
                            "bit_depth is " + std::to_string(f.bit_depth) + " (must lie in 8..16)");
    if (!(std::isfinite(f.exposure_s) && f.exposure_s > 0.0))
        return bracketError(
            i, "exposure_s is " + describe(f.exposure_s) + " (must be finite and > 0)");
    if (!(std::isfinite(f.gain) && f.gain > 0.0))
        return bracketError(i, "gain is " + describe(f.gain) + " (must be finite and > 0)");
    if (!(std::isfinite(f.black_level_dn) && f.black_level_dn >= 0.0))
        return bracketError(
            i, "black_level_dn is " + describe(f.black_level_dn) + " (must be finite and >= 0)");
    const double max_dn = std::ldexp(1.0, f.bit_depth) - 1.0;
    if (!(std::isfinite(f.white_level_dn) && f.white_level_dn <= max_dn))
        return bracketError(i, "white_level_dn is " + describe(f.white_level_dn) +
                                   " (must be at most 2^bit_depth - 1 = " + describe(max_dn) + ")");
    if (!(f.black_level_dn < f.white_level_dn))
        return bracketError(i, "black_level_dn " + describe(f.black_level_dn) +
                                   " is not below white_level_dn " + describe(f.white_level_dn));
    if (!(std::isfinite(f.read_noise_dn) && f.read_noise_dn >= 0.0))
        return bracketError(i, "read_noise_dn is " + describe(f.read_noise_dn) +
                                   " (must be finite and >= 0; 0: not known)");
    if (!(std::isfinite(f.electrons_per_dn) && f.electrons_per_dn >= 0.0))
        return bracketError(i, "electrons_per_dn is " + describe(f.electrons_per_dn) +
                                   " (must be finite and >= 0; 0: not known)");
    if (!std::isfinite(f.angle_deg))
        return bracketError(i, "angle_deg is " + describe(f.angle_deg) + " (must be finite)");
    if (!std::isfinite(f.exposure_s * f.gain))
        return bracketError(i, "exposure_s * gain overflows");
    return Ok{};
}

// Strict weak order of the brackets: by exposure_s * gain, then by every other field the merge
// reads, then by the samples, so that equal keys mean interchangeable brackets and the sums
// below run in the same order whatever order the caller passed.
bool bracketBefore(const RawFrame& a, const RawFrame& b) {
    const auto key = [](const RawFrame& f) {
        return std::array<double, 6>{f.exposure_s * f.gain, f.exposure_s,     f.gain,
                                     f.black_level_dn,      f.white_level_dn, f.read_noise_dn};
    };
    const auto ka = key(a), kb = key(b);
    if (ka != kb) return ka < kb;
    if (a.electrons_per_dn != b.electrons_per_dn) return a.electrons_per_dn < b.electrons_per_dn;
    return a.samples < b.samples;
}

// One bracket, reduced to what the per-sample loops need, in units of the reference bracket (the
// one with the largest exposure_s * gain, T_ref): its signal s = DN - black estimates
// y = radiance * T_ref as s / rel, with rel = exposure_s * gain / T_ref in (0, 1]. The variance
// of that estimate, for a pixel whose y is y0, is
//     var = (y0 * rel / e + r^2 + 1/12) / rel^2 = shot * y0 + floor
// (Granados et al. 2010, eq. 9, in DN of this bracket divided by rel^2).
struct BracketPlan {
    const uint16_t* samples = nullptr;
    float black_dn = 0.0f;
    float saturated_dn = 0.0f;  // DN >= this: saturated (an integer: DN are integers)
    float usable_dn = 0.0f;     // DN >= this and not saturated: usable (an integer)
    float rel = 1.0f;
    float inv_rel = 1.0f;
    float shot = 0.0f;   // 1 / (e * rel)
    float floor = 0.0f;  // (r^2 + 1/12) / rel^2
    // The most signal (reference units) a dark sample of this bracket leaves room for: its
    // threshold plus kDarkCeilingSigmas of its read noise, / rel.
    float dark_ceiling = 0.0f;
};

// The integer thresholds of a bracket: {usable from, saturated from}. DN are integers: DN >= x
// holds exactly when DN >= ceil(x), and DN - black < min_signal exactly when DN < ceil(black +
// min_signal), so both thresholds are exact in float.
std::pair<double, double> thresholdsDn(const RawFrame& f, const MergeOptions& o) {
    const double saturated = std::ceil(
        f.white_level_dn - o.saturation_margin_fraction * (f.white_level_dn - f.black_level_dn));
    return {std::min(std::ceil(f.black_level_dn + o.min_signal_dn), saturated), saturated};
}

BracketPlan planBracket(const RawFrame& f,
                        double reference_exposure,
                        const MergeOptions& o,
                        bool* used_fallback) {
    BracketPlan p;
    p.samples = f.samples.data();
    p.black_dn = static_cast<float>(f.black_level_dn);
    const auto [usable, saturated] = thresholdsDn(f, o);
    p.saturated_dn = static_cast<float>(saturated);
    p.usable_dn = static_cast<float>(usable);
    const double rel = f.exposure_s * f.gain / reference_exposure;
    p.rel = static_cast<float>(rel);
    p.inv_rel = static_cast<float>(1.0 / rel);
    double electrons_per_dn = f.electrons_per_dn;
    if (electrons_per_dn == 0.0) {
        electrons_per_dn = o.fallback_electrons_per_dn / f.gain;
        *used_fallback = true;
    }
    double read_noise_dn = f.read_noise_dn;
    if (read_noise_dn == 0.0) {
        read_noise_dn = o.fallback_read_noise_dn;
        *used_fallback = true;
    }
    p.dark_ceiling = static_cast<float>(std::min(
        (usable - f.black_level_dn +
         kDarkCeilingSigmas * std::sqrt(read_noise_dn * read_noise_dn + kQuantizationVarianceDn2)) /
            rel,
        static_cast<double>(std::numeric_limits<float>::max())));
    p.shot = static_cast<float>(std::min(1.0 / (electrons_per_dn * rel), kMaxShotCoefficient));
    p.floor = static_cast<float>(
        std::min((read_noise_dn * read_noise_dn + kQuantizationVarianceDn2) / (rel * rel),
                 kMaxFloorVariance));
    return p;
}

// The per-sample loops work on L samples at a time in GCC's vector extensions (also understood by
// Clang): L = 4 is one SSE register, the x86-64 baseline; L = 8 one AVX2 register, chosen at run
// time where the processor has AVX2. Both do the same IEEE operations in the same order, so they
// give the same bits.
template <int L>
struct Lanes {
    typedef float F __attribute__((vector_size(4 * L)));
    typedef int32_t I __attribute__((vector_size(4 * L)));
    typedef uint16_t Dn __attribute__((vector_size(2 * L)));
    typedef uint8_t Count __attribute__((vector_size(L)));
};
static_assert(kRun % 8 == 0);
static_assert(std::endian::native == std::endian::little);

// The helpers pass vectors by value; they are always inlined, so no vector crosses a call and
// the ABI note GCC gives for 32-byte vectors without AVX does not apply. (GCC reports it at the
// end of the file, so it stays off to the end.)
#pragma GCC diagnostic ignored "-Wpsabi"

template <int L>
[[gnu::always_inline]] inline typename Lanes<L>::F splat(float v) {
    return typename Lanes<L>::F{} + v;
}

// `v` where `mask` is set (all ones), else 0.
template <int L>
[[gnu::always_inline]] inline typename Lanes<L>::F masked(typename Lanes<L>::F v,
                                                          typename Lanes<L>::I mask) {
    using F = typename Lanes<L>::F;
    using I = typename Lanes<L>::I;
    return reinterpret_cast<F>(reinterpret_cast<I>(v) & mask);
}

// Samples [0, valid) of `src` as floats, valid in 1..L; missing lanes read 0.
template <int L>
[[gnu::always_inline]] inline typename Lanes<L>::F loadDn(const uint16_t* src, int64_t valid) {
    using F = typename Lanes<L>::F;
    using I = typename Lanes<L>::I;
    if constexpr (L == 4) {
        // SSE2 has no zero-extending conversion: the four samples go through one scalar (a
        // vector filled by a partial copy would stall on store forwarding) and are widened by
        // interleaving them with zeros, exact for unsigned values on a little-endian machine.
        typedef uint16_t Wide __attribute__((vector_size(16)));
        typedef uint64_t Halves __attribute__((vector_size(16)));
        uint64_t bits = 0;
        std::memcpy(&bits, src, static_cast<size_t>(valid) * sizeof(uint16_t));
        const Wide v = reinterpret_cast<Wide>(Halves{bits, 0});
        const Wide widened = __builtin_shufflevector(v, Wide{}, 0, 8, 1, 9, 2, 10, 3, 11);
        return __builtin_convertvector(reinterpret_cast<I>(widened), F);
    } else {
        typename Lanes<L>::Dn v;
        if (valid == L) {
            std::memcpy(&v, src, sizeof(v));
        } else {
            uint16_t padded[L] = {};
            std::memcpy(padded, src, static_cast<size_t>(valid) * sizeof(uint16_t));
            std::memcpy(&v, padded, sizeof(v));
        }
        return __builtin_convertvector(__builtin_convertvector(v, I), F);
    }
}

// Samples of a run without a usable bracket, by kind (MergedFrame::saturated_samples and
// dark_samples).
struct RunCounts {
    int64_t saturated = 0;
    int64_t dark = 0;
};

// Merges samples [begin, end) (end - begin <= kRun) of every bracket. Two passes over the
// brackets: the first sums the usable signals for the pilot estimate and keeps the lower bound
// of saturated samples, the second weights each usable sample by the inverse of its variance at
// the pilot estimate. Masks instead of branches, L samples at a time.
template <int L>
[[gnu::always_inline]] inline RunCounts mergeRunLanes(const std::vector<BracketPlan>& plans,
                                                      int64_t begin,
                                                      int64_t end,
                                                      float inv_reference_exposure,
                                                      float* radiance,
                                                      uint8_t* count) {
    using F = typename Lanes<L>::F;
    using I = typename Lanes<L>::I;
    const int64_t n = end - begin;
    FLARELAB_DCHECK(n > 0 && n <= kRun);
    const int64_t vectors = (n + L - 1) / L;
    const auto validIn = [n](int64_t v) { return std::min<int64_t>(L, n - v * L); };
    F sum_signal[kRun / L], sum_rel[kRun / L], bound[kRun / L], sum_w[kRun / L], sum_wy[kRun / L];
    F ceiling[kRun / L];  // the least signal a dark sample allows (reference units)
    I used[kRun / L];
    const F no_ceiling = splat<L>(std::numeric_limits<float>::max());
    for (int64_t v = 0; v < vectors; ++v) {
        sum_signal[v] = sum_rel[v] = bound[v] = sum_w[v] = sum_wy[v] = F{};
        ceiling[v] = no_ceiling;
        used[v] = I{};
    }
    // Pass 1: pilot sums and the saturation bound.
    for (const BracketPlan& p : plans) {
        const uint16_t* src = p.samples + begin;
        const F black = splat<L>(p.black_dn), saturated = splat<L>(p.saturated_dn);
        const F usable = splat<L>(p.usable_dn), rel = splat<L>(p.rel);
        const F inv_rel = splat<L>(p.inv_rel), dark_ceiling = splat<L>(p.dark_ceiling);
        for (int64_t v = 0; v < vectors; ++v) {
            const F dn = loadDn<L>(src + v * L, validIn(v));
            const F signal = dn - black;
            const I is_saturated = dn >= saturated;
            const I is_usable = (dn >= usable) & ~is_saturated;
            sum_signal[v] += masked<L>(signal, is_usable);
            sum_rel[v] += masked<L>(rel, is_usable);
            used[v] -= is_usable;  // masks are -1
            const F lower = masked<L>(signal * inv_rel, is_saturated);
            bound[v] = bound[v] < lower ? lower : bound[v];
            // A dark sample says the signal is under its threshold in this bracket (give or take
            // its read noise).
            const I is_dark = dn < usable;
            const F upper = is_dark ? dark_ceiling : no_ceiling;
            ceiling[v] = upper < ceiling[v] ? upper : ceiling[v];
        }
    }
    // The pilot: shot-noise-optimal (total signal over total exposure), >= 0.
    F pilot[kRun / L];
    const F min_rel = splat<L>(kMinRel);
    for (int64_t v = 0; v < vectors; ++v) {
        pilot[v] = sum_signal[v] / (sum_rel[v] > min_rel ? sum_rel[v] : min_rel);
        pilot[v] = pilot[v] < ceiling[v] ? pilot[v] : ceiling[v];
    }
    // Pass 2: inverse-variance weights at the pilot.
    for (const BracketPlan& p : plans) {
        const uint16_t* src = p.samples + begin;
        const F black = splat<L>(p.black_dn), saturated = splat<L>(p.saturated_dn);
        const F usable = splat<L>(p.usable_dn), inv_rel = splat<L>(p.inv_rel);
        const F shot = splat<L>(p.shot), floor = splat<L>(p.floor), one = splat<L>(1.0f);
        for (int64_t v = 0; v < vectors; ++v) {
            const F dn = loadDn<L>(src + v * L, validIn(v));
            const I is_usable = (dn >= usable) & (dn < saturated);
            const F w = masked<L>(one / (shot * pilot[v] + floor), is_usable);
            sum_w[v] += w;
            sum_wy[v] += w * ((dn - black) * inv_rel);
        }
    }
    const F min_weight = splat<L>(kMinWeight), scale = splat<L>(inv_reference_exposure);
    I saturated_lanes = I{}, dark_lanes = I{};
    RunCounts counts;
    for (int64_t v = 0; v < vectors; ++v) {
        // Without a usable sample sum_wy and the mean are 0, and the bound (or 0) stands.
        const I none = used[v] == 0;
        F mean = sum_wy[v] / (sum_w[v] > min_weight ? sum_w[v] : min_weight);
        // Usable samples of short brackets whose read noise claims more than a dark longer
        // bracket allows are held to what that bracket allows (the pixel's signal is under it).
        mean = mean < ceiling[v] ? mean : ceiling[v];
        const F y = (mean + masked<L>(bound[v], none)) * scale;
        const I positive = y > F{};
        const typename Lanes<L>::Count c =
            __builtin_convertvector(used[v], typename Lanes<L>::Count);
        const int64_t valid = validIn(v);
        if (valid == L) {
            saturated_lanes -= none & positive;
            dark_lanes -= none & ~positive;
        } else {
            for (int64_t lane = 0; lane < valid; ++lane) {
                counts.saturated += none[lane] & positive[lane] & 1;
                counts.dark += none[lane] & ~positive[lane] & 1;
            }
        }
        std::memcpy(radiance + begin + v * L, &y, static_cast<size_t>(valid) * sizeof(float));
        std::memcpy(count + begin + v * L, &c, static_cast<size_t>(valid));
    }
    for (int lane = 0; lane < L; ++lane) {
        counts.saturated += saturated_lanes[lane];
        counts.dark += dark_lanes[lane];
    }
    return counts;
}

using MergeRunFunction =
    RunCounts (*)(const std::vector<BracketPlan>&, int64_t, int64_t, float, float*, uint8_t*);

RunCounts mergeRunSse2(const std::vector<BracketPlan>& plans,
                       int64_t begin,
                       int64_t end,
                       float inv_reference_exposure,
                       float* radiance,
                       uint8_t* count) {
    return mergeRunLanes<4>(plans, begin, end, inv_reference_exposure, radiance, count);
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
[[gnu::target("avx2")]] RunCounts mergeRunAvx2(const std::vector<BracketPlan>& plans,
                                               int64_t begin,
                                               int64_t end,
                                               float inv_reference_exposure,
                                               float* radiance,
                                               uint8_t* count) {
    return mergeRunLanes<8>(plans, begin, end, inv_reference_exposure, radiance, count);
}
#endif

// The widest kernel this processor runs (the baseline unless `allow_avx2`).
MergeRunFunction mergeRunKernel(bool allow_avx2) {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    static const bool has_avx2 = [] {
        __builtin_cpu_init();  // in case this runs before libgcc's own initializer
        return __builtin_cpu_supports("avx2") != 0;
    }();
    if (allow_avx2 && has_avx2) return &mergeRunAvx2;
#else
    (void)allow_avx2;
#endif
    return &mergeRunSse2;
}

// Sizes a fresh output vector to `n` value-initialized elements. A frame's output is some hundred
// megabytes, and faulting it in page by page on one thread (as the zeroing of resize would) costs
// about as much as the merge: on Linux the pages are first faulted in by the kernel from every
// core (MADV_POPULATE_WRITE, Linux 5.14; only a request, and where it fails the zeroing faults
// the pages in as usual).
template <typename T>
void resizeOutput(std::vector<T>& v, size_t n) {
    v.reserve(n);
#if defined(__linux__) && defined(MADV_POPULATE_WRITE)
    constexpr uintptr_t kPage = 4096;
    static constexpr uintptr_t kChunk = uintptr_t{4} << 20;
    const uintptr_t first = reinterpret_cast<uintptr_t>(v.data());
    const uintptr_t begin = (first + kPage - 1) & ~(kPage - 1);
    const uintptr_t end = (first + n * sizeof(T)) & ~(kPage - 1);
    if (end > begin + kChunk)
        tbb::parallel_for(begin, end, kChunk, [end](uintptr_t chunk) {
            (void)madvise(reinterpret_cast<void*>(chunk), std::min(kChunk, end - chunk),
                          MADV_POPULATE_WRITE);
        });
#endif
    v.resize(n);
}

std::string methodText(size_t brackets, const MergeOptions& o, bool used_fallback) {
    std::ostringstream s;
    s << "flarelab inverse-variance merge (Granados et al. 2010), " << brackets
      << " bracket(s), saturation margin " << o.saturation_margin_fraction << ", min signal "
      << o.min_signal_dn << " DN, noise: "
      << (used_fallback ? "fallback model (" + describe(o.fallback_electrons_per_dn) +
                              " e-/DN at unity gain, " + describe(o.fallback_read_noise_dn) +
                              " DN read noise) where the camera gave none"
                        : std::string("camera figures"));
    return s.str();
}

// Which colour (0 red, 1 green, 2 blue) the sample at (x, y) holds.
int bayerColour(RawFormat format, int64_t x, int64_t y) {
    // The 2x2 pattern, row-major from its top-left sample.
    static constexpr int kRGGB[4] = {0, 1, 1, 2};
    static constexpr int kBGGR[4] = {2, 1, 1, 0};
    static constexpr int kGRBG[4] = {1, 0, 2, 1};
    static constexpr int kGBRG[4] = {1, 2, 0, 1};
    const int cell = static_cast<int>((y & 1) * 2 + (x & 1));
    switch (format) {
        case RawFormat::BayerRGGB:
            return kRGGB[cell];
        case RawFormat::BayerBGGR:
            return kBGGR[cell];
        case RawFormat::BayerGRBG:
            return kGRBG[cell];
        case RawFormat::BayerGBRG:
            return kGBRG[cell];
        case RawFormat::Mono:
            break;
    }
    FLARELAB_CHECK(false);  // Mono has no mosaic
    return 1;
}

// The samples the bilinear demosaic averages into pixel (x, y) of a w x h mosaic: its own sample
// for its own colour, and for each other colour the samples of that colour in its 3 x 3
// neighbourhood (cut off at the border, never mirrored). Calls visit(xx, yy, colour) for each, in
// row-major order.
template <typename Visit>
void forDemosaicSamples(
    RawFormat format, int64_t w, int64_t h, int64_t x, int64_t y, Visit&& visit) {
    const int own = bayerColour(format, x, y);
    for (int64_t dy = -1; dy <= 1; ++dy)
        for (int64_t dx = -1; dx <= 1; ++dx) {
            const int64_t xx = x + dx, yy = y + dy;
            if (xx < 0 || xx >= w || yy < 0 || yy >= h) continue;
            const int c = bayerColour(format, xx, yy);
            if (c == own && (dx != 0 || dy != 0)) continue;
            visit(xx, yy, c);
        }
}

}  // namespace

Result<MergedFrame> mergeBrackets(std::span<const RawFrame> brackets, const MergeOptions& options) {
    if (auto ok = checkOptions(options); !ok) return ok.error();
    if (brackets.empty())
        return makeError(ErrorCode::InvalidArgument, "mergeBrackets: no brackets");
    if (brackets.size() > static_cast<size_t>(kMaxBrackets))
        return makeError(ErrorCode::InvalidArgument,
                         "mergeBrackets: " + std::to_string(brackets.size()) +
                             " brackets (at most " + std::to_string(kMaxBrackets) + ")");
    for (size_t i = 0; i < brackets.size(); ++i)
        if (auto ok = checkBracket(brackets[i], i); !ok) return ok.error();
    const RawFrame& first = brackets[0];
    for (size_t i = 1; i < brackets.size(); ++i) {
        const RawFrame& f = brackets[i];
        if (f.width != first.width || f.height != first.height)
            return bracketError(i, "width x height " + std::to_string(f.width) + " x " +
                                       std::to_string(f.height) + " differs from bracket 0's " +
                                       std::to_string(first.width) + " x " +
                                       std::to_string(first.height));
        if (f.format != first.format)
            return bracketError(i, std::string("format ") + formatName(f.format) +
                                       " differs from bracket 0's " + formatName(first.format));
        if (f.bit_depth != first.bit_depth)
            return bracketError(i, "bit_depth " + std::to_string(f.bit_depth) +
                                       " differs from bracket 0's " +
                                       std::to_string(first.bit_depth));
        if (f.camera != first.camera)
            return bracketError(
                i, "camera \"" + f.camera + "\" differs from bracket 0's \"" + first.camera + "\"");
        if (!(std::abs(f.angle_deg - first.angle_deg) <= options.max_angle_spread_deg))
            return bracketError(i, "angle_deg " + describe(f.angle_deg) + " is more than " +
                                       describe(options.max_angle_spread_deg) +
                                       " from bracket 0's " + describe(first.angle_deg) +
                                       " (MergeOptions::max_angle_spread_deg)");
    }

    // Sort, so that nothing depends on the order the caller passed.
    std::vector<size_t> order(brackets.size());
    std::iota(order.begin(), order.end(), size_t{0});
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return bracketBefore(brackets[a], brackets[b]); });
    const RawFrame& shortest = brackets[order.front()];
    const RawFrame& longest = brackets[order.back()];
    const double reference_exposure = longest.exposure_s * longest.gain;
    const double shortest_exposure = shortest.exposure_s * shortest.gain;
    if (!(reference_exposure <= kMaxExposureRatio * shortest_exposure))
        return bracketError(
            order.front(), "exposure_s * gain " + describe(shortest_exposure) + " is more than " +
                               describe(kMaxExposureRatio) + " times below bracket " +
                               std::to_string(order.back()) + "'s " + describe(reference_exposure));
    // The largest radiance any sample can give must fit float, with room for the weighted mean.
    for (const size_t i : order) {
        const RawFrame& f = brackets[i];
        const double largest = (f.white_level_dn - f.black_level_dn) / (f.exposure_s * f.gain);
        if (!(largest <= 0.25 * static_cast<double>(std::numeric_limits<float>::max())))
            return bracketError(i, "exposure_s * gain " + describe(f.exposure_s * f.gain) +
                                       " is so small that the radiance overflows float");
    }

    bool used_fallback = false;
    std::vector<BracketPlan> plans;
    plans.reserve(order.size());
    for (const size_t i : order)
        plans.push_back(planBracket(brackets[i], reference_exposure, options, &used_fallback));

    MergedFrame merged;
    merged.width = first.width;
    merged.height = first.height;
    merged.format = first.format;
    const int64_t total = first.width * first.height;
    resizeOutput(merged.radiance, static_cast<size_t>(total));
    resizeOutput(merged.count, static_cast<size_t>(total));
    const float inv_reference_exposure = static_cast<float>(1.0 / reference_exposure);
    float* radiance = merged.radiance.data();
    uint8_t* count = merged.count.data();
    const MergeRunFunction merge_run = mergeRunKernel(options.allow_avx2);
    std::atomic<int64_t> saturated_samples{0}, dark_samples{0};
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, total, 16 * kRun),
                      [&](const tbb::blocked_range<int64_t>& range) {
                          RunCounts sum;
                          for (int64_t b = range.begin(); b < range.end(); b += kRun) {
                              const RunCounts run =
                                  merge_run(plans, b, std::min(b + kRun, range.end()),
                                            inv_reference_exposure, radiance, count);
                              sum.saturated += run.saturated;
                              sum.dark += run.dark;
                          }
                          saturated_samples += sum.saturated;
                          dark_samples += sum.dark;
                      });
    merged.saturated_samples = saturated_samples.load();
    merged.dark_samples = dark_samples.load();

    double angle_sum = 0.0;
    for (const size_t i : order) {
        angle_sum += brackets[i].angle_deg;
        merged.exposure_times_s.push_back(brackets[i].exposure_s);
    }
    merged.angle_deg = angle_sum / static_cast<double>(order.size());
    merged.gain = longest.gain;
    merged.camera = first.camera;
    merged.method = methodText(brackets.size(), options, used_fallback);
    return merged;
}

Result<ExposureCounts> countExposure(const RawFrame& frame, const MergeOptions& options) {
    if (auto ok = checkOptions(options); !ok) return ok.error();
    if (auto ok = checkBracket(frame, 0); !ok) return ok.error();
    const auto [usable, saturated] = thresholdsDn(frame, options);
    ExposureCounts c;
    for (const uint16_t dn : frame.samples) {
        const double v = dn;
        if (v >= saturated)
            ++c.saturated;
        else if (v >= usable)
            ++c.usable;
        else
            ++c.dark;
    }
    return c;
}

Result<ImageRGB> toImage(const MergedFrame& frame) {
    if (frame.width < 0 || frame.height < 0)
        return makeError(ErrorCode::InvalidArgument, "toImage: width x height is " +
                                                         std::to_string(frame.width) + " x " +
                                                         std::to_string(frame.height));
    if (frame.height > 0 && frame.width > std::numeric_limits<int64_t>::max() / 3 / frame.height)
        return makeError(ErrorCode::InvalidArgument, "toImage: the frame is too large");
    const int64_t w = frame.width, h = frame.height;
    if (static_cast<int64_t>(frame.radiance.size()) != w * h)
        return makeError(ErrorCode::InvalidArgument,
                         "toImage: radiance.size() is " + std::to_string(frame.radiance.size()) +
                             ", width * height is " + std::to_string(w * h));
    for (int64_t i = 0; i < w * h; ++i) {
        const float v = frame.radiance[static_cast<size_t>(i)];
        if (!(std::isfinite(v) && v >= 0.0f))
            return makeError(ErrorCode::InvalidArgument,
                             "toImage: radiance at x " + std::to_string(i % w) + ", y " +
                                 std::to_string(i / w) + " is " + describe(v) +
                                 " (must be finite and >= 0)");
    }
    ImageRGB image(w, h);
    const float* src = frame.radiance.data();
    if (frame.format == RawFormat::Mono) {
        for (int64_t i = 0; i < w * h; ++i)
            for (int c = 0; c < 3; ++c) image.pixels[static_cast<size_t>(3 * i + c)] = src[i];
        return image;
    }
    // Bilinear demosaic: each colour is the mean of its samples in the 3x3 neighbourhood (for the
    // pixel's own colour that is the pixel alone, the next sample of it being 2 away).
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, h),
                      [&](const tbb::blocked_range<int64_t>& rows) {
                          for (int64_t y = rows.begin(); y < rows.end(); ++y)
                              for (int64_t x = 0; x < w; ++x) {
                                  float sum[3] = {0.0f, 0.0f, 0.0f};
                                  int n[3] = {0, 0, 0};
                                  forDemosaicSamples(frame.format, w, h, x, y,
                                                     [&](int64_t xx, int64_t yy, int c) {
                                                         sum[c] += src[yy * w + xx];
                                                         ++n[c];
                                                     });
                                  float* out = image.at(x, y);
                                  for (int c = 0; c < 3; ++c)
                                      out[c] = n[c] > 0 ? sum[c] / static_cast<float>(n[c]) : 0.0f;
                              }
                      });
    return image;
}

Result<std::vector<uint8_t>> lowerBounds(const MergedFrame& frame) {
    if (frame.width < 0 || frame.height < 0 ||
        frame.radiance.size() != static_cast<size_t>(frame.width * frame.height) ||
        frame.count.size() != frame.radiance.size())
        return makeError(ErrorCode::InvalidArgument,
                         "lowerBounds: radiance and count must hold width * height samples");
    const int64_t w = frame.width, h = frame.height;
    const auto clipped = [&](int64_t x, int64_t y) {
        const size_t i = static_cast<size_t>(y * w + x);
        return frame.count[i] == 0 && frame.radiance[i] > 0.0f;
    };
    std::vector<uint8_t> bits(static_cast<size_t>(w * h), 0);
    if (frame.format == RawFormat::Mono) {
        for (int64_t y = 0; y < h; ++y)
            for (int64_t x = 0; x < w; ++x)
                if (clipped(x, y))
                    bits[static_cast<size_t>(y * w + x)] =
                        kLowerBoundRed | kLowerBoundGreen | kLowerBoundBlue;
        return bits;
    }
    // A colour is a bound where any sample toImage's demosaic averages into it is one.
    for (int64_t y = 0; y < h; ++y)
        for (int64_t x = 0; x < w; ++x) {
            uint8_t b = 0;
            forDemosaicSamples(frame.format, w, h, x, y, [&](int64_t xx, int64_t yy, int c) {
                if (clipped(xx, yy)) b |= static_cast<uint8_t>(1u << c);
            });
            bits[static_cast<size_t>(y * w + x)] = b;
        }
    return bits;
}

}  // namespace flarelab::hdr
