#include "apps/capture_command.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <sstream>

#include "apps/camera_flags.h"
#include "apps/fit_command.h"
#include "fit/frame.h"
#include "fit/sweep_fit.h"
#include "hdr/digest.h"
#include "hdr/merge.h"
#include "hdr/sweep.h"
#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun capture(std::vector<std::string> args) {
    args.insert(args.begin(), "capture");
    return testing::runCommand(addCaptureCommand, args);
}

std::string freshDir(const std::string& name) {
    const auto dir = std::filesystem::temp_directory_path() / ("flarelab_capture_test_" + name);
    std::filesystem::remove_all(dir);
    return dir.string();
}

std::vector<std::string> small(const std::string& dir) {
    return {"--sim",    "--fast", "--lens",  flarelab::testing::lensPath("lensbaby-toy.csv"),
            "--from",   "0",      "--to",    "0.4",
            "--step",   "0.2",    "--width", "48",
            "--height", "32",     "-o",      dir};
}

TEST(Capture, WritesASweepThatReadsBackWithRawBracketsAndResumes) {
    const std::string dir = freshDir("sweep");
    auto args = small(dir);
    args.insert(args.end(), {"--keep-raw", "--brackets", "0.25,1,4"});
    CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("3 frames"), std::string::npos) << run.out;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    ASSERT_EQ(sweep->frames.size(), 3u);
    EXPECT_EQ(sweep->frames[2].angle_deg, 0.4);
    EXPECT_EQ(sweep->frames[0].raw_files.size(), 3u);
    EXPECT_EQ(sweep->header.capture.exposure_times_s, (std::vector<double>{0.25, 1.0, 4.0}));
    // Finished: the frame log compacted into the manifest and gone.
    EXPECT_FALSE(std::filesystem::exists(std::filesystem::path(dir) / hdr::kSweepFrameLogFile));
    auto listed = hdr::readSweepManifest(dir);  // with the log gone, the manifest alone
    ASSERT_TRUE(listed) << listed.error().message;
    EXPECT_EQ(listed->frames.size(), 3u);
    // Asked again for a longer range with --resume, only the new frames are taken.
    args = small(dir);
    args[7] = "0.8";
    args.insert(args.end(), {"--keep-raw", "--brackets", "0.25,1,4"});
    run = capture(args);
    EXPECT_EQ(run.code, 1) << "a new range is a different sweep";
    args = small(dir);
    args.insert(args.end(), {"--keep-raw", "--brackets", "0.25,1,4"});
    args.push_back("--resume");
    run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("3 already there"), std::string::npos) << run.out;
}

// A colour capture whose one 4 s bracket clips the Heliar's blue ghosts (its coating reflects blue
// most) but not their red and green: the sweep records the raw format, and each frame says which
// channels of which pixels are only lower bounds, blue alone where only blue clipped; a mono
// capture's bounds are all three channels or none.
TEST(Capture, AColourSweepWhereOneChannelClipsSaysWhichChannel) {
    for (const char* format : {"bayer-rggb", "mono"}) {
        const std::string dir = freshDir(std::string("clipped-") + format);
        const CommandRun run =
            capture({"--sim",   "--fast",     "--format",
                     format,    "--lens",     flarelab::testing::lensPath("heliar-tronnier.csv"),
                     "--from",  "1",          "--to",
                     "1",       "--step",     "1",
                     "--width", "48",         "--height",
                     "32",      "--brackets", "4",
                     "-o",      dir});
        ASSERT_EQ(run.code, 0) << run.err;
        auto sweep = hdr::readSweep(dir);
        ASSERT_TRUE(sweep) << sweep.error().message;
        EXPECT_EQ(sweep->header.camera.raw_format, hdr::parseRawFormat(format));
        auto frame = hdr::loadFrame(*sweep, 0);
        ASSERT_TRUE(frame) << frame.error().message;
        ASSERT_EQ(frame->lower_bound.size(), 48u * 32u);
        std::array<int, 8> kinds{};
        for (const uint8_t b : frame->lower_bound) ++kinds[b];
        EXPECT_GT(kinds[0], 0) << format;  // not everything clipped
        if (std::string(format) == "mono") {
            EXPECT_EQ(kinds[0] + kinds[7], 48 * 32);
            EXPECT_GT(kinds[7], 0);  // at least the light's core
        } else {
            EXPECT_GT(kinds[hdr::kLowerBoundBlue], 100);  // blue alone, over its ghosts
        }
        std::filesystem::remove_all(dir);
    }
}

// A capture with six rotated blades records them with the stop, coating and sensor it used; the
// fit copies them into the model, and the score's lens (captureLens) is that six-bladed lens, not
// a circular one scaled for the f-number.
TEST(Capture, RecordsTheLensSettingsThatFitCopiesAndScoreRebuilds) {
    const std::string dir = freshDir("settings");
    const std::string lens_file = flarelab::testing::lensPath("lensbaby-toy.csv");
    auto args = small(dir);
    args.insert(args.end(), {"--brackets", "1", "--blades", "6", "--blade-rotation-deg", "15",
                             "--sensor-mm", "24x16"});
    const CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    auto sweep = hdr::readSweepManifest(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    const hdr::SweepLens& recorded = sweep->header.lens;
    EXPECT_EQ(sweep->header.format_version, hdr::kSweepFormatVersion);
    EXPECT_EQ(sweep->header.camera.raw_format, hdr::RawFormat::Mono);
    EXPECT_EQ(recorded.aperture_blades, 6);
    EXPECT_EQ(recorded.blade_rotation_deg, 15.0);
    EXPECT_EQ(recorded.coat_unspecified_surfaces, false);
    EXPECT_EQ(recorded.sensor_width_mm, 24.0);
    EXPECT_EQ(recorded.sensor_height_mm, 16.0);
    EXPECT_EQ(recorded.prescription_file, lens_file);
    auto digest = hdr::sha256File(lens_file);
    ASSERT_TRUE(digest) << digest.error().message;
    EXPECT_EQ(recorded.prescription_sha256, *digest);
    // The simulated camera knows its light's power; the fit carries it into the model.
    ASSERT_TRUE(sweep->header.camera.light_power_dn_s);
    EXPECT_GT(*sweep->header.camera.light_power_dn_s, 0.0);
    CameraFlags flags;
    flags.blades = 6;
    flags.blade_rotation_deg = 15.0;
    flags.sensor = "24x16";
    std::ostringstream ignored;
    const auto simulated = loadLens(lens_file, flags, ignored);
    ASSERT_TRUE(simulated);
    const auto stopOf = [](const optics::Lens& lens) {
        return lens.surfaces()[static_cast<size_t>(lens.stopIndex())].semi_aperture_mm;
    };
    EXPECT_EQ(recorded.stop_semi_aperture_mm, stopOf(*simulated));
    EXPECT_EQ(recorded.f_number, simulated->camera().f_number);

    // The fit: the model takes the sweep's settings and sensor.
    const auto size = fit::sweepSensorSize(*sweep);
    ASSERT_TRUE(size) << size.error().message;
    EXPECT_EQ(*size, (std::array<double, 2>{24.0, 16.0}));
    fit::FlareModel model;
    model.lens = fit::modelLens(recorded, (*size)[0], (*size)[1]);
    model.capture.from_deg = 0.0;
    model.capture.to_deg = 0.4;
    model.capture.width_px = 48;
    model.capture.height_px = 32;
    model.valid_from_deg = 0.0;
    model.valid_to_deg = 0.4;
    const std::string path = dir + "/" + hdr::kSweepModelFile;
    ASSERT_TRUE(fit::writeModel(path, model));
    auto read = fit::readModel(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->format_version, fit::kModelFormatVersion);
    EXPECT_EQ(read->lens.aperture_blades, 6);
    EXPECT_EQ(read->lens.prescription_sha256, *digest);

    // The score's lens is the capture's: six blades, rotated, the same stop, nothing assumed.
    std::ostringstream err;
    const auto truth = captureLens(lens_file, *read, path, err);
    ASSERT_TRUE(truth) << err.str();
    EXPECT_TRUE(err.str().empty()) << err.str();
    EXPECT_EQ(truth->aperture().blades, 6);
    EXPECT_NEAR(truth->aperture().rotation_rad, 15.0 * M_PI / 180.0, 1e-15);
    EXPECT_EQ(stopOf(*truth), stopOf(*simulated));
    EXPECT_EQ(truth->camera().sensor_width_mm, 24.0);
    EXPECT_EQ(truth->camera().sensor_height_mm, 16.0);

    // A model from before the settings: a circular stop, and one note saying so.
    fit::FlareModel old = *read;
    old.format_version = 1;
    old.lens.aperture_blades.reset();
    old.lens.blade_rotation_deg.reset();
    old.lens.stop_semi_aperture_mm.reset();
    old.lens.coat_unspecified_surfaces.reset();
    std::ostringstream note;
    const auto assumed = captureLens(lens_file, old, "old.flm", note);
    ASSERT_TRUE(assumed) << note.str();
    EXPECT_EQ(assumed->aperture().blades, 0);
    const std::string text = note.str();
    EXPECT_EQ(std::count(text.begin(), text.end(), '\n'), 1) << text;
    for (const char* part :
         {"note: old.flm (model format 1) does not record",
          "aperture blades (assumed a circular stop)",
          "coating of unspecified surfaces (assumed bare)", "stop semi-aperture (assumed"})
        EXPECT_NE(text.find(part), std::string::npos) << part << " in: " << text;
    std::filesystem::remove_all(dir);
}

TEST(Capture, RecordsEachExposuresClippingAndWarnsOfASaturatedSweep) {
    // The double Gauss's ghosts are far brighter than the lensbaby's: with the brackets of the
    // lensbaby (0.25 / 1 / 4 s) its whole frame saturates every exposure; with 1/64 of them it
    // does not.
    const std::string dir = freshDir("clipped");
    auto args = small(dir);
    args[3] = flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv");
    args.insert(args.end(), {"--brackets", "0.25,1,4"});
    CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.err.find("warning: 3 of 3 frames have more than 1% of their samples saturated"),
              std::string::npos)
        << run.err;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    ASSERT_EQ(sweep->frames[0].brackets.size(), 3u);
    for (const hdr::SweepFrame& f : sweep->frames)
        for (size_t k = 0; k < 3; ++k) {
            EXPECT_EQ(f.brackets[k].exposure_s, f.exposure_times_s[k]);
            EXPECT_LE(f.brackets[k].samples_used + f.brackets[k].samples_clipped, 48u * 32u);
        }
    // Longer exposures clip at least as much.
    EXPECT_LE(sweep->frames[1].brackets[0].samples_clipped,
              sweep->frames[1].brackets[2].samples_clipped);

    const std::string short_dir = freshDir("short");
    args = small(short_dir);
    args[3] = flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv");
    args.insert(args.end(), {"--brackets", "0.004,0.016,0.064"});
    run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(run.err.find("warning"), std::string::npos) << run.err;
}

TEST(Capture, PlansTheBracketWhenNoneIsGivenAndKeepsItsOwnOnResume) {
    // The double Gauss saturates 0.25 / 1 / 4 s; the planned bracket keeps the light's core
    // unclipped in its shortest exposure and reaches the ghosts' floor in its longest.
    const std::string dir = freshDir("auto");
    auto args = small(dir);
    args[3] = flarelab::testing::lensPath("double-gauss-tronnier-50mm.csv");
    args[7] = "0.2";
    CommandRun run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.err.find("flarelab: bracket: "), std::string::npos) << run.err;
    EXPECT_EQ(run.err.find("warning"), std::string::npos) << run.err;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    const std::vector<double> planned = sweep->header.capture.exposure_times_s;
    ASSERT_GE(planned.size(), 2u);
    EXPECT_TRUE(std::is_sorted(planned.begin(), planned.end()));
    // The shortest exposure of the first frame clips nothing.
    EXPECT_EQ(sweep->frames[0].brackets[0].samples_clipped, 0u);
    // Resumed, the sweep keeps the bracket it was taken with instead of planning another.
    args[7] = "0.2";
    args.push_back("--resume");
    run = capture(args);
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_EQ(run.err.find("flarelab: bracket: "), std::string::npos) << run.err;
    EXPECT_NE(run.out.find("2 already there"), std::string::npos) << run.out;
}

TEST(Capture, TakesItsDevicesByUri) {
    const std::string dir = freshDir("uri");
    CommandRun run = capture({"--camera",
                              "sim:?lens=" + flarelab::testing::lensPath("lensbaby-toy.csv") +
                                  "&width=40&height=30&format=rggb",
                              "--head", "sim:?time=fast&settle_s=0", "--from", "0", "--to", "0.2",
                              "--step", "0.2", "--brackets", "0.5,2", "-o", dir});
    ASSERT_EQ(run.code, 0) << run.err;
    auto sweep = hdr::readSweep(dir);
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 2u);
    EXPECT_EQ(sweep->header.capture.width_px, 40);  // the camera's size, not --width's
    EXPECT_GT(sweep->header.camera.pixel_pitch_um, 0.0);
    EXPECT_NE(sweep->header.lens.description.find("ensbaby"), std::string::npos)
        << sweep->header.lens.description;

    run = capture({"--camera", "sim:", "--head", "sim:", "-o", freshDir("nolens")});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("needs a lens"), std::string::npos) << run.err;
    run = capture({"--camera", "aravis:", "--head", "warp:", "-o", freshDir("nohead")});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("head 'warp:'"), std::string::npos) << run.err;
}

TEST(Capture, RefusesBadRequestsNamingWhatIsWrong) {
    const std::string dir = freshDir("bad");
    auto args = small(dir);
    args.erase(args.begin());  // no --sim
    CommandRun run = capture(args);
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--sim"), std::string::npos);
    args = small(dir);
    args.insert(args.end(), {"--brackets", "0.25,abc"});
    run = capture(args);
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("abc"), std::string::npos) << run.err;
    args = small(dir);
    args[5] = "1";  // --from 1 > --to 0.4
    run = capture(args);
    EXPECT_EQ(run.code, 1);
    EXPECT_FALSE(std::filesystem::exists(dir + "/manifest.json"));
}

}  // namespace
}  // namespace flarelab::apps
