#include "optics/glass.h"

#include "common/units.h"

namespace flarelab::optics {

CauchyCoefficients cauchyFromAbbe(double n_d, double abbe) {
    if (abbe <= 0.0 || n_d == 1.0) return {n_d, 0.0};
    const double dn_fc = (n_d - 1.0) / abbe;
    const double inv_f2 = 1.0 / (kLambdaF_nm * kLambdaF_nm);
    const double inv_c2 = 1.0 / (kLambdaC_nm * kLambdaC_nm);
    const double b = dn_fc / (inv_f2 - inv_c2);
    const double a = n_d - b / (kLambdaD_nm * kLambdaD_nm);
    return {a, b};
}

double refractiveIndex(double n_d, double abbe, double wavelength_nm) {
    const CauchyCoefficients c = cauchyFromAbbe(n_d, abbe);
    return c.a + c.b_nm2 / (wavelength_nm * wavelength_nm);
}

}  // namespace flarelab::optics
