#include "apps/predict_command.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>

#include "fit/model_file.h"
#include "hdr/exr.h"
#include "predict/sun.h"
#include "predict/utc_time.h"
#include "tests/apps/command_runner.h"
#include "tests/predict/moving_disc_model.h"
#include "tests/test_files.h"

namespace flarelab::apps {
namespace {

using flarelab::testing::contains;
using flarelab::testing::readText;

namespace fs = std::filesystem;
using testing::CommandRun;

CommandRun predict(const std::vector<std::string>& args) {
    std::vector<std::string> all{"predict"};
    all.insert(all.end(), args.begin(), args.end());
    return testing::runCommand(addPredictCommand, all);
}

class PredictCommand : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("flarelab_predict_cmd_" + std::to_string(::getpid()) + "_" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::create_directories(dir_ / "models");
        ASSERT_TRUE(fit::writeModel((dir_ / "models" / "disc.flm").string(),
                                    predict::testing::movingDiscModel()));
    }
    void TearDown() override { fs::remove_all(dir_); }

    std::string writeScene(const std::string& json) const {
        const std::string path = (dir_ / "scene.json").string();
        std::ofstream(path) << json;
        return path;
    }

    fs::path dir_;
};

// Two cameras: "left" looks north past a flood light, "right" stands north of the flood (which is
// behind it) and looks 3 deg above where the sun stands at 18:10; the sun over 20 minutes.
std::string twoCameraScene() {
    predict::SunSite site;
    site.latitude_deg = 48.2;
    site.longitude_deg = 16.37;
    site.elevation_m = 170.0;
    auto sun = predict::sunPosition(site, *predict::parseIso8601("2026-06-21T18:10:00+02:00"));
    EXPECT_TRUE(sun);
    const std::string right_pan = std::to_string(sun->azimuth_deg);
    const std::string right_tilt = std::to_string(sun->elevation_deg + 3.0);
    return R"({
  "format": "flarelab-scene", "version": 1,
  "cameras": [
    {"name": "left", "model": "models/disc.flm", "position_m": [0, 0, 10],
     "pan_deg": -3, "tilt_deg": 0, "exposure_s": 0.5,
     "scene_min_dn": 5, "scene_max_dn": 500},
    {"name": "right", "model": "models/disc.flm", "position_m": [0, 200, 10],
     "pan_deg": )" +
           right_pan + R"(, "tilt_deg": )" + right_tilt + R"(, "exposure_s": 0.5,
     "scene_min_dn": 5, "scene_max_dn": 500}
  ],
  "lights": [
    {"name": "flood", "position_m": [1, 100, 10], "relative": 1.0}
  ],
  "sun": {"latitude_deg": 48.2, "longitude_deg": 16.37, "elevation_m": 170,
          "from": "2026-06-21T18:00:00+02:00", "to": "2026-06-21T18:20:00+02:00", "step_s": 10,
          "relative": 1.0},
  "switching": {"figure": "contrast-loss", "threshold": 0.05, "min_dwell_s": 60},
  "frames": ["2026-06-21T18:10:00+02:00"]
})";
}

TEST_F(PredictCommand, WritesFiguresATimelineAPlanFramesAndAReport) {
    const fs::path out = dir_ / "report";
    const std::string scene = writeScene(twoCameraScene());
    const CommandRun r = predict({scene, "-o", out.string(), "--table-phi-step", "30"});
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "2 cameras, 1 fixed lights, the sun")) << r.out;
    for (const char* file :
         {"report.html", "report.json", "figures.csv", "timeline.csv", "plan.csv"})
        EXPECT_TRUE(fs::exists(out / file)) << file;
    const auto report = nlohmann::json::parse(readText(out / "report.json"));
    ASSERT_EQ(report["cameras"].size(), 2u);
    // The flood light is 1 m east of north at 100 m: right of the left camera's axis by about
    // 3.6 deg, and behind the right camera.
    const auto& left = report["cameras"][0]["lights"][0];
    EXPECT_EQ(left["state"], "drawn");
    EXPECT_NEAR(left["theta_deg"].get<double>(), 3.57, 0.01);
    EXPECT_EQ(report["cameras"][1]["lights"][0]["state"], "behind-camera");
    EXPECT_GT(left["figures"]["mean"].get<double>(), 0.0);
    EXPECT_EQ(report["timeline"]["steps"], 121);
    // The sun stands far outside the left camera's model (refused: unknown), and near the right
    // camera's axis, which sees it for the whole span.
    const auto& cams = report["timeline"]["cameras"];
    EXPECT_EQ(cams[0]["steps_refused"], 121);
    EXPECT_EQ(cams[1]["steps_drawn"], 121);
    EXPECT_GT(cams[1]["flare_mean_max"].get<double>(), 0.0);
    ASSERT_TRUE(report.contains("switching"));
    ASSERT_EQ(report["switching"]["segments"].size(), 1u);
    EXPECT_EQ(report["switching"]["segments"][0]["camera"], "right");
    ASSERT_EQ(report["frames"].size(), 2u);  // each camera at the one instant
    auto frame = hdr::readExr((out / report["frames"][0]["exr"].get<std::string>()).string());
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_EQ(frame->image.width, 72);
    EXPECT_TRUE(fs::exists(out / report["frames"][0]["png"].get<std::string>()));
    // One CSV row per light and camera; one per step.
    const std::string figures = readText(out / "figures.csv");
    EXPECT_EQ(std::count(figures.begin(), figures.end(), '\n'), 3);
    const std::string timeline = readText(out / "timeline.csv");
    EXPECT_EQ(std::count(timeline.begin(), timeline.end(), '\n'), 122);
    const std::string html = readText(out / "report.html");
    EXPECT_TRUE(contains(html, "<svg")) << html.substr(0, 400);
    EXPECT_FALSE(contains(html, "<script"));
    EXPECT_FALSE(contains(html, "http://"));
    EXPECT_FALSE(contains(html, "https://"));
    // --json prints the same report.
    const CommandRun j = predict({scene, "-o", out.string(), "--table-phi-step", "30", "--json"});
    ASSERT_EQ(j.code, 0) << j.err;
    EXPECT_EQ(nlohmann::json::parse(j.out)["cameras"].size(), 2u);
}

TEST_F(PredictCommand, AStaticSceneDrawsOneFramePerCamera) {
    const fs::path out = dir_ / "static";
    const CommandRun r = predict({writeScene(R"({
      "format": "flarelab-scene", "version": 1,
      "cameras": [{"name": "cam", "model": "models/disc.flm", "position_m": [0, 0, 0],
                   "look_at_m": [0, 50, 0], "exposure_s": 1},
                  {"name": "goal/north, high", "model": "models/disc.flm",
                   "position_m": [0, 0, 0], "look_at_m": [0, 50, 0], "exposure_s": 1},
                  {"name": "goal_north__high", "model": "models/disc.flm",
                   "position_m": [0, 0, 0], "look_at_m": [0, 50, 0], "exposure_s": 1}],
      "lights": [{"name": "behind", "position_m": [0, -10, 0], "relative": 1},
                 {"name": "on axis", "direction": {"azimuth_deg": 0, "elevation_deg": 0},
                  "relative": 1}]
    })"),
                                  "-o", out.string()});
    ASSERT_EQ(r.code, 0) << r.err;
    const auto report = nlohmann::json::parse(readText(out / "report.json"));
    EXPECT_EQ(report["cameras"][0]["lights"][0]["state"], "behind-camera");
    EXPECT_EQ(report["cameras"][0]["lights"][1]["state"], "drawn");
    EXPECT_NEAR(report["cameras"][0]["lights"][1]["theta_deg"].get<double>(), 0.0, 1e-9);
    // One frame per camera, each in a file of its own although two names differ only in what
    // a file name cannot hold; a name with a comma is quoted in the CSV.
    ASSERT_EQ(report["frames"].size(), 3u);
    EXPECT_NE(report["frames"][1]["png"], report["frames"][2]["png"]);
    for (const auto& frame : report["frames"])
        EXPECT_TRUE(fs::exists(out / frame["png"].get<std::string>())) << frame["png"];
    EXPECT_TRUE(contains(readText(out / "figures.csv"), "\"goal/north, high\",behind,"));
    EXPECT_FALSE(fs::exists(out / "timeline.csv"));
}

// A model that knows its light's power gets the lab figures; one that does not says what it
// lacks. The glare indicator follows the scene's log-average and can drive the switching.
TEST_F(PredictCommand, LabFiguresAndTheGlareIndicatorReachTheReport) {
    fit::FlareModel lit = predict::testing::movingDiscModel(1, true);
    lit.capture.light_power_dn_s = 5.0e6;
    ASSERT_TRUE(fit::writeModel((dir_ / "models" / "lit.flm").string(), lit));
    std::string scene = twoCameraScene();
    scene = scene.replace(scene.find("models/disc.flm"), 15, "models/lit.flm");
    const std::string key = "\"scene_log_average_dn\": 50, ";
    for (size_t at = scene.find("\"scene_max_dn\": 500"); at != std::string::npos;
         at = scene.find("\"scene_max_dn\": 500", at + key.size() + 1))
        scene.insert(at, key);
    scene.replace(scene.find("\"contrast-loss\""), 15, "\"glare\"");
    const fs::path out = dir_ / "lab";
    const CommandRun r = predict({writeScene(scene), "-o", out.string(), "--table-phi-step", "30",
                                  "--black-spot-deg", "2", "--lab-heights", "0.5,0.7"});
    ASSERT_EQ(r.code, 0) << r.err;
    const auto report = nlohmann::json::parse(readText(out / "report.json"));
    ASSERT_EQ(report["models"].size(), 2u);
    const auto& with = report["models"][0];
    EXPECT_TRUE(contains(with["model"].get<std::string>(), "models/lit.flm"));
    ASSERT_TRUE(with["scaled"].get<bool>());
    EXPECT_EQ(with["black_spot_deg"], 2.0);
    // The disc covers the image centre up to 2 deg: the bright field from 1 deg adds to it.
    EXPECT_GT(with["veiling_glare_index"].get<double>(), 0.0);
    EXPECT_GE(with["veiling_glare_index"].get<double>(), with["image_flare"].get<double>());
    EXPECT_FALSE(with["image_flare_complete"].get<bool>());  // 10 deg of a 23 deg field
    ASSERT_EQ(with["off_axis"].size(), 2u);                  // image heights 0.5 and 0.7
    EXPECT_EQ(with["off_axis"][1]["image_height"], 0.7);
    // Other heights; a height outside (0, 1] is refused.
    const CommandRun one = predict({writeScene(scene), "-o", (dir_ / "one").string(),
                                    "--table-phi-step", "30", "--lab-heights", "0.9", "--json"});
    ASSERT_EQ(one.code, 0) << one.err;
    const auto one_report = nlohmann::json::parse(one.out);
    ASSERT_EQ(one_report["models"][0]["off_axis"].size(), 1u);
    EXPECT_EQ(one_report["models"][0]["off_axis"][0]["image_height"], 0.9);
    EXPECT_NE(
        predict({writeScene(scene), "-o", (dir_ / "bad").string(), "--lab-heights", "1.5"}).code,
        0);
    EXPECT_GT(with["off_axis"][1]["field_deg"].get<double>(), 0.0);
    const auto& without = report["models"][1];
    EXPECT_FALSE(without["scaled"].get<bool>());
    EXPECT_EQ(without["missing"], "capture.light_power_dn_s");
    const std::string lab = readText(out / "lab.csv");
    EXPECT_TRUE(contains(lab, "model,theta_deg,centre_flare_dn_s,pst\n")) << lab;
    EXPECT_TRUE(contains(lab, "models/lit.flm,0,")) << lab;
    EXPECT_TRUE(contains(lab, "models/disc.flm,10,")) << lab;  // no PST: an empty last column
    const std::string html = readText(out / "report.html");
    EXPECT_TRUE(contains(html, "Point source transmittance")) << html.substr(0, 400);
    EXPECT_TRUE(contains(html, "the model lacks capture.light_power_dn_s"));
    // The kept per-frame values are drawn as dots beside their series; the other model has none.
    EXPECT_TRUE(contains(html, "ghost 1, fitted")) << html.substr(0, 400);
    EXPECT_TRUE(contains(html, "the dots the per-frame fits they compress"));
    EXPECT_TRUE(contains(html, "the model kept no per-frame fits"));

    // The glare indicator: the fixed lights' mean over 50 DN, and the plan's figure.
    const auto& left = report["cameras"][0];
    EXPECT_NEAR(left["glare_indicator"].get<double>(),
                left["fixed_lights"]["mean"].get<double>() / 50.0, 1e-12);
    EXPECT_EQ(report["switching"]["figure"], "glare");
    EXPECT_TRUE(report["timeline"]["cameras"][1].contains("glare_indicator_max"));
    EXPECT_TRUE(contains(readText(out / "timeline.csv"), "right glare_indicator"));
}

TEST_F(PredictCommand, BadScenesAreRefusedNamingTheField) {
    const fs::path out = dir_ / "bad";
    CommandRun r = predict({writeScene(R"({
      "format": "flarelab-scene", "version": 1,
      "cameras": [{"name": "cam", "model": "models/disc.flm", "position_m": [0, 0, 0],
                   "pan_deg": 0, "tilt_deg": 0, "exposure_s": -1}],
      "lights": [{"name": "l", "position_m": [0, 10, 0], "relative": 1}]
    })"),
                            "-o", out.string()});
    EXPECT_EQ(r.code, 2);
    EXPECT_TRUE(contains(r.err, "cameras[0].exposure_s")) << r.err;
    r = predict({writeScene(R"({
      "format": "flarelab-scene", "version": 1,
      "cameras": [{"name": "cam", "model": "models/missing.flm", "position_m": [0, 0, 0],
                   "pan_deg": 0, "tilt_deg": 0, "exposure_s": 1}],
      "lights": [{"name": "l", "position_m": [0, 10, 0], "relative": 1}]
    })"),
                 "-o", out.string()});
    EXPECT_EQ(r.code, 1);
    EXPECT_TRUE(contains(r.err, "missing.flm")) << r.err;
    r = predict({(dir_ / "no-such-scene.json").string(), "-o", out.string()});
    EXPECT_NE(r.code, 0);
    EXPECT_TRUE(contains(r.err, "no-such-scene.json")) << r.err;
}

}  // namespace
}  // namespace flarelab::apps
