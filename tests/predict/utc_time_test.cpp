#include "predict/utc_time.h"

#include <gtest/gtest.h>

#include <chrono>
#include <string>

#include "tests/predict/test_times.h"

namespace flarelab::predict {
namespace {

using test_times::at;

using namespace std::chrono;

UtcInstant parsed(const std::string& text) {
    auto r = parseIso8601(text);
    EXPECT_TRUE(r) << text << ": " << (r ? "" : r.error().message);
    return r ? *r : UtcInstant{};
}

TEST(ParseIso8601, ReadsOffsetsAsUtc) {
    EXPECT_EQ(parsed("2003-10-17T12:30:30-07:00"), at(2003, 10, 17, 19, 30, 30));
    EXPECT_EQ(parsed("2003-10-17T19:30:30Z"), at(2003, 10, 17, 19, 30, 30));
    EXPECT_EQ(parsed("2024-06-21T05:30:00+05:30"), at(2024, 6, 21, 0, 0, 0));
    EXPECT_EQ(parsed("2024-06-21T00:00:00-00:00"), at(2024, 6, 21, 0, 0, 0));
    // An offset that moves the instant into the previous year.
    EXPECT_EQ(parsed("2024-01-01T01:00:00+02:00"), at(2023, 12, 31, 23, 0, 0));
}

TEST(ParseIso8601, KeepsFractionsToTheMicrosecond) {
    EXPECT_EQ(parsed("2024-06-21T00:00:00.5Z"), at(2024, 6, 21, 0, 0, 0, 500000));
    EXPECT_EQ(parsed("2024-06-21T00:00:00,25Z"), at(2024, 6, 21, 0, 0, 0, 250000));
    EXPECT_EQ(parsed("2024-06-21T00:00:00.123456Z"), at(2024, 6, 21, 0, 0, 0, 123456));
    EXPECT_EQ(parsed("2024-06-21T00:00:00.123456789Z"), at(2024, 6, 21, 0, 0, 0, 123456));
}

TEST(ParseIso8601, ReadsALeapSecondAsTheMidnightAfterIt) {
    EXPECT_EQ(parsed("2016-12-31T23:59:60Z"), at(2017, 1, 1, 0, 0, 0));
    EXPECT_EQ(parsed("2016-12-31T15:59:60-08:00"), at(2017, 1, 1, 0, 0, 0));
    EXPECT_EQ(parsed("2016-12-31T23:59:59.999999Z"), at(2016, 12, 31, 23, 59, 59, 999999));
    EXPECT_FALSE(parseIso8601("2016-12-31T12:30:60Z"));
}

TEST(ParseIso8601, ReadsExpandedYearsAndLeapDays) {
    EXPECT_EQ(parsed("-2000-06-21T12:00:00Z"), at(-2000, 6, 21, 12, 0, 0));
    EXPECT_EQ(parsed("+6000-06-21T12:00:00Z"), at(6000, 6, 21, 12, 0, 0));
    EXPECT_EQ(parsed("+010000-01-01T00:00:00Z"), at(10000, 1, 1, 0, 0, 0));
    EXPECT_EQ(parsed("2000-02-29T00:00:00Z"), at(2000, 2, 29, 0, 0, 0));
    EXPECT_EQ(parsed("0000-01-01T00:00:00Z"), at(0, 1, 1, 0, 0, 0));
}

TEST(ParseIso8601, RefusesWhatIsNotIso8601WithTheFieldNamed) {
    const struct {
        const char* text;
        const char* names;
    } cases[] = {
        {"", "empty"},
        {"2003-10-17T12:30:30", "offset"},
        {"2003-10-17 12:30:30Z", "'T'"},
        {"2003-10-17t12:30:30Z", "'T'"},
        {"2003-10-17T12:30:30z", "Z or a UTC offset"},
        {"20031017T123030Z", "'-' after the year"},
        {"03-10-17T12:30:30Z", "4-digit year"},
        {"2003-13-17T12:30:30Z", "month 13"},
        {"2003-00-17T12:30:30Z", "month 0"},
        {"2003-02-29T12:30:30Z", "day 29"},
        {"2004-04-31T12:30:30Z", "day 31"},
        {"2003-10-17T24:00:00Z", "hour 24"},
        {"2003-10-17T12:60:00Z", "minute 60"},
        {"2003-10-17T12:30:61Z", "second 61"},
        {"2003-10-17T12:30Z", "':' after the minutes"},
        {"2003-10-17T12:30:30.Z", "digits after the decimal"},
        {"2003-10-17T12:30:30.1234567890Z", "9 digits"},
        {"2003-10-17T12:30:30+24:00", "offset beyond"},
        {"2003-10-17T12:30:30+05:60", "offset beyond"},
        {"2003-10-17T12:30:30+0530", "offset as"},
        {"2003-10-17T12:30:30Z ", "unexpected text"},
        {"2003-10-17T12:30:30ZZ", "unexpected text"},
        {"-99999-01-01T00:00:00Z", "beyond"},
        {"+20-01-01T00:00:00Z", "4 to 6 digits"},
        {"2003-W42-5T12:00:00Z", "month"},
    };
    for (const auto& c : cases) {
        auto r = parseIso8601(c.text);
        ASSERT_FALSE(r) << c.text;
        EXPECT_EQ(r.error().code, ErrorCode::ParseError) << c.text;
        EXPECT_NE(r.error().message.find(c.names), std::string::npos)
            << c.text << " -> " << r.error().message;
    }
    auto long_text = parseIso8601(std::string(1000, '1'));
    ASSERT_FALSE(long_text);
    EXPECT_NE(long_text.error().message.find("1000 characters"), std::string::npos);
}

TEST(FormatIso8601, RoundTripsThroughTheParser) {
    for (const UtcInstant t :
         {at(2003, 10, 17, 19, 30, 30), at(2024, 6, 21, 0, 0, 0, 1), at(-2000, 1, 1, 0, 0, 0),
          at(6000, 12, 31, 23, 59, 59, 999999), at(0, 3, 1, 12, 0, 0), at(12000, 1, 1, 0, 0, 0)}) {
        const std::string text = formatIso8601(t);
        EXPECT_EQ(parsed(text), t) << text;
    }
    EXPECT_EQ(formatIso8601(at(2003, 10, 17, 19, 30, 30)), "2003-10-17T19:30:30Z");
    EXPECT_EQ(formatIso8601(at(2003, 10, 17, 19, 30, 30, 250000)), "2003-10-17T19:30:30.250000Z");
    EXPECT_EQ(formatIso8601(at(-2000, 1, 1, 0, 0, 0)), "-002000-01-01T00:00:00Z");
}

TEST(JulianDay, MatchesTheSpaPapersExample) {
    // The worked example of Reda & Andreas: JD 2452930.312847 for 2003-10-17 12:30:30 at UTC-7.
    EXPECT_NEAR(julianDay(parsed("2003-10-17T12:30:30-07:00")), 2452930.312847, 1e-6);
    EXPECT_DOUBLE_EQ(julianDay(at(2000, 1, 1, 12, 0, 0)), 2451545.0);
    // Meeus, Astronomical Algorithms, example 7.a's neighbours: 1957-10-04.81 is JD 2436116.31;
    // and the proleptic Gregorian -4713-11-24T12:00 is JD 0.
    EXPECT_NEAR(julianDay(at(1957, 10, 4, 19, 26, 24)), 2436116.31, 1e-9);
    EXPECT_NEAR(julianDay(at(-4713, 11, 24, 12, 0, 0)), 0.0, 1e-9);
    EXPECT_EQ(calendarYear(at(-2000, 12, 31, 23, 59, 59)), -2000);
}

}  // namespace
}  // namespace flarelab::predict
