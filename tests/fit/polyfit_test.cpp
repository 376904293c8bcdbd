#include "fit/polyfit.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <vector>

namespace flarelab::fit {
namespace {

std::vector<double> linspace(double a, double b, int n) {
    std::vector<double> out(n);
    for (int i = 0; i < n; ++i) out[i] = n == 1 ? a : a + (b - a) * i / (n - 1);
    return out;
}

// A polynomial in monomial form on t, the test's own truth.
double horner(const std::vector<double>& c, double t) {
    double v = 0.0;
    for (auto it = c.rbegin(); it != c.rend(); ++it) v = v * t + *it;
    return v;
}

TEST(ChebyshevValue, MatchesExplicitPolynomials) {
    const std::vector<double> c = {0.5, -1.0, 2.0, 0.25};  // 0.5 T0 - T1 + 2 T2 + 0.25 T3
    for (const double x : linspace(-1.0, 1.0, 21)) {
        const double expected = 0.5 - x + 2.0 * (2 * x * x - 1) + 0.25 * (4 * x * x * x - 3 * x);
        EXPECT_NEAR(chebyshevValue(c, x), expected, 1e-14);
        const double slope = -1.0 + 8.0 * x + 0.25 * (12 * x * x - 3);
        EXPECT_NEAR(chebyshevValue(chebyshevDerivative(c), x), slope, 1e-13);
    }
    EXPECT_EQ(chebyshevValue({}, 0.3), 0.0);
    EXPECT_TRUE(chebyshevDerivative(std::vector<double>{3.0}).empty());
}

TEST(FitPolynomial, RecoversPolynomialOfEachDegreeExactly) {
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> coef(-1.0, 1.0);
    for (int d = 0; d <= 8; ++d) {
        std::vector<double> c(d + 1);
        for (double& v : c) v = coef(rng);
        const std::vector<double> angles = linspace(0.0, 30.0, 31);
        std::vector<double> values;
        for (const double a : angles) values.push_back(horner(c, (a - 15.0) / 15.0));
        PolyFitOptions options;
        options.fixed_degree = d;
        const Result<PolyFit> fit = fitPolynomial(angles, values, options);
        ASSERT_TRUE(fit) << fit.error().message;
        ASSERT_EQ(fit->pieces.size(), 1u);
        EXPECT_EQ(fit->pieces[0].degree(), d);
        EXPECT_LT(fit->max_abs_residual, 1e-12);
        for (const double a : linspace(0.0, 30.0, 97)) {
            EXPECT_NEAR(*evaluatePolyFit(*fit, a), horner(c, (a - 15.0) / 15.0), 1e-12);
            // Slope against the monomial derivative, per degree.
            double slope = 0.0;
            for (int k = 1; k <= d; ++k) slope += k * c[k] * std::pow((a - 15.0) / 15.0, k - 1);
            EXPECT_NEAR(*evaluatePolyFitSlope(*fit, a), slope / 15.0, 1e-11);
        }
        // Cross-validation finds the degree too (exact data: no lower degree is within 1 SE).
        const Result<PolyFit> chosen = fitPolynomial(angles, values);
        ASSERT_TRUE(chosen);
        ASSERT_EQ(chosen->pieces.size(), 1u);
        EXPECT_EQ(chosen->pieces[0].degree(), d);
        EXPECT_LT(chosen->max_abs_residual, 1e-12);
    }
}

TEST(FitPolynomial, NoisyLineChoosesLowDegree) {
    for (int seed = 0; seed < 10; ++seed) {
        std::mt19937_64 rng(seed);
        std::normal_distribution<double> noise(0.0, 0.05);
        const std::vector<double> angles = linspace(0.0, 30.0, 61);
        std::vector<double> values;
        for (const double a : angles) values.push_back(0.3 + 0.02 * a + noise(rng));
        const Result<PolyFit> fit = fitPolynomial(angles, values);
        ASSERT_TRUE(fit);
        ASSERT_EQ(fit->pieces.size(), 1u) << "seed " << seed;
        EXPECT_LE(fit->pieces[0].degree(), 2) << "seed " << seed;
        EXPECT_NEAR(fit->noise_estimate, 0.05, 0.02);
        EXPECT_NEAR(*evaluatePolyFit(*fit, 15.0), 0.6, 0.05);
        ASSERT_TRUE(fit->pieces[0].held_out_rms);
        EXPECT_NEAR(*fit->pieces[0].held_out_rms, 0.05, 0.025);
    }
}

// Frames missing from a sweep leave a gap in a track's samples. The interleaved folds hold out
// samples, never the inside of the gap, so a degree that swings there scored as well as any; the
// gap's own folds (the samples next to it held out) judge how a degree predicts across it
// (polyfit.h). A smooth parameter sampled like a sweep with 2.0 .. 3.5 deg missing (the sweep
// fit's gap test), noise 0.02: inside the gap the fit stays within 0.1 of the truth for every
// seed (without the gap's folds, degrees 6 and 7 were chosen for a few seeds, 0.18 off).
TEST(FitPolynomial, NoSwingInsideAGapOfMissingSamples) {
    const std::vector<double> angles = {0.0, 0.5, 1.0, 1.5, 4.0, 4.5, 5.0, 5.5, 6.0};
    const auto truth = [](double a) { return 1.0 + 0.1 * a + 0.02 * a * a; };
    double worst = 0.0;
    for (int seed = 0; seed < 200; ++seed) {
        std::mt19937_64 rng(seed);
        std::normal_distribution<double> noise(0.0, 0.02);
        std::vector<double> values;
        for (const double a : angles) values.push_back(truth(a) + noise(rng));
        const Result<PolyFit> fit = fitPolynomial(angles, values);
        ASSERT_TRUE(fit);
        for (const double a : linspace(1.5, 4.0, 26)) {
            const double error = std::abs(*evaluatePolyFit(*fit, a) - truth(a));
            worst = std::max(worst, error);
            EXPECT_LT(error, 0.1) << "seed " << seed << ", " << a << " deg, degree "
                                  << fit->pieces[0].degree() << " pieces " << fit->pieces.size();
        }
    }
    std::printf("largest error inside the gap: %.4f (noise 0.02)\n", worst);
}

// An exact polynomial across a gap is still found at its own degree when it does not swing
// beyond its neighbours there (a parabola whose turn lies outside the gap).
TEST(FitPolynomial, AnExactCurveAcrossAGapKeepsItsDegree) {
    const std::vector<double> angles = {0.0, 0.5, 1.0, 1.5, 4.0, 4.5, 5.0, 5.5, 6.0};
    std::vector<double> values;
    for (const double a : angles) values.push_back(2.0 - 0.3 * a + 0.05 * a * a * a);
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    ASSERT_EQ(fit->pieces.size(), 1u);
    EXPECT_EQ(fit->pieces[0].degree(), 3);
    EXPECT_NEAR(*evaluatePolyFit(*fit, 2.75), 2.0 - 0.3 * 2.75 + 0.05 * std::pow(2.75, 3), 1e-9);
}

TEST(FitPolynomial, MaxDegreeIsCappedByTheData) {
    // max_degree is a ceiling: 5 samples, leave-one-out, so at most degree 3 is tried.
    const std::vector<double> angles = {0.0, 1.0, 2.0, 3.0, 4.0};
    std::vector<double> values;
    for (const double a : angles) values.push_back(std::cos(a));
    PolyFitOptions options;
    options.max_degree = 20;
    const Result<PolyFit> fit = fitPolynomial(angles, values, options);
    ASSERT_TRUE(fit);
    EXPECT_LE(fit->pieces[0].degree(), 3);
}

TEST(FitPolynomial, FixedDegreeAboveSampleCountIsRefused) {
    const std::vector<double> angles = {0.0, 1.0, 2.0};
    const std::vector<double> values = {1.0, 2.0, 0.0};
    PolyFitOptions options;
    options.fixed_degree = 3;
    const Result<PolyFit> fit = fitPolynomial(angles, values, options);
    ASSERT_FALSE(fit);
    EXPECT_EQ(fit.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(fit.error().message.find("fixed_degree"), std::string::npos);
    options.fixed_degree = 2;  // interpolation is allowed when asked for
    const Result<PolyFit> exact = fitPolynomial(angles, values, options);
    ASSERT_TRUE(exact);
    EXPECT_NEAR(*evaluatePolyFit(*exact, 2.0), 0.0, 1e-14);
}

TEST(FitPolynomial, TinySpanAtHugeOffsetStaysAccurate) {
    // 1e6 deg plus a span of 1e-6 deg: monomials in the angle would be hopeless, the normalized
    // Chebyshev basis sees an ordinary interval.
    const double base = 1e6;
    std::vector<double> angles;
    for (int i = 0; i <= 20; ++i) angles.push_back(base + i * 5e-8);
    const std::vector<double> c = {1.0, -2.0, 0.5, 3.0};
    std::vector<double> values;
    const double lo = angles.front();
    const double span = angles.back() - lo;
    for (const double a : angles) values.push_back(horner(c, (a - lo) / span));
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit) << fit.error().message;
    ASSERT_EQ(fit->pieces.size(), 1u);
    EXPECT_EQ(fit->pieces[0].degree(), 3);
    EXPECT_LT(fit->max_abs_residual, 1e-11);
    EXPECT_NEAR(*evaluatePolyFit(*fit, angles[7]), values[7], 1e-11);

    // The same near 0: a span of 1e-6 deg.
    std::vector<double> small;
    for (const double a : angles) small.push_back(a - base);
    const Result<PolyFit> fit_small = fitPolynomial(small, values);
    ASSERT_TRUE(fit_small);
    EXPECT_LT(fit_small->max_abs_residual, 1e-11);
}

TEST(FitPolynomial, StepSplitsIntoPieces) {
    std::mt19937_64 rng(3);
    std::normal_distribution<double> noise(0.0, 1e-3);
    const std::vector<double> angles = linspace(0.0, 30.0, 151);
    std::vector<double> values;
    for (const double a : angles) values.push_back((a < 12.1 ? 1.0 : 2.0) + noise(rng));
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    ASSERT_GE(fit->pieces.size(), 2u);
    // The cut falls at the step: a knot between the samples at 12.0 and 12.2 deg.
    bool knot_at_step = false;
    for (size_t i = 0; i + 1 < fit->pieces.size(); ++i) {
        EXPECT_EQ(fit->pieces[i].angle_max_deg, fit->pieces[i + 1].angle_min_deg);
        if (std::abs(fit->pieces[i].angle_max_deg - 12.1) < 1e-9) knot_at_step = true;
    }
    EXPECT_TRUE(knot_at_step);
    EXPECT_LT(fit->max_abs_residual, 0.01);
    EXPECT_NEAR(*evaluatePolyFit(*fit, 5.0), 1.0, 0.005);
    EXPECT_NEAR(*evaluatePolyFit(*fit, 20.0), 2.0, 0.005);
}

TEST(FitPolynomial, KinkSplitsIntoPieces) {
    const std::vector<double> angles = linspace(0.0, 30.0, 151);
    std::vector<double> values;
    for (const double a : angles) values.push_back(std::abs(a - 17.0));
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    EXPECT_GE(fit->pieces.size(), 2u);
    EXPECT_LT(fit->max_abs_residual, 1e-6);
    EXPECT_NEAR(*evaluatePolyFit(*fit, 3.0), 14.0, 1e-6);
}

TEST(FitPolynomial, PiecesCanBeTurnedOff) {
    const std::vector<double> angles = linspace(0.0, 30.0, 151);
    std::vector<double> values;
    for (const double a : angles) values.push_back(a < 12.1 ? 1.0 : 2.0);
    PolyFitOptions options;
    options.allow_pieces = false;
    const Result<PolyFit> fit = fitPolynomial(angles, values, options);
    ASSERT_TRUE(fit);
    EXPECT_EQ(fit->pieces.size(), 1u);
}

TEST(FitPolynomial, ThreeSamples) {
    const std::vector<double> angles = {0.0, 10.0, 20.0};
    const std::vector<double> values = {1.0, 2.0, 3.0};
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    ASSERT_EQ(fit->pieces.size(), 1u);
    EXPECT_LE(fit->pieces[0].degree(), 1);  // leave-one-out can test degree 1 at most
    EXPECT_NEAR(*evaluatePolyFit(*fit, 5.0), 1.5, 1e-12);
    EXPECT_NEAR(*evaluatePolyFitSlope(*fit, 5.0), 0.1, 1e-12);
}

TEST(FitPolynomial, OneSampleIsAConstantAtItsAngle) {
    const std::vector<double> angles = {4.0};
    const std::vector<double> values = {2.5};
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    ASSERT_EQ(fit->pieces.size(), 1u);
    EXPECT_EQ(fit->pieces[0].degree(), 0);
    EXPECT_EQ(*evaluatePolyFit(*fit, 4.0), 2.5);
    EXPECT_EQ(*evaluatePolyFitSlope(*fit, 4.0), 0.0);
    EXPECT_FALSE(evaluatePolyFit(*fit, 4.1));
}

TEST(FitPolynomial, TwoSamplesGiveTheLineThroughThem) {
    const std::vector<double> angles = {1.0, 3.0};
    const std::vector<double> values = {1.0, 5.0};
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    EXPECT_NEAR(*evaluatePolyFit(*fit, 2.0), 3.0, 1e-14);
}

TEST(FitPolynomial, WeightsFavourTrustedSamples) {
    const std::vector<double> angles = {0.0, 1.0, 2.0, 3.0};
    const std::vector<double> values = {0.0, 0.0, 0.0, 1.0};
    const std::vector<double> weights = {1.0, 1.0, 1.0, 1e-9};
    PolyFitOptions options;
    options.fixed_degree = 1;
    const Result<PolyFit> fit = fitPolynomial(angles, values, options, weights);
    ASSERT_TRUE(fit);
    EXPECT_NEAR(*evaluatePolyFit(*fit, 1.0), 0.0, 1e-6);
}

TEST(FitPolynomial, RefusesBadInputNamingTheField) {
    const auto message = [](const Result<PolyFit>& r) {
        return r ? std::string("(no error)") : r.error().message;
    };
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const double inf = std::numeric_limits<double>::infinity();
    const std::vector<double> none;
    EXPECT_NE(message(fitPolynomial(none, none)).find("angles_deg"), std::string::npos);
    const std::vector<double> a = {0.0, 1.0, 2.0};
    const std::vector<double> v = {0.0, 1.0, 2.0};
    const std::vector<double> v_nan = {0.0, nan, 2.0};
    EXPECT_NE(message(fitPolynomial(a, v_nan)).find("values[1]"), std::string::npos);
    const std::vector<double> a_inf = {0.0, 1.0, inf};
    EXPECT_NE(message(fitPolynomial(a_inf, v)).find("angles_deg[2]"), std::string::npos);
    const std::vector<double> a_dup = {0.0, 1.0, 1.0};
    EXPECT_NE(message(fitPolynomial(a_dup, v)).find("angles_deg[2]"), std::string::npos);
    const std::vector<double> a_down = {2.0, 1.0, 0.0};
    EXPECT_NE(message(fitPolynomial(a_down, v)).find("angles_deg[1]"), std::string::npos);
    const std::vector<double> a_wide = {-1.7e308, 0.0, 1.7e308};
    EXPECT_NE(message(fitPolynomial(a_wide, v)).find("range"), std::string::npos);
    const std::vector<double> short_v = {0.0, 1.0};
    EXPECT_NE(message(fitPolynomial(a, short_v)).find("values"), std::string::npos);
    const std::vector<double> w_zero = {1.0, 0.0, 1.0};
    EXPECT_NE(message(fitPolynomial(a, v, {}, w_zero)).find("weights[1]"), std::string::npos);
    PolyFitOptions bad;
    bad.max_degree = -1;
    EXPECT_NE(message(fitPolynomial(a, v, bad)).find("max_degree"), std::string::npos);
    bad = {};
    bad.cv_folds = 1;
    EXPECT_NE(message(fitPolynomial(a, v, bad)).find("cv_folds"), std::string::npos);
    bad = {};
    bad.split_factor = nan;
    EXPECT_NE(message(fitPolynomial(a, v, bad)).find("split_factor"), std::string::npos);
    bad = {};
    bad.min_samples_per_piece = 1;
    EXPECT_NE(message(fitPolynomial(a, v, bad)).find("min_samples_per_piece"), std::string::npos);
}

TEST(EvaluatePolyFit, OutsideTheValidRangeIsAnError) {
    const std::vector<double> angles = linspace(2.0, 8.0, 7);
    std::vector<double> values;
    for (const double a : angles) values.push_back(a * a);
    const Result<PolyFit> fit = fitPolynomial(angles, values);
    ASSERT_TRUE(fit);
    EXPECT_TRUE(evaluatePolyFit(*fit, 2.0));  // the ends are inside
    EXPECT_TRUE(evaluatePolyFit(*fit, 8.0));
    const Result<double> below = evaluatePolyFit(*fit, 1.999);
    ASSERT_FALSE(below);
    EXPECT_EQ(below.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(below.error().message.find("angle_deg"), std::string::npos);
    EXPECT_FALSE(evaluatePolyFit(*fit, 8.001));
    EXPECT_FALSE(evaluatePolyFitSlope(*fit, 9.0));
    EXPECT_FALSE(evaluatePolyFit(*fit, std::numeric_limits<double>::quiet_NaN()));
}

}  // namespace
}  // namespace flarelab::fit
