#include "apps/model_command.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "fit/model_file.h"
#include "tests/apps/command_runner.h"

namespace flarelab::apps {
namespace {

namespace fs = std::filesystem;
using testing::CommandRun;

CommandRun model(std::vector<std::string> args) {
    args.insert(args.begin(), "model");
    return testing::runCommand(addModelCommands, args);
}

bool contains(const std::string& text, const std::string& part) {
    return text.find(part) != std::string::npos;
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
    m.valid_from_deg = -4.0;
    m.valid_to_deg = 4.0;
    fit::ModelGhost g;
    g.id = 3;
    g.name = "surfaces 2-5";
    g.parameters.push_back({"segment[0].p0.x_mm", "mm", -18.0, 18.0, {}});
    g.parameters[0].pieces.push_back({-3.0, 0.0, {1.0, 0.5, 0.25}, 0.02, 0.05, 7});
    g.parameters[0].pieces.push_back({0.0, 3.0, {1.0, 0.5}, 0.03, 0.04, 7});
    g.parameters.push_back({"inner_intensity.g", "1", 0.0, std::nullopt, {}});
    g.parameters[1].pieces.push_back({-3.0, 3.0, {0.125}, 0.001, 0.002, 13});
    g.fit = {13, -3.0, 3.0};
    m.ghosts.push_back(g);
    return m;
}

// A model file in a fresh directory, removed afterwards.
class ModelDir {
public:
    ModelDir() {
        static int counter = 0;
        dir_ = fs::temp_directory_path() /
               ("flarelab-model-command-test-" + std::to_string(::getpid()) + "-" +
                std::to_string(counter++));
        fs::remove_all(dir_);
        fs::create_directories(dir_);
    }
    ~ModelDir() {
        std::error_code ec;
        fs::remove_all(dir_, ec);
    }
    std::string file(const std::string& name) const { return (dir_ / name).string(); }

private:
    fs::path dir_;
};

TEST(ModelShow, PrintsLensCaptureRangeAndGhosts) {
    ModelDir dir;
    const std::string path = dir.file("heliar.flaremodel");
    ASSERT_TRUE(fit::writeModel(path, smallModel()));
    const CommandRun run = model({"show", path});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_TRUE(run.err.empty()) << run.err;
    for (const char* part :
         {"format 1", "written by flarelab test", "created 2026-11-29T07:04:02Z",
          "lens: heliar 50mm, 50 mm, f/4.5, sensor 36 x 24 mm", "prescription: heliar-50.csv",
          "capture: -4 to 4 deg in steps of 0.5 deg", "64x48 pixels", "mono test camera",
          "2 exposures of 0.001 0.1 s", "valid range: -4 to 4 deg", "ghosts: 1",
          "ghost 3 (surfaces 2-5): -3 to 3 deg, 13 frames fitted", "2 parameters",
          "segment[0].p0.x_mm [mm], bounds -18..18: 2 pieces, degrees 2 1, residual rms <= 0.03, "
          "max 0.05",
          "inner_intensity.g [1], bounds 0..inf: 1 piece, degree 0, residual rms 0.001, max 0.002"})
        EXPECT_TRUE(contains(run.out, part)) << "missing '" << part << "' in:\n" << run.out;
}

TEST(ModelShow, JsonIsTheModelsJsonMapping) {
    ModelDir dir;
    const std::string path = dir.file("heliar.flaremodel");
    const fit::FlareModel written = smallModel();
    ASSERT_TRUE(fit::writeModel(path, written));
    const CommandRun run = model({"show", path, "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"format_version\": 1")) << run.out;
    const Result<fit::FlareModel> back = fit::modelFromJson(run.out, "stdout");
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(*back, written);
}

TEST(ModelShow, MissingFileIsAnErrorNamingIt) {
    ModelDir dir;
    const CommandRun run = model({"show", dir.file("none.flaremodel")});
    EXPECT_EQ(run.code, 1);
    EXPECT_TRUE(run.out.empty());
    EXPECT_TRUE(contains(run.err, "none.flaremodel")) << run.err;
}

TEST(ModelShow, BrokenFileIsAnErrorNamingIt) {
    ModelDir dir;
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

TEST(ModelShow, RequiresAModelArgument) {
    const CommandRun run = model({"show"});
    EXPECT_NE(run.code, 0);
}

}  // namespace
}  // namespace flarelab::apps
