// ============================================================================
//  flarelab optics: Fresnel reflection and single-layer anti-reflection coatings
// ============================================================================
//
// Unpolarized reflectance R and transmittance T of a smooth interface between two lossless media
// (eq. 1-2 of Bodonyi & Kunkli 2023), and of the same interface carrying one thin dielectric
// layer (a quarter-wave anti-reflection coating, as Hullin et al. 2011 model them). R and T are
// computed from independent amplitude formulas, so R + T = 1 is a check, not a definition. Past
// the critical angle (total internal reflection) R = 1 and T = 0 exactly.
#pragma once

namespace flarelab::optics {

struct FresnelResult {
    double reflectance = 0.0;
    double transmittance = 0.0;
};

// Light in medium n1 meets medium n2 at incidence cosine cos_i in [0, 1].
FresnelResult fresnelUncoated(double n1, double n2, double cos_i);

// A single layer of index n_coat and thickness d_coat_nm between media n1 and n2, for light of
// `wavelength_nm` arriving from n1 at incidence cosine cos_i. Thin-film (Airy) summation for s and
// p polarizations, averaged.
FresnelResult fresnelCoated(
    double n1, double n_coat, double d_coat_nm, double n2, double cos_i, double wavelength_nm);

// The quarter-wave layer flarelab puts on a coated surface: index max(sqrt(n1 n2), 1.38) (1.38 is
// magnesium fluoride, the lowest-index coating material in common use; sqrt(n1 n2) is the ideal
// index, reached on cemented interfaces) and physical thickness design_nm / (4 n_coat), so that it
// cancels reflection best at normal incidence and the design wavelength.
struct QuarterWaveCoating {
    double index = 1.38;
    double thickness_nm = 0.0;
};
QuarterWaveCoating designQuarterWaveCoating(double n1, double n2, double design_wavelength_nm);

}  // namespace flarelab::optics
