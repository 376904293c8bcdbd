#include "apps/sun_command.h"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "tests/apps/command_runner.h"
#include "tests/test_files.h"

namespace flarelab::apps {
namespace {

using flarelab::testing::contains;

using testing::CommandRun;

CommandRun sun(std::vector<std::string> args) {
    args.insert(args.begin(), "sun");
    return testing::runCommand(addSunCommand, args);
}

// The worked example of Reda & Andreas (2004), in its appendix.
const std::vector<std::string> kGolden = {"--lat",         "39.742476",
                                          "--lon",         "-105.1786",
                                          "--elevation",   "1830.14",
                                          "--pressure",    "820",
                                          "--temperature", "11",
                                          "--delta-t",     "67",
                                          "--time",        "2003-10-17T12:30:30-07:00"};

TEST(SunCommand, PrintsThePapersZenithAndAzimuth) {
    const CommandRun r = sun(kGolden);
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "2003-10-17T19:30:30Z")) << r.out;
    EXPECT_TRUE(contains(r.out, "zenith       50.11162 deg")) << r.out;
    EXPECT_TRUE(contains(r.out, "azimuth      194.34024 deg")) << r.out;
    EXPECT_TRUE(contains(r.out, "delta T 67.0 s)")) << r.out;
}

TEST(SunCommand, JsonHasTheAnglesAndTheInputs) {
    std::vector<std::string> args = kGolden;
    args.push_back("--json");
    const CommandRun r = sun(args);
    ASSERT_EQ(r.code, 0) << r.err;
    const auto j = nlohmann::json::parse(r.out);
    EXPECT_NEAR(j.at("zenith_deg").get<double>(), 50.11162, 1e-5);
    EXPECT_NEAR(j.at("azimuth_deg").get<double>(), 194.34024, 1e-5);
    EXPECT_NEAR(j.at("elevation_deg").get<double>(), 90.0 - 50.11162, 1e-5);
    EXPECT_EQ(j.at("time_utc"), "2003-10-17T19:30:30Z");
    EXPECT_EQ(j.at("delta_t_s"), 67.0);
    EXPECT_EQ(j.at("delta_t_estimated"), false);
    for (const char* key : {"hour_angle_deg", "declination_deg", "right_ascension_deg",
                            "distance_au", "refraction_deg", "pressure_mbar", "temperature_c"})
        EXPECT_TRUE(j.contains(key)) << key;
}

TEST(SunCommand, DefaultsThePressureTemperatureAndDeltaT) {
    const CommandRun r = sun({"--lat", "0", "--lon", "0", "--elevation", "0", "--time",
                              "2024-03-20T12:00:00Z", "--json"});
    ASSERT_EQ(r.code, 0) << r.err;
    const auto j = nlohmann::json::parse(r.out);
    EXPECT_EQ(j.at("pressure_mbar"), 1013.25);
    EXPECT_EQ(j.at("temperature_c"), 12.0);
    EXPECT_EQ(j.at("delta_t_estimated"), true);
    // Equinox at noon UTC on the equator: the sun 0.2 deg north, 7.5 minutes (1.9 deg) from
    // culminating (the equation of time).
    EXPECT_NEAR(j.at("zenith_deg").get<double>(), 1.9, 0.1);
}

TEST(SunCommand, BadValuesAreUsageErrorsNamingTheFlag) {
    const struct {
        std::vector<std::string> change;
        const char* names;
    } cases[] = {
        {{"--lat", "91"}, "--lat: latitude"},
        {{"--lon", "-180.5"}, "--lon: longitude"},
        {{"--lon", "nan"}, "--lon"},
        {{"--elevation", "1e7"}, "--elevation: elevation"},
        {{"--pressure", "-3"}, "--pressure: pressure"},
        {{"--temperature", "500"}, "--temperature: temperature"},
        {{"--delta-t", "1e9"}, "--delta-t: delta T"},
        {{"--time", "2003-10-17T12:30:30"}, "--time: time"},
        {{"--time", "2003-02-30T12:00:00Z"}, "day 30"},
        {{"--time", "+6001-01-01T00:00:00Z"}, "--time: time"},
    };
    for (const auto& c : cases) {
        std::vector<std::string> args = kGolden;
        for (size_t i = 0; i + 1 < args.size(); i += 2)
            if (args[i] == c.change[0]) args[i + 1] = c.change[1];
        const CommandRun r = sun(args);
        EXPECT_EQ(r.code, 2) << c.names << ": " << r.err;
        EXPECT_TRUE(contains(r.err, c.names)) << r.err;
        EXPECT_TRUE(r.out.empty()) << r.out;
    }
}

TEST(SunCommand, MissingOrMalformedFlagsAreRefusedByTheParser) {
    CommandRun r = sun({"--lat", "40", "--lon", "0", "--elevation", "0"});
    EXPECT_NE(r.code, 0);
    EXPECT_TRUE(contains(r.err, "--time")) << r.err;
    r = sun({"--lat", "north", "--lon", "0", "--elevation", "0", "--time", "2024-01-01T00:00:00Z"});
    EXPECT_NE(r.code, 0);
    EXPECT_TRUE(contains(r.err, "--lat")) << r.err;
}

}  // namespace
}  // namespace flarelab::apps
