#include "fit/model_file.h"

#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "tests/test_files.h"

namespace flarelab::fit {
namespace {

using flarelab::testing::contains;
using flarelab::testing::readText;
using flarelab::testing::TempDir;
using flarelab::testing::writeText;

namespace fs = std::filesystem;

// Two ghosts, the second with a two-piece parameter; every optional field set.
FlareModel sampleModel() {
    FlareModel m;
    m.software_version = "flarelab 0.1.0 (test)";
    m.created_utc = "2026-11-29T07:04:02Z";
    m.lens.description = "double gauss 50mm f/2";
    m.lens.prescription_file = "data/lenses/double-gauss-50.csv";
    m.lens.prescription_sha256 = std::string(64, 'a');
    m.lens.f_number = 2.0;
    m.lens.focal_length_mm = 50.0;
    m.lens.sensor_width_mm = 36.0;
    m.lens.sensor_height_mm = 24.0;
    m.lens.aperture_blades = 6;
    m.lens.blade_rotation_deg = 15.0;
    m.lens.stop_semi_aperture_mm = 12.4033203125;
    m.lens.coat_unspecified_surfaces = true;
    m.capture.from_deg = -10.0;
    m.capture.to_deg = 10.0;
    m.capture.step_deg = 0.2;
    m.capture.roll_deg = 0.0;
    m.capture.exposure_times_s = {0.001, 0.01, 0.1};
    m.capture.width_px = 640;
    m.capture.height_px = 480;
    m.capture.camera = "simulated camera";
    m.capture.raw_format = "bayer-rggb";
    m.capture.light_power_dn_s = 2.5e6;
    m.capture.light_discs = {{-5.0, 31.5}, {-4.8, 0.0}, {5.0, 12.25}};  // version 5
    m.valid_from_deg = -5.0;
    m.valid_to_deg = 5.0;

    ModelGhost a;
    a.id = 7;
    a.name = "surfaces 4-7";
    ModelParameter x{"segment[0].p0.x_mm", "mm", -18.0, 18.0, {}, {}, {}};
    x.pieces.push_back({-5.0, 5.0, {0.5, 1.25, -0.125}, 0.01, 0.03, 51});
    ModelParameter r{"border_intensity.r", "1", 0.0, std::nullopt, {}, {}, {}};
    r.pieces.push_back({-5.0, 5.0, {0.1}, 0.0, 0.0, 51});
    a.parameters = {x, r};
    a.fit = {51, -5.0, 5.0};

    ModelGhost b;
    b.id = 9;
    b.name = "surfaces 2-3";
    ModelParameter y{"segment[0].p0.y_mm", "mm", std::nullopt, std::nullopt, {}, {}, {}};
    y.pieces.push_back({-2.0, 0.5, {1.0, 2.0}, 0.5, 1.5, 13});
    y.pieces.push_back({0.5, 3.0, {-1.0, 0.0, 3.0, 1e-300}, 0.25, 0.75, 13});
    y.sample_angles_deg = {-2.0, 0.5, 3.0};  // the per-frame values kept (version 4)
    y.sample_values = {1.0, 2.5, -1.0};
    b.parameters = {y};
    b.fit = {26, -2.0, 3.0};
    m.ghosts = {a, b};
    return m;
}

std::string replaced(std::string text, const std::string& from, const std::string& to) {
    const size_t at = text.find(from);
    EXPECT_NE(at, std::string::npos) << from;
    if (at != std::string::npos) text.replace(at, from.size(), to);
    return text;
}

// The bytes of a valid model, through a file (the only way to get them from the API).
std::string modelBytes(const FlareModel& model) {
    TempDir dir;
    EXPECT_TRUE(writeModel(dir.file("m.flaremodel"), model));
    return readText(dir.file("m.flaremodel"));
}

TEST(ModelFile, SampleModelIsValid) {
    const Status ok = validateModel(sampleModel());
    EXPECT_TRUE(ok) << ok.error().message;
}

TEST(ModelFile, BinaryRoundTripKeepsEveryField) {
    TempDir dir;
    const FlareModel model = sampleModel();
    const std::string path = dir.file("lens.flaremodel");
    const Status written = writeModel(path, model);
    ASSERT_TRUE(written) << written.error().message;
    const Result<FlareModel> read = readModel(path);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(*read, model);
    // No temporary file is left beside it.
    EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()), 1);
}

TEST(ModelFile, JsonRoundTripKeepsEveryField) {
    const FlareModel model = sampleModel();
    const Result<std::string> json = modelToJson(model);
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_TRUE(contains(*json, "\"residual_rms\"")) << *json;
    EXPECT_TRUE(contains(*json, "\"created\": \"2026-11-29T07:04:02Z\"")) << *json;
    const Result<FlareModel> back = modelFromJson(*json, "model.json");
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(*back, model);
    const Result<std::string> again = modelToJson(*back);
    ASSERT_TRUE(again);
    EXPECT_EQ(*again, *json);
}

TEST(ModelFile, RoundTripsRandomCoefficientsExactly) {
    std::mt19937_64 rng(11);
    std::uniform_real_distribution<double> exponent(-300.0, 300.0);
    for (int trial = 0; trial < 50; ++trial) {
        FlareModel model = sampleModel();
        for (ModelGhost& g : model.ghosts)
            for (ModelParameter& p : g.parameters)
                for (ModelPiece& piece : p.pieces)
                    for (double& c : piece.coefficients)
                        c = std::pow(10.0, exponent(rng)) * (rng() % 2 ? 1.0 : -1.0);
        const Result<std::string> json = modelToJson(model);
        ASSERT_TRUE(json);
        const Result<FlareModel> back = modelFromJson(*json);
        ASSERT_TRUE(back) << back.error().message;
        EXPECT_EQ(*back, model);
        const Result<FlareModel> binary = readModelFromMemory(modelBytes(model));
        ASSERT_TRUE(binary) << binary.error().message;
        EXPECT_EQ(*binary, model);
    }
}

TEST(ModelFile, AcceptsCamelCaseJsonAndMinimalModel) {
    const std::string json = R"({
        "formatVersion": 1,
        "lens": {"sensorWidthMm": 36, "sensorHeightMm": 24},
        "capture": {"fromDeg": 0, "toDeg": 1, "stepDeg": 0.5, "widthPx": 4, "heightPx": 3},
        "validRange": {"fromDeg": 0, "toDeg": 1}
    })";
    const Result<FlareModel> model = modelFromJson(json);
    ASSERT_TRUE(model) << model.error().message;
    EXPECT_TRUE(model->ghosts.empty());
    EXPECT_EQ(model->lens.sensor_width_mm, 36.0);
    EXPECT_FALSE(model->lens.f_number.has_value());
}

// Each rule: one change to the sample model, the field the error must name.
struct BrokenCase {
    const char* field;
    std::function<void(FlareModel&)> breaks;
};

std::vector<BrokenCase> brokenCases() {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const double inf = std::numeric_limits<double>::infinity();
    return {
        {"format_version", [](FlareModel& m) { m.format_version = 6; }},
        // Version 5's light discs in a version 4 model; broken discs.
        {"capture.light_discs", [](FlareModel& m) { m.format_version = 4; }},
        {"capture.light_discs[1].angle_deg",
         [](FlareModel& m) { m.capture.light_discs[1].angle_deg = -5.0; }},
        {"capture.light_discs[2].angle_deg",
         [](FlareModel& m) { m.capture.light_discs[2].angle_deg = 10.5; }},
        {"capture.light_discs[0].angle_deg",
         [nan](FlareModel& m) { m.capture.light_discs[0].angle_deg = nan; }},
        {"capture.light_discs[0].radius_px",
         [](FlareModel& m) { m.capture.light_discs[0].radius_px = -1.0; }},
        {"capture.light_discs[2].radius_px",
         [inf](FlareModel& m) { m.capture.light_discs[2].radius_px = inf; }},
        {"capture.light_discs[2].radius_px",
         [](FlareModel& m) { m.capture.light_discs[2].radius_px = 801.0; }},  // 640 x 480: 800
        // Version 4's light power in a version 3 model; one that is not a power.
        {"capture.light_power_dn_s", [](FlareModel& m) { m.format_version = 3; }},
        // Version 4's kept samples in a version 3 model; broken samples.
        {"ghosts[1].parameters[0].sample_angles_deg",
         [](FlareModel& m) {
             m.format_version = 3;
             m.capture.light_power_dn_s.reset();
             m.capture.light_discs.clear();
         }},
        {"ghosts[1].parameters[0].sample_values",
         [](FlareModel& m) { m.ghosts[1].parameters[0].sample_values.pop_back(); }},
        {"ghosts[1].parameters[0].sample_angles_deg[1]",
         [](FlareModel& m) { m.ghosts[1].parameters[0].sample_angles_deg[1] = -2.0; }},
        {"ghosts[1].parameters[0].sample_angles_deg[2]",
         [](FlareModel& m) { m.ghosts[1].parameters[0].sample_angles_deg[2] = 3.5; }},
        {"ghosts[1].parameters[0].sample_values[0]",
         [nan](FlareModel& m) { m.ghosts[1].parameters[0].sample_values[0] = nan; }},
        {"capture.light_power_dn_s", [](FlareModel& m) { m.capture.light_power_dn_s = 0.0; }},
        {"capture.light_power_dn_s", [nan](FlareModel& m) { m.capture.light_power_dn_s = nan; }},
        // Version 3's raw format in a version 2 model; a name that is no raw format.
        {"capture.raw_format", [](FlareModel& m) { m.format_version = 2; }},
        {"capture.raw_format", [](FlareModel& m) { m.capture.raw_format = "rggb"; }},
        {"format_version", [](FlareModel& m) { m.format_version = 0; }},
        // Version 2's lens fields in a version 1 model.
        {"lens.aperture_blades",
         [](FlareModel& m) {
             m.format_version = 1;
             m.capture.raw_format.clear();
         }},
        {"lens.coat_unspecified_surfaces",
         [](FlareModel& m) {
             m.format_version = 1;
             m.capture.raw_format.clear();
             m.lens.aperture_blades.reset();
             m.lens.blade_rotation_deg.reset();
             m.lens.stop_semi_aperture_mm.reset();
         }},
        {"lens.aperture_blades", [](FlareModel& m) { m.lens.aperture_blades = 2; }},
        {"lens.aperture_blades", [](FlareModel& m) { m.lens.aperture_blades = 65; }},
        {"lens.aperture_blades", [](FlareModel& m) { m.lens.aperture_blades = -1; }},
        {"lens.blade_rotation_deg", [inf](FlareModel& m) { m.lens.blade_rotation_deg = inf; }},
        {"lens.stop_semi_aperture_mm", [](FlareModel& m) { m.lens.stop_semi_aperture_mm = 0.0; }},
        {"lens.stop_semi_aperture_mm",
         [nan](FlareModel& m) { m.lens.stop_semi_aperture_mm = nan; }},
        {"software_version", [](FlareModel& m) { m.software_version = std::string("a\0b", 3); }},
        {"software_version", [](FlareModel& m) { m.software_version.assign(2, '\xff'); }},
        {"lens.description",
         [](FlareModel& m) { m.lens.description.assign(kModelMaxStringBytes + 1, 'x'); }},
        {"created", [](FlareModel& m) { m.created_utc = "yesterday"; }},
        {"lens.prescription_sha256", [](FlareModel& m) { m.lens.prescription_sha256 = "ABC"; }},
        {"lens.f_number", [](FlareModel& m) { m.lens.f_number = 0.0; }},
        {"lens.focal_length_mm", [nan](FlareModel& m) { m.lens.focal_length_mm = nan; }},
        {"lens.sensor_width_mm", [](FlareModel& m) { m.lens.sensor_width_mm = -1.0; }},
        {"lens.sensor_height_mm", [](FlareModel& m) { m.lens.sensor_height_mm = 0.0; }},
        {"capture.from_deg", [inf](FlareModel& m) { m.capture.from_deg = -inf; }},
        {"capture.step_deg", [](FlareModel& m) { m.capture.step_deg = 0.0; }},
        {"capture.to_deg", [](FlareModel& m) { m.capture.to_deg = -20.0; }},
        {"capture.exposure_times_s[1]", [](FlareModel& m) { m.capture.exposure_times_s[1] = 0; }},
        {"capture.width_px", [](FlareModel& m) { m.capture.width_px = 0; }},
        {"capture.height_px", [](FlareModel& m) { m.capture.height_px = kModelMaxSide + 1; }},
        {"valid_range.to_deg", [](FlareModel& m) { m.valid_to_deg = m.valid_from_deg; }},
        {"valid_range.from_deg", [nan](FlareModel& m) { m.valid_from_deg = nan; }},
        {"valid_range", [](FlareModel& m) { m.valid_to_deg = 11.0; }},
        {"ghosts", [](FlareModel& m) { m.ghosts.resize(kModelMaxGhosts + 1, m.ghosts[0]); }},
        {"ghosts[1].id", [](FlareModel& m) { m.ghosts[1].id = 7; }},
        {"ghosts[1].id", [](FlareModel& m) { m.ghosts[1].id = int64_t{1} << 32; }},
        {"ghosts[0].name", [](FlareModel& m) { m.ghosts[0].name = std::string("g\0", 2); }},
        {"ghosts[1].parameters", [](FlareModel& m) { m.ghosts[1].parameters.clear(); }},
        {"ghosts[0].parameters",
         [](FlareModel& m) {
             m.ghosts[0].parameters.resize(kModelMaxParameters + 1, m.ghosts[0].parameters[0]);
         }},
        {"ghosts[0].parameters[1].name",
         [](FlareModel& m) { m.ghosts[0].parameters[1].name = m.ghosts[0].parameters[0].name; }},
        {"ghosts[0].parameters[0].name",
         [](FlareModel& m) { m.ghosts[0].parameters[0].name = ""; }},
        {"ghosts[0].parameters[1].unit",
         [](FlareModel& m) { m.ghosts[0].parameters[1].unit = "\xc0\x80"; }},
        {"ghosts[0].parameters[0].upper_bound",
         [](FlareModel& m) { m.ghosts[0].parameters[0].upper_bound = -19.0; }},
        {"ghosts[0].parameters[0].lower_bound",
         [inf](FlareModel& m) { m.ghosts[0].parameters[0].lower_bound = -inf; }},
        {"ghosts[0].parameters[0].pieces",
         [](FlareModel& m) { m.ghosts[0].parameters[0].pieces.clear(); }},
        {"ghosts[1].parameters[0].pieces",
         [](FlareModel& m) {
             auto& pieces = m.ghosts[1].parameters[0].pieces;
             for (size_t i = 0; i < kModelMaxPieces; ++i) {
                 ModelPiece next = pieces.back();
                 next.angle_from_deg = pieces.back().angle_to_deg;
                 next.angle_to_deg = next.angle_from_deg + 1e-3;
                 pieces.push_back(next);
             }
         }},
        {"ghosts[1].parameters[0].pieces[0].coefficients",
         [](FlareModel& m) { m.ghosts[1].parameters[0].pieces[0].coefficients.clear(); }},
        {"ghosts[1].parameters[0].pieces[0].coefficients",
         [](FlareModel& m) {
             m.ghosts[1].parameters[0].pieces[0].coefficients.assign(kModelMaxCoefficients + 1,
                                                                     1.0);
         }},
        {"ghosts[1].parameters[0].pieces[1].coefficients[2]",
         [nan](FlareModel& m) { m.ghosts[1].parameters[0].pieces[1].coefficients[2] = nan; }},
        {"ghosts[1].parameters[0].pieces[0].angle_to_deg",
         [](FlareModel& m) { m.ghosts[1].parameters[0].pieces[0].angle_to_deg = -2.0; }},
        {"ghosts[1].parameters[0].pieces[1].angle_from_deg",
         [](FlareModel& m) { m.ghosts[1].parameters[0].pieces[1].angle_from_deg = 0.25; }},
        {"ghosts[1].parameters[0].pieces[1].angle_from_deg",  // a gap
         [](FlareModel& m) { m.ghosts[1].parameters[0].pieces[1].angle_from_deg = 0.75; }},
        {"ghosts[1].parameters[0].pieces",  // beyond valid_range
         [](FlareModel& m) { m.ghosts[1].parameters[0].pieces[1].angle_to_deg = 6.0; }},
        {"ghosts[0].parameters[1].pieces",  // spans differ
         [](FlareModel& m) { m.ghosts[0].parameters[1].pieces[0].angle_to_deg = 4.0; }},
        {"ghosts[0].parameters[0].pieces[0].residual_rms",
         [](FlareModel& m) { m.ghosts[0].parameters[0].pieces[0].residual_rms = -0.5; }},
        {"ghosts[0].parameters[0].pieces[0].residual_max",
         [inf](FlareModel& m) { m.ghosts[0].parameters[0].pieces[0].residual_max = inf; }},
        {"ghosts[0].parameters[0].pieces[0].samples",
         [](FlareModel& m) { m.ghosts[0].parameters[0].pieces[0].samples = 0; }},
        {"ghosts[0].fit.frames_fitted", [](FlareModel& m) { m.ghosts[0].fit.frames_fitted = 0; }},
        {"ghosts[0].fit.last_angle_deg",
         [](FlareModel& m) { m.ghosts[0].fit.last_angle_deg = -6.0; }},
        {"ghosts[0].fit.first_angle_deg",
         [nan](FlareModel& m) { m.ghosts[0].fit.first_angle_deg = nan; }},
    };
}

TEST(ValidateModel, EachRuleNamesItsField) {
    for (const BrokenCase& broken : brokenCases()) {
        FlareModel model = sampleModel();
        broken.breaks(model);
        const Status ok = validateModel(model);
        ASSERT_FALSE(ok) << broken.field;
        EXPECT_EQ(ok.error().code, ErrorCode::InvalidArgument) << ok.error().message;
        EXPECT_TRUE(contains(ok.error().message, std::string("model: ") + broken.field + ": "))
            << "expected field " << broken.field << " in: " << ok.error().message;
    }
}

TEST(ValidateModel, WritersRefuseWhatValidateRefuses) {
    TempDir dir;
    for (const BrokenCase& broken : brokenCases()) {
        FlareModel model = sampleModel();
        broken.breaks(model);
        const Status written = writeModel(dir.file("x.flaremodel"), model);
        ASSERT_FALSE(written) << broken.field;
        EXPECT_EQ(written.error().code, ErrorCode::InvalidArgument);
        EXPECT_TRUE(contains(written.error().message, broken.field)) << written.error().message;
        EXPECT_FALSE(modelToJson(model)) << broken.field;
    }
    EXPECT_FALSE(fs::exists(dir.file("x.flaremodel")));
}

TEST(ValidateModel, AcceptsExtremes) {
    FlareModel model = sampleModel();
    // One coefficient, and the most; a bound equal on both sides; residuals exactly zero.
    auto& pieces = model.ghosts[1].parameters[0].pieces;
    pieces[0].coefficients = {0.0};
    pieces[1].coefficients.assign(kModelMaxCoefficients, -1e300);
    pieces[0].residual_rms = pieces[0].residual_max = 0.0;
    model.ghosts[0].parameters[0].lower_bound = 2.0;
    model.ghosts[0].parameters[0].upper_bound = 2.0;
    model.ghosts[0].id = 0;
    model.ghosts[1].id = std::numeric_limits<uint32_t>::max();
    // The valid range equal to the capture range; spans touching its ends.
    model.valid_from_deg = model.capture.from_deg;
    model.valid_to_deg = model.capture.to_deg;
    pieces.back().angle_to_deg = model.capture.to_deg;
    model.created_utc.clear();
    const Status ok = validateModel(model);
    EXPECT_TRUE(ok) << ok.error().message;
    const Result<FlareModel> back = readModelFromMemory(modelBytes(model));
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(*back, model);
}

TEST(ValidateModel, AcceptsAGhostFittedAtOneAngleOnly) {
    // fit/polyfit.h fits a single sample as a constant valid at its own angle.
    FlareModel model = sampleModel();
    ModelGhost& g = model.ghosts[0];
    for (ModelParameter& p : g.parameters) p.pieces = {{1.5, 1.5, {0.25}, 0.0, 0.0, 1}};
    g.fit = {1, 1.5, 1.5};
    const Status ok = validateModel(model);
    EXPECT_TRUE(ok) << ok.error().message;
    // Not when the parameter has more pieces.
    g.parameters[0].pieces.push_back({1.5, 2.0, {0.25}, 0.0, 0.0, 1});
    const Status two = validateModel(model);
    ASSERT_FALSE(two);
    EXPECT_TRUE(contains(two.error().message, "ghosts[0].parameters[0].pieces[0].angle_to_deg"))
        << two.error().message;
}

TEST(ReadModel, RefusesTruncatedBinaryAtEveryLength) {
    const std::string bytes = modelBytes(sampleModel());
    ASSERT_GT(bytes.size(), 100u);
    int refused = 0;
    for (size_t n = 0; n < bytes.size(); ++n) {
        const Result<FlareModel> model = readModelFromMemory(bytes.substr(0, n), "cut.flaremodel");
        // A cut may by chance end between two complete fields and still parse; it must then
        // break a rule (or be the valid prefix), never crash. Most cuts are refused.
        if (!model) {
            ++refused;
            EXPECT_TRUE(contains(model.error().message, "cut.flaremodel: "))
                << model.error().message;
        }
    }
    EXPECT_GT(refused, static_cast<int>(bytes.size()) * 9 / 10);
}

TEST(ReadModel, RefusesUnknownVersion) {
    FlareModel model = sampleModel();
    const std::string bytes = modelBytes(model);
    // Field 1 (format_version, varint) comes first: tag 0x08, value 5.
    ASSERT_GE(bytes.size(), 2u);
    ASSERT_EQ(bytes.substr(0, 2), std::string("\x08\x05", 2));
    for (const char version : {'\x00', '\x06'}) {
        std::string other = bytes;
        other[1] = version;
        const Result<FlareModel> read = readModelFromMemory(other, "other.flaremodel");
        ASSERT_FALSE(read);
        EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
        EXPECT_TRUE(contains(read.error().message,
                             "other.flaremodel: format_version: " + std::to_string(version)))
            << read.error().message;
    }

    const Result<FlareModel> json = modelFromJson(R"({"format_version": 6, "new_field": 1})");
    ASSERT_FALSE(json);
    EXPECT_EQ(json.error().code, ErrorCode::Unsupported) << json.error().message;
    const Result<FlareModel> missing = modelFromJson(R"({"lens": {}})");
    ASSERT_FALSE(missing);
    EXPECT_TRUE(contains(missing.error().message, "format_version: missing"));
}

// A model written before version 2 (no camera settings beyond f-number, focal length and sensor)
// still reads, from a file of the repository as from this writer, and keeps its version.
TEST(ReadModel, AVersion1ModelStillReads) {
    const Result<FlareModel> shipped =
        readModel(std::string(FLARELAB_SOURCE_DIR) + "/fuzz/corpus/model/valid-full.flaremodel");
    ASSERT_TRUE(shipped) << shipped.error().message;
    EXPECT_EQ(shipped->format_version, 1);
    EXPECT_FALSE(shipped->lens.aperture_blades);
    EXPECT_FALSE(shipped->lens.stop_semi_aperture_mm);
    EXPECT_EQ(shipped->lens.sensor_width_mm, 36.0);

    FlareModel old = sampleModel();
    old.format_version = 1;
    old.lens.aperture_blades.reset();
    old.lens.blade_rotation_deg.reset();
    old.lens.stop_semi_aperture_mm.reset();
    old.lens.coat_unspecified_surfaces.reset();
    old.capture.raw_format.clear();
    old.capture.light_power_dn_s.reset();
    old.capture.light_discs.clear();
    for (ModelGhost& g : old.ghosts)
        for (ModelParameter& p : g.parameters) {
            p.sample_angles_deg.clear();
            p.sample_values.clear();
        }
    const std::string bytes = modelBytes(old);
    ASSERT_EQ(bytes.substr(0, 2), std::string("\x08\x01", 2));
    const Result<FlareModel> binary = readModelFromMemory(bytes, "old.flaremodel");
    ASSERT_TRUE(binary) << binary.error().message;
    EXPECT_EQ(*binary, old);
    const Result<std::string> json = modelToJson(old);
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_FALSE(contains(*json, "aperture_blades")) << *json;
    const Result<FlareModel> text = modelFromJson(*json, "old.json");
    ASSERT_TRUE(text) << text.error().message;
    EXPECT_EQ(*text, old);
    // Version 2's fields in a version 1 text are refused by name.
    const Result<FlareModel> mixed =
        modelFromJson(replaced(*json, "\"sensor_width_mm\": 36",
                               "\"sensor_width_mm\": 36, \"aperture_blades\": 6"),
                      "mixed.json");
    ASSERT_FALSE(mixed);
    EXPECT_EQ(mixed.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(mixed.error().message,
                         "mixed.json: lens.aperture_blades: is a field of format version 2"))
        << mixed.error().message;
}

TEST(ModelFile, Version4RecordsTheCaptureSettingsRawFormatAndLightPower) {
    const Result<std::string> json = modelToJson(sampleModel());
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_TRUE(contains(*json, "\"format_version\": 5")) << *json;
    EXPECT_TRUE(contains(*json, "\"light_power_dn_s\": 2500000")) << *json;
    FlareModel unmeasured = sampleModel();
    unmeasured.capture.light_power_dn_s.reset();
    const Result<std::string> without = modelToJson(unmeasured);
    ASSERT_TRUE(without) << without.error().message;
    EXPECT_FALSE(contains(*without, "light_power")) << *without;
    const Result<FlareModel> unmeasured_back = readModelFromMemory(modelBytes(unmeasured));
    ASSERT_TRUE(unmeasured_back) << unmeasured_back.error().message;
    EXPECT_EQ(*unmeasured_back, unmeasured);
    EXPECT_TRUE(contains(*json, "\"raw_format\": \"bayer-rggb\"")) << *json;
    // Not recorded: left out, and read back empty.
    FlareModel unknown = sampleModel();
    unknown.capture.raw_format.clear();
    const Result<std::string> bare = modelToJson(unknown);
    ASSERT_TRUE(bare) << bare.error().message;
    EXPECT_FALSE(contains(*bare, "raw_format")) << *bare;
    const Result<FlareModel> back = modelFromJson(*bare);
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(*back, unknown);
    EXPECT_TRUE(contains(*json, "\"aperture_blades\": 6")) << *json;
    EXPECT_TRUE(contains(*json, "\"blade_rotation_deg\": 15")) << *json;
    EXPECT_TRUE(contains(*json, "\"stop_semi_aperture_mm\": 12.4033203125")) << *json;
    EXPECT_TRUE(contains(*json, "\"coat_unspecified_surfaces\": true")) << *json;
    // A circular stop and bare surfaces are settings too, kept apart from "not recorded".
    FlareModel circle = sampleModel();
    circle.lens.aperture_blades = 0;
    circle.lens.coat_unspecified_surfaces = false;
    const Result<FlareModel> read = readModelFromMemory(modelBytes(circle));
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->lens.aperture_blades, 0);
    EXPECT_EQ(read->lens.coat_unspecified_surfaces, false);
    const std::string shown = describeModel(sampleModel(), "m.flm");
    EXPECT_TRUE(contains(shown, "aperture: 6 blades, blades rotated 15 deg")) << shown;
}

TEST(ModelFile, Version5RecordsTheLightsDiscPerFittedFrame) {
    const FlareModel m = sampleModel();
    const Result<std::string> json = modelToJson(m);
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_TRUE(contains(*json, "\"light_discs\"")) << *json;
    EXPECT_TRUE(contains(*json, "\"radius_px\": 31.5")) << *json;
    const Result<FlareModel> text = modelFromJson(*json, "v5.json");
    ASSERT_TRUE(text) << text.error().message;
    EXPECT_EQ(text->capture.light_discs, m.capture.light_discs);
    const Result<FlareModel> binary = readModelFromMemory(modelBytes(m));
    ASSERT_TRUE(binary) << binary.error().message;
    EXPECT_EQ(*binary, m);
    const std::string shown = describeModel(m, "m.flm");
    EXPECT_TRUE(contains(shown, "light's disc: left out in 2 of 3 fitted frames, radius 12.25 to "
                                "31.5 px"))
        << shown;
    FlareModel none = m;
    none.capture.light_discs.clear();
    EXPECT_TRUE(contains(describeModel(none, "m.flm"), "light's disc: not recorded"));
    // A version 4 text that names them is refused by name.
    FlareModel v4 = none;
    v4.format_version = 4;
    const Result<std::string> v4_json = modelToJson(v4);
    ASSERT_TRUE(v4_json) << v4_json.error().message;
    const Result<FlareModel> mixed = modelFromJson(
        replaced(*v4_json, "\"light_discs\": []",
                 "\"light_discs\": [{\"angle_deg\": 0, \"radius_px\": 3}]"),
        "mixed.json");
    ASSERT_FALSE(mixed);
    EXPECT_TRUE(contains(mixed.error().message,
                         "mixed.json: capture.light_discs: is a field of format version 5"))
        << mixed.error().message;
}

TEST(ReadModel, RefusesUnknownFieldsInBinary) {
    // A version 1 file with an extra field 99 (varint 5) appended: a newer writer's data.
    const std::string bytes = modelBytes(sampleModel()) + std::string("\x98\x06\x05", 3);
    const Result<FlareModel> read = readModelFromMemory(bytes, "extra.flaremodel");
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(read.error().message, "field number 99: unknown field"))
        << read.error().message;
}

TEST(ReadModel, RefusesUnknownJsonFieldNamingItsPath) {
    const Result<std::string> json = modelToJson(sampleModel());
    ASSERT_TRUE(json);
    std::string text = *json;
    const size_t at = text.find("\"residual_rms\"");
    ASSERT_NE(at, std::string::npos);
    text.insert(at, "\"residual_mean\": 0.5, ");
    const Result<FlareModel> read = modelFromJson(text, "model.json");
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(read.error().message, "residual_mean: unknown field"))
        << read.error().message;
    EXPECT_TRUE(contains(read.error().message, "model.json: ")) << read.error().message;
}

TEST(ReadModel, BrokenJsonNamesTheFieldPath) {
    const Result<std::string> json = modelToJson(sampleModel());
    ASSERT_TRUE(json);
    std::string text = *json;
    const std::string samples = "\"samples\": 13";
    const size_t at = text.find(samples);
    ASSERT_NE(at, std::string::npos);
    text.replace(at, samples.size(), "\"samples\": 0");
    const Result<FlareModel> read = modelFromJson(text, "model.json");
    ASSERT_FALSE(read);
    EXPECT_EQ(read.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(
        contains(read.error().message, "model.json: ghosts[1].parameters[0].pieces[0].samples"))
        << read.error().message;
    EXPECT_FALSE(modelFromJson("{\"format_version\": 1,"));
    EXPECT_FALSE(modelFromJson("[]"));
    EXPECT_FALSE(modelFromJson(""));
    const Result<FlareModel> nan_json = modelFromJson(
        R"({"format_version": 1, "lens": {"sensor_width_mm": "NaN", "sensor_height_mm": 1}})");
    ASSERT_FALSE(nan_json);
    EXPECT_TRUE(contains(nan_json.error().message, "lens.sensor_width_mm"))
        << nan_json.error().message;
}

TEST(ReadModel, MissingAndNonModelFiles) {
    TempDir dir;
    const Result<FlareModel> missing = readModel(dir.file("none.flaremodel"));
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(contains(missing.error().message, "none.flaremodel"));
    const Result<FlareModel> directory = readModel(dir.path());
    ASSERT_FALSE(directory);
    EXPECT_EQ(directory.error().code, ErrorCode::IoError);
    // A JSON model handed to the binary reader.
    writeText(dir.file("text.flaremodel"), *modelToJson(sampleModel()));
    const Result<FlareModel> text = readModel(dir.file("text.flaremodel"));
    ASSERT_FALSE(text);
    EXPECT_TRUE(contains(text.error().message, "text.flaremodel: ")) << text.error().message;
}

TEST(WriteModel, ReplacesAnOldModel) {
    TempDir dir;
    const std::string path = dir.file("m.flaremodel");
    FlareModel model = sampleModel();
    ASSERT_TRUE(writeModel(path, model));
    model.software_version = "second";
    model.ghosts.pop_back();
    ASSERT_TRUE(writeModel(path, model));
    const Result<FlareModel> read = readModel(path);
    ASSERT_TRUE(read);
    EXPECT_EQ(*read, model);
}

TEST(WriteModel, KeepsTheOldFileWhenWritingFails) {
    if (::geteuid() == 0) GTEST_SKIP() << "root ignores directory permissions";
    TempDir dir;
    const std::string path = dir.file("m.flaremodel");
    const FlareModel model = sampleModel();
    ASSERT_TRUE(writeModel(path, model));
    const std::string before = readText(path);
    // A directory that refuses the temporary file.
    fs::permissions(dir.path(), fs::perms::owner_read | fs::perms::owner_exec);
    FlareModel changed = model;
    changed.software_version = "never written";
    const Status written = writeModel(path, changed);
    fs::permissions(dir.path(), fs::perms::owner_all);
    ASSERT_FALSE(written);
    EXPECT_EQ(written.error().code, ErrorCode::IoError);
    EXPECT_TRUE(contains(written.error().message, path)) << written.error().message;
    EXPECT_EQ(readText(path), before);
    EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()), 1);
}

TEST(WriteModel, KeepsTheOldFileWhenTheTemporaryFileCannotBeCreated) {
    // Works as root too: a directory where the writer puts its temporary file (model_file.cpp
    // names it PATH.tmp-PID) cannot be opened for writing.
    TempDir dir;
    const std::string path = dir.file("m.flaremodel");
    const FlareModel model = sampleModel();
    ASSERT_TRUE(writeModel(path, model));
    const std::string before = readText(path);
    const std::string temporary = path + ".tmp-" + std::to_string(::getpid());
    fs::create_directories(temporary);
    FlareModel changed = model;
    changed.software_version = "never written";
    const Status written = writeModel(path, changed);
    ASSERT_FALSE(written);
    EXPECT_EQ(written.error().code, ErrorCode::IoError);
    EXPECT_TRUE(contains(written.error().message, path + ": cannot create"))
        << written.error().message;
    EXPECT_EQ(readText(path), before);
    EXPECT_TRUE(fs::is_directory(temporary));  // someone else's; left alone
    const Result<FlareModel> read = readModel(path);
    ASSERT_TRUE(read);
    EXPECT_EQ(*read, model);
}

TEST(WriteModel, KeepsTheOldFileWhenTheRenameFails) {
    // Works as root too: renaming a file over a non-empty directory fails, and the temporary file
    // must be gone afterwards.
    TempDir dir;
    const std::string path = dir.file("m.flaremodel");
    fs::create_directories(fs::path(path) / "inside");
    const Status written = writeModel(path, sampleModel());
    ASSERT_FALSE(written);
    EXPECT_EQ(written.error().code, ErrorCode::IoError);
    EXPECT_TRUE(fs::is_directory(fs::path(path) / "inside"));
    EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()), 1);
}

}  // namespace
}  // namespace flarelab::fit
