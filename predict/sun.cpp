#include "predict/sun.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <span>
#include <string>

#include "common/check.h"
#include "predict/detail/spa_terms.h"

namespace flarelab::predict {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kRad = 180.0 / std::numbers::pi;

// Limits of the time scales (SunTimeScale).
constexpr double kMaxAbsDeltaT_s = 100000.0;
constexpr double kMaxAbsDut1_s = 1.0;
// The most positions one timeline may hold (72 bytes each: 720 MB).
constexpr int64_t kMaxTimelinePositions = 10'000'000;
// Geocentric nodes of a timeline, interpolated between (sunTimeline).
constexpr std::chrono::microseconds kNodeSpacing = std::chrono::hours{1};

double wrap360(double deg) {
    const double r = std::fmod(deg, 360.0);
    return r < 0.0 ? r + 360.0 : r;
}
// asin whose argument rounding may push past ±1 (the sun at the zenith, a site at a pole).
double safeAsin(double x) { return std::asin(std::clamp(x, -1.0, 1.0)); }

// Σ A cos(B + C τ) over one series (section 3.2 of the paper).
double sumSeries(std::span<const detail::PeriodicTerm> terms, double tau) {
    double sum = 0.0;
    for (const detail::PeriodicTerm& t : terms) sum += t.a * std::cos(t.b + t.c * tau);
    return sum;
}
// (S0 + S1 τ + S2 τ² + ...) / 1e8 (section 3.2), by Horner's scheme.
template <size_t N>
double evaluateSeries(const std::span<const detail::PeriodicTerm> (&series)[N], double tau) {
    double value = 0.0;
    for (size_t i = N; i-- > 0;) value = value * tau + sumSeries(series[i], tau);
    return value / 1e8;
}

// What does not depend on the site: the sun's geocentric apparent place at one TT instant.
struct Geocentric {
    double ra_deg = 0.0;                     // α, apparent right ascension (3.9)
    double dec_deg = 0.0;                    // δ, apparent declination (3.10)
    double distance_au = 0.0;                // R, from the R series (3.2)
    double equation_of_equinoxes_deg = 0.0;  // Δψ cos ε: apparent less mean sidereal time (3.8)
};

// jce: Julian ephemeris centuries from J2000.0 (TT).
Geocentric geocentricSun(double jce) {
    const double jme = jce / 10.0;  // millennia, the series' τ

    // Heliocentric longitude, latitude, radius of the Earth (section 3.2 of the paper).
    static constexpr std::span<const detail::PeriodicTerm> kL[] = {
        detail::kL0, detail::kL1, detail::kL2, detail::kL3, detail::kL4, detail::kL5};
    static constexpr std::span<const detail::PeriodicTerm> kB[] = {detail::kB0, detail::kB1};
    static constexpr std::span<const detail::PeriodicTerm> kR[] = {
        detail::kR0, detail::kR1, detail::kR2, detail::kR3, detail::kR4};
    const double l_rad = evaluateSeries(kL, jme);
    const double b_rad = evaluateSeries(kB, jme);
    const double r_au = evaluateSeries(kR, jme);

    // Geocentric: the Earth seen from the sun turned around (section 3.3), radians.
    const double theta = l_rad + std::numbers::pi;
    const double beta = -b_rad;

    // Nutation in longitude and obliquity (section 3.4): the fundamental arguments, degrees.
    const double t = jce;
    const double x[5] = {
        297.85036 + 445267.111480 * t - 0.0019142 * t * t + t * t * t / 189474.0,
        357.52772 + 35999.050340 * t - 0.0001603 * t * t - t * t * t / 300000.0,
        134.96298 + 477198.867398 * t + 0.0086972 * t * t + t * t * t / 56250.0,
        93.27191 + 483202.017538 * t - 0.0036825 * t * t + t * t * t / 327270.0,
        125.04452 - 1934.136261 * t + 0.0020708 * t * t + t * t * t / 450000.0,
    };
    double dpsi = 0.0, deps = 0.0;  // 0.0001 arcsec
    for (const detail::NutationTerm& n : detail::kNutation) {
        double arg = 0.0;
        for (int j = 0; j < 5; ++j) arg += n.y[j] * x[j];
        arg = std::fmod(arg, 360.0) * kDeg;
        dpsi += (n.a + n.b * t) * std::sin(arg);
        deps += (n.c + n.d * t) * std::cos(arg);
    }
    const double dpsi_deg = dpsi / 36e6;
    const double deps_deg = deps / 36e6;

    // True obliquity of the ecliptic (section 3.5): Laskar's polynomial in U = τ / 10, arcsec.
    const double u = jme / 10.0;
    static constexpr double kObliquity[] = {84381.448, -4680.93, -1.55, 1999.25, -51.38, -249.67,
                                            -39.05,    7.12,     27.87, 5.79,    2.45};
    double eps0_arcsec = 0.0;
    for (size_t i = std::size(kObliquity); i-- > 0;) eps0_arcsec = eps0_arcsec * u + kObliquity[i];
    const double eps = (eps0_arcsec / 3600.0 + deps_deg) * kDeg;

    // Aberration (section 3.6) and the apparent longitude (3.7).
    const double aberration_deg = -20.4898 / (3600.0 * r_au);
    const double lambda = theta + (dpsi_deg + aberration_deg) * kDeg;

    // Equatorial coordinates (sections 3.9-3.10).
    const double alpha = std::atan2(
        std::sin(lambda) * std::cos(eps) - std::tan(beta) * std::sin(eps), std::cos(lambda));
    const double delta = safeAsin(std::sin(beta) * std::cos(eps) +
                                  std::cos(beta) * std::sin(eps) * std::sin(lambda));

    Geocentric g;
    g.ra_deg = wrap360(alpha * kRad);
    g.dec_deg = delta * kRad;
    g.distance_au = r_au;
    g.equation_of_equinoxes_deg = dpsi_deg * std::cos(eps);
    return g;
}

// Mean sidereal time at Greenwich (section 3.8 of the paper), degrees in [0, 360); d: UT1 days
// since J2000.0. The 360° a day is taken out of d's fraction first, so that years far from 2000
// keep their precision.
double meanSiderealDeg(double d) {
    const double jc = d / 36525.0;
    const double whole = std::floor(d);
    const double rotation = 360.0 * (d - whole) + 0.98564736629 * d;
    return wrap360(280.46061837 + rotation + 0.000387933 * jc * jc - jc * jc * jc / 38710000.0);
}

// The site's view of a geocentric place (sections 3.9-3.14 of the paper).
SunPosition topocentric(const SunSite& site, const Geocentric& g, double apparent_sidereal_deg) {
    const double phi = site.latitude_deg * kDeg;
    const double h = wrap360(apparent_sidereal_deg + site.longitude_deg - g.ra_deg) * kDeg;
    const double delta = g.dec_deg * kDeg;

    // Parallax (section 3.12): the equatorial horizontal parallax and the site's geocentric place
    // on the ellipsoid (0.99664719 = b/a, Earth radius 6378140 m).
    const double xi = 8.794 / (3600.0 * g.distance_au) * kDeg;
    const double u = std::atan(0.99664719 * std::tan(phi));
    const double x = std::cos(u) + site.elevation_m / 6378140.0 * std::cos(phi);
    const double y = 0.99664719 * std::sin(u) + site.elevation_m / 6378140.0 * std::sin(phi);
    const double sin_xi = std::sin(xi);
    const double denominator = std::cos(delta) - x * sin_xi * std::cos(h);
    const double dalpha = std::atan2(-x * sin_xi * std::sin(h), denominator);
    const double delta_topo =
        std::atan2((std::sin(delta) - y * sin_xi) * std::cos(dalpha), denominator);
    const double h_topo = h - dalpha;

    // Elevation without refraction, then the refraction (section 3.14), where the sun's upper
    // limb is above the refracted horizon (the paper's 0.26667° radius plus 0.5667°).
    const double e0_deg = safeAsin(std::sin(phi) * std::sin(delta_topo) +
                                   std::cos(phi) * std::cos(delta_topo) * std::cos(h_topo)) *
                          kRad;
    double refraction_deg = 0.0;
    if (e0_deg >= -(0.26667 + 0.5667)) {
        refraction_deg = site.pressure_mbar / 1010.0 * 283.0 / (273.0 + site.temperature_c) * 1.02 /
                         (60.0 * std::tan((e0_deg + 10.3 / (e0_deg + 5.11)) * kDeg));
    }
    const double e_deg = e0_deg + refraction_deg;

    // Azimuth (section 3.15): the astronomers' Γ from south, turned to Φ from north.
    const double gamma = std::atan2(
        std::sin(h_topo), std::cos(h_topo) * std::sin(phi) - std::tan(delta_topo) * std::cos(phi));

    SunPosition p;
    p.elevation_deg = e_deg;
    p.zenith_deg = 90.0 - e_deg;
    p.azimuth_deg = wrap360(gamma * kRad + 180.0);
    double h_deg = wrap360(h_topo * kRad);
    if (h_deg > 180.0) h_deg -= 360.0;
    p.hour_angle_deg = h_deg;
    p.declination_deg = delta_topo * kRad;
    p.right_ascension_deg = g.ra_deg;
    p.distance_au = g.distance_au;
    p.refraction_deg = refraction_deg;
    return p;
}

Error invalid(std::string message) {
    return makeError(ErrorCode::InvalidArgument, std::move(message));
}

std::string number(double value) {
    char buffer[32];
    std::snprintf(buffer, sizeof buffer, "%.10g", value);
    return buffer;
}

Status checkRange(const char* field, double value, double low, double high, const char* unit) {
    if (!std::isfinite(value)) return invalid(std::string(field) + " is not a finite number");
    if (value < low || value > high)
        return invalid(std::string(field) + " " + number(value) + " " + unit + " is outside [" +
                       number(low) + ", " + number(high) + "]");
    return Ok{};
}

Status checkTimeScale(const SunTimeScale& scale) {
    if (scale.delta_t_s)
        if (auto s =
                checkRange("delta T", *scale.delta_t_s, -kMaxAbsDeltaT_s, kMaxAbsDeltaT_s, "s");
            !s)
            return s;
    return checkRange("UT1 - UTC", scale.ut1_minus_utc_s, -kMaxAbsDut1_s, kMaxAbsDut1_s, "s");
}

Status checkYear(UtcInstant instant) {
    const int year = calendarYear(instant);
    if (year < kSunFirstYear || year > kSunLastYear)
        return invalid("time " + formatIso8601(instant) + ": year " + std::to_string(year) +
                       " is outside the years the solar position algorithm covers (" +
                       std::to_string(kSunFirstYear) + ".." + std::to_string(kSunLastYear) + ")");
    return Ok{};
}

double decimalYear(double days_since_j2000) { return 2000.0 + days_since_j2000 / 365.2425; }

double deltaTAt(const SunTimeScale& scale, double days_since_j2000) {
    return scale.delta_t_s ? *scale.delta_t_s : estimateDeltaT(decimalYear(days_since_j2000));
}

bool finite(const SunPosition& p) {
    return std::isfinite(p.zenith_deg) && std::isfinite(p.azimuth_deg) &&
           std::isfinite(p.hour_angle_deg) && std::isfinite(p.declination_deg) &&
           std::isfinite(p.right_ascension_deg) && std::isfinite(p.distance_au);
}

Error notFinite(UtcInstant instant) {
    return makeError(ErrorCode::Internal,
                     "sun position at " + formatIso8601(instant) + " is not finite");
}

// A four-point Lagrange interpolation on a uniform grid: values at -1, 0, 1, 2, read at s in
// [0, 1].
double cubic(const double v[4], double s) {
    const double a = -s * (s - 1.0) * (s - 2.0) / 6.0;
    const double b = (s + 1.0) * (s - 1.0) * (s - 2.0) / 2.0;
    const double c = -(s + 1.0) * s * (s - 2.0) / 2.0;
    const double d = (s + 1.0) * s * (s - 1.0) / 6.0;
    return a * v[0] + b * v[1] + c * v[2] + d * v[3];
}

}  // namespace

Status checkSunSite(const SunSite& site) {
    if (auto s = checkRange("latitude", site.latitude_deg, -90.0, 90.0, "deg"); !s) return s;
    if (auto s = checkRange("longitude", site.longitude_deg, -180.0, 180.0, "deg"); !s) return s;
    if (auto s = checkRange("elevation", site.elevation_m, -1000.0, 50000.0, "m"); !s) return s;
    if (auto s = checkRange("pressure", site.pressure_mbar, 0.0, 1200.0, "mbar"); !s) return s;
    return checkRange("temperature", site.temperature_c, -100.0, 70.0, "C");
}

Result<SunPosition> sunPosition(const SunSite& site,
                                UtcInstant instant,
                                const SunTimeScale& time_scale) {
    if (auto s = checkSunSite(site); !s) return s.error();
    if (auto s = checkTimeScale(time_scale); !s) return s.error();
    if (auto s = checkYear(instant); !s) return s.error();

    const double d_utc = daysSinceJ2000(instant);
    const double d_ut1 = d_utc + time_scale.ut1_minus_utc_s / 86400.0;
    const double delta_t = deltaTAt(time_scale, d_utc);
    const double jce = (d_ut1 + delta_t / 86400.0) / 36525.0;
    const Geocentric g = geocentricSun(jce);
    SunPosition p = topocentric(site, g, meanSiderealDeg(d_ut1) + g.equation_of_equinoxes_deg);
    p.delta_t_s = delta_t;
    if (!finite(p)) return notFinite(instant);
    return p;
}

Result<SunTimeline> sunTimeline(const SunSite& site,
                                UtcInstant start,
                                UtcInstant end,
                                std::chrono::microseconds step,
                                const SunTimeScale& time_scale) {
    if (auto s = checkSunSite(site); !s) return s.error();
    if (auto s = checkTimeScale(time_scale); !s) return s.error();
    if (step.count() <= 0) return invalid("timeline step must be > 0");
    if (end < start)
        return invalid("timeline end " + formatIso8601(end) + " is before its start " +
                       formatIso8601(start));
    if (auto s = checkYear(start); !s) return s.error();
    if (auto s = checkYear(end); !s) return s.error();
    const int64_t steps = (end - start) / step;
    if (steps >= kMaxTimelinePositions)
        return invalid("timeline of " + std::to_string(steps + 1) + " positions, more than " +
                       std::to_string(kMaxTimelinePositions));

    SunTimeline timeline;
    timeline.start = start;
    timeline.step = step;
    timeline.positions.reserve(static_cast<size_t>(steps + 1));

    // Geocentric nodes every kNodeSpacing from one before the start's to two after the end's, so
    // that every sample has nodes -1, 0, 1, 2 around it. Right ascension is unwrapped so that it
    // interpolates smoothly across 0°/360°.
    const UtcInstant first_node = std::chrono::floor<std::chrono::hours>(start) - kNodeSpacing;
    const int64_t node_count = (end - first_node) / kNodeSpacing + 3;
    std::vector<Geocentric> nodes(static_cast<size_t>(node_count));
    for (int64_t k = 0; k < node_count; ++k) {
        const double d_utc = daysSinceJ2000(first_node + k * kNodeSpacing);
        const double d_ut1 = d_utc + time_scale.ut1_minus_utc_s / 86400.0;
        nodes[k] = geocentricSun((d_ut1 + deltaTAt(time_scale, d_utc) / 86400.0) / 36525.0);
        if (k > 0) {
            double& ra = nodes[k].ra_deg;
            const double previous = nodes[k - 1].ra_deg;
            ra = previous + std::remainder(ra - previous, 360.0);
        }
    }

    for (int64_t i = 0; i <= steps; ++i) {
        const UtcInstant t = start + i * step;
        const int64_t since_first = (t - first_node).count();
        const int64_t k = since_first / kNodeSpacing.count();  // node 0 of the four is k
        const double s = static_cast<double>(since_first - k * kNodeSpacing.count()) /
                         static_cast<double>(kNodeSpacing.count());
        FLARELAB_DCHECK(k >= 1 && k + 2 < node_count);
        const Geocentric* n = &nodes[static_cast<size_t>(k - 1)];
        const double ra[4] = {n[0].ra_deg, n[1].ra_deg, n[2].ra_deg, n[3].ra_deg};
        const double dec[4] = {n[0].dec_deg, n[1].dec_deg, n[2].dec_deg, n[3].dec_deg};
        const double r[4] = {n[0].distance_au, n[1].distance_au, n[2].distance_au,
                             n[3].distance_au};
        const double eq[4] = {n[0].equation_of_equinoxes_deg, n[1].equation_of_equinoxes_deg,
                              n[2].equation_of_equinoxes_deg, n[3].equation_of_equinoxes_deg};
        Geocentric g;
        g.ra_deg = wrap360(cubic(ra, s));
        g.dec_deg = cubic(dec, s);
        g.distance_au = cubic(r, s);
        g.equation_of_equinoxes_deg = cubic(eq, s);

        const double d_utc = daysSinceJ2000(t);
        const double d_ut1 = d_utc + time_scale.ut1_minus_utc_s / 86400.0;
        SunPosition p = topocentric(site, g, meanSiderealDeg(d_ut1) + g.equation_of_equinoxes_deg);
        p.delta_t_s = deltaTAt(time_scale, d_utc);
        if (!finite(p)) return notFinite(t);
        timeline.positions.push_back(p);
    }
    return timeline;
}

double estimateDeltaT(double y) {
    // Espenak & Meeus (2006), piece by piece; t in years from the piece's epoch.
    const auto parabola = [](double year) {
        const double u = (year - 1820.0) / 100.0;
        return -20.0 + 32.0 * u * u;
    };
    if (y < -500.0 || y >= 2150.0) return parabola(y);
    if (y < 500.0) {
        const double u = y / 100.0;
        return 10583.6 +
               u * (-1014.41 +
                    u * (33.78311 + u * (-5.952053 +
                                         u * (-0.1798452 + u * (0.022174192 + u * 0.0090316521)))));
    }
    if (y < 1600.0) {
        const double u = (y - 1000.0) / 100.0;
        return 1574.2 +
               u * (-556.01 +
                    u * (71.23472 + u * (0.319781 + u * (-0.8503463 +
                                                         u * (-0.005050998 + u * 0.0083572073)))));
    }
    if (y < 1700.0) {
        const double t = y - 1600.0;
        return 120.0 + t * (-0.9808 + t * (-0.01532 + t / 7129.0));
    }
    if (y < 1800.0) {
        const double t = y - 1700.0;
        return 8.83 + t * (0.1603 + t * (-0.0059285 + t * (0.00013336 - t / 1174000.0)));
    }
    if (y < 1860.0) {
        const double t = y - 1800.0;
        return 13.72 +
               t * (-0.332447 +
                    t * (0.0068612 +
                         t * (0.0041116 +
                              t * (-0.00037436 + t * (0.0000121272 +
                                                      t * (-0.0000001699 + t * 0.000000000875))))));
    }
    if (y < 1900.0) {
        const double t = y - 1860.0;
        return 7.62 + t * (0.5737 +
                           t * (-0.251754 + t * (0.01680668 + t * (-0.0004473624 + t / 233174.0))));
    }
    if (y < 1920.0) {
        const double t = y - 1900.0;
        return -2.79 + t * (1.494119 + t * (-0.0598939 + t * (0.0061966 - t * 0.000197)));
    }
    if (y < 1941.0) {
        const double t = y - 1920.0;
        return 21.20 + t * (0.84493 + t * (-0.076100 + t * 0.0020936));
    }
    if (y < 1961.0) {
        const double t = y - 1950.0;
        return 29.07 + t * (0.407 + t * (-1.0 / 233.0 + t / 2547.0));
    }
    if (y < 1986.0) {
        const double t = y - 1975.0;
        return 45.45 + t * (1.067 + t * (-1.0 / 260.0 - t / 718.0));
    }
    if (y < 2005.0) {
        const double t = y - 2000.0;
        return 63.86 + t * (0.3345 + t * (-0.060374 +
                                          t * (0.0017275 + t * (0.000651814 + t * 0.00002373599))));
    }
    if (y < 2050.0) {
        const double t = y - 2000.0;
        return 62.92 + t * (0.32217 + t * 0.005589);
    }
    return parabola(y) - 0.5628 * (2150.0 - y);
}

}  // namespace flarelab::predict
