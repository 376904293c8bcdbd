#include "predict/prediction.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>

#include "fit/model_file.h"
#include "tests/test_paths.h"

namespace flarelab::predict {
namespace {

namespace fs = std::filesystem;

// Two cameras on the moving disc's model, a flood light and the sun for 20 minutes with a
// switching rule and one frame instant (its model lies in ../models/).
const std::string kScene = flarelab::testing::sourcePath("tests/data/scenes/report-test.json");

class PredictScene : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("flarelab_prediction_" + std::to_string(::getpid()) + "_" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::create_directories(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }

    PredictOptions fastOptions() const {
        PredictOptions options;
        options.table.phi_step_deg = 30.0;
        return options;
    }

    fs::path dir_;
};

// A JSON number or null, as report.json writes a figure; NaN for null.
double number(const nlohmann::json& value) {
    return value.is_null() ? std::nan("") : value.get<double>();
}

void expectSame(double json_value, double value, const std::string& what) {
    if (std::isnan(value))
        EXPECT_TRUE(std::isnan(json_value)) << what;
    else
        EXPECT_EQ(json_value, value) << what;
}

void expectFigures(const nlohmann::json& json, const FlareFigures& f, const std::string& what) {
    expectSame(number(json["min"]), f.min, what + ".min");
    expectSame(number(json["max"]), f.max, what + ".max");
    expectSame(number(json["mean"]), f.mean, what + ".mean");
    expectSame(number(json["log_average"]), f.log_average, what + ".log_average");
    expectSame(number(json["total"]), f.total, what + ".total");
}

TEST_F(PredictScene, ReturnsTheVeryFiguresItWritesToReportJson) {
    const fs::path out = dir_ / "report";
    auto p = predictScene(kScene, out.string(), fastOptions());
    ASSERT_TRUE(p) << p.error().message;
    std::ifstream in(out / "report.json");
    std::stringstream text;
    text << in.rdbuf();
    EXPECT_EQ(text.str(), p->report_json);
    const auto report = nlohmann::json::parse(p->report_json);

    ASSERT_EQ(p->cameras.size(), 2u);
    ASSERT_EQ(report["cameras"].size(), 2u);
    for (size_t c = 0; c < p->cameras.size(); ++c) {
        const PredictedCamera& camera = p->cameras[c];
        const auto& j = report["cameras"][c];
        EXPECT_EQ(j["name"], camera.name);
        EXPECT_EQ(j["known"], camera.fixed.known);
        expectFigures(j["fixed_lights"], camera.fixed.sum, camera.name);
        ASSERT_TRUE(camera.fixed.contrast_ratio);
        EXPECT_EQ(j["contrast_ratio"].get<double>(), *camera.fixed.contrast_ratio);
        ASSERT_EQ(j["lights"].size(), camera.fixed.lights.size());
        for (size_t l = 0; l < camera.fixed.lights.size(); ++l) {
            const LightFigures& lf = camera.fixed.lights[l];
            EXPECT_EQ(j["lights"][l]["state"], lightStateName(lf.placed.state));
            EXPECT_EQ(j["lights"][l]["theta_deg"].get<double>(), lf.placed.constellation.theta_deg);
            expectFigures(j["lights"][l]["figures"], lf.figures, camera.name + " light");
        }
    }
    // The flood is drawn for the first camera and behind the second.
    EXPECT_EQ(p->cameras[0].fixed.lights[0].placed.state, LightState::Drawn);
    EXPECT_GT(p->cameras[0].fixed.sum.mean, 0.0);
    EXPECT_EQ(p->cameras[1].fixed.lights[0].placed.state, LightState::BehindCamera);

    ASSERT_TRUE(p->timeline);
    EXPECT_EQ(p->timeline->steps, 121);
    EXPECT_EQ(report["timeline"]["steps"], p->timeline->steps);
    for (size_t c = 0; c < 2; ++c) {
        const auto& j = report["timeline"]["cameras"][c];
        const CameraTimelineSummary& t = p->timeline->cameras[c];
        EXPECT_EQ(j["steps_drawn"], t.steps_drawn);
        expectSame(number(j["flare_mean_median"]), t.flare_mean_median, "median");
        expectSame(number(j["flare_peak_max"]), t.flare_peak_max, "peak");
        expectSame(number(j["contrast_loss_max"]), t.contrast_loss_max, "loss");
    }
    ASSERT_TRUE(p->switching);
    ASSERT_EQ(report["switching"]["segments"].size(), p->switching->shots.size());
    EXPECT_EQ(report["switching"]["steps_over"], p->switching->steps_over);
    for (size_t s = 0; s < p->switching->shots.size(); ++s) {
        EXPECT_EQ(report["switching"]["segments"][s]["camera"], p->switching->shots[s].camera);
        EXPECT_EQ(report["switching"]["segments"][s]["steps_over"],
                  p->switching->shots[s].steps_over);
    }
    ASSERT_EQ(report["switching"]["no_clean_camera"].size(), p->switching->no_clean_camera.size());
    ASSERT_EQ(p->frames.size(), 2u);
    expectFigures(report["frames"][1]["figures"], p->frames[1].figures, "frame");

    // Every file it says it wrote is there, each once; the summary is the command's.
    for (const std::string& file : p->files) EXPECT_TRUE(fs::is_regular_file(out / file)) << file;
    for (const char* file :
         {"report.html", "report.json", "figures.csv", "lab.csv", "timeline.csv", "plan.csv"})
        EXPECT_EQ(std::count(p->files.begin(), p->files.end(), file), 1) << file;
    // And an EXR and a PNG per frame.
    EXPECT_EQ(p->files.size(), 6u + 4u) << ::testing::PrintToString(p->files);
    EXPECT_EQ(
        p->summary.rfind(
            "predict: 2 cameras, 1 fixed lights, the sun -> " + out.string() + "/report.html\n", 0),
        0u)
        << p->summary;
}

TEST_F(PredictScene, ShowsTheSceneByItsLabelAndItsFilesBelowItsFolder) {
    PredictOptions options = fastOptions();
    options.scene_label = "plan.json";
    options.paths_relative_to_scene = true;
    auto p = predictScene(kScene, (dir_ / "out").string(), options);
    ASSERT_TRUE(p) << p.error().message;
    const auto report = nlohmann::json::parse(p->report_json);
    EXPECT_EQ(report["scene"], "plan.json");
    EXPECT_EQ(report["cameras"][0]["model"], "../models/moving-disc.flm");
    EXPECT_EQ(p->cameras[0].model, "../models/moving-disc.flm");

    // Errors too: a model that is not there is named as the scene names it.
    fs::create_directories(dir_ / "scene");
    std::ofstream(dir_ / "scene" / "s.json") << R"({
      "format": "flarelab-scene", "version": 1,
      "cameras": [{"name": "cam", "model": "missing.flm", "position_m": [0, 0, 0],
                   "pan_deg": 0, "tilt_deg": 0, "exposure_s": 1}],
      "lights": [{"name": "l", "position_m": [0, 10, 0], "relative": 1}]
    })";
    auto missing =
        predictScene((dir_ / "scene" / "s.json").string(), (dir_ / "o2").string(), options);
    ASSERT_FALSE(missing);
    EXPECT_NE(missing.error().message.find("missing.flm"), std::string::npos);
    EXPECT_EQ(missing.error().message.find(dir_.string()), std::string::npos)
        << missing.error().message;
}

TEST_F(PredictScene, RefusesWorkOverItsBoundsBeforeDoingIt) {
    PredictOptions options = fastOptions();
    options.max_timeline_samples = 241;  // 121 steps x 2 cameras = 242
    auto p = predictScene(kScene, (dir_ / "a").string(), options);
    ASSERT_FALSE(p);
    EXPECT_EQ(p.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(p.error().message.find("sun: 121 steps for 2 camera(s)"), std::string::npos)
        << p.error().message;
    EXPECT_FALSE(fs::exists(dir_ / "a"));
    options.max_timeline_samples = 242;
    ASSERT_TRUE(predictScene(kScene, (dir_ / "b").string(), options));

    options.max_frame_pixels = 2 * 72 * 48 - 1;  // one instant of two 72 x 48 cameras
    p = predictScene(kScene, (dir_ / "c").string(), options);
    ASSERT_FALSE(p);
    EXPECT_EQ(p.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(p.error().message.find("frames:"), std::string::npos) << p.error().message;
    EXPECT_FALSE(fs::exists(dir_ / "c" / "report.json"));
    EXPECT_TRUE(fs::is_empty(dir_ / "c" / "frames"));
    options.max_frame_pixels = 2 * 72 * 48;
    EXPECT_TRUE(predictScene(kScene, (dir_ / "d").string(), options));
}

TEST_F(PredictScene, StopsAtTheStepWhereItIsAsked) {
    // Count the checks of a whole run, then stop at each of them in turn: every stop is an
    // Unsupported "stopped" and leaves no report.json.
    int checks = 0;
    PredictOptions options = fastOptions();
    options.stop_requested = [&] {
        ++checks;
        return false;
    };
    ASSERT_TRUE(predictScene(kScene, (dir_ / "all").string(), options));
    // One per model and one per angle of its table, one after the tables, one per camera's
    // figures, the timeline, 2 frames.
    auto model = fit::readModel(flarelab::testing::sourcePath("tests/data/models/moving-disc.flm"));
    ASSERT_TRUE(model) << model.error().message;
    auto table = FlareFigureTable::build(*model, options.table);
    ASSERT_TRUE(table) << table.error().message;
    const int angles = static_cast<int>(table->thetaCount());
    EXPECT_EQ(checks, 1 + angles + 1 + 2 + 1 + 2);
    for (int stop_at = 1; stop_at <= checks; ++stop_at) {
        std::atomic<int> asked{0};
        options.stop_requested = [&] { return ++asked == stop_at; };
        const fs::path out = dir_ / ("stop" + std::to_string(stop_at));
        auto p = predictScene(kScene, out.string(), options);
        ASSERT_FALSE(p) << stop_at;
        EXPECT_EQ(p.error().code, ErrorCode::Unsupported);
        EXPECT_NE(p.error().message.find("stopped"), std::string::npos);
        // Inside the table, the workers on other angles may each have asked once more.
        if (stop_at >= 2 && stop_at <= 1 + angles)
            EXPECT_LE(asked.load(), stop_at + static_cast<int>(std::thread::hardware_concurrency()));
        else
            EXPECT_EQ(asked.load(), stop_at);
        EXPECT_FALSE(fs::exists(out / "report.json")) << stop_at;
    }
}

}  // namespace
}  // namespace flarelab::predict
