#include "optics/fresnel.h"

#include <algorithm>
#include <cmath>
#include <complex>

#include "common/units.h"

namespace flarelab::optics {
namespace {

using Complex = std::complex<double>;

// cos of the refraction angle in medium n_to for light from n_from at cos_i; imaginary when the
// wave is evanescent there. The branch with non-negative imaginary part decays into the medium.
Complex cosineIn(double n_from, double n_to, double cos_i) {
    const double sin_i2 = std::max(0.0, 1.0 - cos_i * cos_i);
    const double ratio = n_from / n_to;
    const Complex c2 = Complex(1.0 - ratio * ratio * sin_i2, 0.0);
    Complex c = std::sqrt(c2);
    if (c.imag() < 0.0) c = -c;
    return c;
}

struct Amplitudes {
    Complex r_s, t_s, r_p, t_p;
};

// Amplitude coefficients for the electric field (s: perpendicular, p: parallel to the plane of
// incidence), with the sign convention r_p = (n2 cos1 - n1 cos2) / (n2 cos1 + n1 cos2).
Amplitudes interfaceAmplitudes(double n1, Complex cos1, double n2, Complex cos2) {
    Amplitudes a;
    const Complex s_den = n1 * cos1 + n2 * cos2;
    const Complex p_den = n2 * cos1 + n1 * cos2;
    a.r_s = (n1 * cos1 - n2 * cos2) / s_den;
    a.t_s = 2.0 * n1 * cos1 / s_den;
    a.r_p = (n2 * cos1 - n1 * cos2) / p_den;
    a.t_p = 2.0 * n1 * cos1 / p_den;
    return a;
}

}  // namespace

FresnelResult fresnelUncoated(double n1, double n2, double cos_i) {
    cos_i = std::clamp(cos_i, 0.0, 1.0);
    const double sin_t = n1 / n2 * std::sqrt(std::max(0.0, 1.0 - cos_i * cos_i));
    if (sin_t >= 1.0) return {1.0, 0.0};  // total internal reflection
    const double cos_t = std::sqrt(std::max(0.0, 1.0 - sin_t * sin_t));
    // eq. 1 of Bodonyi & Kunkli 2023 for R; T from the transmitted amplitudes with the
    // irradiance factor n2 cos_t / (n1 cos_i), so R + T = 1 tests both.
    const double rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
    const double rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i);
    const double reflectance = 0.5 * (rs * rs + rp * rp);
    if (cos_i == 0.0) return {1.0, 0.0};  // grazing: everything is reflected
    const double ts = 2.0 * n1 * cos_i / (n1 * cos_i + n2 * cos_t);
    const double tp = 2.0 * n1 * cos_i / (n2 * cos_i + n1 * cos_t);
    const double factor = (n2 * cos_t) / (n1 * cos_i);
    const double transmittance = 0.5 * factor * (ts * ts + tp * tp);
    return {reflectance, transmittance};
}

FresnelResult fresnelCoated(
    double n1, double n_coat, double d_coat_nm, double n2, double cos_i, double wavelength_nm) {
    cos_i = std::clamp(cos_i, 0.0, 1.0);
    const double sin_i2 = std::max(0.0, 1.0 - cos_i * cos_i);
    const double ratio_2 = n1 / n2;
    const double sin_22 = ratio_2 * ratio_2 * sin_i2;  // sin^2 of the angle in n2
    if (sin_22 >= 1.0) return {1.0, 0.0};  // no propagating wave in n2: all is reflected
    if (cos_i == 0.0) return {1.0, 0.0};
    const double ratio_c = n1 / n_coat;
    const double sin_c2 = ratio_c * ratio_c * sin_i2;
    if (sin_c2 < 1.0) {
        // The wave propagates in the layer: every amplitude coefficient is real and the Airy sums
        // reduce to real formulas (no complex division, about ten times faster). Each pair of
        // coefficients shares one reciprocal of its denominator.
        const double cos_c = std::sqrt(1.0 - sin_c2);
        const double cos_2 = std::sqrt(1.0 - sin_22);
        const double phase = 4.0 * kPi * n_coat * d_coat_nm * cos_c / wavelength_nm;  // 2 delta
        const double cos_phase = std::cos(phase);
        const auto airy = [&](double r12, double r23, double t12, double t23, double& r2,
                              double& t2) {
            const double cross = 2.0 * r12 * r23 * cos_phase;
            const double inverse = 1.0 / (1.0 + r12 * r12 * r23 * r23 + cross);
            r2 = (r12 * r12 + r23 * r23 + cross) * inverse;
            t2 = (t12 * t12 * t23 * t23) * inverse;
        };
        const double a1 = n1 * cos_i, ac = n_coat * cos_c, a2 = n2 * cos_2;  // s admittances
        const double b1 = n_coat * cos_i, bc = n1 * cos_c;                   // p, first interface
        const double b2 = n2 * cos_c, bc2 = n_coat * cos_2;                  // p, second
        const double s12 = 1.0 / (a1 + ac), s23 = 1.0 / (ac + a2);
        const double p12 = 1.0 / (b1 + bc), p23 = 1.0 / (b2 + bc2);
        double rs2, ts2, rp2, tp2;
        airy((a1 - ac) * s12, (ac - a2) * s23, 2.0 * a1 * s12, 2.0 * ac * s23, rs2, ts2);
        airy((b1 - bc) * p12, (b2 - bc2) * p23, 2.0 * a1 * p12, 2.0 * ac * p23, rp2, tp2);
        const double factor = a2 / a1;
        return {0.5 * (rs2 + rp2), 0.5 * factor * (ts2 + tp2)};
    }
    // Evanescent in the layer (frustrated total reflection): the general complex form.
    const Complex cos1(cos_i, 0.0);
    const Complex cos_c = cosineIn(n1, n_coat, cos_i);  // may be evanescent (frustrated TIR)
    const Complex cos2 = cosineIn(n1, n2, cos_i);
    const Amplitudes a12 = interfaceAmplitudes(n1, cos1, n_coat, cos_c);
    const Amplitudes a23 = interfaceAmplitudes(n_coat, cos_c, n2, cos2);
    // Phase thickness of the layer; imaginary for an evanescent wave (it then attenuates).
    const Complex delta = 2.0 * kPi * n_coat * d_coat_nm * cos_c / wavelength_nm;
    const Complex e1 = std::exp(Complex(0.0, 1.0) * delta);
    const Complex e2 = e1 * e1;
    const auto airy_r = [&](Complex r12, Complex r23) {
        return (r12 + r23 * e2) / (1.0 + r12 * r23 * e2);
    };
    const auto airy_t = [&](Complex r12, Complex r23, Complex t12, Complex t23) {
        return t12 * t23 * e1 / (1.0 + r12 * r23 * e2);
    };
    const Complex r_s = airy_r(a12.r_s, a23.r_s);
    const Complex r_p = airy_r(a12.r_p, a23.r_p);
    const Complex t_s = airy_t(a12.r_s, a23.r_s, a12.t_s, a23.t_s);
    const Complex t_p = airy_t(a12.r_p, a23.r_p, a12.t_p, a23.t_p);
    const double reflectance = 0.5 * (std::norm(r_s) + std::norm(r_p));
    const double factor = (n2 * cos2.real()) / (n1 * cos_i);
    const double transmittance = 0.5 * factor * (std::norm(t_s) + std::norm(t_p));
    return {reflectance, transmittance};
}

QuarterWaveCoating designQuarterWaveCoating(double n1, double n2, double design_wavelength_nm) {
    QuarterWaveCoating coating;
    coating.index = std::max(std::sqrt(n1 * n2), 1.38);
    coating.thickness_nm = design_wavelength_nm / (4.0 * coating.index);
    return coating;
}

}  // namespace flarelab::optics
