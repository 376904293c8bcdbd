// ============================================================================
//  flarelab optics: glass dispersion
// ============================================================================
//
// A lens file gives each medium as (n_d, V_d). We turn that into n(lambda) with the two-term
// Cauchy formula n(lambda) = A + B / lambda^2, fitted so that it reproduces n_d at the d line
// (587.56 nm) and the principal dispersion n_F - n_C = (n_d - 1) / V_d between the F (486.13 nm)
// and C (656.27 nm) lines. Cauchy is exact at those three constraints and within a few 1e-4 of
// catalogue Sellmeier curves across 400-700 nm for ordinary crown and flint glasses; it is the
// usual choice when only n_d and V_d are known (Hullin et al. 2011 do the same).
#pragma once

namespace flarelab::optics {

struct CauchyCoefficients {
    double a = 1.0;
    double b_nm2 = 0.0;  // nm^2
};

// V_d <= 0 (or n_d == 1) means "no dispersion": n(lambda) = n_d.
CauchyCoefficients cauchyFromAbbe(double n_d, double abbe);

// Refractive index at `wavelength_nm` (> 0).
double refractiveIndex(double n_d, double abbe, double wavelength_nm);

}  // namespace flarelab::optics
