// ============================================================================
//  flarelab common: units and physical constants
// ============================================================================
//
// Millimetres for optics, nanometres for wavelengths, degrees wherever a person reads or types
// an angle, radians inside math. The conversions live here so that no file carries its own pi.
#pragma once

#include <numbers>

namespace flarelab {

inline constexpr double kPi = std::numbers::pi;

constexpr double degToRad(double deg) { return deg * (kPi / 180.0); }
constexpr double radToDeg(double rad) { return rad * (180.0 / kPi); }

// Fraunhofer lines that define n_d and the Abbe number V_d = (n_d - 1) / (n_F - n_C).
inline constexpr double kLambdaD_nm = 587.5618;  // helium d line
inline constexpr double kLambdaF_nm = 486.1327;  // hydrogen F line
inline constexpr double kLambdaC_nm = 656.2725;  // hydrogen C line

// The wavelengths the renderer samples for its red, green and blue channels.
inline constexpr double kLambdaRed_nm = 650.0;
inline constexpr double kLambdaGreen_nm = 550.0;
inline constexpr double kLambdaBlue_nm = 450.0;

}  // namespace flarelab
