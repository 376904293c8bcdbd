#include "apps/model_command.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "apps/bench_command.h"
#include "fit/model_file.h"
#include "fit/sweep_fit.h"
#include "hdr/exr.h"
#include "tests/apps/command_runner.h"
#include "tests/test_files.h"

namespace flarelab::apps {
namespace {

using flarelab::testing::contains;
using flarelab::testing::TempDir;

namespace fs = std::filesystem;
using testing::CommandRun;

CommandRun model(std::vector<std::string> args) {
    args.insert(args.begin(), "model");
    return testing::runCommand(addModelCommands, args);
}

fit::FlareModel smallModel() {
    fit::FlareModel m;
    m.software_version = "flarelab test";
    m.created_utc = "2026-11-29T07:04:02Z";
    m.lens.description = "heliar 50mm";
    m.lens.prescription_file = "heliar-50.csv";
    m.lens.f_number = 4.5;
    m.lens.focal_length_mm = 50.0;
    m.lens.sensor_width_mm = 36.0;
    m.lens.sensor_height_mm = 24.0;
    m.capture.from_deg = -4.0;
    m.capture.to_deg = 4.0;
    m.capture.step_deg = 0.5;
    m.capture.exposure_times_s = {0.001, 0.1};
    m.capture.width_px = 64;
    m.capture.height_px = 48;
    m.capture.camera = "mono test camera";
    m.capture.raw_format = "mono";
    m.valid_from_deg = -4.0;
    m.valid_to_deg = 4.0;
    fit::ModelGhost g;
    g.id = 3;
    g.name = "surfaces 2-5";
    g.parameters.push_back({"segment[0].p0.x_mm", "mm", -18.0, 18.0, {}, {}, {}});
    g.parameters[0].pieces.push_back({-3.0, 0.0, {1.0, 0.5, 0.25}, 0.02, 0.05, 7});
    g.parameters[0].pieces.push_back({0.0, 3.0, {1.0, 0.5}, 0.03, 0.04, 7});
    g.parameters.push_back({"inner_intensity.g", "1", 0.0, std::nullopt, {}, {}, {}});
    g.parameters[1].pieces.push_back({-3.0, 3.0, {0.125}, 0.001, 0.002, 13});
    g.fit = {13, -3.0, 3.0};
    m.ghosts.push_back(g);
    return m;
}

TEST(ModelShow, PrintsLensCaptureRangeAndGhosts) {
    TempDir dir;
    const std::string path = dir.file("heliar.flaremodel");
    ASSERT_TRUE(fit::writeModel(path, smallModel()));
    const CommandRun run = model({"show", path});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_TRUE(run.err.empty()) << run.err;
    for (const char* part :
         {"format 5", "written by flarelab test", "created 2026-11-29T07:04:02Z",
          "lens: heliar 50mm, 50 mm, f/4.5, sensor 36 x 24 mm", "prescription: heliar-50.csv",
          "capture: -4 to 4 deg in steps of 0.5 deg", "64x48 pixels",
          "camera mono test camera, raw format mono", "light power: not measured",
          "2 exposures of 0.001 0.1 s", "valid range: -4 to 4 deg", "ghosts: 1",
          "ghost 3 (surfaces 2-5): -3 to 3 deg, 13 frames fitted", "2 parameters",
          "segment[0].p0.x_mm [mm], bounds -18..18: 2 pieces, degrees 2 1, residual rms <= 0.03, "
          "max 0.05",
          "inner_intensity.g [1], bounds 0..inf: 1 piece, degree 0, residual rms 0.001, max 0.002"})
        EXPECT_TRUE(contains(run.out, part)) << "missing '" << part << "' in:\n" << run.out;
}

TEST(ModelShow, JsonIsTheModelsJsonMapping) {
    TempDir dir;
    const std::string path = dir.file("heliar.flaremodel");
    const fit::FlareModel written = smallModel();
    ASSERT_TRUE(fit::writeModel(path, written));
    const CommandRun run = model({"show", path, "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"format_version\": 5")) << run.out;
    const Result<fit::FlareModel> back = fit::modelFromJson(run.out, "stdout");
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(*back, written);
}

TEST(ModelShow, MissingFileIsAnErrorNamingIt) {
    TempDir dir;
    const CommandRun run = model({"show", dir.file("none.flaremodel")});
    EXPECT_EQ(run.code, 1);
    EXPECT_TRUE(run.out.empty());
    EXPECT_TRUE(contains(run.err, "none.flaremodel")) << run.err;
}

TEST(ModelShow, BrokenFileIsAnErrorNamingIt) {
    TempDir dir;
    const std::string path = dir.file("broken.flaremodel");
    ASSERT_TRUE(fit::writeModel(path, smallModel()));
    // Cut the file short.
    fs::resize_file(path, fs::file_size(path) / 2);
    const CommandRun run = model({"show", path, "--json"});
    EXPECT_EQ(run.code, 1);
    EXPECT_TRUE(run.out.empty()) << run.out;
    EXPECT_TRUE(contains(run.err, "flarelab: " + path + ": ")) << run.err;

    const std::string text = dir.file("text.flaremodel");
    std::ofstream(text) << "not a model\n";
    const CommandRun text_run = model({"show", text});
    EXPECT_EQ(text_run.code, 1);
    EXPECT_TRUE(contains(text_run.err, text)) << text_run.err;
}

// A model of one still disc (radius 4 mm at the sensor's centre, border 2, inner 3, sharp edge)
// fitted at three angles, on a 36 x 24 mm sensor of 72 x 48 pixels.
fit::FlareModel discModel() {
    fit::GhostState disc;
    disc.shape.half_height_mm = disc.shape.left_mm = disc.shape.right_mm = 4.0;
    for (double* h : {&disc.shape.left_handle_x_mm, &disc.shape.left_handle_y_mm,
                      &disc.shape.right_handle_x_mm, &disc.shape.right_handle_y_mm})
        *h = 4.0 * render::kCircleHandle;
    disc.shading.border_rgb = {2.0, 2.0, 2.0};
    disc.shading.inner_rgb = {3.0, 3.0, 3.0};
    disc.shading.inner_falloff_mm = 0.5;
    disc.shading.outer_falloff_mm = 0.05;
    fit::SweepFitResult tracks;
    tracks.frame_count = 3;
    tracks.tracks.resize(1);
    tracks.tracks[0].id = 1;
    for (double angle : {0.0, 1.0, 2.0}) tracks.tracks[0].samples.push_back({angle, disc, 0.0});
    fit::FlareModel shell = smallModel();
    shell.ghosts.clear();
    shell.capture.from_deg = shell.valid_from_deg = 0.0;
    shell.capture.to_deg = shell.valid_to_deg = 2.0;
    shell.capture.width_px = 72;
    shell.capture.height_px = 48;
    auto built = fit::buildModel(tracks, shell, fit::SweepFitOptions{});
    EXPECT_TRUE(built) << built.error().message;
    return *built;
}

TEST(ModelRender, DrawsTheModelAtAnAngleToExrAndPng) {
    const fs::path dir =
        fs::temp_directory_path() / ("flarelab_model_render_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const std::string path = (dir / "disc.flm").string();
    ASSERT_TRUE(fit::writeModel(path, discModel()));
    const std::string exr = (dir / "disc.exr").string(), png = (dir / "disc.png").string();
    CommandRun r = model({"render", path, "--angle", "1.5", "-o", exr, "--png", png});
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "1 ghosts at 1.5 deg")) << r.out;
    EXPECT_TRUE(fs::exists(png));
    auto image = hdr::readExr(exr);
    ASSERT_TRUE(image) << image.error().message;
    ASSERT_EQ(image->image.width, 72);
    ASSERT_EQ(image->image.height, 48);
    EXPECT_EQ(image->meta.angle_deg, 1.5);
    EXPECT_NEAR(image->image.at(36, 24)[1], 3.0, 1e-3);  // the centre: inner intensity
    EXPECT_EQ(image->image.at(2, 2)[1], 0.0f);           // far outside the disc
    // Another size and a light twice as strong.
    r = model({"render", path, "--angle", "1.5", "--width", "36", "--height", "24", "--intensity",
               "2", "-o", exr});
    ASSERT_EQ(r.code, 0) << r.err;
    image = hdr::readExr(exr);
    ASSERT_TRUE(image);
    EXPECT_EQ(image->image.width, 36);
    EXPECT_NEAR(image->image.at(18, 12)[0], 6.0, 2e-3);
    // Outside the valid range, no output, a bad intensity: refused, naming what is wrong.
    r = model({"render", path, "--angle", "2.5", "-o", exr});
    EXPECT_EQ(r.code, 1);
    EXPECT_TRUE(contains(r.err, "valid range")) << r.err;
    r = model({"render", path, "--angle", "1"});
    EXPECT_EQ(r.code, 2);
    EXPECT_TRUE(contains(r.err, "--png")) << r.err;
    r = model({"render", path, "--angle", "1", "--intensity", "-1", "-o", exr});
    EXPECT_NE(r.code, 0);
    EXPECT_TRUE(contains(r.err, "--intensity")) << r.err;
    r = model({"render", (dir / "missing.flm").string(), "--angle", "1", "-o", exr});
    EXPECT_EQ(r.code, 1);
    EXPECT_TRUE(contains(r.err, "missing.flm")) << r.err;
    fs::remove_all(dir);
}

// --exact draws every pixel the old way; the default fast image stays within the fast path's
// error of it, and `flarelab bench playback` measures the two (frame time, ghosts, error).
TEST(ModelRender, ExactIsTheReferenceThatBenchPlaybackMeasuresAgainst) {
    const fs::path dir =
        fs::temp_directory_path() / ("flarelab_model_playback_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const std::string path = (dir / "disc.flm").string();
    ASSERT_TRUE(fit::writeModel(path, discModel()));
    const std::string fast_exr = (dir / "fast.exr").string(),
                      exact_exr = (dir / "exact.exr").string();
    ASSERT_EQ(model({"render", path, "--angle", "1", "-o", fast_exr}).code, 0);
    ASSERT_EQ(model({"render", path, "--angle", "1", "--exact", "-o", exact_exr}).code, 0);
    const auto fast = hdr::readExr(fast_exr), exact = hdr::readExr(exact_exr);
    ASSERT_TRUE(fast && exact);
    double peak = 0.0, worst = 0.0;
    for (size_t i = 0; i < exact->image.pixels.size(); ++i) {
        peak = std::max(peak, static_cast<double>(exact->image.pixels[i]));
        worst = std::max(
            worst, static_cast<double>(std::abs(fast->image.pixels[i] - exact->image.pixels[i])));
    }
    EXPECT_GT(peak, 2.9);
    EXPECT_LT(worst, 2e-3 * peak);

    const std::string json_path = (dir / "playback.json").string();
    const CommandRun run = testing::runCommand(
        addBenchCommands, {"bench", "playback", path, "--width", "72", "--height", "48", "--frames",
                           "2", "--json", json_path});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "frame_ms")) << run.out;
    std::ifstream file(json_path);
    const nlohmann::json doc = nlohmann::json::parse(file);
    EXPECT_EQ(doc.at("ghosts").get<int>(), 1);
    EXPECT_GT(doc.at("frame_ms").get<double>(), 0.0);
    EXPECT_GE(doc.at("max_rel_err").get<double>(), 0.0);
    EXPECT_LT(doc.at("max_rel_err").get<double>(), 2e-3);
    EXPECT_EQ(doc.at("width").get<int>(), 72);

    const CommandRun missing = testing::runCommand(
        addBenchCommands, {"bench", "playback", (dir / "missing.flm").string()});
    EXPECT_EQ(missing.code, 1);
    EXPECT_TRUE(contains(missing.err, "missing.flm")) << missing.err;
    fs::remove_all(dir);
}

TEST(ModelShow, RequiresAModelArgument) {
    const CommandRun run = model({"show"});
    EXPECT_NE(run.code, 0);
}

}  // namespace
}  // namespace flarelab::apps
