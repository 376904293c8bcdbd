#include "bench/merge_bench.h"

#include <tbb/blocked_range.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <iomanip>
#include <limits>
#include <memory>
#include <opencv2/core.hpp>
#include <opencv2/photo.hpp>
#include <ostream>
#include <random>
#include <sstream>
#include <string>

#include "hdr/merge.h"
#include "hdr/raw_frame.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;

// The simulated camera (merge_bench.h).
constexpr double kPeak = 5e6;        // DN/s at unity gain
constexpr double kBackground = 4.0;  // DN/s, times 0.5 .. 1.5 across the frame
constexpr double kFalloffDecades = 7.0;
constexpr double kElectronsPerDn = 2.0;
constexpr double kReadNoiseDn = 2.5;
constexpr double kGain = 1.0;
// Below this many electrons shot noise is drawn from the Poisson distribution, above it from its
// normal approximation (the difference is far below the read noise there).
constexpr double kPoissonBelowElectrons = 30.0;
// Lowest and highest decade of true radiance in the per-decade table.
constexpr int kFirstDecade = -1;
constexpr int kLastDecade = 7;

double msSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

std::string fixed(double v, int digits = 1) {
    if (std::isinf(v)) return "inf";
    if (std::isnan(v)) return "n/a";
    std::ostringstream s;
    s << std::fixed << std::setprecision(digits) << v;
    return s.str();
}

std::string percent(double v) { return std::isfinite(v) ? fixed(100.0 * v, 3) + " %" : "n/a"; }

nlohmann::json finiteOrNull(double v) { return std::isfinite(v) ? nlohmann::json(v) : nullptr; }

// SplitMix64's finalizer: independent seeds for each bracket and row from one seed.
uint64_t mixSeed(uint64_t z) {
    z += 0x9E3779B97F4A7C15ull;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

// The noiseless scene, DN per second at unity gain (merge_bench.h).
std::vector<float> makeScene(int64_t width, int64_t height) {
    std::vector<float> truth(static_cast<size_t>(width * height));
    const double half_min = 0.5 * static_cast<double>(std::min(width, height));
    const double r_core = std::max(0.5, 2.0 * half_min / 1000.0);
    const double q = kFalloffDecades / std::log10(1.0 + (half_min / r_core) * (half_min / r_core));
    // The peak sits on the centre of the pixel at (width / 2, height / 2), so that pixel holds
    // all of it whatever the size.
    const double cx = static_cast<double>(width / 2) + 0.5;
    const double cy = static_cast<double>(height / 2) + 0.5;
    tbb::parallel_for(int64_t{0}, height, [&](int64_t y) {
        for (int64_t x = 0; x < width; ++x) {
            const double dx = (static_cast<double>(x) + 0.5 - cx) / r_core;
            const double dy = (static_cast<double>(y) + 0.5 - cy) / r_core;
            const double peak = kPeak * std::pow(1.0 + dx * dx + dy * dy, -q);
            const double background =
                kBackground * (0.5 + (static_cast<double>(x) + 0.5) / static_cast<double>(width));
            truth[static_cast<size_t>(y * width + x)] = static_cast<float>(peak + background);
        }
    });
    return truth;
}

// One noisy exposure of the scene (merge_bench.h: the simulated camera).
hdr::RawFrame expose(const std::vector<float>& truth,
                     int64_t width,
                     int64_t height,
                     int bit_depth,
                     double exposure_s,
                     int bracket,
                     uint64_t seed) {
    hdr::RawFrame f;
    f.width = width;
    f.height = height;
    f.format = hdr::RawFormat::Mono;
    f.exposure_s = exposure_s;
    f.gain = kGain;
    f.bit_depth = bit_depth;
    f.black_level_dn = std::ldexp(1.0, bit_depth - 5);
    f.white_level_dn = std::ldexp(1.0, bit_depth) - 1.0;
    f.read_noise_dn = kReadNoiseDn;
    f.electrons_per_dn = kElectronsPerDn;
    f.camera = "flarelab bench merge: simulated";
    f.sequence = bracket;
    f.samples.resize(static_cast<size_t>(width * height));
    tbb::parallel_for(int64_t{0}, height, [&](int64_t y) {
        std::mt19937_64 rng(mixSeed(
            seed ^ mixSeed(static_cast<uint64_t>(bracket) << 32 ^ static_cast<uint64_t>(y))));
        std::normal_distribution<double> normal(0.0, 1.0);
        for (int64_t x = 0; x < width; ++x) {
            const size_t i = static_cast<size_t>(y * width + x);
            const double electrons_mean = truth[i] * exposure_s * kGain * kElectronsPerDn;
            double electrons;
            if (electrons_mean < kPoissonBelowElectrons) {
                std::poisson_distribution<int64_t> poisson(electrons_mean);
                electrons = static_cast<double>(poisson(rng));
            } else {
                electrons = electrons_mean + std::sqrt(electrons_mean) * normal(rng);
            }
            const double dn =
                f.black_level_dn + electrons / kElectronsPerDn + kReadNoiseDn * normal(rng);
            f.samples[i] = static_cast<uint16_t>(std::clamp(std::round(dn), 0.0, f.white_level_dn));
        }
    });
    return f;
}

// The bracket as OpenCV's merges take it (merge_bench.h).
cv::Mat toEightBit(const hdr::RawFrame& f) {
    cv::Mat m(static_cast<int>(f.height), static_cast<int>(f.width), CV_8UC1);
    const double scale = 255.0 / (f.white_level_dn - f.black_level_dn);
    for (int64_t y = 0; y < f.height; ++y) {
        uint8_t* row = m.ptr<uint8_t>(static_cast<int>(y));
        for (int64_t x = 0; x < f.width; ++x) {
            const double dn = f.samples[static_cast<size_t>(y * f.width + x)];
            row[x] = static_cast<uint8_t>(
                std::clamp(std::round((dn - f.black_level_dn) * scale), 0.0, 255.0));
        }
    }
    return m;
}

// The same 8-bit samples packed three to a pixel (row y, column x / 3, channel x % 3; the last
// pixel of a row padded with 0): OpenCV's MergeRobertson takes only 3-channel weights, and merges
// each channel on its own, so this is the 1-channel merge of the same bytes.
cv::Mat packThree(const cv::Mat& mono) {
    const int cols = (mono.cols + 2) / 3;
    cv::Mat packed(mono.rows, cols, CV_8UC3, cv::Scalar::all(0));
    for (int y = 0; y < mono.rows; ++y) {
        const uint8_t* src = mono.ptr<uint8_t>(y);
        uint8_t* dst = packed.ptr<uint8_t>(y);
        std::memcpy(dst, src, static_cast<size_t>(mono.cols));
    }
    return packed;
}

struct Accuracy {
    double median = std::nan("");
    double mean = std::nan("");
    double frame = std::nan("");
    int64_t evaluated = 0;
    int64_t non_finite = 0;
    std::vector<double> decade_median;  // kFirstDecade .. kLastDecade
};

double medianOf(std::vector<float>& v) {
    if (v.empty()) return std::nan("");
    const size_t mid = v.size() / 2;
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(mid), v.end());
    return v[mid];
}

int decadeOf(float truth) {
    return std::clamp(static_cast<int>(std::floor(std::log10(truth))), kFirstDecade, kLastDecade);
}

// `estimate(i)` is a method's radiance at sample i in DN/s; `evaluated` marks the pixels scored.
template <typename Estimate>
Accuracy score(const std::vector<float>& truth,
               const std::vector<uint8_t>& evaluated,
               Estimate estimate) {
    Accuracy a;
    std::vector<float> errors;
    std::vector<std::vector<float>> by_decade(kLastDecade - kFirstDecade + 1);
    double sum_error = 0.0, sum_estimate = 0.0, sum_truth = 0.0;
    for (size_t i = 0; i < truth.size(); ++i) {
        if (!evaluated[i]) continue;
        const double est = estimate(i);
        const double t = truth[i];
        ++a.evaluated;
        float e = std::numeric_limits<float>::infinity();
        if (std::isfinite(est)) {
            e = static_cast<float>(std::abs(est - t) / t);
            sum_error += e;
            sum_estimate += est;
        } else {
            ++a.non_finite;
        }
        sum_truth += t;
        errors.push_back(e);
        by_decade[static_cast<size_t>(decadeOf(truth[i]) - kFirstDecade)].push_back(e);
    }
    a.median = medianOf(errors);
    a.mean = a.non_finite > 0 || a.evaluated == 0 ? std::numeric_limits<double>::infinity()
                                                  : sum_error / static_cast<double>(a.evaluated);
    a.frame = a.non_finite > 0 ? std::numeric_limits<double>::infinity()
                               : std::abs(sum_estimate - sum_truth) / sum_truth;
    for (auto& d : by_decade) a.decade_median.push_back(medianOf(d));
    return a;
}

nlohmann::json accuracyJson(const Accuracy& a) {
    nlohmann::json decades = nlohmann::json::array();
    for (const double d : a.decade_median) decades.push_back(finiteOrNull(d));
    return {{"median", finiteOrNull(a.median)}, {"mean", finiteOrNull(a.mean)},
            {"frame", finiteOrNull(a.frame)},   {"evaluated_pixels", a.evaluated},
            {"non_finite", a.non_finite},       {"decade_median", decades}};
}

// Best of `repeat` runs of `run`, in milliseconds. `release` frees what the previous run made
// before the clock starts, so that no run pays for freeing the last one's memory; the last run's
// result is left to the caller.
template <typename Release, typename Run>
double bestOf(int repeat, Release release, Run run) {
    double best = std::numeric_limits<double>::infinity();
    for (int r = 0; r < repeat; ++r) {
        release();
        const auto start = Clock::now();
        run();
        best = std::min(best, msSince(start));
    }
    return best;
}

// Keeps the compiler from dropping the copies of the floor.
volatile uint64_t g_sink = 0;

// The bandwidth floor (merge_bench.h): the inputs copied into a fresh buffer, the output's bytes
// written into fresh buffers; on one thread, or split over every core.
struct CopyBuffers {
    std::unique_ptr<uint16_t[]> in;
    std::unique_ptr<float[]> radiance;
    std::unique_ptr<uint8_t[]> count;
};

CopyBuffers copyFloor(const std::vector<hdr::RawFrame>& brackets, int64_t total, bool parallel) {
    const size_t n = static_cast<size_t>(total);
    auto in = std::make_unique_for_overwrite<uint16_t[]>(n * brackets.size());
    auto radiance = std::make_unique_for_overwrite<float[]>(n);
    auto count = std::make_unique_for_overwrite<uint8_t[]>(n);
    const auto chunked = [&](auto body) {
        if (!parallel) {
            body(size_t{0}, n);
            return;
        }
        tbb::parallel_for(tbb::blocked_range<size_t>(0, n, size_t{1} << 18),
                          [&](const tbb::blocked_range<size_t>& r) { body(r.begin(), r.end()); });
    };
    for (size_t k = 0; k < brackets.size(); ++k)
        chunked([&](size_t b, size_t e) {
            std::memcpy(in.get() + k * n + b, brackets[k].samples.data() + b,
                        (e - b) * sizeof(uint16_t));
        });
    chunked([&](size_t b, size_t e) {
        std::fill(radiance.get() + b, radiance.get() + e, 0.0f);
        std::memset(count.get() + b, 0, e - b);
    });
    g_sink = g_sink + in[n * brackets.size() - 1] + count[n / 2] +
             static_cast<uint64_t>(radiance[n - 1]);
    return {std::move(in), std::move(radiance), std::move(count)};
}

// The pure bandwidth floor: the same copies into buffers allocated and touched beforehand.
struct WarmBuffers {
    std::vector<uint16_t> in;
    std::vector<float> radiance;
    std::vector<uint8_t> count;
};

void copyWarm(const std::vector<hdr::RawFrame>& brackets, int64_t total, WarmBuffers& b) {
    const size_t n = static_cast<size_t>(total);
    for (size_t k = 0; k < brackets.size(); ++k)
        std::memcpy(b.in.data() + k * n, brackets[k].samples.data(), n * sizeof(uint16_t));
    std::fill(b.radiance.begin(), b.radiance.end(), 0.0f);
    std::memset(b.count.data(), 0, n);
    g_sink = g_sink + b.in[n * brackets.size() - 1] + b.count[n / 2] +
             static_cast<uint64_t>(b.radiance[n - 1]);
}

Status checkOptions(const MergeBenchOptions& o) {
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "bench merge: " + what);
    };
    if (o.width < 8 || o.width > 32768 || o.height < 8 || o.height > 32768)
        return bad("--width and --height must lie in 8..32768");
    if (o.width * o.height > (int64_t{1} << 28))
        return bad("--width x --height must be at most 2^28 pixels");
    if (o.repeat < 1 || o.repeat > 100) return bad("--repeat must lie in 1..100");
    if (o.bit_depth < 10 || o.bit_depth > 16) return bad("--bit-depth must lie in 10..16");
    if (o.exposure_times_s.empty() || o.exposure_times_s.size() > 16)
        return bad("exposure_times_s must hold 1 to 16 times");
    for (const double t : o.exposure_times_s)
        if (!(std::isfinite(t) && t > 0.0 && t < 1e4))
            return bad("exposure_times_s: each must lie in (0, 1e4) s");
    return Ok{};
}

}  // namespace

Result<nlohmann::json> runMergeBench(const MergeBenchOptions& input,
                                     std::ostream& out,
                                     std::ostream& log) {
    MergeBenchOptions o = input;
    if (o.quick) {
        o.width = std::min<int64_t>(o.width, 1200);
        o.height = std::min<int64_t>(o.height, 800);
        o.repeat = std::min(o.repeat, 2);
    }
    if (auto ok = checkOptions(o); !ok) return ok.error();
    const int64_t total = o.width * o.height;

    log << "bench merge: scene and " << o.exposure_times_s.size() << " brackets, " << o.width << "x"
        << o.height << "\n";
    const std::vector<float> truth = makeScene(o.width, o.height);
    std::vector<hdr::RawFrame> brackets;
    for (size_t k = 0; k < o.exposure_times_s.size(); ++k)
        brackets.push_back(expose(truth, o.width, o.height, o.bit_depth, o.exposure_times_s[k],
                                  static_cast<int>(k), o.seed));
    const hdr::RawFrame& proto = brackets.front();
    const double t_min =
        *std::min_element(o.exposure_times_s.begin(), o.exposure_times_s.end()) * kGain;
    double true_min = std::numeric_limits<double>::infinity(), true_max = 0.0;
    for (const float t : truth) {
        true_min = std::min<double>(true_min, t);
        true_max = std::max<double>(true_max, t);
    }
    // Scored: true > 0 and, on average, not clipped in the shortest exposure.
    std::vector<uint8_t> evaluated(truth.size());
    int64_t clipped_everywhere = 0;
    for (size_t i = 0; i < truth.size(); ++i) {
        const bool clipped = proto.black_level_dn + truth[i] * t_min >= proto.white_level_dn;
        evaluated[i] = truth[i] > 0.0f && !clipped;
        clipped_everywhere += clipped ? 1 : 0;
    }

    // Ours.
    log << "bench merge: flarelab merge\n";
    Result<hdr::MergedFrame> merged = makeError(ErrorCode::Internal, "not run");
    const double ours_ms = bestOf(
        o.repeat,
        [&] {
            if (merged) merged = makeError(ErrorCode::Internal, "released");
        },
        [&] { merged = hdr::mergeBrackets(brackets); });
    if (!merged) return merged.error().withContext("bench merge");
    double ours_one_thread_ms = std::nan("");
    if (!o.quick) {
        log << "bench merge: flarelab merge on one thread\n";
        tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
        Result<hdr::MergedFrame> single = makeError(ErrorCode::Internal, "not run");
        ours_one_thread_ms = bestOf(
            o.repeat, [&] { single = makeError(ErrorCode::Internal, "released"); },
            [&] { single = hdr::mergeBrackets(brackets); });
    }
    const Accuracy ours =
        score(truth, evaluated, [&](size_t i) { return static_cast<double>(merged->radiance[i]); });

    // The floor.
    log << "bench merge: copy floor\n";
    CopyBuffers copied;
    const auto release_copy = [&] { copied = CopyBuffers{}; };
    const double copy_ms =
        bestOf(o.repeat, release_copy, [&] { copied = copyFloor(brackets, total, false); });
    const double copy_parallel_ms =
        bestOf(o.repeat, release_copy, [&] { copied = copyFloor(brackets, total, true); });
    release_copy();
    double copy_warm_ms = 0.0;
    {
        WarmBuffers warm{std::vector<uint16_t>(static_cast<size_t>(total) * brackets.size()),
                         std::vector<float>(static_cast<size_t>(total)),
                         std::vector<uint8_t>(static_cast<size_t>(total))};
        copy_warm_ms = bestOf(
            o.repeat, [] {}, [&] { copyWarm(brackets, total, warm); });
    }

    // OpenCV.
    double debevec_ms = std::nan(""), robertson_ms = std::nan("");
    Accuracy debevec, robertson;
    int opencv_threads = 0;
    if (o.opencv) {
        try {
            opencv_threads = cv::getNumThreads();
            std::vector<cv::Mat> images;
            for (const auto& b : brackets) images.push_back(toEightBit(b));
            std::vector<float> times;
            for (const double t : o.exposure_times_s) times.push_back(static_cast<float>(t));
            std::vector<cv::Mat> packed_images;
            for (const auto& m : images) packed_images.push_back(packThree(m));
            cv::Mat log_safe_response(256, 1, CV_32FC1), linear_response(256, 1, CV_32FC3);
            for (int z = 0; z < 256; ++z) {
                linear_response.at<cv::Vec3f>(z) = cv::Vec3f::all(static_cast<float>(z));
                log_safe_response.at<float>(z) = static_cast<float>(std::max(z, 1));
            }
            const double to_dn = (proto.white_level_dn - proto.black_level_dn) / 255.0 / kGain;
            cv::Mat result;
            log << "bench merge: OpenCV MergeDebevec\n";
            const auto merge_debevec = cv::createMergeDebevec();
            debevec_ms = bestOf(
                o.repeat, [&] { result = cv::Mat(); },
                [&] { merge_debevec->process(images, result, times, log_safe_response); });
            debevec = score(truth, evaluated, [&](size_t i) {
                return static_cast<double>(result.ptr<float>()[i]) * to_dn;
            });
            log << "bench merge: OpenCV MergeRobertson\n";
            const auto merge_robertson = cv::createMergeRobertson();
            robertson_ms = bestOf(
                o.repeat, [&] { result = cv::Mat(); },
                [&] { merge_robertson->process(packed_images, result, times, linear_response); });
            const int64_t packed_row = 3 * static_cast<int64_t>(result.cols);
            robertson = score(truth, evaluated, [&](size_t i) {
                const int64_t y = static_cast<int64_t>(i) / o.width;
                const int64_t x = static_cast<int64_t>(i) % o.width;
                return static_cast<double>(result.ptr<float>()[y * packed_row + x]) * to_dn;
            });
        } catch (const cv::Exception& e) {
            return makeError(ErrorCode::Internal, std::string("bench merge: OpenCV: ") + e.what());
        }
    }

    const int threads = static_cast<int>(
        tbb::global_control::active_value(tbb::global_control::max_allowed_parallelism));
    nlohmann::json doc;
    doc["settings"] = {{"width", o.width},
                       {"height", o.height},
                       {"brackets", o.exposure_times_s.size()},
                       {"exposure_times_s", o.exposure_times_s},
                       {"bit_depth", o.bit_depth},
                       {"black_level_dn", proto.black_level_dn},
                       {"white_level_dn", proto.white_level_dn},
                       {"electrons_per_dn", kElectronsPerDn},
                       {"read_noise_dn", kReadNoiseDn},
                       {"seed", o.seed},
                       {"repeat", o.repeat},
                       {"quick", o.quick},
                       {"threads", threads},
                       {"opencv_threads", opencv_threads},
                       {"true_min", true_min},
                       {"true_max", true_max},
                       {"dynamic_range", true_max / true_min},
                       {"input_bytes", total * 2 * static_cast<int64_t>(brackets.size())},
                       {"output_bytes", total * 5},
                       {"clipped_in_every_bracket", clipped_everywhere},
                       {"method", merged->method}};
    doc["ours_ms"] = ours_ms;
    doc["ours_one_thread_ms"] = finiteOrNull(ours_one_thread_ms);
    doc["debevec_ms"] = finiteOrNull(debevec_ms);
    doc["robertson_ms"] = finiteOrNull(robertson_ms);
    doc["copy_ms"] = copy_ms;
    doc["copy_parallel_ms"] = copy_parallel_ms;
    doc["copy_warm_ms"] = copy_warm_ms;
    doc["ours_rel_err"] = finiteOrNull(ours.median);
    doc["debevec_rel_err"] = finiteOrNull(debevec.median);
    doc["robertson_rel_err"] = finiteOrNull(robertson.median);
    doc["speedup_vs_debevec"] = finiteOrNull(debevec_ms / ours_ms);
    doc["speedup_vs_robertson"] = finiteOrNull(robertson_ms / ours_ms);
    doc["ours_over_copy"] = ours_ms / copy_ms;
    doc["ours_over_copy_parallel"] = ours_ms / copy_parallel_ms;
    doc["ours_over_copy_warm"] = ours_ms / copy_warm_ms;
    doc["accuracy"] = {{"ours", accuracyJson(ours)}};
    if (o.opencv) {
        doc["accuracy"]["debevec"] = accuracyJson(debevec);
        doc["accuracy"]["robertson"] = accuracyJson(robertson);
    }

    const double mb =
        static_cast<double>(total) * (2.0 * static_cast<double>(brackets.size()) + 5.0) / 1e6;
    out << "## HDR bracket merge: speed (" << o.width << "x" << o.height << ", " << brackets.size()
        << " brackets of " << o.bit_depth << " bits in 16-bit samples, best of " << o.repeat
        << ")\n\n"
        << "OpenCV gets the same samples scaled to 8 bits (its merges take only 8-bit images); "
           "MergeDebevec as one channel, MergeRobertson packed three samples to a pixel (its "
           "weights are 3-channel; it merges each channel on its own). Conversion and packing "
           "are not timed; no run pays for freeing the previous run's result. The copy floor "
           "moves the same bytes ("
        << fixed(mb, 0)
        << " MB: the inputs copied, the float radiance and uint8 count written) into fresh "
           "buffers.\n\n"
        << "| method | threads | ms | GB/s of input + output | time / ours |\n"
        << "|---|---|---|---|---|\n";
    const auto speed_row = [&](const std::string& name, const std::string& th, double ms) {
        out << "| " << name << " | " << th << " | " << fixed(ms) << " | " << fixed(mb / ms, 2)
            << " | " << fixed(ms / ours_ms, 2) << " |\n";
    };
    speed_row("flarelab mergeBrackets", std::to_string(threads), ours_ms);
    if (!o.quick) speed_row("flarelab mergeBrackets", "1", ours_one_thread_ms);
    if (o.opencv) {
        speed_row("OpenCV MergeDebevec (8-bit)", std::to_string(opencv_threads), debevec_ms);
        speed_row("OpenCV MergeRobertson (8-bit)", std::to_string(opencv_threads), robertson_ms);
    }
    speed_row("copy floor (std::memcpy)", "1", copy_ms);
    speed_row("copy floor (split over cores)", std::to_string(threads), copy_parallel_ms);
    speed_row("copy into warm buffers (std::memcpy)", "1", copy_warm_ms);
    out << "\nSpeed-up over MergeDebevec: " << fixed(debevec_ms / ours_ms, 1)
        << "x; ours over the one-thread copy floor: " << fixed(ours_ms / copy_ms, 2)
        << "x, over the all-core copy: " << fixed(ours_ms / copy_parallel_ms, 2)
        << "x, over the copy into warm buffers (no page faults): "
        << fixed(ours_ms / copy_warm_ms, 2) << "x.\n\n";

    out << "## HDR bracket merge: accuracy against the noiseless scene\n\n"
        << "Scene: true radiance " << fixed(true_min, 2) << " .. " << fixed(true_max, 0)
        << " DN/s (dynamic range " << fixed(true_max / true_min, 0)
        << "); seeded shot and read noise, " << o.bit_depth << "-bit converter. Scored: the "
        << ours.evaluated << " pixels with true > 0 not clipped in the shortest exposure ("
        << clipped_everywhere
        << " clipped pixels left out). Per pixel |est - true| / true; frame: |sum est - sum true| "
           "/ sum true.\n\n"
        << "| method | median rel. error | mean rel. error | frame rel. error | non-finite |\n"
        << "|---|---|---|---|---|\n";
    const auto accuracy_row = [&](const std::string& name, const Accuracy& a) {
        out << "| " << name << " | " << percent(a.median) << " | " << percent(a.mean) << " | "
            << percent(a.frame) << " | " << a.non_finite << " |\n";
    };
    accuracy_row("flarelab mergeBrackets", ours);
    if (o.opencv) {
        accuracy_row("OpenCV MergeDebevec (8-bit)", debevec);
        accuracy_row("OpenCV MergeRobertson (8-bit)", robertson);
    }
    out << "\n### Median relative error per decade of true radiance\n\n"
        << "| true DN/s | ours | Debevec | Robertson |\n|---|---|---|---|\n";
    nlohmann::json decades = nlohmann::json::array();
    for (int d = kFirstDecade; d <= kLastDecade; ++d) {
        const size_t k = static_cast<size_t>(d - kFirstDecade);
        const double od = ours.decade_median[k];
        if (std::isnan(od)) continue;  // no pixel there
        const double dd = o.opencv ? debevec.decade_median[k] : std::nan("");
        const double rd = o.opencv ? robertson.decade_median[k] : std::nan("");
        decades.push_back({{"decade", d},
                           {"ours", finiteOrNull(od)},
                           {"debevec", finiteOrNull(dd)},
                           {"robertson", finiteOrNull(rd)}});
        out << "| 1e" << d << (d == kFirstDecade ? " and below" : "")
            << (d == kLastDecade ? " and above" : "") << " | " << percent(od) << " | "
            << percent(dd) << " | " << percent(rd) << " |\n";
    }
    doc["decades"] = decades;
    out.flush();
    return doc;
}

}  // namespace flarelab::bench
