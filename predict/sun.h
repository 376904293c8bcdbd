// ============================================================================
//  flarelab predict: SunSite, SunPosition, sunPosition, sunTimeline, estimateDeltaT
// ============================================================================
//
// The sun's topocentric position (zenith and azimuth as an observer at a site sees it, with
// atmospheric refraction) for any UTC instant of the years -2000..6000, by NREL's Solar Position
// Algorithm: Reda & Andreas, "Solar position algorithm for solar radiation applications", NREL
// technical report TP-560-34302 (2004, revised 2008); "the paper" below. Its stated uncertainty is
// ±0.0003° over those years; flarelab reproduces the paper's worked example (its appendix) to
// better than 1e-5° (tests/predict/sun_test.cpp). Why SPA and not libnova: docs/sun.md.
//
// Angles are degrees at this interface (DESIGN.md), radians inside sun.cpp.
#pragma once

#include <chrono>
#include <optional>
#include <vector>

#include "common/result.h"
#include "predict/utc_time.h"

namespace flarelab::predict {

// The years the paper states the algorithm for; instants outside are refused.
inline constexpr int kSunFirstYear = -2000;
inline constexpr int kSunLastYear = 6000;

struct SunSite {
    double latitude_deg = 0.0;   // geodetic, north positive, [-90, 90]
    double longitude_deg = 0.0;  // east positive, [-180, 180]
    double elevation_m = 0.0;    // above mean sea level, [-1000, 50000]
    // For the refraction only: the site's (annual mean) pressure and temperature. Pressure 0
    // means no atmosphere (no refraction). Ranges: [0, 1200] mbar, [-100, 70] °C.
    double pressure_mbar = 1013.25;
    double temperature_c = 12.0;
};

// Time scales. The ephemeris runs on TT = UT1 + ΔT, the Earth's rotation on UT1 = UTC + DUT1.
struct SunTimeScale {
    // ΔT = TT - UT1 in seconds, |ΔT| <= 100000; none: estimateDeltaT of the instant's year. For
    // a recent instant the error of the estimate (a few seconds) moves the sun by under 0.0001°;
    // millennia away ΔT is known to minutes at best (about 0.001° a minute).
    std::optional<double> delta_t_s;
    // DUT1 = UT1 - UTC in seconds, |DUT1| < 1 (IERS Bulletin A); 0 is at most 0.004° off.
    double ut1_minus_utc_s = 0.0;
};

struct SunPosition {
    double zenith_deg = 0.0;           // topocentric, refraction included, [0, 180]
    double azimuth_deg = 0.0;          // eastward from north, [0, 360), as the paper's Φ
    double elevation_deg = 0.0;        // 90 - zenith_deg
    double hour_angle_deg = 0.0;       // topocentric local hour angle, (-180, 180], < 0 before noon
    double declination_deg = 0.0;      // topocentric
    double right_ascension_deg = 0.0;  // geocentric apparent, [0, 360)
    double distance_au = 0.0;          // Earth to sun
    double refraction_deg = 0.0;       // what refraction added to the elevation (0 below -0.83°)
    double delta_t_s = 0.0;            // the ΔT the position was computed with
};

// Checks a site's fields: in range and finite; the error names the field.
Status checkSunSite(const SunSite& site);

// The sun at one instant. Errors (InvalidArgument): a site field out of range or not finite
// (checkSunSite), ΔT or DUT1 out of range, an instant outside the years -2000..6000.
Result<SunPosition> sunPosition(const SunSite& site,
                                UtcInstant instant,
                                const SunTimeScale& time_scale = {});

// The sun at start, start + step, ... up to and including end where a step lands on it.
struct SunTimeline {
    UtcInstant start;
    std::chrono::microseconds step{0};
    std::vector<SunPosition> positions;  // positions[i] is at start + i * step

    UtcInstant instant(size_t i) const { return start + static_cast<int64_t>(i) * step; }
};

// The same positions as sunPosition at every step (within 1e-6°), fast: the geocentric part (the
// periodic series, nutation, aberration) is evaluated every hour and interpolated (cubic
// Lagrange); the Earth's rotation, parallax and refraction at every step. Errors as sunPosition's,
// and for end before start, a step <= 0, or more than 10 million positions.
Result<SunTimeline> sunTimeline(const SunSite& site,
                                UtcInstant start,
                                UtcInstant end,
                                std::chrono::microseconds step,
                                const SunTimeScale& time_scale = {});

// ΔT = TT - UT1 in seconds for a decimal year: the polynomials of Espenak & Meeus (NASA's "Five
// Millennium Canon of Solar Eclipses", 2006) for -500..2150, and Morrison & Stephenson's parabola
// -20 + 32 u², u = (year - 1820) / 100, outside. Observed values differ by a few seconds since
// 1900 (the 2024 estimate is 5 s high); pass the IERS value in SunTimeScale where it matters.
double estimateDeltaT(double decimal_year);

}  // namespace flarelab::predict
