#include "hdr/merge.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <random>
#include <string>
#include <utility>
#include <vector>

namespace flarelab::hdr {
namespace {

// A 12-bit bracket, black 128, of the given size, every sample `dn`.
RawFrame frame(int64_t width, int64_t height, double exposure_s, uint16_t dn = 128) {
    RawFrame f;
    f.width = width;
    f.height = height;
    f.samples.assign(static_cast<size_t>(width * height), dn);
    f.exposure_s = exposure_s;
    f.bit_depth = 12;
    f.black_level_dn = 128.0;
    f.white_level_dn = 4095.0;
    f.read_noise_dn = 2.5;
    f.electrons_per_dn = 2.0;
    f.camera = "test camera";
    return f;
}

// Noise-free exposures of `radiance` (DN/s at unity gain), rounded and clipped like a converter.
std::vector<RawFrame> exposeExactly(const std::vector<double>& radiance,
                                    const std::vector<double>& exposures_s,
                                    int bit_depth = 12,
                                    double black_dn = 128.0) {
    std::vector<RawFrame> brackets;
    for (const double t : exposures_s) {
        RawFrame f = frame(static_cast<int64_t>(radiance.size()), 1, t);
        f.bit_depth = bit_depth;
        f.black_level_dn = black_dn;
        f.white_level_dn = std::ldexp(1.0, bit_depth) - 1.0;
        for (size_t i = 0; i < radiance.size(); ++i)
            f.samples[i] = static_cast<uint16_t>(
                std::clamp(std::round(black_dn + radiance[i] * t), 0.0, f.white_level_dn));
        brackets.push_back(f);
    }
    return brackets;
}

// Noisy exposures: Poisson electrons, Gaussian read noise, rounding, clipping; seeded.
std::vector<RawFrame> exposeWithNoise(const std::vector<double>& radiance,
                                      const std::vector<double>& exposures_s,
                                      uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::vector<RawFrame> brackets;
    for (const double t : exposures_s) {
        RawFrame f = frame(static_cast<int64_t>(radiance.size()), 1, t);
        std::normal_distribution<double> read(0.0, f.read_noise_dn);
        for (size_t i = 0; i < radiance.size(); ++i) {
            std::poisson_distribution<int64_t> electrons(radiance[i] * t * f.electrons_per_dn);
            const double dn = f.black_level_dn +
                              static_cast<double>(electrons(rng)) / f.electrons_per_dn + read(rng);
            f.samples[i] = static_cast<uint16_t>(std::clamp(std::round(dn), 0.0, f.white_level_dn));
        }
        brackets.push_back(f);
    }
    return brackets;
}

void expectAllFinite(const MergedFrame& m) {
    ASSERT_EQ(m.radiance.size(), static_cast<size_t>(m.width * m.height));
    ASSERT_EQ(m.count.size(), m.radiance.size());
    for (size_t i = 0; i < m.radiance.size(); ++i) {
        ASSERT_TRUE(std::isfinite(m.radiance[i])) << i;
        ASSERT_GE(m.radiance[i], 0.0f) << i;
    }
}

TEST(MergeBrackets, RecoversRadianceWithoutNoise) {
    // Multiples of 4 DN/s: every bracket's signal is a whole DN, so each unsaturated sample
    // estimates the radiance exactly.
    const std::vector<double> radiance = {4, 40, 400, 900, 1000, 4000, 9000, 15000};
    const auto brackets = exposeExactly(radiance, {0.25, 1.0, 4.0});
    auto merged = mergeBrackets(brackets);
    ASSERT_TRUE(merged) << merged.error().message;
    expectAllFinite(*merged);
    for (size_t i = 0; i < radiance.size(); ++i)
        EXPECT_NEAR(merged->radiance[i], radiance[i], 1e-6 * radiance[i]) << i;
    // Saturation at 4095 - 1 % of 3967 DN, i.e. DN >= 4056: 4 s saturates above 982 DN/s, 1 s above
    // 3928 DN/s; 4 DN/s gives 1 DN in 0.25 s, still above black.
    const std::vector<uint8_t> expected_count = {3, 3, 3, 3, 2, 1, 1, 1};
    EXPECT_EQ(merged->count, expected_count);
    EXPECT_EQ(merged->saturated_samples, 0);
    EXPECT_EQ(merged->dark_samples, 0);
    EXPECT_EQ(merged->exposure_times_s, (std::vector<double>{0.25, 1.0, 4.0}));
    EXPECT_EQ(merged->camera, "test camera");
    EXPECT_NE(merged->method.find("Granados"), std::string::npos) << merged->method;
}

TEST(MergeBrackets, NoiseWeightedMergeBeatsEachSingleBracket) {
    // Radiance that no bracket saturates: every bracket alone is an unbiased estimate.
    std::vector<double> radiance;
    for (int i = 0; i < 4000; ++i) radiance.push_back(5.0 + 900.0 * i / 4000.0);
    const std::vector<double> exposures = {0.25, 1.0, 4.0};
    const auto brackets = exposeWithNoise(radiance, exposures, 11);
    auto merged = mergeBrackets(brackets);
    ASSERT_TRUE(merged) << merged.error().message;
    const auto rms = [&](const std::function<double(size_t)>& estimate) {
        double sum = 0.0;
        for (size_t i = 0; i < radiance.size(); ++i) {
            const double e = (estimate(i) - radiance[i]) / radiance[i];
            sum += e * e;
        }
        return std::sqrt(sum / static_cast<double>(radiance.size()));
    };
    const double merged_rms = rms([&](size_t i) { return merged->radiance[i]; });
    for (size_t k = 0; k < brackets.size(); ++k) {
        const double single_rms = rms([&](size_t i) {
            return (brackets[k].samples[i] - brackets[k].black_level_dn) / exposures[k];
        });
        EXPECT_LT(merged_rms, single_rms) << "bracket " << k;
    }
    // Shot noise dominates most samples: the merge is close to the total-exposure estimate,
    // 21 % better than the 4 s bracket alone (sqrt(4 / 5.25)), not merely a little.
    const double longest_rms = rms([&](size_t i) {
        return (brackets[2].samples[i] - brackets[2].black_level_dn) / exposures[2];
    });
    EXPECT_LT(merged_rms, 0.93 * longest_rms);
}

TEST(MergeBrackets, OrderOfBracketsDoesNotMatter) {
    std::vector<double> radiance;
    for (int i = 0; i < 3000; ++i) radiance.push_back(std::pow(10.0, -0.5 + 5.0 * i / 3000.0));
    auto brackets = exposeWithNoise(radiance, {0.25, 1.0, 4.0, 0.5}, 5);
    brackets[3].gain = 2.0;  // exposure_s * gain 1 as bracket 1: ties are broken by other fields
    auto reference = mergeBrackets(brackets);
    ASSERT_TRUE(reference) << reference.error().message;
    std::vector<size_t> order = {0, 1, 2, 3};
    do {
        std::vector<RawFrame> permuted;
        for (const size_t i : order) permuted.push_back(brackets[i]);
        auto merged = mergeBrackets(permuted);
        ASSERT_TRUE(merged) << merged.error().message;
        EXPECT_EQ(merged->radiance, reference->radiance);  // bit for bit
        EXPECT_EQ(merged->count, reference->count);
        EXPECT_EQ(merged->exposure_times_s, reference->exposure_times_s);
        EXPECT_EQ(merged->gain, reference->gain);
    } while (std::next_permutation(order.begin(), order.end()));
    EXPECT_EQ(reference->exposure_times_s, (std::vector<double>{0.25, 0.5, 1.0, 4.0}));
}

TEST(MergeBrackets, SampleSaturatedInEveryBracketIsALowerBoundWithCountZero) {
    std::vector<RawFrame> brackets = {frame(2, 1, 4.0, 4095), frame(2, 1, 0.25, 4095),
                                      frame(2, 1, 1.0, 4095)};
    brackets[1].samples[1] = 1128;  // the second sample is fine in the shortest exposure
    brackets[0].samples[1] = 4060;  // and saturated (>= 4056) in the longest
    auto merged = mergeBrackets(brackets);
    ASSERT_TRUE(merged) << merged.error().message;
    // The shortest exposure's clipped value: (4095 - 128) / 0.25.
    EXPECT_FLOAT_EQ(merged->radiance[0], (4095.0f - 128.0f) / 0.25f);
    EXPECT_EQ(merged->count[0], 0);
    EXPECT_EQ(merged->count[1], 1);
    EXPECT_FLOAT_EQ(merged->radiance[1], 1000.0f / 0.25f);
    EXPECT_EQ(merged->saturated_samples, 1);
    EXPECT_EQ(merged->dark_samples, 0);
}

TEST(CountExposure, SortsSamplesByTheMergesThresholds) {
    // Black 128, white 4095, margin 1 %: saturated from ceil(4095 - 0.01 * 3967) = 4056; usable
    // from 129 (DN - black >= 0.5).
    RawFrame f = frame(6, 1, 1.0);
    f.samples = {0, 128, 129, 4055, 4056, 4095};
    auto c = countExposure(f);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_EQ(c->dark, 2);
    EXPECT_EQ(c->usable, 2);
    EXPECT_EQ(c->saturated, 2);
    // The same thresholds as the merge: a sample is saturated in one exactly when the other
    // drops it as saturated.
    std::vector<RawFrame> one = {f};
    auto merged = mergeBrackets(one);
    ASSERT_TRUE(merged);
    EXPECT_EQ(merged->saturated_samples, c->saturated);
    EXPECT_EQ(merged->dark_samples, c->dark);
    MergeOptions wide;
    wide.saturation_margin_fraction = 0.5;  // saturated from ceil(4095 - 1983.5) = 2112
    c = countExposure(f, wide);
    ASSERT_TRUE(c);
    EXPECT_EQ(c->saturated, 3);
    wide.saturation_margin_fraction = 1.5;
    c = countExposure(f, wide);
    ASSERT_FALSE(c);
    EXPECT_NE(c.error().message.find("saturation_margin_fraction"), std::string::npos);
    f.samples.pop_back();  // no longer width x height
    EXPECT_FALSE(countExposure(f));
}

TEST(MergeBrackets, SampleBlackInEveryBracketIsZeroWithCountZero) {
    std::vector<RawFrame> brackets = {frame(3, 1, 0.25, 128), frame(3, 1, 4.0, 120),
                                      frame(3, 1, 1.0, 0)};
    brackets[1].samples[2] = 129;  // one DN above black in the longest exposure counts
    auto merged = mergeBrackets(brackets);
    ASSERT_TRUE(merged) << merged.error().message;
    EXPECT_EQ(merged->radiance[0], 0.0f);
    EXPECT_EQ(merged->count[0], 0);
    EXPECT_EQ(merged->radiance[1], 0.0f);
    EXPECT_EQ(merged->count[1], 0);
    EXPECT_EQ(merged->count[2], 1);
    EXPECT_FLOAT_EQ(merged->radiance[2], 0.25f);
    EXPECT_EQ(merged->dark_samples, 2);
    EXPECT_EQ(merged->saturated_samples, 0);
}

// Outside a lens's image circle a pixel sees nothing: the long brackets read black (dark, dropped)
// and the read noise of a very short one may read a DN or two. Alone, those made the pixel 1e8
// DN/s; a dark bracket bounds the signal (its threshold plus four read-noise sigmas), so the
// pixel stays under what the longest dark one allows. A lit pixel of the same brackets keeps its
// value.
TEST(MergeBrackets, AShortBracketsReadNoiseIsHeldUnderWhatADarkLongerBracketAllows) {
    const std::vector<double> exposures = {3.6e-9, 4.2e-8, 4.9e-7, 5.7e-6, 6.6e-5, 7.8e-4, 9.1e-3};
    std::vector<RawFrame> brackets = exposeExactly({0.0, 2.0e5}, exposures);
    brackets[0].samples[0] = 130;  // two DN of read noise in the shortest bracket
    brackets[2].samples[0] = 129;  // and one in the third
    auto merged = mergeBrackets(brackets);
    ASSERT_TRUE(merged) << merged.error().message;
    // At most one DN plus four read-noise sigmas over the longest exposure.
    EXPECT_LE(merged->radiance[0], (1.0 + 4.0 * std::sqrt(2.5 * 2.5 + 1.0 / 12.0)) / 9.1e-3 * 1.0001);
    EXPECT_GT(merged->count[0], 0);
    EXPECT_NEAR(merged->radiance[1], 2.0e5, 2.0e5 * 2e-3);
    // Without the dark brackets' bound the noise alone was the pixel's value.
    std::vector<RawFrame> shortest = {brackets[0]};
    auto alone = mergeBrackets(shortest);
    ASSERT_TRUE(alone);
    EXPECT_GT(alone->radiance[0], 1e8);
}

TEST(MergeBrackets, OneBracketIsItsOwnRadianceAtUnityGain) {
    RawFrame f = frame(4, 1, 0.5);
    f.gain = 2.0;
    f.samples = {128, 228, 1128, 4095};
    f.angle_deg = 12.5;
    auto merged = mergeBrackets(std::span<const RawFrame>(&f, 1));
    ASSERT_TRUE(merged) << merged.error().message;
    EXPECT_EQ(merged->radiance[0], 0.0f);
    EXPECT_FLOAT_EQ(merged->radiance[1], 100.0f);
    EXPECT_FLOAT_EQ(merged->radiance[2], 1000.0f);
    EXPECT_FLOAT_EQ(merged->radiance[3], 3967.0f);  // saturated: the clipped value, count 0
    EXPECT_EQ(merged->count, (std::vector<uint8_t>{0, 1, 1, 0}));
    EXPECT_EQ(merged->gain, 2.0);
    EXPECT_EQ(merged->angle_deg, 12.5);
    EXPECT_EQ(merged->width, 4);
    EXPECT_EQ(merged->height, 1);
}

TEST(MergeBrackets, RejectsMismatchedBracketsNamingBracketAndField) {
    const auto expectError = [](std::vector<RawFrame> brackets, const std::string& field) {
        auto merged = mergeBrackets(brackets);
        ASSERT_FALSE(merged) << field;
        EXPECT_EQ(merged.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(merged.error().message.find("bracket 1"), std::string::npos)
            << merged.error().message;
        EXPECT_NE(merged.error().message.find(field), std::string::npos) << merged.error().message;
    };
    expectError({frame(4, 4, 1.0), frame(4, 5, 0.5)}, "width x height");
    expectError({frame(4, 4, 1.0), frame(5, 4, 0.5)}, "width x height");
    RawFrame bayer = frame(4, 4, 0.5);
    bayer.format = RawFormat::BayerRGGB;
    expectError({frame(4, 4, 1.0), bayer}, "format BayerRGGB");
    RawFrame fourteen = frame(4, 4, 0.5);
    fourteen.bit_depth = 14;
    expectError({frame(4, 4, 1.0), fourteen}, "bit_depth");
    RawFrame other = frame(4, 4, 0.5);
    other.camera = "another camera";
    expectError({frame(4, 4, 1.0), other}, "camera");
    RawFrame moved = frame(4, 4, 0.5);
    moved.angle_deg = 0.2;
    expectError({frame(4, 4, 1.0), moved}, "angle_deg");
}

TEST(MergeBrackets, RejectsBadMetadataNamingTheField) {
    struct Case {
        std::function<void(RawFrame&)> spoil;
        std::string field;
    };
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const double inf = std::numeric_limits<double>::infinity();
    const std::vector<Case> cases = {
        {[](RawFrame& f) { f.exposure_s = 0.0; }, "exposure_s"},
        {[](RawFrame& f) { f.exposure_s = -1.0; }, "exposure_s"},
        {[&](RawFrame& f) { f.exposure_s = nan; }, "exposure_s"},
        {[&](RawFrame& f) { f.exposure_s = inf; }, "exposure_s"},
        {[](RawFrame& f) { f.gain = 0.0; }, "gain"},
        {[&](RawFrame& f) { f.gain = nan; }, "gain"},
        {[](RawFrame& f) { f.black_level_dn = 4095.0; }, "black_level_dn"},
        {[](RawFrame& f) { f.black_level_dn = -1.0; }, "black_level_dn"},
        {[&](RawFrame& f) { f.black_level_dn = nan; }, "black_level_dn"},
        {[](RawFrame& f) { f.white_level_dn = 4096.0; }, "white_level_dn"},
        {[&](RawFrame& f) { f.white_level_dn = nan; }, "white_level_dn"},
        {[](RawFrame& f) { f.bit_depth = 7; }, "bit_depth"},
        {[](RawFrame& f) { f.bit_depth = 17; }, "bit_depth"},
        {[](RawFrame& f) { f.samples.pop_back(); }, "samples.size()"},
        {[](RawFrame& f) { f.width = 0; }, "width x height"},
        {[](RawFrame& f) { f.height = -3; }, "width x height"},
        {[](RawFrame& f) { f.read_noise_dn = -1.0; }, "read_noise_dn"},
        {[&](RawFrame& f) { f.electrons_per_dn = nan; }, "electrons_per_dn"},
        {[&](RawFrame& f) { f.angle_deg = inf; }, "angle_deg"},
        {[](RawFrame& f) { f.exposure_s = 1e-12; }, "exposure_s * gain"},
        {[](RawFrame& f) { f.exposure_s = 1e-40; }, "exposure_s * gain"},
    };
    for (const Case& c : cases) {
        std::vector<RawFrame> brackets = {frame(4, 4, 1.0), frame(4, 4, 0.5)};
        c.spoil(brackets[1]);
        auto merged = mergeBrackets(brackets);
        ASSERT_FALSE(merged) << c.field;
        EXPECT_EQ(merged.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(merged.error().message.find("bracket 1"), std::string::npos)
            << merged.error().message;
        EXPECT_NE(merged.error().message.find(c.field), std::string::npos)
            << merged.error().message;
    }
    auto none = mergeBrackets({});
    ASSERT_FALSE(none);
    EXPECT_NE(none.error().message.find("no brackets"), std::string::npos);
}

TEST(MergeBrackets, RejectsOptionsOutOfRangeNamingTheOption) {
    const std::vector<RawFrame> brackets = {frame(2, 2, 1.0)};
    const auto expectError = [&](const MergeOptions& o, const std::string& field) {
        auto merged = mergeBrackets(brackets, o);
        ASSERT_FALSE(merged) << field;
        EXPECT_NE(merged.error().message.find(field), std::string::npos) << merged.error().message;
    };
    MergeOptions o;
    o.saturation_margin_fraction = 1.0;
    expectError(o, "saturation_margin_fraction");
    o = {};
    o.min_signal_dn = -1.0;
    expectError(o, "min_signal_dn");
    o = {};
    o.fallback_electrons_per_dn = 0.0;
    expectError(o, "fallback_electrons_per_dn");
    o = {};
    o.fallback_read_noise_dn = std::numeric_limits<double>::quiet_NaN();
    expectError(o, "fallback_read_noise_dn");
    o = {};
    o.max_angle_spread_deg = -1.0;
    expectError(o, "max_angle_spread_deg");
}

TEST(MergeBrackets, RecoversAHugeDynamicRange) {
    // 16-bit converter, exposures 100x apart: 100 .. 6e8 DN/s, a range of 6e6, each value within
    // the rounding of its best bracket.
    std::vector<double> radiance;
    for (int i = 0; i <= 680; ++i) radiance.push_back(100.0 * std::pow(10.0, i / 100.0));
    const auto brackets = exposeExactly(radiance, {1e-4, 1e-2, 1.0}, 16, 0.0);
    auto merged = mergeBrackets(brackets);
    ASSERT_TRUE(merged) << merged.error().message;
    expectAllFinite(*merged);
    EXPECT_GT(radiance.back() / radiance.front(), 1e6);
    for (size_t i = 0; i < radiance.size(); ++i) {
        EXPECT_GE(merged->count[i], 1) << i;
        EXPECT_NEAR(merged->radiance[i] / radiance[i], 1.0, 5e-3) << radiance[i];
    }
}

TEST(MergeBrackets, WorksWithoutNoiseFiguresFromTheCamera) {
    std::vector<double> radiance;
    for (int i = 0; i < 4000; ++i) radiance.push_back(5.0 + 900.0 * i / 4000.0);
    auto brackets = exposeWithNoise(radiance, {0.25, 1.0, 4.0}, 3);
    auto with_figures = mergeBrackets(brackets);
    for (auto& b : brackets) b.read_noise_dn = b.electrons_per_dn = 0.0;
    auto fallback = mergeBrackets(brackets);
    ASSERT_TRUE(with_figures && fallback);
    EXPECT_NE(fallback->method.find("fallback"), std::string::npos) << fallback->method;
    double sum_with = 0.0, sum_fallback = 0.0;
    for (size_t i = 0; i < radiance.size(); ++i) {
        sum_with += std::abs(with_figures->radiance[i] - radiance[i]) / radiance[i];
        sum_fallback += std::abs(fallback->radiance[i] - radiance[i]) / radiance[i];
    }
    // The fallback model is a little off (1 e-/DN, 2 DN read noise against 2 and 2.5), which
    // costs little.
    EXPECT_LT(sum_fallback, 1.05 * sum_with);
}

TEST(MergeBrackets, NeverProducesNaNOverRandomBrackets) {
    std::mt19937_64 rng(7);
    std::uniform_int_distribution<int> dn(0, 65535), count(1, 5), depth(8, 16);
    std::uniform_real_distribution<double> log_exposure(-4.0, 0.0), unit(0.0, 1.0);
    for (int trial = 0; trial < 300; ++trial) {
        const int n = count(rng);
        const int bits = depth(rng);
        std::vector<RawFrame> brackets;
        for (int k = 0; k < n; ++k) {
            RawFrame f = frame(7, 5, std::pow(10.0, log_exposure(rng)));
            f.bit_depth = bits;
            f.white_level_dn = std::ldexp(1.0, bits) - 1.0 - std::floor(unit(rng) * 10.0);
            f.black_level_dn = std::floor(unit(rng) * f.white_level_dn * 0.5);
            f.gain = std::pow(10.0, 2.0 * unit(rng) - 1.0);
            f.read_noise_dn = unit(rng) < 0.3 ? 0.0 : 20.0 * unit(rng);
            f.electrons_per_dn = unit(rng) < 0.3 ? 0.0 : std::pow(10.0, 4.0 * unit(rng) - 2.0);
            for (auto& s : f.samples) {
                const double u = unit(rng);
                s = u < 0.1   ? 0
                    : u < 0.2 ? static_cast<uint16_t>(f.white_level_dn)
                              : static_cast<uint16_t>(dn(rng) % (1 << bits));
            }
            brackets.push_back(f);
        }
        MergeOptions o;
        o.min_signal_dn = unit(rng) < 0.5 ? 0.0 : 3.0 * unit(rng);
        o.saturation_margin_fraction = 0.2 * unit(rng);
        o.allow_avx2 = unit(rng) < 0.5;
        auto merged = mergeBrackets(brackets, o);
        ASSERT_TRUE(merged) << "trial " << trial << ": " << merged.error().message;
        expectAllFinite(*merged);
        for (const uint8_t c : merged->count) EXPECT_LE(c, n);
    }
}

TEST(MergeBrackets, BaselineAndAvx2KernelsGiveTheSameBits) {
    // Odd sizes leave partial vectors at the end of every run; the brackets cover dark, usable
    // and saturated samples.
    std::vector<double> radiance;
    for (int i = 0; i < 5003; ++i) radiance.push_back(std::pow(10.0, -1.0 + 6.0 * i / 5003.0));
    const auto brackets = exposeWithNoise(radiance, {0.25, 1.0, 4.0}, 17);
    MergeOptions baseline;
    baseline.allow_avx2 = false;
    auto fast = mergeBrackets(brackets);
    auto slow = mergeBrackets(brackets, baseline);
    ASSERT_TRUE(fast && slow);
    EXPECT_EQ(fast->radiance, slow->radiance);
    EXPECT_EQ(fast->count, slow->count);
    EXPECT_EQ(fast->saturated_samples, slow->saturated_samples);
    EXPECT_EQ(fast->dark_samples, slow->dark_samples);
    EXPECT_GT(fast->saturated_samples, 0);
    EXPECT_GT(fast->dark_samples, 0);
}

TEST(ToImage, MonoCopiesTheSampleToEveryChannel) {
    MergedFrame m;
    m.width = 3;
    m.height = 2;
    m.radiance = {0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5e9f};
    m.count.assign(6, 1);
    auto image = toImage(m);
    ASSERT_TRUE(image) << image.error().message;
    ASSERT_EQ(image->width, 3);
    ASSERT_EQ(image->height, 2);
    for (int64_t i = 0; i < 6; ++i)
        for (int c = 0; c < 3; ++c)
            EXPECT_EQ(image->pixels[static_cast<size_t>(3 * i + c)],
                      m.radiance[static_cast<size_t>(i)]);
}

TEST(ToImage, BayerDemosaicRecoversFlatColoursEverywhereForEveryPattern) {
    // Red 1, green 2, blue 3 laid out as each pattern: every pixel, the border included, must come
    // back as (1, 2, 3).
    const std::vector<std::pair<RawFormat, std::array<float, 4>>> patterns = {
        {RawFormat::BayerRGGB, {1, 2, 2, 3}},
        {RawFormat::BayerBGGR, {3, 2, 2, 1}},
        {RawFormat::BayerGRBG, {2, 1, 3, 2}},
        {RawFormat::BayerGBRG, {2, 3, 1, 2}}};
    for (const auto& [format, cell] : patterns)
        for (const auto& [w, h] :
             std::vector<std::pair<int64_t, int64_t>>{{6, 4}, {5, 7}, {2, 2}}) {
            MergedFrame m;
            m.width = w;
            m.height = h;
            m.format = format;
            for (int64_t y = 0; y < h; ++y)
                for (int64_t x = 0; x < w; ++x) m.radiance.push_back(cell[(y % 2) * 2 + x % 2]);
            auto image = toImage(m);
            ASSERT_TRUE(image) << image.error().message;
            for (int64_t y = 0; y < h; ++y)
                for (int64_t x = 0; x < w; ++x) {
                    const float* p = image->at(x, y);
                    EXPECT_EQ(p[0], 1.0f) << x << "," << y;
                    EXPECT_EQ(p[1], 2.0f) << x << "," << y;
                    EXPECT_EQ(p[2], 3.0f) << x << "," << y;
                }
        }
}

TEST(ToImage, BayerDemosaicInterpolatesALinearRampExactlyInside) {
    // A horizontal ramp in every colour: bilinear interpolation is exact for it away from the
    // border.
    MergedFrame m;
    m.width = 8;
    m.height = 6;
    m.format = RawFormat::BayerRGGB;
    for (int64_t y = 0; y < m.height; ++y)
        for (int64_t x = 0; x < m.width; ++x) m.radiance.push_back(10.0f * static_cast<float>(x));
    auto image = toImage(m);
    ASSERT_TRUE(image) << image.error().message;
    for (int64_t y = 1; y < m.height - 1; ++y)
        for (int64_t x = 1; x < m.width - 1; ++x)
            for (int c = 0; c < 3; ++c)
                EXPECT_FLOAT_EQ(image->at(x, y)[c], 10.0f * static_cast<float>(x)) << x << "," << y;
}

TEST(ToImage, RejectsBrokenFramesNamingThePixel) {
    MergedFrame m;
    m.width = 2;
    m.height = 2;
    m.radiance = {1.0f, 2.0f, 3.0f};
    auto short_frame = toImage(m);
    ASSERT_FALSE(short_frame);
    EXPECT_NE(short_frame.error().message.find("radiance.size()"), std::string::npos);
    m.radiance = {1.0f, 2.0f, -3.0f, 4.0f};
    auto negative = toImage(m);
    ASSERT_FALSE(negative);
    EXPECT_NE(negative.error().message.find("x 0, y 1"), std::string::npos)
        << negative.error().message;
    m.radiance[2] = std::numeric_limits<float>::quiet_NaN();
    EXPECT_FALSE(toImage(m));
}

TEST(LowerBounds, MarkWhatASampleSaturatedInEveryBracketReaches) {
    // Mono: the saturated sample's pixel, all three channels; a dark one (count 0, radiance 0)
    // is a measurement of black, not a bound.
    MergedFrame m;
    m.width = 3;
    m.height = 2;
    m.radiance = {1.0f, 9e9f, 2.0f, 0.0f, 4.0f, 5.0f};
    m.count = {3, 0, 2, 0, 1, 3};
    auto mono = lowerBounds(m);
    ASSERT_TRUE(mono) << mono.error().message;
    EXPECT_EQ(*mono, (std::vector<uint8_t>{0, 7, 0, 0, 0, 0}));

    // RGGB, 4 x 4, the blue sample at (1, 1) saturated: its own pixel's blue, and the blue its
    // eight neighbours average in (toImage's 3 x 3 neighbourhood); red and green nowhere.
    m = MergedFrame{};
    m.width = 4;
    m.height = 4;
    m.format = RawFormat::BayerRGGB;
    m.radiance.assign(16, 1.0f);
    m.count.assign(16, 2);
    m.count[1 * 4 + 1] = 0;
    m.radiance[1 * 4 + 1] = 7e9f;
    auto bayer = lowerBounds(m);
    ASSERT_TRUE(bayer) << bayer.error().message;
    for (int64_t y = 0; y < 4; ++y)
        for (int64_t x = 0; x < 4; ++x) {
            const bool near = std::abs(x - 1) <= 1 && std::abs(y - 1) <= 1;
            EXPECT_EQ((*bayer)[static_cast<size_t>(y * 4 + x)], near ? kLowerBoundBlue : 0)
                << x << ", " << y;
        }
    // A green sample at (2, 1): green is a bound at its own pixel and at its four edge
    // neighbours, which average it in; its diagonal neighbours are green samples of their own.
    m.count[1 * 4 + 1] = 2;
    m.radiance[1 * 4 + 1] = 1.0f;
    m.count[1 * 4 + 2] = 0;
    m.radiance[1 * 4 + 2] = 7e9f;
    bayer = lowerBounds(m);
    ASSERT_TRUE(bayer) << bayer.error().message;
    for (int64_t y = 0; y < 4; ++y)
        for (int64_t x = 0; x < 4; ++x) {
            const int64_t d = std::abs(x - 2) + std::abs(y - 1);
            EXPECT_EQ((*bayer)[static_cast<size_t>(y * 4 + x)], d <= 1 ? kLowerBoundGreen : 0)
                << x << ", " << y;
        }
    m.count.pop_back();
    EXPECT_FALSE(lowerBounds(m));
}

TEST(MergeThenToImage, BayerBracketsMergeSamplewise) {
    // The merge keeps the mosaic: a Bayer bracket merges like a mono one, then demosaics.
    RawFrame a = frame(4, 4, 1.0), b = frame(4, 4, 0.25);
    a.format = b.format = RawFormat::BayerRGGB;
    for (int64_t y = 0; y < 4; ++y)
        for (int64_t x = 0; x < 4; ++x) {
            const int colour = (y % 2) + (x % 2);  // 0 red, 1 green, 2 blue
            const double radiance = 100.0 * (colour + 1);
            a.samples[static_cast<size_t>(y * 4 + x)] = static_cast<uint16_t>(128 + radiance);
            b.samples[static_cast<size_t>(y * 4 + x)] = static_cast<uint16_t>(128 + radiance / 4);
        }
    auto merged = mergeBrackets(std::vector<RawFrame>{a, b});
    ASSERT_TRUE(merged) << merged.error().message;
    EXPECT_EQ(merged->format, RawFormat::BayerRGGB);
    auto image = toImage(*merged);
    ASSERT_TRUE(image) << image.error().message;
    for (int64_t y = 0; y < 4; ++y)
        for (int64_t x = 0; x < 4; ++x) {
            EXPECT_NEAR(image->at(x, y)[0], 100.0f, 1e-3f);
            EXPECT_NEAR(image->at(x, y)[1], 200.0f, 1e-3f);
            EXPECT_NEAR(image->at(x, y)[2], 300.0f, 1e-3f);
        }
}

}  // namespace
}  // namespace flarelab::hdr
