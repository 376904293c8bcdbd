// The daemon's Predict call through its gRPC API, in process: the figures of `flarelab predict`
// for the same scene, the files handed back, refusals of paths, names, sizes and broken files,
// one prediction at a time, a prediction beside a running sweep, and the private folder gone
// after every call.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <functional>
#include <nlohmann/json.hpp>
#include <thread>

#include "apps/predict_command.h"
#include "predict/prediction.h"
#include "tests/apps/command_runner.h"
#include "tests/daemon/daemon_fixture.h"

namespace flarelab::daemon {
namespace {

using namespace testing;

const std::string kModelName = "moving-disc.flm";

std::string modelBytes() {
    return readText(flarelab::testing::sourcePath("tests/data/models/moving-disc.flm"));
}

// tests/data/scenes/report-test.json with its model named as a file of the request.
std::string sceneText() {
    std::string scene =
        readText(flarelab::testing::sourcePath("tests/data/scenes/report-test.json"));
    const std::string from = "../models/moving-disc.flm";
    for (size_t at = scene.find(from); at != std::string::npos; at = scene.find(from))
        scene.replace(at, from.size(), kModelName);
    return scene;
}

v1::PredictRequest request() {
    v1::PredictRequest r;
    r.set_scene_json(sceneText());
    auto* model = r.add_files();
    model->set_name(kModelName);
    model->set_content(modelBytes());
    r.mutable_options()->set_table_phi_step_deg(30.0);
    return r;
}

// A finer table than the default: seconds, long enough for two calls to meet.
v1::PredictRequest slowRequest() {
    v1::PredictRequest r = request();
    r.mutable_options()->set_table_theta_step_deg(0.1);
    r.mutable_options()->set_table_phi_step_deg(2.0);
    return r;
}

grpc::Status predict(v1::FlareLab::Stub& stub,
                     const v1::PredictRequest& r,
                     v1::PredictResponse* out,
                     const std::string& client = "planner",
                     double deadline_s = 120.0) {
    auto ctx = context(client, deadline_s);
    return stub.Predict(ctx.get(), r, out);
}

// The daemon's folder for predictions holds nothing once calls are over.
void expectNoPredictionFolder(const std::string& state_dir) {
    const fs::path root = fs::path(state_dir) / "predict";
    if (!fs::exists(root)) return;
    for (const auto& entry : fs::directory_iterator(root))
        ADD_FAILURE() << "left behind: " << entry.path();
}

double number(const nlohmann::json& value) {
    return value.is_null() ? std::nan("") : value.get<double>();
}

void expectSame(double a, double b, const std::string& what) {
    if (std::isnan(a) || std::isnan(b))
        EXPECT_TRUE(std::isnan(a) && std::isnan(b)) << what << ": " << a << " against " << b;
    else
        EXPECT_EQ(a, b) << what;
}

void expectFigures(const v1::FlareFigures& f, const nlohmann::json& j, const std::string& what) {
    expectSame(f.min(), number(j["min"]), what + ".min");
    expectSame(f.max(), number(j["max"]), what + ".max");
    expectSame(f.mean(), number(j["mean"]), what + ".mean");
    expectSame(f.log_average(), number(j["log_average"]), what + ".log_average");
    expectSame(f.total(), number(j["total"]), what + ".total");
}

// report.json without what differs between two runs of one scene: timings, and where the scene
// and its model lay.
nlohmann::json comparable(nlohmann::json report) {
    report.erase("timings_ms");
    report.erase("scene");
    report["timeline"].erase("ms");
    report["switching"].erase("ms");
    for (auto& camera : report["cameras"]) camera.erase("model");
    for (auto& model : report["models"]) model.erase("model");
    return report;
}

std::vector<std::string> lines(const std::string& text) {
    std::vector<std::string> out;
    std::stringstream s(text);
    for (std::string line; std::getline(s, line);) out.push_back(line);
    return out;
}

TEST(Predict, GivesTheFiguresOfFlarelabPredictForTheSameScene) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::PredictRequest r = request();
    r.mutable_options()->set_return_report_files(true);
    r.mutable_options()->set_return_frames(true);
    v1::PredictResponse response;
    const grpc::Status status = predict(*stub, r, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
    expectNoPredictionFolder(dir.path);

    // The same scene through the command line, in a folder of its own.
    const fs::path local = fs::path(dir.path) / "local";
    fs::create_directories(local);
    std::ofstream(local / "scene.json") << sceneText();
    std::ofstream(local / kModelName, std::ios::binary) << modelBytes();
    const auto cli = apps::testing::runCommand(
        apps::addPredictCommand, {"predict", (local / "scene.json").string(), "-o",
                                  (local / "out").string(), "--table-phi-step", "30"});
    ASSERT_EQ(cli.code, 0) << cli.err;
    const auto cli_report =
        nlohmann::json::parse(readText((local / "out" / "report.json").string()));
    const auto report = nlohmann::json::parse(response.report_json());
    EXPECT_EQ(comparable(report), comparable(cli_report));
    EXPECT_EQ(report["scene"], "scene.json");
    EXPECT_EQ(report["cameras"][0]["model"], kModelName);
    // The summary's lines per camera and plan are the command's.
    const auto daemon_lines = lines(response.summary());
    const auto cli_lines = lines(cli.out);
    ASSERT_EQ(daemon_lines.size(), cli_lines.size());
    EXPECT_EQ(daemon_lines[0], "predict: 2 cameras, 1 fixed lights, the sun -> report.html");
    for (size_t i = 1; i + 1 < cli_lines.size(); ++i) EXPECT_EQ(daemon_lines[i], cli_lines[i]);
    for (const char* file : {"figures.csv", "lab.csv", "timeline.csv", "plan.csv"}) {
        bool found = false;
        for (const auto& out : response.outputs())
            if (out.name() == file) {
                found = true;
                // The command names the model by its path, the daemon as the scene does.
                std::string expected = readText((local / "out" / file).string());
                const std::string folder = local.string() + "/";
                for (size_t at = expected.find(folder); at != std::string::npos;
                     at = expected.find(folder))
                    expected.erase(at, folder.size());
                EXPECT_EQ(out.content(), expected) << file;
            }
        EXPECT_TRUE(found) << file;
    }

    // The structured figures are report.json's.
    ASSERT_EQ(response.cameras_size(), 2);
    for (int c = 0; c < 2; ++c) {
        const v1::PredictedCamera& camera = response.cameras(c);
        const auto& j = report["cameras"][c];
        EXPECT_EQ(camera.name(), j["name"]);
        EXPECT_EQ(camera.known(), j["known"].get<bool>());
        expectFigures(camera.fixed_lights(), j["fixed_lights"], camera.name());
        ASSERT_TRUE(camera.has_contrast_ratio());
        EXPECT_EQ(camera.contrast_ratio(), j["contrast_ratio"].get<double>());
        ASSERT_EQ(camera.lights_size(), 1);
        EXPECT_EQ(camera.lights(0).state(), j["lights"][0]["state"]);
        EXPECT_EQ(camera.lights(0).theta_deg(), j["lights"][0]["theta_deg"].get<double>());
        expectFigures(camera.lights(0).figures(), j["lights"][0]["figures"], "light");
        EXPECT_EQ(camera.lights(0).has_model_theta_deg(),
                  !j["lights"][0]["model_theta_deg"].is_null());
        const auto& t = report["timeline"]["cameras"][c];
        ASSERT_TRUE(camera.has_timeline());
        EXPECT_EQ(camera.timeline().steps_drawn(), t["steps_drawn"].get<uint64_t>());
        expectSame(camera.timeline().flare_mean_max(), number(t["flare_mean_max"]), "mean max");
        expectSame(camera.timeline().contrast_loss_max(), number(t["contrast_loss_max"]), "loss");
    }
    EXPECT_GT(response.cameras(0).fixed_lights().mean(), 0.0);
    EXPECT_EQ(response.cameras(1).lights(0).state(), "behind-camera");
    ASSERT_TRUE(response.has_timeline());
    EXPECT_EQ(response.timeline().step_count(), 121u);
    ASSERT_TRUE(response.has_switching());
    ASSERT_EQ(response.switching().shots_size(),
              static_cast<int>(report["switching"]["segments"].size()));
    for (int s = 0; s < response.switching().shots_size(); ++s) {
        EXPECT_EQ(response.switching().shots(s).camera(),
                  report["switching"]["segments"][s]["camera"]);
        EXPECT_EQ(response.switching().shots(s).steps_over(),
                  report["switching"]["segments"][s]["steps_over"].get<uint64_t>());
    }
    EXPECT_EQ(response.switching().no_clean_camera_size(),
              static_cast<int>(report["switching"]["no_clean_camera"].size()));

    // Frames: an EXR and a PNG per camera at the one instant, as report.json names them.
    ASSERT_EQ(response.frames_size(), 2);
    int frame_files = 0;
    for (const auto& out : response.outputs()) frame_files += out.name().rfind("frames/", 0) == 0;
    EXPECT_EQ(frame_files, 4);
    for (const auto& frame : response.frames())
        for (const std::string& name : {frame.png(), frame.exr()}) {
            bool found = false;
            for (const auto& out : response.outputs())
                found = found || (out.name() == name && !out.content().empty());
            EXPECT_TRUE(found) << name;
        }
    bool html = false;
    for (const auto& out : response.outputs()) html = html || out.name() == "report.html";
    EXPECT_TRUE(html);
}

TEST(Predict, HandsBackOnlyTheFilesAskedFor) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::PredictResponse response;
    ASSERT_TRUE(predict(*stub, request(), &response).ok());
    EXPECT_EQ(response.outputs_size(), 0);
    EXPECT_FALSE(response.report_json().empty());
    v1::PredictRequest frames_only = request();
    frames_only.mutable_options()->set_return_frames(true);
    response.Clear();
    ASSERT_TRUE(predict(*stub, frames_only, &response).ok());
    EXPECT_EQ(response.outputs_size(), 4);
    for (const auto& out : response.outputs()) EXPECT_EQ(out.name().rfind("frames/", 0), 0u);
    expectNoPredictionFolder(dir.path);
}

TEST(Predict, RefusesWhatItMustNotReadNamingTheField) {
    TempDir dir;
    ServerOptions server;
    server.service.predict.max_input_bytes = 256 << 10;
    server.service.predict.max_files = 8;
    Daemon daemon(dir.path, {}, server);
    auto stub = daemon.stub();
    fs::create_directories(dir.path + "/elsewhere");
    std::ofstream(dir.path + "/elsewhere/" + kModelName, std::ios::binary) << modelBytes();

    const auto scene_with = [](const std::string& model) {
        std::string scene = sceneText();
        scene.replace(scene.find(kModelName), kModelName.size(), model);
        return scene;
    };
    struct Case {
        const char* what;
        std::function<void(v1::PredictRequest&)> spoil;
        grpc::StatusCode code;
        std::string message;  // a part of the message
    };
    const auto invalid = grpc::StatusCode::INVALID_ARGUMENT;
    const Case cases[] = {
        {"an absolute path",
         [&](auto& r) { r.set_scene_json(scene_with(dir.path + "/elsewhere/" + kModelName)); },
         invalid, "scene.json: cameras[0].model: "},
        {"a path with '/'", [&](auto& r) { r.set_scene_json(scene_with("sub/" + kModelName)); },
         invalid, "cameras[0].model: \"sub/moving-disc.flm\" holds a '/'"},
        {"a path with '..'", [&](auto& r) { r.set_scene_json(scene_with("../" + kModelName)); },
         invalid, "cameras[0].model: \"../moving-disc.flm\" holds \"..\""},
        {"a path that is '..'", [&](auto& r) { r.set_scene_json(scene_with("..")); }, invalid,
         "cameras[0].model: \"..\" holds \"..\""},
        {"a file not in the request", [&](auto& r) { r.set_scene_json(scene_with("other.flm")); },
         invalid,
         "cameras[0].model: \"other.flm\" is no file of the request (files: "
         "moving-disc.flm)"},
        {"a glTF venue with '/'",
         [&](auto& r) {
             std::string scene = r.scene_json();
             scene.replace(scene.find("\"cameras\""), 0,
                           "\"gltf\": {\"file\": \"/etc/venue.glb\", \"lights\": false}, ");
             r.set_scene_json(scene);
         },
         invalid, "scene.json: gltf.file: \"/etc/venue.glb\" is an absolute path"},
        {"a name given twice", [](auto& r) { *r.add_files() = r.files(0); }, invalid,
         "files[1].name: \"moving-disc.flm\" is given twice"},
        {"a name with a '/'", [](auto& r) { r.mutable_files(0)->set_name("a/b.flm"); }, invalid,
         "files[0].name: may hold only"},
        {"a name of '..'", [](auto& r) { r.mutable_files(0)->set_name(".."); }, invalid,
         "files[0].name: must not start with '.'"},
        {"a hidden name", [](auto& r) { r.mutable_files(0)->set_name(".scene.json"); }, invalid,
         "files[0].name: must not start with '.'"},
        {"an empty name", [](auto& r) { r.mutable_files(0)->set_name(""); }, invalid,
         "files[0].name: must not be empty"},
        {"a name with a space", [](auto& r) { r.mutable_files(0)->set_name("a b.flm"); }, invalid,
         "files[0].name: may hold only"},
        {"a name too long", [](auto& r) { r.mutable_files(0)->set_name(std::string(129, 'a')); },
         invalid, "files[0].name: must be at most 128"},
        {"a bad scene name", [](auto& r) { r.set_scene_name("../scene.json"); }, invalid,
         "scene_name: "},
        {"too many files",
         [](auto& r) {
             for (int i = 0; i < 8; ++i) r.add_files()->set_name("extra" + std::to_string(i));
         },
         invalid, "files: 9 files, more than the 8"},
        {"too many bytes",
         [](auto& r) {
             auto* f = r.add_files();
             f->set_name("big.bin");
             f->set_content(std::string(300 << 10, 'x'));
         },
         grpc::StatusCode::RESOURCE_EXHAUSTED, "files: "},
        {"no scene", [](auto& r) { r.clear_scene_json(); }, invalid, "scene_json: must not be"},
        {"a scene that is not JSON", [](auto& r) { r.set_scene_json("{\"format\": "); }, invalid,
         "scene.json: "},
        {"a scene with an unknown field",
         [](auto& r) {
             std::string scene = r.scene_json();
             scene.replace(scene.find("\"exposure_s\""), 0, "\"exposure\": 1, ");
             r.set_scene_json(scene);
         },
         invalid, "scene.json: cameras[0]"},
        {"a model that is not a model",
         [](auto& r) { r.mutable_files(0)->set_content("format,flarelab-model\nnot,a,model\n"); },
         invalid, "moving-disc.flm"},
        {"an empty model", [](auto& r) { r.mutable_files(0)->clear_content(); }, invalid,
         "moving-disc.flm"},
        {"a timeline too long",
         [](auto& r) {
             std::string scene = r.scene_json();
             scene.replace(scene.find("\"step_s\": 10"), 12, "\"step_s\": 0.001");
             r.set_scene_json(scene);
         },
         invalid, "scene.json: sun: 1200001 steps for 2 camera(s)"},
        {"a table too wide", [](auto& r) { r.mutable_options()->set_table_width_px(4096); },
         invalid, "options.table_width_px"},
        {"a roll step that does not divide 360",
         [](auto& r) { r.mutable_options()->set_table_phi_step_deg(7.0); }, invalid,
         "options.table_phi_step_deg"},
        {"a theta step too fine",
         [](auto& r) { r.mutable_options()->set_table_theta_step_deg(0.01); }, invalid,
         "options.table_theta_step_deg"},
        {"exposure stops that are not a number",
         [](auto& r) { r.mutable_options()->set_exposure_stops(std::nan("")); }, invalid,
         "options.exposure_stops"},
    };
    for (const Case& k : cases) {
        v1::PredictRequest r = request();
        k.spoil(r);
        v1::PredictResponse response;
        const grpc::Status s = predict(*stub, r, &response);
        EXPECT_EQ(s.error_code(), k.code) << k.what << ": " << s.error_message();
        EXPECT_NE(s.error_message().find(k.message), std::string::npos)
            << k.what << ": expected \"" << k.message << "\" in: " << s.error_message();
        // Nothing of the daemon's own folders in what a client is told.
        EXPECT_EQ(s.error_message().find(dir.path + "/predict"), std::string::npos)
            << k.what << ": " << s.error_message();
        EXPECT_EQ(response.cameras_size(), 0) << k.what;
        expectNoPredictionFolder(dir.path);
    }
    // After all that, it still predicts.
    v1::PredictResponse response;
    const grpc::Status s = predict(*stub, request(), &response);
    EXPECT_TRUE(s.ok()) << s.error_message();
}

TEST(Predict, RefusesFramesAndOutputsBeyondTheDaemonsLimits) {
    TempDir dir;
    ServerOptions server;
    server.service.predict.max_frame_pixels = 2 * 72 * 48 - 1;
    Daemon daemon(dir.path, {}, server);
    auto stub = daemon.stub();
    v1::PredictResponse response;
    grpc::Status s = predict(*stub, request(), &response);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(s.error_message().find("scene.json: frames: 1 instant(s) of 2 camera(s)"),
              std::string::npos)
        << s.error_message();
    expectNoPredictionFolder(dir.path);

    TempDir other;
    ServerOptions small;
    small.service.predict.max_output_bytes = 4096;
    Daemon second(other.path, {}, small);
    auto stub2 = second.stub();
    v1::PredictRequest r = request();
    r.mutable_options()->set_return_frames(true);
    s = predict(*stub2, r, &response);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(s.error_message().find("outputs: "), std::string::npos) << s.error_message();
    expectNoPredictionFolder(other.path);
}

TEST(Predict, RunsOneAtATimeAndRefusesASecondMeanwhile) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    const v1::PredictRequest slow = slowRequest();
    std::atomic<int> ready{0};
    grpc::Status statuses[2];
    std::thread callers[2];
    for (int i = 0; i < 2; ++i)
        callers[i] = std::thread([&, i] {
            auto own = daemon.stub();
            ++ready;
            while (ready.load() < 2) std::this_thread::yield();
            v1::PredictResponse response;
            statuses[i] = predict(*own, slow, &response, "planner-" + std::to_string(i));
        });
    for (auto& t : callers) t.join();
    int ok = 0, busy = 0;
    for (const grpc::Status& s : statuses) {
        ok += s.ok();
        if (s.error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED) {
            ++busy;
            EXPECT_NE(s.error_message().find("another prediction is running"), std::string::npos)
                << s.error_message();
        }
    }
    EXPECT_EQ(ok, 1) << statuses[0].error_message() << " / " << statuses[1].error_message();
    EXPECT_EQ(busy, 1);
    // Once it ended, the next one runs.
    v1::PredictResponse response;
    EXPECT_TRUE(predict(*stub, request(), &response).ok());
    expectNoPredictionFolder(dir.path);
}

TEST(Predict, AClientThatGivesUpFreesTheDaemonAtTheNextStep) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::PredictResponse response;
    const grpc::Status s = predict(*stub, slowRequest(), &response, "impatient", 0.5);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::DEADLINE_EXCEEDED) << s.error_message();
    // The table under way stops at its next angle (FlareFigureTable.StopsBetweenAngles), then
    // the call ends and another may run.
    grpc::Status next;
    for (int i = 0; i < 1200; ++i) {
        response.Clear();
        next = predict(*stub, request(), &response);
        if (next.error_code() != grpc::StatusCode::RESOURCE_EXHAUSTED) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    EXPECT_TRUE(next.ok()) << next.error_message();
    expectNoPredictionFolder(dir.path);
}

TEST(Predict, RunsWhileASweepRunsAndLeavesItAlone) {
    TempDir dir;
    Daemon daemon(dir.path);
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, simConfig("beside", 0.0, 1.0, 0.2, false), &job).ok());
    waitFor(*stub, job.id(), [](const v1::Job& j) { return j.state() == v1::RUNNING; });
    v1::PredictResponse response;
    const grpc::Status s = predict(*stub, request(), &response, "someone-else");
    EXPECT_TRUE(s.ok()) << s.error_message();
    EXPECT_EQ(response.cameras_size(), 2);
    const v1::Job last = waitFor(*stub, job.id(), ended);
    EXPECT_EQ(last.state(), v1::SUCCEEDED) << last.reason();
    EXPECT_EQ(last.controller(), "test");
}

TEST(Predict, AsksForTheTokenLikeEveryCall) {
    TempDir dir;
    ServerOptions server;
    server.service.token = "predict-token-0123456789";
    Daemon daemon(dir.path, {}, server);
    auto stub = daemon.stub();
    v1::PredictResponse response;
    EXPECT_EQ(predict(*stub, request(), &response).error_code(), grpc::StatusCode::UNAUTHENTICATED);
    testToken() = server.service.token;
    EXPECT_TRUE(predict(*stub, request(), &response).ok());
    testToken().clear();
}

TEST(Predict, AStartingDaemonRemovesWhatAKilledOneLeft) {
    TempDir dir;
    const fs::path left = fs::path(dir.path) / "predict" / "p-abc123" / "in";
    fs::create_directories(left);
    std::ofstream(left / "scene.json") << "{}";
    Daemon daemon(dir.path);
    EXPECT_FALSE(fs::exists(left.parent_path()));
}

}  // namespace
}  // namespace flarelab::daemon
