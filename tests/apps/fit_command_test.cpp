#include "apps/fit_command.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "apps/capture_command.h"
#include "drivers/sim_truth.h"
#include "fit/model_eval.h"
#include "fit/model_file.h"
#include "fit/score.h"
#include "hdr/sweep.h"
#include "render/preview.h"
#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

namespace fs = std::filesystem;
using testing::CommandRun;

CommandRun run(const std::vector<std::string>& args) {
    return testing::runCommand(addFitCommands, args);
}

std::string sweepDir() {
    return std::string(FLARELAB_SOURCE_DIR) + "/tests/data/sweeps/heliar-raw";
}
std::string lensFile() { return flarelab::testing::lensPath("heliar-tronnier.csv"); }

fs::path tempPath(const std::string& name) {
    return fs::temp_directory_path() /
           ("flarelab_fit_test_" + std::to_string(getpid()) + "_" + name);
}

// The recorded 160 x 107 Heliar sweep (0 to 2 deg, 5 frames) is fitted with no human input into a
// model that records the lens, and `score` re-simulates it and reports both error summaries.
TEST(FitCommand, FitsARecordedSweepAndScoresTheModel) {
    const fs::path model = tempPath("heliar.flm");
    const CommandRun fitted =
        run({"fit", sweepDir(), "--lens", lensFile(), "-o", model.string(), "--quiet"});
    ASSERT_EQ(fitted.code, 0) << fitted.err;
    EXPECT_NE(fitted.out.find("ghosts from 5 frames"), std::string::npos) << fitted.out;
    auto read = fit::readModel(model.string());
    ASSERT_TRUE(read.has_value()) << read.error().message;
    EXPECT_EQ(read->lens.prescription_sha256.size(), 64u);
    EXPECT_EQ(read->capture.width_px, 160);
    EXPECT_EQ(read->valid_from_deg, 0.0);
    EXPECT_EQ(read->valid_to_deg, 2.0);

    const CommandRun scored = run({"score", model.string(), "--lens", lensFile(), "--json",
                                   "--halfway", "2", "--random", "1", "--fitted", "2"});
    ASSERT_EQ(scored.code, 0) << scored.err;
    const auto json = nlohmann::json::parse(scored.out);
    for (const char* key : {"heldout_rel_l2", "fit_rel_l2"}) {
        ASSERT_TRUE(json.contains(key)) << key;
        EXPECT_TRUE(json[key].contains("median"));
        EXPECT_TRUE(json[key].contains("worst"));
        EXPECT_GE(json[key]["worst"].get<double>(), json[key]["median"].get<double>());
        EXPECT_TRUE(std::isfinite(json[key]["worst"].get<double>()));
    }
    EXPECT_EQ(json["heldout_rel_l2"]["count"].get<int>(), 3);
    // The recorded sweep (format 1) does not say whether its camera was colour: the score says
    // what it chose and why.
    EXPECT_NE(scored.err.find("does not record the camera's raw format; its ghosts' colour "
                              "channels agree, so it is scored against the monochrome (green) "
                              "truth"),
              std::string::npos)
        << scored.err;
    // Explicit held-out angles outside the model's range are refused by name.
    const CommandRun outside =
        run({"score", model.string(), "--lens", lensFile(), "--angles", "5"});
    EXPECT_NE(outside.code, 0);
    EXPECT_NE(outside.err.find("outside the model's valid range"), std::string::npos)
        << outside.err;
    // A model is scored only with the lens it was fitted with.
    const CommandRun other = run({"score", model.string(), "--lens",
                                  flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv")});
    EXPECT_EQ(other.code, 2);
    EXPECT_NE(other.err.find("not the lens the model was fitted with"), std::string::npos)
        << other.err;
    fs::remove(model);
}

// The sparse protocol: a fit of every other frame (0, 1 and 2 deg) scored with its sweep holds
// the frames it left out (0.5 and 1.5 deg) out, reports every figure per kind, and draws truth,
// model and difference side by side for each angle.
TEST(FitCommand, ASparseFitIsScoredOnTheFramesItLeftOut) {
    const fs::path model = tempPath("sparse.flm");
    const fs::path images = tempPath("score-images");
    const CommandRun fitted = run(
        {"fit", sweepDir(), "--lens", lensFile(), "--every", "2", "-o", model.string(), "--quiet"});
    ASSERT_EQ(fitted.code, 0) << fitted.err;
    EXPECT_NE(fitted.out.find("ghosts from 3 frames (one in every 2)"), std::string::npos)
        << fitted.out;
    auto read = fit::readModel(model.string());
    ASSERT_TRUE(read.has_value()) << read.error().message;
    EXPECT_EQ(read->capture.step_deg, 1.0);
    EXPECT_EQ(read->valid_to_deg, 2.0);

    const CommandRun scored =
        run({"score", model.string(), "--lens", lensFile(), "--sweep", sweepDir(), "--json",
             "--halfway", "0", "--random", "1", "--fitted", "1", "--images", images.string()});
    ASSERT_EQ(scored.code, 0) << scored.err;
    const auto json = nlohmann::json::parse(scored.out);
    ASSERT_TRUE(json["by_kind"].contains("left-out")) << scored.out;
    EXPECT_EQ(json["by_kind"]["left-out"]["count"].get<int>(), 2);
    std::vector<double> left;
    // The fit recorded the light's disc of each frame it fitted; the score leaves out that disc
    // (between fitted frames, interpolated).
    ASSERT_EQ(read->capture.light_discs.size(), 3u);
    for (const auto& a : json["angles"]) {
        for (const char* key :
             {"rel_l2", "energy_error", "log_rel_l2", "masked_energy_fraction", "light_mask_px"})
            EXPECT_TRUE(std::isfinite(a[key].get<double>())) << key;
        if (a["kind"] == "left-out") left.push_back(a["angle_deg"].get<double>());
        EXPECT_DOUBLE_EQ(a["light_mask_px"].get<double>(),
                         *fit::lightDiscRadius(*read, a["angle_deg"].get<double>()))
            << a["angle_deg"];
    }
    EXPECT_EQ(left, (std::vector<double>{0.5, 1.5}));
    const CommandRun fixed =
        run({"score", model.string(), "--lens", lensFile(), "--json", "--halfway", "1", "--random",
             "0", "--fitted", "1", "--light-mask-px", "7.5"});
    ASSERT_EQ(fixed.code, 0) << fixed.err;
    const auto fixed_json = nlohmann::json::parse(fixed.out);
    for (const auto& a : fixed_json["angles"])
        EXPECT_TRUE(a["light_mask_px"] == 7.5 || a["light_mask_px"] == 0.0) << fixed.out;
    EXPECT_EQ(run({"score", model.string(), "--lens", lensFile(), "--light-mask-px", "-1"}).code,
              2);
    // A model of format 4 records no disc: 3 % of the diagonal, and the score says so.
    fit::FlareModel older = *read;
    older.format_version = 4;
    older.capture.light_discs.clear();
    const fs::path older_path = tempPath("older.flm");
    ASSERT_TRUE(fit::writeModel(older_path.string(), older));
    const CommandRun old_score = run({"score", older_path.string(), "--lens", lensFile(), "--json",
                                      "--halfway", "1", "--random", "0", "--fitted", "1"});
    ASSERT_EQ(old_score.code, 0) << old_score.err;
    EXPECT_NE(old_score.err.find("does not record the light's disc"), std::string::npos)
        << old_score.err;
    const auto old_json = nlohmann::json::parse(old_score.out);
    for (const auto& a : old_json["angles"])
        EXPECT_TRUE(a["light_mask_px"] == 0.0 || std::abs(a["light_mask_px"].get<double>() -
                                                          0.03 * std::hypot(160.0, 107.0)) < 1e-9)
            << old_score.out;
    fs::remove(older_path);
    // One image per angle, three frames wide.
    int pngs = 0;
    for (const auto& entry : fs::directory_iterator(images)) {
        auto png = render::readPng(entry.path().string());
        ASSERT_TRUE(png) << png.error().message;
        EXPECT_EQ(png->width, 3 * 160 + 8);
        EXPECT_EQ(png->height, 107);
        ++pngs;
    }
    EXPECT_EQ(pngs, static_cast<int>(json["angles"].size()));

    // A sweep that is not the model's is refused by what differs.
    const CommandRun other = run({"score", model.string(), "--lens", lensFile(), "--sweep",
                                  flarelab::testing::sourcePath("tests/data/sweeps/nikon-hdr")});
    EXPECT_EQ(other.code, 2);
    EXPECT_NE(other.err.find("not the sweep the model was fitted to"), std::string::npos)
        << other.err;
    // Every frame fitted: nothing is left out, and the score says so.
    EXPECT_EQ(run({"fit", sweepDir(), "--lens", lensFile(), "-o", model.string(), "--quiet"}).code,
              0);
    const CommandRun dense = run({"score", model.string(), "--lens", lensFile(), "--sweep",
                                  sweepDir(), "--halfway", "1", "--random", "0", "--fitted", "1"});
    EXPECT_EQ(dense.code, 0) << dense.err;
    EXPECT_NE(dense.err.find("no frame is left out"), std::string::npos) << dense.err;
    EXPECT_EQ(run({"fit", sweepDir(), "--lens", lensFile(), "--every", "9", "-o", model.string(),
                   "--quiet"})
                  .code,
              1);
    fs::remove(model);
    fs::remove_all(images);
}

// A colour capture (a Bayer sensor, demosaiced frames) is fitted in colour and scored against a
// colour truth. The Heliar's coating (a quarter wave at 620 nm) reflects several times more blue
// than green, so its ghosts are blue: a model scored against the green truth copied to three
// channels, as every capture was before the sweep recorded its raw format, was off by some 200 %
// in energy however well it fitted.
TEST(FitCommand, AColourCaptureIsFittedAndScoredInColour) {
    const fs::path sweep = tempPath("colour");
    const fs::path model = tempPath("colour.flm");
    fs::remove_all(sweep);
    const CommandRun captured = testing::runCommand(
        addCaptureCommand, {"capture", "--sim", "--fast", "--format", "bayer-rggb", "--lens",
                            lensFile(), "--from", "0", "--to", "2", "--step", "0.5", "--width",
                            "160", "--height", "107", "-o", sweep.string()});
    ASSERT_EQ(captured.code, 0) << captured.err;
    const CommandRun fitted = run(
        {"fit", sweep.string(), "--lens", lensFile(), "--paths", "-o", model.string(), "--quiet"});
    ASSERT_EQ(fitted.code, 0) << fitted.err;
    auto read = fit::readModel(model.string());
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->capture.raw_format, "bayer-rggb");
    bool recorded = false;
    EXPECT_TRUE(fit::fittedInColour(*read, &recorded));
    EXPECT_TRUE(recorded);

    // Channel by channel, the model's light against the colour truth's at an angle between frames.
    std::ostringstream notes;
    const auto lens = captureLens(lensFile(), *read, model.string(), notes);
    ASSERT_TRUE(lens) << notes.str();
    auto truth = drivers::simulatedGhostTruth(*lens, 160, 107, {}, true);
    ASSERT_TRUE(truth) << truth.error().message;
    const auto frame = (*truth)(1.25);
    ASSERT_TRUE(frame) << frame.error().message;
    const auto drawn = fit::renderModel(*read, 1.25, read->capture.roll_deg, 160, 107);
    ASSERT_TRUE(drawn) << drawn.error().message;
    std::array<double, 3> truth_energy{}, model_energy{};
    for (size_t i = 0; i < drawn->pixels.size(); ++i) {
        truth_energy[i % 3] += frame->image.pixels[i];
        model_energy[i % 3] += drawn->pixels[i];
    }
    EXPECT_GT(truth_energy[2], 2.0 * truth_energy[1]);  // blue ghosts
    for (size_t c = 0; c < 3; ++c)
        EXPECT_NEAR(model_energy[c] / truth_energy[c], 1.0, 0.4) << "channel " << c;
    EXPECT_NEAR((model_energy[2] / model_energy[1]) / (truth_energy[2] / truth_energy[1]), 1.0,
                0.25);

    // The score chooses the colour truth from the model, with no note.
    const CommandRun scored = run({"score", model.string(), "--lens", lensFile(), "--json",
                                   "--angles", "1.25", "--fitted", "1"});
    ASSERT_EQ(scored.code, 0) << scored.err;
    EXPECT_EQ(scored.err.find("note:"), std::string::npos) << scored.err;
    const auto json = nlohmann::json::parse(scored.out);
    for (const auto& a : json["angles"])
        EXPECT_LT(std::abs(a["energy_error"].get<double>()), 0.4) << a["angle_deg"];
    // A model that does not record its raw format (one fitted before sweep format 4) is scored in
    // colour by its channels, and the score says so.
    fit::FlareModel unrecorded = *read;
    unrecorded.capture.raw_format.clear();
    ASSERT_TRUE(fit::writeModel(model.string(), unrecorded));
    const CommandRun inferred = run({"score", model.string(), "--lens", lensFile(), "--json",
                                     "--angles", "1.25", "--fitted", "1"});
    ASSERT_EQ(inferred.code, 0) << inferred.err;
    EXPECT_NE(inferred.err.find("its ghosts' colour channels differ, so it is scored against the "
                                "colour (RGB) truth"),
              std::string::npos)
        << inferred.err;
    EXPECT_EQ(nlohmann::json::parse(inferred.out)["heldout_rel_l2"], json["heldout_rel_l2"]);
    fs::remove_all(sweep);
    fs::remove(model);
}

// A lab without the prescription scores a sparse fit against the sweep's own frames: the
// fitted and the left-out ones, no others (no frame was captured between them); the model
// explains most of their ghost light, and an empty model none of it.
TEST(FitCommand, ASparseFitIsScoredAgainstTheSweepsOwnFrames) {
    const fs::path model = tempPath("measured.flm");
    const fs::path empty = tempPath("measured-empty.flm");
    ASSERT_EQ(run({"fit", sweepDir(), "--lens", lensFile(), "--every", "2", "-o", model.string(),
                   "--quiet"})
                  .code,
              0);
    const auto medianOf = [&](const fs::path& path) {
        const CommandRun scored =
            run({"score", path.string(), "--measured", "--sweep", sweepDir(), "--json"});
        EXPECT_EQ(scored.code, 0) << scored.err;
        if (scored.code != 0) return -1.0;
        const auto json = nlohmann::json::parse(scored.out);
        EXPECT_EQ(json["by_kind"].size(), 2u) << scored.out;
        EXPECT_EQ(json["by_kind"]["left-out"]["count"].get<int>(), 2) << scored.out;
        EXPECT_EQ(json["by_kind"]["fitted"]["count"].get<int>(), 3) << scored.out;
        for (const auto& a : json["angles"])
            for (const char* key : {"rel_l2", "energy_error", "log_rel_l2", "light_mask_px"})
                EXPECT_TRUE(std::isfinite(a[key].get<double>())) << key;
        return json["heldout_rel_l2"]["median"].get<double>();
    };
    const double fitted = medianOf(model);
    EXPECT_GT(fitted, 0.0);
    EXPECT_LT(fitted, 0.5);
    auto read = fit::readModel(model.string());
    ASSERT_TRUE(read.has_value()) << read.error().message;
    read->ghosts.clear();
    ASSERT_TRUE(fit::writeModel(empty.string(), *read));
    EXPECT_NEAR(medianOf(empty), 1.0, 1e-9);
    // What it needs: the sweep, whose frames it scores against; without --measured, the lens.
    CommandRun r = run({"score", model.string(), "--measured", "--json"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("--sweep"), std::string::npos) << r.err;
    r = run({"score", model.string(), "--sweep", sweepDir(), "--json"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("--lens is required"), std::string::npos) << r.err;
    r = run({"score", model.string(), "--measured", "--sweep", sweepDir(), "--lens", lensFile()});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("simulates nothing"), std::string::npos) << r.err;
    r = run({"score", model.string(), "--measured", "--sweep", sweepDir(), "--angles", "0.25"});
    EXPECT_NE(r.code, 0);
    EXPECT_NE(r.err.find("no frame captured at 0.25"), std::string::npos) << r.err;
    fs::remove(model);
    fs::remove(empty);
}

TEST(FitCommand, RefusesWhatItCannotUse) {
    const fs::path model = tempPath("refused.flm");
    // The recorded sweep has no pixel pitch: without --lens or --sensor-mm the sensor is unknown.
    CommandRun r = run({"fit", sweepDir(), "-o", model.string(), "--quiet"});
    EXPECT_NE(r.code, 0);
    EXPECT_NE(r.err.find("--sensor-mm"), std::string::npos) << r.err;
    r = run({"fit", sweepDir(), "-o", model.string(), "--sensor-mm", "36x", "--quiet"});
    EXPECT_EQ(r.code, 2);
    r = run(
        {"fit", sweepDir(), "-o", model.string(), "--sensor-mm", "36x24", "--optimizer", "newton"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("--optimizer"), std::string::npos);
    r = run({"fit", sweepDir(), "-o", model.string(), "--sensor-mm", "36x24", "--samples", "2"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("max_samples"), std::string::npos) << r.err;
    r = run({"fit", sweepDir(), "-o", model.string(), "--sensor-mm", "36x24", "--paths"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("--paths needs --lens"), std::string::npos) << r.err;
    r = run({"fit", "/nonexistent/sweep", "-o", model.string()});
    EXPECT_NE(r.code, 0);
    EXPECT_FALSE(fs::exists(model));
    // (A model scored with another lens than its own: FitsARecordedSweepAndScoresTheModel.)
}

// The tracking and cost knobs reach the fit: a culling share of 0.9 ends every ghost holding less
// than nine tenths of its frame's ghost light, so the model holds fewer ghosts than with no cull;
// values out of range are refused by name.
TEST(FitCommand, TheTrackAndCostKnobsReachTheFit) {
    const fs::path model = tempPath("knobs.flm");
    const auto ghostsWith = [&](std::vector<std::string> extra) -> int64_t {
        std::vector<std::string> args = {"fit", sweepDir(),     "--lens", lensFile(),
                                         "-o",  model.string(), "--quiet"};
        args.insert(args.end(), extra.begin(), extra.end());
        const CommandRun fitted = run(args);
        EXPECT_EQ(fitted.code, 0) << fitted.err;
        auto read = fit::readModel(model.string());
        EXPECT_TRUE(read.has_value());
        return read ? static_cast<int64_t>(read->ghosts.size()) : -1;
    };
    const int64_t every = ghostsWith({"--min-energy-fraction", "0"});
    const int64_t culled = ghostsWith({"--min-energy-fraction", "0.9"});
    EXPECT_GE(every, 2);
    EXPECT_LT(culled, every);
    // Tracks shorter than the sweep are dropped when every track must span all 5 frames.
    EXPECT_LE(ghostsWith({"--min-track-frames", "5"}), ghostsWith({"--min-track-frames", "1"}));
    EXPECT_GE(ghostsWith({"--residual-detection"}), 1);
    for (const auto& [flag, value] :
         std::vector<std::pair<std::string, std::string>>{{"--min-track-frames", "0"},
                                                          {"--min-energy-fraction", "-0.1"},
                                                          {"--min-energy-fraction", "1"},
                                                          {"--max-missed", "-1"},
                                                          {"--max-circles", "-1"},
                                                          {"--transform-fraction", "-1"},
                                                          {"--robust-scale", "0"}}) {
        const CommandRun r = run({"fit", sweepDir(), "--lens", lensFile(), flag, value, "-o",
                                  model.string(), "--quiet"});
        EXPECT_NE(r.code, 0) << flag << " " << value;
        EXPECT_NE(r.err.find(flag == "--min-energy-fraction" && value == "1" ? "min_energy_fraction"
                                                                             : flag),
                  std::string::npos)
            << flag << ": " << r.err;
    }
    fs::remove(model);
}

TEST(FitCommand, PathsSeedTheTracksFromThePrescription) {
    // The recorded Heliar sweep, 0 to 2 deg: with --paths its ghosts are the lens's paths, each
    // one track, so the model holds no more ghosts than the lens has paths lit there.
    const fs::path model = tempPath("heliar-paths.flm");
    const CommandRun fitted =
        run({"fit", sweepDir(), "--lens", lensFile(), "--paths", "-o", model.string(), "--quiet"});
    ASSERT_EQ(fitted.code, 0) << fitted.err;
    auto read = fit::readModel(model.string());
    ASSERT_TRUE(read.has_value()) << read.error().message;
    EXPECT_GE(read->ghosts.size(), 1u);
    EXPECT_LE(read->ghosts.size(), 13u);  // the Heliar's two-reflection paths
    const CommandRun scored = run({"score", model.string(), "--lens", lensFile(), "--json",
                                   "--halfway", "2", "--random", "1", "--fitted", "2"});
    ASSERT_EQ(scored.code, 0) << scored.err;
    fs::remove(model);
}

// A simulated capture of format version 3 with six blades, fitted and scored through the
// commands: the model copies the sweep's settings, `score` rebuilds that lens without a note, and
// flags or files that contradict what the sweep records are refused rather than one picked.
TEST(FitCommand, TheSweepsLensSettingsReachTheModelAndContradictionsAreRefused) {
    const fs::path sweep = tempPath("six-blades");
    const fs::path model = tempPath("six-blades.flm");
    fs::remove_all(sweep);
    const std::string lens = flarelab::testing::lensPath("lensbaby-toy.csv");
    const CommandRun captured = testing::runCommand(
        addCaptureCommand,
        {"capture",    "--sim",   "--fast",      "--lens",   lens,
         "--from",     "0",       "--to",        "0.4",      "--step",
         "0.2",        "--width", "48",          "--height", "32",
         "--brackets", "1",       "--blades",    "6",        "--blade-rotation-deg",
         "15",         "-o",      sweep.string()});
    ASSERT_EQ(captured.code, 0) << captured.err;

    const CommandRun fitted = run({"fit", sweep.string(), "-o", model.string(), "--quiet"});
    ASSERT_EQ(fitted.code, 0) << fitted.err;
    auto read = fit::readModel(model.string());
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->format_version, fit::kModelFormatVersion);
    EXPECT_EQ(read->lens.aperture_blades, 6);
    EXPECT_EQ(read->lens.blade_rotation_deg, 15.0);
    EXPECT_TRUE(read->lens.stop_semi_aperture_mm);
    EXPECT_EQ(read->lens.coat_unspecified_surfaces, false);
    EXPECT_EQ(read->lens.sensor_width_mm, 36.0);
    EXPECT_EQ(read->lens.sensor_height_mm, 24.0);
    EXPECT_EQ(read->lens.prescription_file, lens);  // from the sweep, without fit --lens
    EXPECT_EQ(read->lens.prescription_sha256.size(), 64u);
    // The light's power the simulated camera recorded, for the lab figures.
    auto recorded = hdr::readSweepManifest(sweep.string());
    ASSERT_TRUE(recorded) << recorded.error().message;
    ASSERT_TRUE(recorded->header.camera.light_power_dn_s);
    EXPECT_EQ(read->capture.light_power_dn_s, recorded->header.camera.light_power_dn_s);

    const CommandRun scored = run({"score", model.string(), "--lens", lens, "--halfway", "0",
                                   "--random", "0", "--fitted", "1"});
    EXPECT_EQ(scored.code, 0) << scored.err;
    EXPECT_EQ(scored.err.find("note:"), std::string::npos) << scored.err;

    // --sensor-mm against the recorded sensor, --lens against the recorded prescription.
    CommandRun r =
        run({"fit", sweep.string(), "-o", model.string(), "--sensor-mm", "24x16", "--quiet"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("24 x 16 mm contradicts the 36 x 24 mm"), std::string::npos) << r.err;
    r = run({"fit", sweep.string(), "-o", model.string(), "--lens",
             flarelab::testing::lensPath("heliar-tronnier.csv"), "--quiet"});
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("not the lens the sweep was captured with"), std::string::npos) << r.err;
    // The same values given again agree, and the recorded lens is accepted.
    r = run({"fit", sweep.string(), "-o", model.string(), "--sensor-mm", "36x24", "--lens", lens,
             "--quiet"});
    EXPECT_EQ(r.code, 0) << r.err;
    // A power measured apart overrides the record; one that is no power is refused.
    r = run(
        {"fit", sweep.string(), "-o", model.string(), "--light-power-dn-s", "1.5e9", "--quiet"});
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_EQ(fit::readModel(model.string())->capture.light_power_dn_s, 1.5e9);
    for (const char* bad : {"0", "-3", "inf", "nan"}) {
        r = run(
            {"fit", sweep.string(), "-o", model.string(), "--light-power-dn-s", bad, "--quiet"});
        EXPECT_NE(r.code, 0) << bad;
        EXPECT_NE(r.err.find("light-power-dn-s"), std::string::npos) << bad << ": " << r.err;
    }
    fs::remove_all(sweep);
    fs::remove(model);
}

}  // namespace
}  // namespace flarelab::apps
