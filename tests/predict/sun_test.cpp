#include "predict/sun.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <string>

#include "tests/predict/test_times.h"

namespace flarelab::predict {
namespace {

using test_times::at;

using namespace std::chrono;

SunPosition sunAt(const SunSite& site, UtcInstant t, const SunTimeScale& scale = {}) {
    auto p = sunPosition(site, t, scale);
    EXPECT_TRUE(p) << formatIso8601(t) << ": " << (p ? "" : p.error().message);
    return p ? *p : SunPosition{};
}

// Site and instant of the paper's worked example (Reda & Andreas 2004, appendix).
SunSite golden() {
    SunSite s;
    s.latitude_deg = 39.742476;
    s.longitude_deg = -105.1786;
    s.elevation_m = 1830.14;
    s.pressure_mbar = 820.0;
    s.temperature_c = 11.0;
    return s;
}

double angleDifference(double a, double b) { return std::abs(std::remainder(a - b, 360.0)); }

TEST(SunPosition, ReproducesTheSpaPapersExample) {
    SunTimeScale scale;
    scale.delta_t_s = 67.0;
    scale.ut1_minus_utc_s = 0.0;
    const SunPosition p = sunAt(golden(), at(2003, 10, 17, 19, 30, 30), scale);
    // The paper prints 5 decimals; the required 0.01° is met with two orders to spare.
    EXPECT_NEAR(p.zenith_deg, 50.11162, 1e-5);
    EXPECT_NEAR(p.azimuth_deg, 194.34024, 1e-5);
    EXPECT_NEAR(p.elevation_deg, 90.0 - 50.11162, 1e-5);
    // Intermediate values of the same table.
    EXPECT_NEAR(p.right_ascension_deg, 202.22741, 1e-5);
    EXPECT_NEAR(p.declination_deg, -9.316179, 1e-6);  // δ', topocentric
    // H' = H - Δα: the table's 11.105900° less its parallax in right ascension, -0.000369°.
    EXPECT_NEAR(p.hour_angle_deg, 11.105900 + 0.000369, 1e-5);
    EXPECT_NEAR(p.distance_au, 0.9965422974, 1e-9);
    EXPECT_NEAR(p.refraction_deg, 0.016332, 1e-6);
    EXPECT_EQ(p.delta_t_s, 67.0);
}

TEST(SunPosition, EstimatedDeltaTMovesThePapersExampleByLittle) {
    const SunPosition p = sunAt(golden(), at(2003, 10, 17, 19, 30, 30));
    EXPECT_NEAR(p.delta_t_s, 64.5, 1.0);  // observed 2003: 64.5 s
    EXPECT_NEAR(p.zenith_deg, 50.11162, 1e-4);
    EXPECT_NEAR(p.azimuth_deg, 194.34024, 1e-4);
}

TEST(SunPosition, MeetsTheAlmanacsEquinoxAndSolstice) {
    // USNO: the 2024 March equinox at 03:06 UTC on 20 March, the June solstice at 20:51 UTC on
    // 20 June (rounded to the minute). The apparent right ascension is then 0° and 90°; the sun
    // gains about 0.0015° of it in 2 minutes.
    SunSite site;
    const SunPosition equinox = sunAt(site, at(2024, 3, 20, 3, 6, 0));
    EXPECT_LT(angleDifference(equinox.right_ascension_deg, 0.0), 0.0015);
    const SunPosition solstice = sunAt(site, at(2024, 6, 20, 20, 51, 0));
    EXPECT_LT(angleDifference(solstice.right_ascension_deg, 90.0), 0.0015);
    // The declination at the solstice is the obliquity of the ecliptic, 23.44° in 2024.
    EXPECT_NEAR(solstice.declination_deg, 23.44, 0.01);
}

// The smallest zenith angle over one UTC day, from a timeline at 10 s steps.
double noonZenith(const SunSite& site, UtcInstant day_start) {
    auto timeline = sunTimeline(site, day_start, day_start + hours{24}, seconds{10});
    EXPECT_TRUE(timeline) << (timeline ? "" : timeline.error().message);
    double smallest = 180.0;
    for (const SunPosition& p : timeline->positions) smallest = std::min(smallest, p.zenith_deg);
    return smallest;
}

TEST(SunPosition, NoonZenithAtSolsticeAndEquinoxFollowsTheLatitude) {
    for (const double latitude : {-33.9, 0.0, 23.44, 40.0, 51.5, 60.2}) {
        SunSite site;
        site.latitude_deg = latitude;
        EXPECT_NEAR(noonZenith(site, at(2024, 6, 20, 0, 0, 0)), std::abs(latitude - 23.44), 0.1)
            << latitude;
        // 2024-03-20 at noon on the prime meridian the declination is +0.2°.
        EXPECT_NEAR(noonZenith(site, at(2024, 3, 20, 0, 0, 0)), std::abs(latitude - 0.2), 0.1)
            << latitude;
    }
}

TEST(SunPosition, BelowTheHorizonAtMidnightAtMidLatitudes) {
    SunSite paris;
    paris.latitude_deg = 48.85;
    paris.longitude_deg = 2.35;
    // Local solar midnight at 2.35° E is 23:51 UTC: the sun 90 - 48.85 - 23.44 = 17.7° below.
    const SunPosition p = sunAt(paris, at(2024, 6, 20, 23, 51, 0));
    EXPECT_NEAR(p.zenith_deg, 90.0 + 17.71, 0.1);
    EXPECT_LT(angleDifference(p.azimuth_deg, 0.0), 1.0) << "north at midnight";
    EXPECT_EQ(p.refraction_deg, 0.0);
}

TEST(SunPosition, MidnightSunAndPolarNightAtSvalbard) {
    SunSite longyearbyen;
    longyearbyen.latitude_deg = 78.2;
    longyearbyen.longitude_deg = 15.6;
    // Local midnight at 15.6° E is 22:58 UTC: the sun 23.44 - (90 - 78.2) = 11.6° up, north.
    const SunPosition midnight = sunAt(longyearbyen, at(2024, 6, 20, 22, 58, 0));
    EXPECT_LT(midnight.zenith_deg, 90.0);
    EXPECT_NEAR(midnight.elevation_deg, 11.6, 0.15);
    EXPECT_LT(angleDifference(midnight.azimuth_deg, 0.0), 1.0);
    // Midwinter: below the horizon all day, at noon 11.6° down.
    EXPECT_NEAR(noonZenith(longyearbyen, at(2024, 12, 21, 0, 0, 0)), 90.0 + 11.6, 0.15);
}

TEST(SunPosition, AtThePolesTheElevationIsTheDeclination) {
    for (const double latitude : {90.0, -90.0}) {
        for (const double longitude : {-180.0, 0.0, 77.0, 180.0}) {
            SunSite pole;
            pole.latitude_deg = latitude;
            pole.longitude_deg = longitude;
            pole.pressure_mbar = 0.0;  // no refraction: the elevation is the bare geometry
            for (int hour = 0; hour < 24; hour += 5) {
                const SunPosition p = sunAt(pole, at(2024, 6, 20, hour, 0, 0));
                EXPECT_NEAR(p.elevation_deg, latitude > 0 ? p.declination_deg : -p.declination_deg,
                            1e-6)
                    << latitude << " " << longitude << " " << hour;
                EXPECT_GE(p.azimuth_deg, 0.0);
                EXPECT_LT(p.azimuth_deg, 360.0);
            }
        }
    }
}

TEST(SunPosition, BothSidesOfTheDateLineAgree) {
    SunSite east, west;
    east.latitude_deg = west.latitude_deg = -17.7;  // Fiji's latitude
    east.longitude_deg = 180.0;
    west.longitude_deg = -180.0;
    for (int hour = 0; hour < 24; hour += 3) {
        const SunPosition a = sunAt(east, at(2024, 1, 1, hour, 0, 0));
        const SunPosition b = sunAt(west, at(2024, 1, 1, hour, 0, 0));
        EXPECT_NEAR(a.zenith_deg, b.zenith_deg, 1e-9);
        EXPECT_LT(angleDifference(a.azimuth_deg, b.azimuth_deg), 1e-9);
    }
}

TEST(SunPosition, StaysFiniteWithTheSunAtTheZenith) {
    // The subsolar point: a site at the sun's declination and on its meridian, refined twice
    // (the topocentric declination and hour angle depend on the site a little).
    const UtcInstant t = at(2024, 6, 20, 12, 0, 0);
    SunSite site;
    site.pressure_mbar = 0.0;
    for (int i = 0; i < 3; ++i) {
        const SunPosition p = sunAt(site, t);
        site.latitude_deg += p.declination_deg - site.latitude_deg;
        site.longitude_deg = std::remainder(site.longitude_deg - p.hour_angle_deg, 360.0);
    }
    const SunPosition overhead = sunAt(site, t);
    EXPECT_LT(overhead.zenith_deg, 1e-4);
    EXPECT_TRUE(std::isfinite(overhead.azimuth_deg));
    EXPECT_GE(overhead.azimuth_deg, 0.0);
    EXPECT_LT(overhead.azimuth_deg, 360.0);
    // And from the nadir side: the antipode sees it straight down.
    SunSite antipode = site;
    antipode.latitude_deg = -site.latitude_deg;
    antipode.longitude_deg = std::remainder(site.longitude_deg + 180.0, 360.0);
    EXPECT_GT(sunAt(antipode, t).zenith_deg, 179.99);
}

TEST(SunPosition, ContinuousOverTheLastSecondsOfAYear) {
    const SunSite site = golden();
    const SunPosition before = sunAt(site, *parseIso8601("2016-12-31T23:59:59Z"));
    const SunPosition leap = sunAt(site, *parseIso8601("2016-12-31T23:59:60Z"));
    const SunPosition after = sunAt(site, *parseIso8601("2017-01-01T00:00:00Z"));
    EXPECT_EQ(leap.zenith_deg, after.zenith_deg);
    EXPECT_LT(std::abs(before.zenith_deg - after.zenith_deg), 0.005);
    EXPECT_LT(angleDifference(before.azimuth_deg, after.azimuth_deg), 0.005);
}

TEST(SunPosition, CoversTheYearsMinus2000To6000AndRefusesBeyond) {
    const SunSite site = golden();
    for (const UtcInstant t :
         {at(-2000, 1, 1, 0, 0, 0), at(-1000, 6, 21, 12, 0, 0), at(1000, 6, 21, 12, 0, 0),
          at(4000, 6, 21, 12, 0, 0), at(6000, 12, 31, 23, 59, 59)}) {
        const SunPosition p = sunAt(site, t);
        EXPECT_GE(p.zenith_deg, 0.0);
        EXPECT_LE(p.zenith_deg, 180.0);
        EXPECT_NEAR(p.distance_au, 1.0, 0.02);
        EXPECT_LT(std::abs(p.declination_deg), 24.5);
    }
    for (const UtcInstant t : {at(-2001, 12, 31, 23, 59, 59), at(6001, 1, 1, 0, 0, 0)}) {
        auto p = sunPosition(site, t);
        ASSERT_FALSE(p);
        EXPECT_EQ(p.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(p.error().message.find("-2000..6000"), std::string::npos) << p.error().message;
    }
}

TEST(SunPosition, RefusesBadInputNamingTheField) {
    const struct {
        void (*spoil)(SunSite&, SunTimeScale&);
        const char* names;
    } cases[] = {
        {[](SunSite& s, SunTimeScale&) { s.latitude_deg = 90.0001; }, "latitude"},
        {[](SunSite& s, SunTimeScale&) { s.latitude_deg = -91.0; }, "latitude"},
        {[](SunSite& s, SunTimeScale&) { s.latitude_deg = std::nan(""); }, "latitude"},
        {[](SunSite& s, SunTimeScale&) { s.longitude_deg = 180.5; }, "longitude"},
        {[](SunSite& s, SunTimeScale&) {
             s.longitude_deg = -std::numeric_limits<double>::infinity();
         },
         "longitude"},
        {[](SunSite& s, SunTimeScale&) { s.elevation_m = 1e6; }, "elevation"},
        {[](SunSite& s, SunTimeScale&) { s.elevation_m = -5000.0; }, "elevation"},
        {[](SunSite& s, SunTimeScale&) { s.pressure_mbar = -1.0; }, "pressure"},
        {[](SunSite& s, SunTimeScale&) { s.pressure_mbar = 5000.0; }, "pressure"},
        {[](SunSite& s, SunTimeScale&) { s.temperature_c = -300.0; }, "temperature"},
        {[](SunSite& s, SunTimeScale&) { s.temperature_c = 1e300 * 1e300; }, "temperature"},
        {[](SunSite&, SunTimeScale& t) { t.delta_t_s = 2e5; }, "delta T"},
        {[](SunSite&, SunTimeScale& t) { t.delta_t_s = std::nan(""); }, "delta T"},
        {[](SunSite&, SunTimeScale& t) { t.ut1_minus_utc_s = 1.5; }, "UT1 - UTC"},
    };
    for (const auto& c : cases) {
        SunSite site = golden();
        SunTimeScale scale;
        c.spoil(site, scale);
        auto p = sunPosition(site, at(2024, 1, 1, 0, 0, 0), scale);
        ASSERT_FALSE(p) << c.names;
        EXPECT_EQ(p.error().code, ErrorCode::InvalidArgument);
        EXPECT_EQ(p.error().message.rfind(c.names, 0), 0u) << p.error().message;
        auto timeline =
            sunTimeline(site, at(2024, 1, 1, 0, 0, 0), at(2024, 1, 1, 1, 0, 0), seconds{1}, scale);
        ASSERT_FALSE(timeline) << c.names;
        EXPECT_EQ(timeline.error().message, p.error().message);
    }
}

TEST(SunTimeline, MatchesThePositionAtEveryStep) {
    // Three hours at 1 s steps (the broadcast case), and two days at 67 s steps across the March
    // equinox, where the right ascension wraps from 360° to 0°.
    const struct {
        UtcInstant start;
        seconds length, step;
        int check_every;
    } cases[] = {
        {at(2003, 10, 17, 17, 0, 0), seconds{3 * 3600}, seconds{1}, 97},
        {at(2024, 3, 19, 0, 0, 0), seconds{2 * 86400}, seconds{67}, 1},
        {at(-1500, 7, 1, 0, 30, 0), seconds{86400}, seconds{600}, 1},
    };
    for (const auto& c : cases) {
        auto timeline = sunTimeline(golden(), c.start, c.start + c.length, c.step);
        ASSERT_TRUE(timeline) << timeline.error().message;
        ASSERT_EQ(timeline->positions.size(), static_cast<size_t>(c.length / c.step + 1));
        double worst = 0.0;
        for (size_t i = 0; i < timeline->positions.size(); i += c.check_every) {
            const SunPosition& fast = timeline->positions[i];
            const SunPosition exact = sunAt(golden(), timeline->instant(i));
            worst = std::max({worst, std::abs(fast.zenith_deg - exact.zenith_deg),
                              angleDifference(fast.azimuth_deg, exact.azimuth_deg),
                              angleDifference(fast.right_ascension_deg, exact.right_ascension_deg),
                              std::abs(fast.declination_deg - exact.declination_deg)});
            EXPECT_EQ(fast.delta_t_s, exact.delta_t_s);
        }
        EXPECT_LT(worst, 1e-6) << formatIso8601(c.start);
    }
}

TEST(SunTimeline, EndsOnTheLastStepThatFits) {
    auto timeline =
        sunTimeline(golden(), at(2024, 1, 1, 0, 0, 0), at(2024, 1, 1, 0, 0, 10), seconds{3});
    ASSERT_TRUE(timeline);
    EXPECT_EQ(timeline->positions.size(), 4u);  // 0, 3, 6, 9 s
    EXPECT_EQ(timeline->instant(3), at(2024, 1, 1, 0, 0, 9));
    auto single =
        sunTimeline(golden(), at(2024, 1, 1, 0, 0, 0), at(2024, 1, 1, 0, 0, 0), seconds{1});
    ASSERT_TRUE(single);
    EXPECT_EQ(single->positions.size(), 1u);
}

TEST(SunTimeline, RefusesBadSpans) {
    const UtcInstant t = at(2024, 1, 1, 0, 0, 0);
    EXPECT_FALSE(sunTimeline(golden(), t, t - seconds{1}, seconds{1}));
    EXPECT_FALSE(sunTimeline(golden(), t, t + hours{1}, seconds{0}));
    EXPECT_FALSE(sunTimeline(golden(), t, t + hours{1}, seconds{-1}));
    auto huge = sunTimeline(golden(), t, t + days{365}, microseconds{1000});
    ASSERT_FALSE(huge);
    EXPECT_NE(huge.error().message.find("more than"), std::string::npos);
    auto late = sunTimeline(golden(), at(6000, 12, 31, 0, 0, 0), at(6001, 1, 1, 1, 0, 0), hours{1});
    ASSERT_FALSE(late);
    EXPECT_NE(late.error().message.find("year 6001"), std::string::npos);
}

TEST(EstimateDeltaT, FollowsObservedValuesAndIsContinuous) {
    // Observed ΔT (IERS): 1900 -2.7 s, 1950 29.1 s, 2000 63.8 s, 2003 64.5 s, 2020 69.4 s.
    EXPECT_NEAR(estimateDeltaT(1900.0), -2.7, 1.0);
    EXPECT_NEAR(estimateDeltaT(1950.0), 29.1, 1.0);
    EXPECT_NEAR(estimateDeltaT(2000.0), 63.8, 1.0);
    EXPECT_NEAR(estimateDeltaT(2003.8), 64.5, 1.0);
    EXPECT_NEAR(estimateDeltaT(2020.0), 69.4, 3.0);
    // The pieces meet within a few seconds (-500 and 2150 are where they meet the parabola).
    for (const double y : {-500.0, 500.0, 1600.0, 1700.0, 1800.0, 1860.0, 1900.0, 1920.0, 1941.0,
                           1961.0, 1986.0, 2005.0, 2050.0, 2150.0}) {
        EXPECT_NEAR(estimateDeltaT(y - 1e-9), estimateDeltaT(y), 5.0) << y;
    }
    EXPECT_GT(estimateDeltaT(-2000.0), 40000.0);
    EXPECT_LT(estimateDeltaT(-2000.0), 100000.0);  // within what SunTimeScale accepts
    EXPECT_LT(estimateDeltaT(6000.0), 100000.0);
}

}  // namespace
}  // namespace flarelab::predict
