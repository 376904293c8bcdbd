#include "predict/scene.h"

#include <gtest/gtest.h>
#include <stdlib.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <numbers>
#include <string>
#include <vector>

#include "tests/predict/test_times.h"
#include "tests/test_files.h"

namespace flarelab::predict {
namespace {

using test_times::at;

using flarelab::testing::TempDir;

using nlohmann::json;
using namespace std::chrono;

// Every field of the format, each with a value other than its default.
constexpr const char* kFullScene = R"({
  "format": "flarelab-scene", "version": 1,
  "out_of_range": "clamp",
  "cameras": [{
    "name": "main",
    "model": "models/heliar.flm",
    "position_m": [0, -40, 12],
    "pan_deg": 10, "tilt_deg": -10, "roll_deg": 2.5,
    "exposure_s": 0.01,
    "f_number": 8,
    "gain": 2,
    "width_px": 1920, "height_px": 1080,
    "scene_min_dn": 40, "scene_max_dn": 3500, "scene_log_average_dn": 600,
    "rig_illuminance_lux": 2000
  }, {
    "name": "side",
    "model": "/lab/models/tessar.flm",
    "position_m": [10, 0, 2],
    "look_at_m": [10, 10, 12],
    "exposure_s": 0.002,
    "scene_min_dn": 0, "scene_max_dn": 4000,
    "rig_illuminance_lux": 1500
  }],
  "lights": [{
    "name": "flood 1",
    "position_m": [30, 0, 25],
    "intensity_cd": 150000,
    "colour": [1, 0.9, 0.8]
  }, {
    "name": "moon",
    "direction": {"azimuth_deg": 90, "elevation_deg": 30},
    "illuminance_lux": 0.25
  }, {
    "name": "screen",
    "direction": {"azimuth_deg": 180, "elevation_deg": 0},
    "relative": 0.5
  }],
  "sun": {
    "latitude_deg": 48.2, "longitude_deg": 16.37, "elevation_m": 170,
    "pressure_mbar": 990, "temperature_c": 20,
    "from": "2026-06-21T18:00:00+02:00", "to": "2026-06-21T21:00:00+02:00", "step_s": 0.5,
    "illuminance_lux": 100000,
    "colour": [1, 0.95, 0.9]
  },
  "switching": {"figure": "contrast-loss", "threshold": 0.05, "min_dwell_s": 10},
  "frames": ["2026-06-21T20:30:00+02:00", "2026-06-21T19:00:00Z"]
})";

// A small valid scene for the rules to break one at a time.
json minimalScene() {
    return json::parse(R"({
      "format": "flarelab-scene", "version": 1,
      "cameras": [{"name": "main", "model": "heliar.flm", "position_m": [0, 0, 1.5],
                   "pan_deg": 0, "tilt_deg": 0, "exposure_s": 0.01}],
      "lights": [{"name": "lamp", "position_m": [0, 20, 5], "relative": 1}]
    })");
}

// minimalScene with a sun and frames inside its span.
json sunScene() {
    json scene = minimalScene();
    scene["sun"] = json::parse(R"({
      "latitude_deg": 48.2, "longitude_deg": 16.37, "elevation_m": 170,
      "from": "2026-06-21T16:00:00Z", "to": "2026-06-21T19:00:00Z", "step_s": 1,
      "relative": 50
    })");
    scene["frames"] = {"2026-06-21T18:30:00Z"};
    return scene;
}

Result<Scene> parseText(const std::string& text) {
    return parseScene(text, "scene.json", "scenes");
}
Result<Scene> parse(const json& scene) { return parseText(scene.dump()); }

// The scene fails to parse with `code` and a message holding every one of `parts`.
void expectError(const Result<Scene>& result,
                 const std::vector<std::string>& parts,
                 ErrorCode code = ErrorCode::ParseError) {
    ASSERT_FALSE(result) << "parsed, expected an error with \"" << parts.front() << "\"";
    EXPECT_EQ(result.error().code, code) << result.error().message;
    for (const std::string& part : parts)
        EXPECT_NE(result.error().message.find(part), std::string::npos)
            << "\"" << result.error().message << "\" lacks \"" << part << "\"";
}

// minimalScene (or `base`) edited by `edit` fails with a message holding `parts`.
void expectBroken(const std::function<void(json&)>& edit,
                  const std::vector<std::string>& parts,
                  json base = minimalScene()) {
    edit(base);
    SCOPED_TRACE(base.dump());
    expectError(parse(base), parts);
}

double length(const Vec3& v) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

TEST(ParseScene, ReadsEveryFieldOfAFullScene) {
    auto parsed = parseText(kFullScene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    const Scene& s = *parsed;
    EXPECT_EQ(s.out_of_range, RangePolicy::Clamp);

    ASSERT_EQ(s.cameras.size(), 2u);
    const SceneCamera& main = s.cameras[0];
    EXPECT_EQ(main.name, "main");
    EXPECT_EQ(main.model_path, "scenes/models/heliar.flm");
    EXPECT_EQ(main.pose.position_m, (Vec3{0.0, -40.0, 12.0}));
    EXPECT_EQ(main.pose.pan_deg, 10.0);
    EXPECT_EQ(main.pose.tilt_deg, -10.0);
    EXPECT_EQ(main.pose.roll_deg, 2.5);
    EXPECT_EQ(main.exposure_s, 0.01);
    EXPECT_EQ(main.f_number, 8.0);
    EXPECT_EQ(main.gain, 2.0);
    EXPECT_EQ(main.width_px, 1920);
    EXPECT_EQ(main.height_px, 1080);
    EXPECT_EQ(main.scene_min_dn, 40.0);
    EXPECT_EQ(main.scene_max_dn, 3500.0);
    EXPECT_EQ(main.scene_log_average_dn, 600.0);
    EXPECT_EQ(main.rig_illuminance_lux, 2000.0);

    const SceneCamera& side = s.cameras[1];
    EXPECT_EQ(side.model_path, "/lab/models/tessar.flm");  // absolute: kept
    EXPECT_EQ(side.pose.position_m, (Vec3{10.0, 0.0, 2.0}));
    EXPECT_NEAR(side.pose.pan_deg, 0.0, 1e-12);  // due north
    EXPECT_NEAR(side.pose.tilt_deg, 45.0, 1e-12);
    EXPECT_EQ(side.pose.roll_deg, 0.0);
    EXPECT_EQ(side.f_number, std::nullopt);
    EXPECT_EQ(side.gain, 1.0);
    EXPECT_EQ(side.width_px, std::nullopt);
    EXPECT_EQ(side.height_px, std::nullopt);
    EXPECT_EQ(side.scene_min_dn, 0.0);

    ASSERT_EQ(s.lights.size(), 3u);
    const SceneLight& flood = s.lights[0];
    EXPECT_EQ(flood.name, "flood 1");
    EXPECT_EQ(flood.position_m, (Vec3{30.0, 0.0, 25.0}));
    EXPECT_EQ(flood.direction, std::nullopt);
    EXPECT_EQ(flood.intensity.intensity_cd, 150000.0);
    EXPECT_EQ(flood.intensity.illuminance_lux, std::nullopt);
    EXPECT_EQ(flood.intensity.relative, std::nullopt);
    EXPECT_EQ(flood.colour, (std::array<double, 3>{1.0, 0.9, 0.8}));
    const SceneLight& moon = s.lights[1];
    EXPECT_EQ(moon.position_m, std::nullopt);
    ASSERT_TRUE(moon.direction);
    const Vec3 east_30 = directionFromAzimuthElevation(90.0, 30.0);
    for (int k = 0; k < 3; ++k) EXPECT_EQ((*moon.direction)[k], east_30[k]);
    EXPECT_NEAR((*moon.direction)[0], std::cos(std::numbers::pi / 6), 1e-15);
    EXPECT_NEAR((*moon.direction)[2], 0.5, 1e-15);
    EXPECT_NEAR(length(*moon.direction), 1.0, 1e-15);
    EXPECT_EQ(moon.intensity.illuminance_lux, 0.25);
    EXPECT_EQ(moon.colour, (std::array<double, 3>{1.0, 1.0, 1.0}));
    EXPECT_EQ(s.lights[2].intensity.relative, 0.5);

    ASSERT_TRUE(s.sun);
    EXPECT_EQ(s.sun->site.latitude_deg, 48.2);
    EXPECT_EQ(s.sun->site.longitude_deg, 16.37);
    EXPECT_EQ(s.sun->site.elevation_m, 170.0);
    EXPECT_EQ(s.sun->site.pressure_mbar, 990.0);
    EXPECT_EQ(s.sun->site.temperature_c, 20.0);
    EXPECT_EQ(s.sun->from, at(2026, 6, 21, 16, 0, 0));
    EXPECT_EQ(s.sun->to, at(2026, 6, 21, 19, 0, 0));
    EXPECT_EQ(s.sun->step, milliseconds(500));
    EXPECT_EQ(s.sun->intensity.illuminance_lux, 100000.0);
    EXPECT_EQ(s.sun->intensity.relative, std::nullopt);
    EXPECT_EQ(s.sun->colour, (std::array<double, 3>{1.0, 0.95, 0.9}));

    ASSERT_TRUE(s.switching);
    EXPECT_EQ(s.switching->figure, SwitchFigure::ContrastLoss);
    EXPECT_EQ(s.switching->threshold, 0.05);
    EXPECT_EQ(s.switching->min_dwell_s, 10.0);

    ASSERT_EQ(s.frames.size(), 2u);
    EXPECT_EQ(s.frames[0], at(2026, 6, 21, 18, 30, 0));
    EXPECT_EQ(s.frames[1], at(2026, 6, 21, 19, 0, 0));  // the span's last instant is inside
}

TEST(ParseScene, FillsDefaultsOfAMinimalScene) {
    auto parsed = parse(minimalScene());
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->out_of_range, RangePolicy::Refuse);
    const SceneCamera& c = parsed->cameras.at(0);
    EXPECT_EQ(c.pose.roll_deg, 0.0);
    EXPECT_EQ(c.gain, 1.0);
    EXPECT_EQ(c.f_number, std::nullopt);
    EXPECT_EQ(c.rig_illuminance_lux, std::nullopt);
    EXPECT_EQ(c.scene_min_dn, std::nullopt);
    EXPECT_EQ(parsed->lights.at(0).colour, (std::array<double, 3>{1.0, 1.0, 1.0}));
    EXPECT_FALSE(parsed->sun);
    EXPECT_FALSE(parsed->switching);
    EXPECT_TRUE(parsed->frames.empty());
}

TEST(ParseScene, JoinsRelativeModelPathsToTheBaseFolder) {
    json scene = minimalScene();
    scene["cameras"][0]["model"] = "../models/a.flm";
    auto parsed = parseScene(scene.dump(), "scene.json", "/data/scenes");
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->cameras[0].model_path, "/data/scenes/../models/a.flm");
    parsed = parseScene(scene.dump(), "scene.json", "");
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->cameras[0].model_path, "../models/a.flm");
}

TEST(ParseScene, AimsACameraByLookAt) {
    json scene = minimalScene();
    json& camera = scene["cameras"][0];
    camera.erase("pan_deg");
    camera.erase("tilt_deg");
    camera["position_m"] = {0, 0, 0};
    camera["look_at_m"] = {1, 0, 1};  // east, 45 degrees up
    auto parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_NEAR(parsed->cameras[0].pose.pan_deg, 90.0, 1e-12);
    EXPECT_NEAR(parsed->cameras[0].pose.tilt_deg, 45.0, 1e-12);
    EXPECT_EQ(parsed->cameras[0].pose.roll_deg, 0.0);
    EXPECT_EQ(parsed->cameras[0].pose.position_m, (Vec3{0.0, 0.0, 0.0}));

    expectBroken([](json& s) { s["cameras"][0]["pan_deg"] = 3; },
                 {"cameras[0].pan_deg", "look_at_m"}, scene);
    expectBroken([](json& s) { s["cameras"][0]["roll_deg"] = 3; },
                 {"cameras[0].roll_deg", "no roll"}, scene);
    expectBroken(
        [](json& s) {
            s["cameras"][0]["look_at_m"] = {0, 0, 0.0005};
        },
        {"cameras[0].look_at_m", "at least 1 mm"}, scene);
    expectBroken(
        [](json& s) {
            s["cameras"][0]["look_at_m"] = {0, 0};
        },
        {"cameras[0].look_at_m", "3 numbers", "got 2 elements"}, scene);
}

TEST(ParseScene, RefusesACameraWithoutAPose) {
    expectBroken([](json& s) { s["cameras"][0].erase("pan_deg"); },
                 {"cameras[0].pan_deg: missing", "look_at_m"});
    expectBroken([](json& s) { s["cameras"][0].erase("tilt_deg"); },
                 {"cameras[0].tilt_deg: missing"});
    expectBroken([](json& s) { s["cameras"][0].erase("position_m"); },
                 {"cameras[0].position_m: missing"});
}

TEST(ParseScene, RefusesUnknownFieldsByName) {
    expectBroken([](json& s) { s["camera"] = json::array(); },
                 {"scene.json: unknown field \"camera\""});
    // A misspelt optional field must not fall back to its default.
    expectBroken([](json& s) { s["cameras"][0]["exposure"] = 0.5; },
                 {"cameras[0]: unknown field \"exposure\"", "exposure_s"});
    expectBroken(
        [](json& s) {
            s["lights"][0]["color"] = {1, 1, 1};
        },
        {"lights[0]: unknown field \"color\"", "colour"});
    expectBroken(
        [](json& s) {
            s["lights"][0].erase("position_m");
            s["lights"][0]["direction"] = {{"azimuth_deg", 0}, {"elevation", 3}};
        },
        {"lights[0].direction: unknown field \"elevation\""});
    expectBroken([](json& s) { s["sun"]["timezone"] = "CET"; }, {"sun: unknown field \"timezone\""},
                 sunScene());
    expectBroken(
        [](json& s) {
            s["switching"] = {{"figure", "flare-mean"}, {"threshold", 1}, {"dwell_s", 3}};
        },
        {"switching: unknown field \"dwell_s\""}, sunScene());
    // A key with control characters is shown escaped.
    expectBroken([](json& s) { s["cameras"][0]["ex\nposure"] = 1; }, {"\"ex\\u000Aposure\""});
}

TEST(ParseScene, NamesWrongTypes) {
    expectBroken([](json& s) { s["cameras"][0]["exposure_s"] = "0.01"; },
                 {"scene.json: cameras[0].exposure_s: must be a number, got a string"});
    expectBroken([](json& s) { s["cameras"][0]["exposure_s"] = nullptr; },
                 {"cameras[0].exposure_s: must be a number, got null"});
    expectBroken([](json& s) { s["cameras"] = s["cameras"][0]; },
                 {"cameras: must be an array, got an object"});
    expectBroken([](json& s) { s["cameras"][0] = 3; },
                 {"cameras[0]: must be an object, got a number"});
    expectBroken([](json& s) { s["cameras"][0]["name"] = 7; },
                 {"cameras[0].name: must be a string, got a number"});
    expectBroken([](json& s) { s["cameras"][0]["position_m"][1] = true; },
                 {"cameras[0].position_m[1]: must be a number, got true"});
    expectBroken(
        [](json& s) {
            s["lights"][0]["colour"] = {1, 1, 1, 1};
        },
        {"lights[0].colour: must be an array of 3 numbers", "got 4 elements"});
    expectBroken(
        [](json& s) {
            s["lights"][0]["direction"] = 3;
            s["lights"][0].erase("position_m");
        },
        {"lights[0].direction: must be an object, got a number"});
    expectBroken([](json& s) { s["frames"][0] = 1782000000; },
                 {"frames[0]: must be a string, got a number"}, sunScene());
    expectBroken([](json& s) { s["out_of_range"] = "extrapolate"; },
                 {"out_of_range: \"extrapolate\" is not a policy"});
}

TEST(ParseScene, RefusesNumbersOutOfRange) {
    struct Case {
        std::function<void(json&)> edit;
        std::string message;
    };
    const std::vector<Case> cases = {
        {[](json& s) { s["cameras"][0]["exposure_s"] = -1; },
         "scene.json: cameras[0].exposure_s: must be > 0, got -1"},
        {[](json& s) { s["cameras"][0]["exposure_s"] = 0; }, "cameras[0].exposure_s: must be > 0"},
        {[](json& s) { s["cameras"][0]["f_number"] = 0; }, "cameras[0].f_number: must be > 0"},
        {[](json& s) { s["cameras"][0]["gain"] = -2; }, "cameras[0].gain: must be > 0"},
        {[](json& s) { s["cameras"][0]["tilt_deg"] = 90.5; },
         "cameras[0].tilt_deg: must be in [-90, 90], got 90.5"},
        {[](json& s) { s["cameras"][0]["rig_illuminance_lux"] = 0; },
         "cameras[0].rig_illuminance_lux: must be > 0"},
        {[](json& s) { s["lights"][0]["relative"] = -0.5; }, "lights[0].relative: must be >= 0"},
        {[](json& s) {
             s["lights"][0].erase("relative");
             s["lights"][0]["intensity_cd"] = 0;
         },
         "lights[0].intensity_cd: must be > 0"},
        {[](json& s) {
             s["lights"][0]["colour"] = {1, -0.1, 1};
         },
         "lights[0].colour[1]: must be >= 0, got -0.1"},
        {[](json& s) {
             s["lights"][0].erase("position_m");
             s["lights"][0]["direction"] = {{"azimuth_deg", 0}, {"elevation_deg", -91}};
         },
         "lights[0].direction.elevation_deg: must be in [-90, 90], got -91"},
        {[](json& s) {
             s["cameras"][0]["scene_min_dn"] = -1;
             s["cameras"][0]["scene_max_dn"] = 10;
         },
         "cameras[0].scene_min_dn: must be >= 0, got -1"},
        {[](json& s) {
             s["cameras"][0]["scene_min_dn"] = 0;
             s["cameras"][0]["scene_max_dn"] = 0;
         },
         "cameras[0].scene_max_dn: must be > 0, got 0"},
        {[](json& s) {
             s["cameras"][0]["scene_min_dn"] = 11;
             s["cameras"][0]["scene_max_dn"] = 10;
         },
         "cameras[0].scene_min_dn: 11 is above scene_max_dn (10)"},
        {[](json& s) {
             s["cameras"][0]["width_px"] = 0;
             s["cameras"][0]["height_px"] = 10;
         },
         "cameras[0].width_px: must be in 1..32768, got 0"},
        {[](json& s) {
             s["cameras"][0]["width_px"] = 10;
             s["cameras"][0]["height_px"] = 32769;
         },
         "cameras[0].height_px: must be in 1..32768, got 32769"},
        {[](json& s) {
             s["cameras"][0]["width_px"] = 1920.5;
             s["cameras"][0]["height_px"] = 1080;
         },
         "cameras[0].width_px: must be an integer, got 1920.5"},
        {[](json& s) {
             s["cameras"][0]["width_px"] = 18446744073709551615u;
             s["cameras"][0]["height_px"] = 1080;
         },
         "cameras[0].width_px: must be in 1..32768, got 18446744073709551615"},
    };
    for (const Case& c : cases) expectBroken(c.edit, {c.message});
}

TEST(ParseScene, ReadsIntegralNumbersAsIntegers) {
    json scene = minimalScene();
    scene["cameras"][0]["width_px"] = 1920.0;
    scene["cameras"][0]["height_px"] = 1080;
    auto parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->cameras[0].width_px, 1920);
    // As text too: 1.08e3 is 1080.
    std::string text = minimalScene().dump();
    text.insert(text.find("\"exposure_s\""), "\"width_px\": 1920, \"height_px\": 1.08e3, ");
    parsed = parseText(text);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->cameras[0].height_px, 1080);
}

TEST(ParseScene, WantsSizesAndSceneLevelsInPairs) {
    expectBroken([](json& s) { s["cameras"][0]["width_px"] = 100; },
                 {"cameras[0].height_px: missing", "come together"});
    expectBroken([](json& s) { s["cameras"][0]["height_px"] = 100; },
                 {"cameras[0].width_px: missing"});
    expectBroken([](json& s) { s["cameras"][0]["scene_max_dn"] = 100; },
                 {"cameras[0].scene_min_dn: missing"});
    expectBroken([](json& s) { s["cameras"][0]["scene_min_dn"] = 100; },
                 {"cameras[0].scene_max_dn: missing"});
}

TEST(ParseScene, RefusesNumbersBeyondADouble) {
    // JSON has no NaN or infinity; a number too large for a double is the nearest thing, and
    // nlohmann refuses it rather than reading infinity.
    for (const char* huge : {"1e999", "-1e999", "1e400"}) {
        std::string text = minimalScene().dump();
        const std::string exposure = "\"exposure_s\":0.01";
        ASSERT_NE(text.find(exposure), std::string::npos);
        text.replace(text.find(exposure), exposure.size(), std::string("\"exposure_s\":") + huge);
        expectError(parseText(text),
                    {"scene.json: not valid JSON", "number overflow", huge, "at byte"});
    }
    // Below the smallest double is zero, and then refused as such.
    std::string text = minimalScene().dump();
    text.replace(text.find("0.01"), 4, "1e-999");
    expectError(parseText(text), {"cameras[0].exposure_s: must be > 0, got 0"});
}

TEST(ParseScene, RefusesDuplicateKeys) {
    std::string text = minimalScene().dump();
    text.insert(text.find("\"exposure_s\""), "\"exposure_s\": 5, ");
    expectError(parseText(text),
                {"scene.json: cameras[0]: the field \"exposure_s\" is given twice"});
    text = minimalScene().dump();
    text.insert(1, "\"version\": 1, ");
    expectError(parseText(text), {"scene.json: the field \"version\" is given twice"});
}

TEST(ParseScene, RefusesDuplicateNamesWithinCamerasAndWithinLights) {
    expectBroken([](json& s) { s["cameras"].push_back(s["cameras"][0]); },
                 {"cameras[1].name: \"main\" is also the name of cameras[0]"});
    expectBroken(
        [](json& s) {
            s["lights"].push_back(s["lights"][0]);
            s["lights"].push_back(s["lights"][0]);
            s["lights"][1]["name"] = "other";
        },
        {"lights[2].name: \"lamp\" is also the name of lights[0]"});
    // A camera and a light may share a name: reports never mix the two.
    json scene = minimalScene();
    scene["lights"][0]["name"] = "main";
    EXPECT_TRUE(parse(scene));
}

TEST(ParseScene, ChecksNames) {
    expectBroken([](json& s) { s["cameras"][0]["name"] = ""; },
                 {"cameras[0].name: must not be empty"});
    expectBroken([](json& s) { s["cameras"][0]["name"] = std::string(65, 'a'); },
                 {"cameras[0].name", "65 characters long"});
    expectBroken([](json& s) { s["lights"][0]["name"] = "bell\a"; },
                 {"lights[0].name: \"bell\\u0007\" holds a control character"});
    expectBroken([](json& s) { s["lights"][0]["name"] = "next\u0085line"; },
                 {"lights[0].name", "\\u0085", "control character"});
    expectBroken([](json& s) { s["cameras"][0]["model"] = ""; },
                 {"cameras[0].model: must not be empty"});
    expectBroken([](json& s) { s["cameras"][0]["model"] = std::string("a\0b", 3); },
                 {"cameras[0].model", "control character"});
    // 64 characters of two bytes each: 128 bytes but a valid name.
    json scene = minimalScene();
    std::string name;
    for (int i = 0; i < 64; ++i) name += "\u00e9";
    scene["cameras"][0]["name"] = name;
    auto parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->cameras[0].name, name);
}

TEST(ParseScene, RefusesOtherFormatsAndVersions) {
    expectBroken([](json& s) { s.erase("format"); }, {"scene.json: format: missing"});
    expectBroken([](json& s) { s["format"] = "flarelab-model"; },
                 {"format: must be \"flarelab-scene\", got \"flarelab-model\""});
    expectBroken([](json& s) { s.erase("version"); }, {"scene.json: version: missing"});
    expectBroken([](json& s) { s["version"] = "1"; },
                 {"version: must be an integer, got a string"});
    expectBroken([](json& s) { s["version"] = 1.5; }, {"version: must be an integer, got 1.5"});
    json huge = minimalScene();
    huge["version"] = 18446744073709551615u;
    expectError(parse(huge), {"scene.json: version: ", "this reader knows version 1"},
                ErrorCode::Unsupported);
    json later = minimalScene();
    later["version"] = 2;
    later["a_field_of_version_2"] = true;  // named by its version, not as unknown
    expectError(parse(later), {"scene.json: version: 2; this reader knows version 1"},
                ErrorCode::Unsupported);
}

TEST(ParseScene, RefusesTextThatIsNotAJsonObject) {
    expectError(parseText(""), {"scene.json: not valid JSON", "line 1"});
    expectError(parseText("{\"format\": \"flarelab-scene\""), {"not valid JSON"});
    expectError(parseText(minimalScene().dump() + " {}"), {"not valid JSON"});
    expectError(parseText("[1, 2]"), {"scene.json: must be a JSON object, got an array"});
    expectError(parseText("{\"format\": \"flarelab-scene\", // comment\n \"version\": 1}"),
                {"not valid JSON"});
    expectError(parseText("\xff"), {"not valid JSON"});
    std::string deep = "{\"format\": \"flarelab-scene\", \"version\": 1, \"x\": ";
    deep += std::string(100000, '[') + std::string(100000, ']') + "}";
    expectError(parseText(deep), {"scene.json: x[0][0]", "nested more than 16 levels"});
}

TEST(ParseScene, StaysFastAndShortWithLongKeys) {
    // A megabyte-long key over 200 000 arrays: paths are put together only for the error, so
    // this takes milliseconds, and the message shows the key cut short.
    const std::string key(1 << 20, 'k');
    std::string text = "{\"format\": \"flarelab-scene\", \"version\": 1, \"" + key + "\": [";
    for (int i = 0; i < 200000; ++i) text += "[], ";
    text += "[[[[[[[[[[[[[[[[[[]]]]]]]]]]]]]]]]]]]}";
    const auto start = steady_clock::now();
    auto parsed = parseText(text);
    EXPECT_LT(steady_clock::now() - start, seconds(20));
    expectError(parsed, {"scene.json: \"kkkk", "k...\"[200000][0]", "nested more than 16"});
    EXPECT_LT(parsed.error().message.size(), 300u) << parsed.error().message;
}

TEST(ParseScene, NeedsACameraAndALightOrTheSun) {
    expectBroken([](json& s) { s.erase("cameras"); }, {"scene.json: cameras: missing"});
    expectBroken([](json& s) { s["cameras"] = json::array(); }, {"cameras: is empty"});
    expectBroken([](json& s) { s.erase("lights"); }, {"no light and no sun"});
    expectBroken([](json& s) { s["lights"] = json::array(); }, {"no light and no sun"});
    expectBroken(
        [](json& s) {
            for (int i = 1; i <= 64; ++i) {
                s["cameras"].push_back(s["cameras"][0]);
                s["cameras"].back()["name"] = "c" + std::to_string(i);
            }
        },
        {"cameras: has 65 elements; at most 64"});
    // The sun alone is enough.
    json scene = sunScene();
    scene.erase("lights");
    EXPECT_TRUE(parse(scene));
}

TEST(ParseScene, WantsExactlyOneIntensityAndPlace) {
    expectBroken(
        [](json& s) { s["lights"][0].erase("relative"); },
        {"lights[0]: no intensity: give one of intensity_cd, illuminance_lux or relative"});
    expectBroken([](json& s) { s["lights"][0]["illuminance_lux"] = 3; },
                 {"lights[0]: illuminance_lux and relative are given together"});
    expectBroken([](json& s) { s["lights"][0].erase("position_m"); },
                 {"lights[0]: no place: give position_m", "direction"});
    expectBroken(
        [](json& s) {
            s["lights"][0]["direction"] = {{"azimuth_deg", 0}, {"elevation_deg", 0}};
        },
        {"lights[0]: position_m and direction are both given"});
    expectBroken(
        [](json& s) {
            s["lights"][0].erase("position_m");
            s["lights"][0]["direction"] = {{"azimuth_deg", 0}};
        },
        {"lights[0].direction.elevation_deg: missing"});
    expectBroken(
        [](json& s) {
            s["lights"][0].erase("position_m");
            s["lights"][0].erase("relative");
            s["lights"][0]["direction"] = {{"azimuth_deg", 0}, {"elevation_deg", 10}};
            s["lights"][0]["intensity_cd"] = 1000;
        },
        {"lights[0].intensity_cd: only for a light with position_m"});
    expectBroken(
        [](json& s) {
            s["sun"]["intensity_cd"] = 1000;
            s["sun"].erase("relative");
        },
        {"sun.intensity_cd: the sun is at infinity"}, sunScene());
    expectBroken([](json& s) { s["sun"]["illuminance_lux"] = 1000; },
                 {"sun: illuminance_lux and relative are given together"}, sunScene());
}

TEST(ParseScene, RefusesALightOfNoColour) {
    expectBroken(
        [](json& s) {
            s["lights"][0]["colour"] = {0, 0, 0};
        },
        {"lights[0].colour: is [0, 0, 0]", "mistake"});
    expectBroken(
        [](json& s) {
            s["sun"]["colour"] = {0, 0, 0};
        },
        {"sun.colour: is [0, 0, 0]"}, sunScene());
    // One channel of zero is a coloured light.
    json scene = minimalScene();
    scene["lights"][0]["colour"] = {0, 0, 1};
    EXPECT_TRUE(parse(scene));
}

TEST(ParseScene, PhotometricLightsNeedTheRigIlluminance) {
    expectBroken(
        [](json& s) {
            s["lights"][0].erase("relative");
            s["lights"][0]["intensity_cd"] = 5000;
        },
        {"cameras[0].rig_illuminance_lux: missing", "lights[0] (\"lamp\") gives intensity_cd"});
    expectBroken(
        [](json& s) {
            s["sun"].erase("relative");
            s["sun"]["illuminance_lux"] = 100000;
        },
        {"cameras[0].rig_illuminance_lux: missing", "the sun gives illuminance_lux"}, sunScene());
}

TEST(ParseScene, ChecksTheSunsSiteAndSpan) {
    auto parsed = parse(sunScene());
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->sun->site.pressure_mbar, SunSite{}.pressure_mbar);  // the defaults
    EXPECT_EQ(parsed->sun->site.temperature_c, SunSite{}.temperature_c);
    EXPECT_EQ(parsed->sun->step, seconds(1));

    expectBroken([](json& s) { s["sun"]["latitude_deg"] = 91; }, {"scene.json: sun: latitude 91"},
                 sunScene());
    expectBroken([](json& s) { s["sun"]["pressure_mbar"] = 1300; }, {"sun: pressure 1300"},
                 sunScene());
    expectBroken([](json& s) { s["sun"].erase("elevation_m"); }, {"sun.elevation_m: missing"},
                 sunScene());
    expectBroken([](json& s) { s["sun"]["to"] = "2026-06-21T15:59:59Z"; },
                 {"sun.to: 2026-06-21T15:59:59Z is before from (2026-06-21T16:00:00Z)"},
                 sunScene());
    expectBroken([](json& s) { s["sun"]["from"] = "2026-06-21T16:00:00"; },
                 {"sun.from: time \"2026-06-21T16:00:00\""}, sunScene());
    expectBroken([](json& s) { s["sun"]["to"] = "6001-01-01T00:00:00Z"; },
                 {"sun.to: year 6001 is outside"}, sunScene());
    expectBroken([](json& s) { s["sun"]["step_s"] = 0.0009; },
                 {"sun.step_s: must be in [0.001, 86400], got 0.0009"}, sunScene());
    expectBroken([](json& s) { s["sun"]["step_s"] = 86401; }, {"sun.step_s: must be in"},
                 sunScene());
    expectBroken([](json& s) { s["sun"].erase("step_s"); }, {"sun.step_s: missing"}, sunScene());

    // Steps are rounded to the microsecond.
    json scene = sunScene();
    scene["sun"]["step_s"] = 0.0012345;
    parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->sun->step, microseconds(1235));

    // 10 million steps are allowed (from and to included), one more is not.
    scene = sunScene();
    scene.erase("frames");
    scene["sun"]["from"] = "2026-01-01T00:00:00Z";
    scene["sun"]["to"] = "2026-01-01T02:46:39.999Z";  // 9 999 999 ms after from
    scene["sun"]["step_s"] = 0.001;
    parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    scene["sun"]["to"] = "2026-01-01T02:46:40Z";
    expectError(parse(scene), {"sun.step_s", "takes 10000001 steps", "at most 10000000"});

    // A span of one instant is a timeline of one step.
    scene = sunScene();
    scene["sun"]["to"] = scene["sun"]["from"];
    scene["frames"] = {scene["sun"]["from"]};
    EXPECT_TRUE(parse(scene));
}

TEST(ParseScene, KeepsFramesInsideTheSunsSpan) {
    expectBroken([](json& s) { s["frames"].push_back("2026-06-21T19:00:00.000001Z"); },
                 {"frames[1]: 2026-06-21T19:00:00.000001Z is outside the sun's span, "
                  "2026-06-21T16:00:00Z to 2026-06-21T19:00:00Z"},
                 sunScene());
    expectBroken([](json& s) { s["frames"] = {"2026-06-21T15:00:00Z"}; },
                 {"frames[0]", "outside the sun's span"}, sunScene());
    expectBroken([](json& s) { s["frames"] = {"yesterday"}; }, {"frames[0]: time \"yesterday\""},
                 sunScene());
    expectBroken([](json& s) { s.erase("sun"); }, {"scene.json: frames: needs a sun"}, sunScene());
    expectBroken(
        [](json& s) {
            for (int i = 0; i < 64; ++i) s["frames"].push_back("2026-06-21T18:00:00Z");
        },
        {"frames: has 65 elements; at most 64"}, sunScene());
}

TEST(ParseScene, SwitchingNeedsASunAndSceneLevelsForContrast) {
    json scene = sunScene();
    scene["switching"] = {{"figure", "flare-peak"}, {"threshold", 250}};
    auto parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->switching->figure, SwitchFigure::FlarePeak);
    EXPECT_EQ(parsed->switching->threshold, 250.0);
    EXPECT_EQ(parsed->switching->min_dwell_s, 0.0);

    expectBroken(
        [](json& s) {
            s.erase("sun");
            s.erase("frames");
        },
        {"scene.json: switching: needs a sun"}, scene);
    expectBroken([](json& s) { s["switching"]["figure"] = "veiling"; },
                 {"switching.figure: \"veiling\" is not a figure"}, scene);
    expectBroken([](json& s) { s["switching"]["threshold"] = -1; },
                 {"switching.threshold: must be >= 0, got -1"}, scene);
    expectBroken([](json& s) { s["switching"]["min_dwell_s"] = -1; },
                 {"switching.min_dwell_s: must be >= 0, got -1"}, scene);
    expectBroken([](json& s) { s["switching"].erase("threshold"); },
                 {"switching.threshold: missing"}, scene);

    scene["switching"] = {{"figure", "contrast-loss"}, {"threshold", 0.1}};
    expectBroken([](json&) {}, {"cameras[0]: camera \"main\" has no scene_min_dn and scene_max_dn"},
                 scene);
    scene["cameras"][0]["scene_min_dn"] = 10;
    scene["cameras"][0]["scene_max_dn"] = 1000;
    EXPECT_TRUE(parse(scene));
    expectBroken([](json& s) { s["switching"]["threshold"] = 1.5; },
                 {"switching.threshold: must be in [0, 1], got 1.5"}, scene);

    // The glare indicator needs each camera's log-average.
    scene["switching"] = {{"figure", "glare"}, {"threshold", 0.2}};
    expectBroken([](json&) {}, {"cameras[0]: camera \"main\" has no scene_log_average_dn"}, scene);
    expectBroken([](json& s) { s["cameras"][0]["scene_log_average_dn"] = 0; },
                 {"cameras[0].scene_log_average_dn: must be > 0, got 0"}, scene);
    scene["cameras"][0]["scene_log_average_dn"] = 400;
    parsed = parse(scene);
    ASSERT_TRUE(parsed) << parsed.error().message;
    EXPECT_EQ(parsed->switching->figure, SwitchFigure::GlareIndicator);
    EXPECT_EQ(parsed->cameras[0].scene_log_average_dn, 400.0);
}

TEST(ParseScene, NeverFailsSilentlyOnATruncatedScene) {
    // Every prefix of a valid scene but the whole is broken JSON: each must give a message.
    const std::string text = kFullScene;
    for (size_t n = 0; n + 1 < text.size(); ++n) {
        auto parsed = parseText(text.substr(0, n));
        if (parsed) {
            ADD_FAILURE() << "a prefix of " << n << " bytes parsed";
        } else {
            EXPECT_EQ(parsed.error().message.rfind("scene.json: ", 0), 0u)
                << parsed.error().message;
        }
    }
}

TEST(LoadScene, JoinsModelPathsToTheScenesFolder) {
    TempDir dir;
    ASSERT_FALSE(dir.path().empty());
    const std::string path = dir.path() + "/night.json";
    std::ofstream(path) << minimalScene().dump(2);
    auto scene = loadScene(path);
    ASSERT_TRUE(scene) << scene.error().message;
    EXPECT_EQ(scene->cameras[0].model_path, dir.path() + "/heliar.flm");

    // Errors name the file.
    json broken = minimalScene();
    broken["cameras"][0]["exposure_s"] = -1;
    std::ofstream(path) << broken.dump();
    scene = loadScene(path);
    ASSERT_FALSE(scene);
    EXPECT_EQ(scene.error().message, path + ": cameras[0].exposure_s: must be > 0, got -1");
}

TEST(LoadScene, ReadsAFileInTheWorkingFolderWithItAsBase) {
    TempDir dir;
    ASSERT_FALSE(dir.path().empty());
    std::ofstream(dir.path() + "/here.json") << minimalScene().dump();
    const auto previous = std::filesystem::current_path();
    std::filesystem::current_path(dir.path());
    auto scene = loadScene("here.json");
    std::filesystem::current_path(previous);
    ASSERT_TRUE(scene) << scene.error().message;
    EXPECT_EQ(scene->cameras[0].model_path, "./heliar.flm");
}

TEST(LoadScene, RefusesMissingFilesFoldersAndHugeFiles) {
    TempDir dir;
    ASSERT_FALSE(dir.path().empty());
    auto scene = loadScene(dir.path() + "/absent.json");
    ASSERT_FALSE(scene);
    EXPECT_EQ(scene.error().code, ErrorCode::NotFound);
    EXPECT_NE(scene.error().message.find("absent.json"), std::string::npos);

    scene = loadScene(dir.path());
    ASSERT_FALSE(scene);
    EXPECT_EQ(scene.error().code, ErrorCode::IoError);
    EXPECT_NE(scene.error().message.find("directory"), std::string::npos) << scene.error().message;

    // A sparse file one byte over the limit costs no disk.
    const std::string huge = dir.path() + "/huge.json";
    std::ofstream(huge).close();
    std::filesystem::resize_file(huge, static_cast<uintmax_t>(kSceneMaxFileBytes) + 1);
    scene = loadScene(huge);
    ASSERT_FALSE(scene);
    EXPECT_EQ(scene.error().code, ErrorCode::ParseError);
    EXPECT_NE(scene.error().message.find("more than a scene file may hold"), std::string::npos)
        << scene.error().message;
}

SceneCamera rigCamera(std::optional<double> rig_lux) {
    SceneCamera camera;
    camera.name = "main";
    camera.exposure_s = 0.01;
    camera.rig_illuminance_lux = rig_lux;
    return camera;
}

TEST(LightRatio, IsTheIrradianceOverTheRigLights) {
    LightIntensity relative;
    relative.relative = 0.25;
    auto ratio = lightRatio(relative, rigCamera(std::nullopt), 0.0, "lamp");
    ASSERT_TRUE(ratio) << ratio.error().message;
    EXPECT_EQ(*ratio, 0.25);  // the distance does not matter

    LightIntensity lux;
    lux.illuminance_lux = 500.0;
    ratio = lightRatio(lux, rigCamera(2000.0), 1e9, "moon");
    ASSERT_TRUE(ratio) << ratio.error().message;
    EXPECT_DOUBLE_EQ(*ratio, 0.25);

    // 150 000 cd at 50 m: 60 lux, the inverse-square law.
    LightIntensity cd;
    cd.intensity_cd = 150000.0;
    ratio = lightRatio(cd, rigCamera(2000.0), 50.0, "flood");
    ASSERT_TRUE(ratio) << ratio.error().message;
    EXPECT_DOUBLE_EQ(*ratio, 60.0 / 2000.0);
}

TEST(LightRatio, RefusesWhatItCannotCompare) {
    const auto expectInvalid = [](const Result<double>& r, const std::string& part) {
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(r.error().message.find(part), std::string::npos) << r.error().message;
    };
    LightIntensity cd;
    cd.intensity_cd = 1000.0;
    expectInvalid(lightRatio(cd, rigCamera(std::nullopt), 10.0, "lights[0]"),
                  "lights[0]: a photometric intensity needs the camera's rig_illuminance_lux");
    LightIntensity lux;
    lux.illuminance_lux = 1000.0;
    expectInvalid(lightRatio(lux, rigCamera(std::nullopt), 10.0, "sun"),
                  "sun: a photometric intensity needs the camera's rig_illuminance_lux");
    expectInvalid(lightRatio(cd, rigCamera(2000.0), 0.0009, "lamp"), "lamp: the light is 0.0009 m");
    expectInvalid(lightRatio(cd, rigCamera(2000.0), std::nan(""), "lamp"), "at least 1 mm");
    EXPECT_TRUE(lightRatio(cd, rigCamera(2000.0), 0.001, "lamp"));
    expectInvalid(lightRatio(LightIntensity{}, rigCamera(2000.0), 1.0, "none"),
                  "exactly one intensity");
    LightIntensity two = cd;
    two.relative = 1.0;
    expectInvalid(lightRatio(two, rigCamera(2000.0), 1.0, "two"), "exactly one intensity");
    expectInvalid(lightRatio(cd, rigCamera(0.0), 1.0, "lamp"), "rig_illuminance_lux must be > 0");
}

}  // namespace
}  // namespace flarelab::predict

namespace flarelab::predict {
namespace {

// A venue of two cameras and two lights as a 3D tool exports it (glTF: Y up, -Z north).
const char* kVenue = R"({
  "asset": {"version": "2.0"},
  "scene": 0,
  "scenes": [{"nodes": [0, 1, 2, 3]}],
  "nodes": [
    {"name": "Cam West", "camera": 0, "translation": [-60, 20, 0],
     "rotation": [0, -0.7071067811865476, 0, 0.7071067811865476]},
    {"name": "Cam Twin", "camera": 0, "translation": [10, 5, 0]},
    {"name": "Tower", "translation": [30, 40, -10],
     "extensions": {"KHR_lights_punctual": {"light": 0}}},
    {"name": "lamp", "extensions": {"KHR_lights_punctual": {"light": 1}},
     "rotation": [-0.7071067811865476, 0, 0, 0.7071067811865476]}
  ],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.1}}],
  "extensions": {"KHR_lights_punctual": {"lights": [
    {"type": "point", "intensity": 150000, "color": [1, 0.9, 0.8]},
    {"type": "directional", "intensity": 20000}
  ]}}
})";

TEST(LoadScene, TakesCamerasAndLightsFromAGltfVenue) {
    TempDir dir;
    ASSERT_FALSE(dir.path().empty());
    std::ofstream(dir.path() + "/venue.gltf") << kVenue;
    json scene = minimalScene();
    scene["gltf"] = {{"file", "venue.gltf"}};
    scene["cameras"][0].erase("position_m");
    scene["cameras"][0].erase("pan_deg");
    scene["cameras"][0].erase("tilt_deg");
    scene["cameras"][0]["gltf_camera"] = "Cam West";
    scene["cameras"][0]["rig_illuminance_lux"] = 1000;
    const std::string path = dir.path() + "/scene.json";
    std::ofstream(path) << scene.dump();
    auto loaded = loadScene(path);
    ASSERT_TRUE(loaded) << loaded.error().message;
    // glTF -Z is north; the node turned -90 deg about +Y looks along glTF +X: east.
    const CameraPose& pose = loaded->cameras[0].pose;
    EXPECT_NEAR(pose.position_m[0], -60.0, 1e-9);
    EXPECT_NEAR(pose.position_m[1], 0.0, 1e-9);
    EXPECT_NEAR(pose.position_m[2], 20.0, 1e-9);
    EXPECT_NEAR(pose.pan_deg, 90.0, 1e-9);
    EXPECT_NEAR(pose.tilt_deg, 0.0, 1e-9);
    // The scene's own lamp keeps its name; the glTF's "lamp" gets one of its own.
    ASSERT_EQ(loaded->lights.size(), 3u);
    EXPECT_EQ(loaded->lights[1].name, "Tower");
    ASSERT_TRUE(loaded->lights[1].position_m);
    EXPECT_NEAR((*loaded->lights[1].position_m)[1], 10.0, 1e-9);  // north = -z
    EXPECT_EQ(loaded->lights[1].intensity.intensity_cd, 150000.0);
    EXPECT_EQ(loaded->lights[1].colour[2], 0.8);
    EXPECT_EQ(loaded->lights[2].name, "lamp (glTF)");
    ASSERT_TRUE(loaded->lights[2].direction);
    EXPECT_NEAR((*loaded->lights[2].direction)[2], 1.0, 1e-9);  // shining down: the sun overhead
    EXPECT_EQ(loaded->lights[2].intensity.illuminance_lux, 20000.0);

    // Without its lights the venue gives the pose only.
    scene["gltf"]["lights"] = false;
    std::ofstream(path) << scene.dump();
    loaded = loadScene(path);
    ASSERT_TRUE(loaded) << loaded.error().message;
    EXPECT_EQ(loaded->lights.size(), 1u);
}

TEST(LoadScene, NamesAMissingGltfCameraAndWhatAVenueNeeds) {
    TempDir dir;
    ASSERT_FALSE(dir.path().empty());
    std::ofstream(dir.path() + "/venue.gltf") << kVenue;
    json scene = minimalScene();
    scene["gltf"] = {{"file", "venue.gltf"}, {"lights", false}};
    scene["cameras"][0].erase("position_m");
    scene["cameras"][0].erase("pan_deg");
    scene["cameras"][0].erase("tilt_deg");
    scene["cameras"][0]["gltf_camera"] = "Cam East";
    const std::string path = dir.path() + "/scene.json";
    std::ofstream(path) << scene.dump();
    auto loaded = loadScene(path);
    ASSERT_FALSE(loaded);
    EXPECT_NE(loaded.error().message.find("cameras[0].gltf_camera: no camera \"Cam East\""),
              std::string::npos)
        << loaded.error().message;
    EXPECT_NE(loaded.error().message.find("\"Cam Twin\""), std::string::npos);
    // Lights in candela need the rig's illuminance on every camera.
    scene["cameras"][0]["gltf_camera"] = "Cam Twin";
    scene["gltf"]["lights"] = true;
    std::ofstream(path) << scene.dump();
    loaded = loadScene(path);
    ASSERT_FALSE(loaded);
    EXPECT_NE(loaded.error().message.find("cameras[0].rig_illuminance_lux: missing"),
              std::string::npos)
        << loaded.error().message;
    // A pose and a glTF camera together, a glTF camera without a glTF, a missing file.
    json both = scene;
    both["cameras"][0]["pan_deg"] = 0;
    auto refused = parse(both);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("cameras[0].pan_deg: not with gltf_camera"),
              std::string::npos);
    json alone = scene;
    alone.erase("gltf");
    refused = parse(alone);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("needs the scene's \"gltf\""), std::string::npos);
    scene["gltf"]["file"] = "absent.glb";
    std::ofstream(path) << scene.dump();
    loaded = loadScene(path);
    ASSERT_FALSE(loaded);
    EXPECT_NE(loaded.error().message.find("gltf.file"), std::string::npos)
        << loaded.error().message;
}

}  // namespace
}  // namespace flarelab::predict
