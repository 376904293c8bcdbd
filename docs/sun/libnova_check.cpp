// The measurement behind docs/sun.md's choice of SPA over libnova: libnova 0.16's solar position,
// with its parallax and refraction, against the SPA paper's test case (Reda & Andreas 2004,
// appendix). Not part of the build; with libnova-dev installed:
//   g++ -O2 -std=c++20 docs/sun/libnova_check.cpp -lnova -o /tmp/libnova_check &&
//   /tmp/libnova_check
#include <libnova/libnova.h>

#include <cmath>
#include <cstdio>

int main() {
    // 2003-10-17 12:30:30 at UTC-7 = 19:30:30 UTC; Golden, Colorado.
    ln_date date{2003, 10, 17, 19, 30, 30.0};
    const double jd_ut = ln_get_julian_day(&date);
    const double delta_t_s = 67.0;                 // the paper's TT - UT1
    ln_lnlat_posn observer{-105.1786, 39.742476};  // libnova: east-positive longitude
    const double elevation_m = 1830.14, pressure_mbar = 820.0, temperature_c = 11.0;
    const double want_zenith = 50.11162, want_azimuth = 194.34024;

    // Variant 1: the ephemeris at UT (libnova's solar functions take whatever JD they get);
    // variant 2: at TT = UT + delta T, as the ephemeris is meant to be read; variant 3: libnova's
    // own delta T table (ln_get_jde).
    const double jds[3] = {jd_ut, jd_ut + delta_t_s / 86400.0, ln_get_jde(jd_ut)};
    const char* names[3] = {"JD = UT", "JD = UT + 67 s", "JD = ln_get_jde(UT)"};
    for (int i = 0; i < 3; ++i) {
        ln_equ_posn sun{};
        ln_get_solar_equ_coords(jds[i], &sun);
        const double distance_au = ln_get_earth_solar_dist(jds[i]);
        ln_equ_posn shift{};
        ln_get_parallax(&sun, distance_au, &observer, elevation_m, jd_ut, &shift);
        ln_equ_posn topo{sun.ra + shift.ra, sun.dec + shift.dec};
        ln_hrz_posn hrz{};
        ln_get_hrz_from_equ(&topo, &observer, jd_ut, &hrz);  // hour angle from UT
        const double alt = hrz.alt + ln_get_refraction_adj(hrz.alt, pressure_mbar, temperature_c);
        const double zenith = 90.0 - alt;
        const double azimuth = std::fmod(hrz.az + 180.0, 360.0);  // libnova: 0 = south
        std::printf("%-22s zenith %.5f (err %+.5f)  azimuth %.5f (err %+.5f)  libnova dT %.1f s\n",
                    names[i], zenith, zenith - want_zenith, azimuth, azimuth - want_azimuth,
                    ln_get_dynamical_time_diff(jd_ut));
    }
}
