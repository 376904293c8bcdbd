#include "optics/fresnel.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "common/units.h"
#include "optics/glass.h"

namespace flarelab::optics {
namespace {

TEST(FresnelUncoated, NormalIncidenceOnCrownGlassReflectsFourPercent) {
    const FresnelResult f = fresnelUncoated(1.0, 1.5, 1.0);
    EXPECT_NEAR(f.reflectance, 0.04, 1e-15);
    EXPECT_NEAR(f.transmittance, 0.96, 1e-15);
}

TEST(FresnelUncoated, ReflectancePlusTransmittanceIsOneOverRandomCases) {
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> index(1.0, 2.2), cosine(0.0, 1.0);
    for (int i = 0; i < 1000000; ++i) {
        const double n1 = index(rng), n2 = index(rng), c = cosine(rng);
        const FresnelResult f = fresnelUncoated(n1, n2, c);
        ASSERT_NEAR(f.reflectance + f.transmittance, 1.0, 1e-12) << n1 << " " << n2 << " " << c;
        ASSERT_GE(f.reflectance, 0.0);
        ASSERT_LE(f.reflectance, 1.0);
    }
}

TEST(FresnelUncoated, TotalInternalReflectionReflectsEverything) {
    const double critical_cos = std::sqrt(1.0 - std::pow(1.0 / 1.5, 2));
    const FresnelResult past = fresnelUncoated(1.5, 1.0, critical_cos * 0.999);
    EXPECT_EQ(past.reflectance, 1.0);
    EXPECT_EQ(past.transmittance, 0.0);
    const FresnelResult before = fresnelUncoated(1.5, 1.0, std::min(1.0, critical_cos * 1.001));
    EXPECT_LT(before.reflectance, 1.0);
    EXPECT_NEAR(before.reflectance + before.transmittance, 1.0, 1e-12);
}

TEST(FresnelUncoated, GrazingIncidenceReflectsEverythingWithoutNaN) {
    const FresnelResult f = fresnelUncoated(1.0, 1.5, 0.0);
    EXPECT_EQ(f.reflectance, 1.0);
    EXPECT_EQ(f.transmittance, 0.0);
}

TEST(FresnelUncoated, EqualIndicesTransmitEverything) {
    const FresnelResult f = fresnelUncoated(1.5, 1.5, 0.3);
    EXPECT_NEAR(f.reflectance, 0.0, 1e-15);
    EXPECT_NEAR(f.transmittance, 1.0, 1e-12);
}

TEST(FresnelUncoated, PPolarizationVanishesAtBrewsterAngle) {
    // At Brewster's angle only s light is reflected: R = rs^2 / 2.
    const double n1 = 1.0, n2 = 1.5;
    const double theta_b = std::atan(n2 / n1);
    const double cos_i = std::cos(theta_b);
    const double cos_t = std::cos(std::asin(n1 / n2 * std::sin(theta_b)));
    const double rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
    EXPECT_NEAR(fresnelUncoated(n1, n2, cos_i).reflectance, 0.5 * rs * rs, 1e-15);
}

TEST(FresnelCoated, ReflectancePlusTransmittanceIsOneOverRandomCases) {
    std::mt19937_64 rng(11);
    std::uniform_real_distribution<double> index(1.0, 2.0), coat(1.2, 2.4), cosine(0.0, 1.0),
        thickness(0.0, 400.0), wavelength(380.0, 780.0);
    int evaluated = 0;
    for (int i = 0; i < 200000; ++i) {
        const double n1 = index(rng), nc = coat(rng), n2 = index(rng), c = cosine(rng);
        const FresnelResult f = fresnelCoated(n1, nc, thickness(rng), n2, c, wavelength(rng));
        ASSERT_NEAR(f.reflectance + f.transmittance, 1.0, 1e-12)
            << n1 << " " << nc << " " << n2 << " " << c;
        ASSERT_GE(f.reflectance, 0.0);
        ASSERT_LE(f.reflectance, 1.0 + 1e-12);
        ++evaluated;
    }
    EXPECT_EQ(evaluated, 200000);
}

TEST(FresnelCoated, FrustratedTotalReflectionInTheLayerStillConservesEnergy) {
    // Light from n1 = 1.9 at a steep angle is evanescent in a 1.38 layer but propagates in 1.7:
    // the thin layer lets part of it tunnel through.
    const double cos_i = std::cos(degToRad(50.0));
    const FresnelResult thin = fresnelCoated(1.9, 1.38, 50.0, 1.7, cos_i, 550.0);
    const FresnelResult thick = fresnelCoated(1.9, 1.38, 5000.0, 1.7, cos_i, 550.0);
    EXPECT_NEAR(thin.reflectance + thin.transmittance, 1.0, 1e-12);
    EXPECT_GT(thin.transmittance, thick.transmittance);
    EXPECT_NEAR(thick.reflectance, 1.0, 1e-9);
}

TEST(FresnelCoated, IsContinuousWhereTheLayerTurnsEvanescent) {
    // Real (propagating) and complex (evanescent) evaluations meet at the layer's critical angle.
    const double n1 = 1.9, n_coat = 1.38, n2 = 1.7;
    const double critical_cos = std::sqrt(1.0 - std::pow(n_coat / n1, 2));
    for (double thickness : {20.0, 110.0, 300.0}) {
        const FresnelResult below =
            fresnelCoated(n1, n_coat, thickness, n2, critical_cos * (1.0 + 1e-9), 550.0);
        const FresnelResult above =
            fresnelCoated(n1, n_coat, thickness, n2, critical_cos * (1.0 - 1e-9), 550.0);
        EXPECT_NEAR(below.reflectance, above.reflectance, 1e-6) << thickness;
        EXPECT_NEAR(below.transmittance, above.transmittance, 1e-6) << thickness;
    }
}

TEST(FresnelCoated, ZeroThicknessLayerIsTheBareInterface) {
    for (double c : {1.0, 0.8, 0.3, 0.05}) {
        const FresnelResult bare = fresnelUncoated(1.0, 1.62, c);
        const FresnelResult coated = fresnelCoated(1.0, 1.38, 0.0, 1.62, c, 550.0);
        EXPECT_NEAR(coated.reflectance, bare.reflectance, 1e-14) << c;
    }
}

TEST(FresnelCoated, IdealQuarterWaveCancelsReflectionAtDesignWavelength) {
    const double n2 = 1.9044;  // sqrt(n2) = 1.38: magnesium fluoride is ideal on it
    const QuarterWaveCoating coat = designQuarterWaveCoating(1.0, n2, 550.0);
    EXPECT_NEAR(coat.index, 1.38, 1e-12);
    const FresnelResult f = fresnelCoated(1.0, coat.index, coat.thickness_nm, n2, 1.0, 550.0);
    EXPECT_NEAR(f.reflectance, 0.0, 1e-15);
}

TEST(FresnelCoated, QuarterWaveOnCrownGlassBeatsBareGlassAcrossTheVisible) {
    const QuarterWaveCoating coat = designQuarterWaveCoating(1.0, 1.52, 550.0);
    for (double lambda = 420.0; lambda <= 700.0; lambda += 20.0) {
        const double coated =
            fresnelCoated(1.0, coat.index, coat.thickness_nm, 1.52, 1.0, lambda).reflectance;
        EXPECT_LT(coated, fresnelUncoated(1.0, 1.52, 1.0).reflectance) << lambda;
    }
    // MgF2 on n = 1.52 at its design wavelength: ((1.52 - 1.38^2) / (1.52 + 1.38^2))^2 = 1.26%.
    const double r_design =
        fresnelCoated(1.0, coat.index, coat.thickness_nm, 1.52, 1.0, 550.0).reflectance;
    const double expected = std::pow((1.52 - 1.38 * 1.38) / (1.52 + 1.38 * 1.38), 2);
    EXPECT_NEAR(r_design, expected, 1e-12);
}

TEST(CauchyFromAbbe, ReproducesIndexAndPrincipalDispersion) {
    for (const auto& [nd, vd] : {std::pair{1.5168, 64.17}, {1.7847, 25.68}, {1.603, 38.03}}) {
        EXPECT_NEAR(refractiveIndex(nd, vd, kLambdaD_nm), nd, 1e-14);
        const double dn =
            refractiveIndex(nd, vd, kLambdaF_nm) - refractiveIndex(nd, vd, kLambdaC_nm);
        EXPECT_NEAR(dn, (nd - 1.0) / vd, 1e-14);
        EXPECT_GT(refractiveIndex(nd, vd, 450.0), refractiveIndex(nd, vd, 650.0));
    }
}

TEST(CauchyFromAbbe, BK7StaysWithinTwoThousandthsOfItsCatalogue) {
    // Schott N-BK7 catalogue values (Sellmeier) at 435.8 and 706.5 nm.
    EXPECT_NEAR(refractiveIndex(1.5168, 64.17, 435.8343), 1.52668, 2e-3);
    EXPECT_NEAR(refractiveIndex(1.5168, 64.17, 706.5188), 1.51289, 2e-3);
}

TEST(CauchyFromAbbe, NoAbbeNumberMeansNoDispersion) {
    EXPECT_EQ(refractiveIndex(1.62, 0.0, 400.0), 1.62);
    EXPECT_EQ(refractiveIndex(1.0, 50.0, 400.0), 1.0);
}

}  // namespace
}  // namespace flarelab::optics
