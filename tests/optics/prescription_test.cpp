#include "optics/prescription.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <limits>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "common/units.h"
#include "optics/lens.h"
#include "optics/paraxial.h"
#include "tests/test_paths.h"

namespace flarelab::optics {
namespace {

using flarelab::testing::kShippedLenses;
using flarelab::testing::lensPath;
using flarelab::testing::sourcePath;

// A small valid lens without its header: a biconvex singlet and a stop behind it.
constexpr char kRows[] = "surface,50,5,1.5,50,10,550\nsurface,-50,10,1,,10,550\nstop,0,40,1,,5,\n";
constexpr char kHeader[] =
    "kind,radius_mm,thickness_mm,ior_d,abbe,semi_aperture_mm,coating_wavelength_nm\n";

std::string badPath(const std::string& file) { return sourcePath("tests/data/bad/" + file); }
std::string edgePath(const std::string& file) { return sourcePath("tests/data/lenses/" + file); }

// One broken file in tests/data/bad/ and where its first fault is.
struct BadFile {
    const char* file;
    int line;
    int column;
    const char* names;  // a piece of the message that says what is wrong
};

const BadFile kBadFiles[] = {
    {"abbe-too-small.csv", 3, 18, "abbe must be empty (no dispersion) or at least 5"},
    {"coating-out-of-range.csv", 4, 22, "coating_wavelength_nm must be empty or in 100..5000"},
    {"doubled-stop.csv", 6, 1, "second aperture stop (the first is on line 5)"},
    {"empty-required-field.csv", 4, 9, "radius_mm is empty"},
    {"empty.csv", 1, 1, "no header line"},
    {"header-duplicated-column.csv", 2, 57, "column 'ior_d' appears twice in header"},
    {"header-missing-column.csv", 2, 1, "header lacks column 'coating_wavelength_nm'"},
    {"header-unknown-column.csv", 2, 79, "unknown column 'glass_name'"},
    {"inf-field.csv", 4, 13, "thickness_mm 'inf' is not a finite number"},
    {"ior-above-four.csv", 3, 14, "ior_d above 4"},
    {"ior-below-one.csv", 3, 14, "ior_d below 1"},
    {"last-thickness-zero.csv", 5, 8, "last row's thickness_mm"},
    {"missing-stop.csv", 4, 1, "no aperture stop"},
    {"nan-field.csv", 3, 9, "radius_mm 'nan' is not a finite number"},
    {"negative-thickness.csv", 4, 13, "negative thickness_mm"},
    {"no-surface-rows.csv", 2, 1, "no surface rows after the header"},
    {"non-numeric-unit-suffix.csv", 4, 13, "thickness_mm '1.2mm' is not a finite number"},
    {"non-numeric-word.csv", 5, 14, "semi_aperture_mm 'abc' is not a finite number"},
    {"nul-byte.csv", 4, 18, "NUL byte"},
    {"only-comments.csv", 3, 1, "no header line"},
    {"out-of-double-range.csv", 3, 9, "radius_mm '1e400' is out of the range of double"},
    {"plus-minus-sign.csv", 4, 9, "radius_mm '+-50' is not a finite number"},
    {"row-too-few-fields.csv", 4, 21, "row has 6 fields, header (line 2) has 7"},
    {"row-too-many-fields.csv", 5, 17, "row has 8 fields, header (line 2) has 7"},
    {"semi-aperture-exceeds-radius.csv", 4, 18, "semi_aperture_mm exceeds |radius_mm|"},
    {"semi-aperture-negative.csv", 5, 14, "semi_aperture_mm must be positive"},
    {"semi-aperture-too-small.csv", 5, 14, "semi_aperture_mm must lie in 1e-6..1e6"},
    {"semi-aperture-zero.csv", 4, 19, "semi_aperture_mm must be positive"},
    {"stop-changes-dispersion.csv", 4, 14, "abbe must equal the medium before it"},
    {"stop-changes-medium.csv", 5, 11, "ior_d must equal the medium before it"},
    {"stop-nonzero-radius.csv", 5, 6, "the stop must be flat"},
    {"thickness-too-large.csv", 4, 13, "thickness_mm above 1e6"},
    {"too-many-surfaces.csv", 515, 1, "more than 512 surfaces"},
    {"unknown-kind.csv", 3, 1, "kind must be 'surface' or 'stop', not 'mirror'"},
};

TEST(LoadPrescription, EveryBrokenFileNamesPathLineColumnAndFault) {
    for (const BadFile& bad : kBadFiles) {
        SCOPED_TRACE(bad.file);
        const std::string path = badPath(bad.file);
        ASSERT_TRUE(std::filesystem::exists(path));
        const auto lens = loadPrescription(path);
        ASSERT_FALSE(lens) << "parsed without error";
        EXPECT_EQ(lens.error().code, ErrorCode::ParseError);
        std::ostringstream prefix;
        prefix << path << ":" << bad.line << ":" << bad.column << ": ";
        EXPECT_EQ(lens.error().message.rfind(prefix.str(), 0), 0u)
            << "expected prefix " << prefix.str() << "\n got " << lens.error().message;
        EXPECT_NE(lens.error().message.find(bad.names), std::string::npos)
            << "expected '" << bad.names << "' in " << lens.error().message;
    }
}

TEST(LoadPrescription, EveryFileInTheBrokenFolderHasAnExpectedError) {
    std::set<std::string> expected;
    for (const BadFile& bad : kBadFiles) expected.insert(bad.file);
    for (const auto& entry : std::filesystem::directory_iterator(badPath(""))) {
        const std::string name = entry.path().filename().string();
        EXPECT_EQ(expected.count(name), 1u) << name << " has no expectation in kBadFiles";
    }
}

TEST(LoadPrescription, MissingFileIsNotFoundAndNamesThePath) {
    const std::string path = badPath("no-such-lens.csv");
    const auto lens = loadPrescription(path);
    ASSERT_FALSE(lens);
    EXPECT_EQ(lens.error().code, ErrorCode::NotFound);
    EXPECT_EQ(lens.error().message.rfind(path + ": ", 0), 0u) << lens.error().message;
}

TEST(LoadPrescription, EveryShippedLensLoadsWithOneStopAndMakesALens) {
    for (const char* file : kShippedLenses) {
        SCOPED_TRACE(file);
        const auto prescription = loadPrescription(lensPath(file));
        ASSERT_TRUE(prescription) << prescription.error().message;
        ASSERT_GE(prescription->stop_index, 0);
        ASSERT_LT(prescription->stop_index, static_cast<int>(prescription->surfaces.size()));
        EXPECT_EQ(prescription->surfaces[prescription->stop_index].kind, SurfaceKind::Stop);
        EXPECT_FALSE(prescription->name.empty());
        EXPECT_GT(prescription->metadataNumber("focal_length_mm").value_or(0.0), 0.0);
        const auto lens = Lens::make(*prescription, CameraDescription{});
        EXPECT_TRUE(lens) << lens.error().message;
    }
}

// The three rows that the CRLF, BOM and reordered-column files all describe.
std::vector<Surface> threeRowLens() {
    std::vector<Surface> rows(3);
    rows[0] = {SurfaceKind::Refracting, 50.0, 5.0, 1.5, 50.0, 10.0, 550.0, 3};
    rows[1] = {SurfaceKind::Refracting, -50.0, 10.0, 1.0, 0.0, 10.0, 550.0, 4};
    rows[2] = {SurfaceKind::Stop, 0.0, 40.0, 1.0, 0.0, 5.0, 0.0, 5};
    return rows;
}

TEST(LoadPrescription, CrlfBomAndReorderedColumnsGiveTheSameSurfaces) {
    for (const char* file : {"crlf-line-endings.csv", "utf8-bom.csv", "columns-reordered.csv"}) {
        SCOPED_TRACE(file);
        const auto lens = loadPrescription(edgePath(file));
        ASSERT_TRUE(lens) << lens.error().message;
        EXPECT_EQ(lens->surfaces, threeRowLens());
        EXPECT_EQ(lens->stop_index, 2);
        EXPECT_EQ(lens->name, std::filesystem::path(file).stem().string());
        EXPECT_EQ(lens->source, edgePath(file));
    }
}

TEST(LoadPrescription, CrlfFileKeepsNoCarriageReturnInMetadata) {
    const auto lens = loadPrescription(edgePath("crlf-line-endings.csv"));
    ASSERT_TRUE(lens);
    EXPECT_EQ(lens->metadata.at("good"), "Windows line endings");
}

TEST(LoadPrescription, GlassWithoutAbbeIsNonDispersive) {
    const auto prescription = loadPrescription(edgePath("glass-without-abbe.csv"));
    ASSERT_TRUE(prescription) << prescription.error().message;
    EXPECT_EQ(prescription->surfaces[0].ior_d, 1.5);
    EXPECT_EQ(prescription->surfaces[0].abbe, 0.0);
    const auto lens = Lens::make(*prescription, CameraDescription{});
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->nonDispersiveGlasses(), 1);
    // Without dispersion the index is the same at every wavelength.
    EXPECT_EQ(lens->mediumIndex(0, kLambdaBlue_nm), lens->mediumIndex(0, kLambdaRed_nm));
}

TEST(LoadPrescription, SingleRefractingSurfaceBehindAStopIsALens) {
    const auto prescription = loadPrescription(edgePath("single-surface.csv"));
    ASSERT_TRUE(prescription) << prescription.error().message;
    ASSERT_EQ(prescription->surfaces.size(), 2u);
    EXPECT_EQ(prescription->stop_index, 0);
    EXPECT_EQ(prescription->surfaces[1].radius_mm, 30.0);
    EXPECT_EQ(prescription->surfaces[1].ior_d, 1.5);
    const auto lens = Lens::make(*prescription, CameraDescription{});
    ASSERT_TRUE(lens) << lens.error().message;
    const auto p = paraxialProperties(*lens, kLambdaD_nm);
    ASSERT_TRUE(p);
    // One surface from air into n = 1.5 with R = 30: rear focal length n R / (n - 1) = 90 mm,
    // which is where the table puts the image plane.
    EXPECT_NEAR(p->efl_mm, 90.0, 1e-9);
    EXPECT_NEAR(p->bfl_mm, 90.0, 1e-9);
}

TEST(LoadPrescription, FlatOnlyLensParsesButIsAfocal) {
    const auto prescription = loadPrescription(edgePath("flat-only.csv"));
    ASSERT_TRUE(prescription) << prescription.error().message;
    ASSERT_EQ(prescription->surfaces.size(), 5u);
    for (const Surface& s : prescription->surfaces) EXPECT_EQ(s.radius_mm, 0.0);
    EXPECT_EQ(prescription->stop_index, 2);
    const auto lens = Lens::make(*prescription, CameraDescription{});
    ASSERT_FALSE(lens);
    EXPECT_NE(lens.error().message.find("afocal"), std::string::npos) << lens.error().message;
}

TEST(LoadPrescription, RadiusOfTenMillionMillimetresIsNearlyFlat) {
    const auto prescription = loadPrescription(edgePath("radius-1e7.csv"));
    ASSERT_TRUE(prescription) << prescription.error().message;
    EXPECT_EQ(prescription->surfaces[0].radius_mm, 1e7);
    const auto lens = Lens::make(*prescription, CameraDescription{});
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_NEAR(lens->surfaces()[0].curvature, 1e-7, 1e-20);
    const auto p = paraxialProperties(*lens, kLambdaD_nm);
    ASSERT_TRUE(p);
    // A plano-convex lens with R = 50 and n = 1.5 has f near R / (n - 1) = 100 mm.
    EXPECT_NEAR(p->efl_mm, 100.0, 2.0);
}

TEST(ParsePrescription, ErrorsInTextNameTheSourceLabel) {
    const auto lens = parsePrescription(std::string(kHeader) + "stop,0,10,1,,5,,\n", "my label");
    ASSERT_FALSE(lens);
    EXPECT_EQ(lens.error().message.rfind("my label:2:17: ", 0), 0u) << lens.error().message;
}

TEST(ParsePrescription, AcceptsSignedAndBareDecimalForms) {
    const auto lens = parsePrescription(
        std::string(kHeader) + "surface,+1.5e2,.5,1.,5.,1e1,6E2\nstop,-0,100,1,,2.5e0,\n", "t");
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->surfaces[0].radius_mm, 150.0);
    EXPECT_EQ(lens->surfaces[0].thickness_mm, 0.5);
    EXPECT_EQ(lens->surfaces[0].ior_d, 1.0);
    EXPECT_EQ(lens->surfaces[0].semi_aperture_mm, 10.0);
    EXPECT_EQ(lens->surfaces[0].coating_wavelength_nm, 600.0);
    EXPECT_EQ(lens->surfaces[1].semi_aperture_mm, 2.5);
}

TEST(ParsePrescription, AbbeOfAirIsIgnoredAndEmptyOptionalFieldsAreZero) {
    const auto lens = parsePrescription(std::string(kHeader) +
                                            "surface,50,5,1.5,,10,\nsurface,-50,40,1,64,10,"
                                            "\nstop,0,5,1,,4,\n",
                                        "t");
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->surfaces[0].abbe, 0.0);
    EXPECT_EQ(lens->surfaces[0].coating_wavelength_nm, 0.0);
    EXPECT_EQ(lens->surfaces[1].abbe, 0.0);
}

TEST(ParsePrescription, FieldsMayCarrySpacesAndTabs) {
    const auto lens = parsePrescription(
        std::string(kHeader) +
            " surface ,\t50, 5 ,1.5,50,10,550\nsurface,-50,10,1,,10,550\nstop,0,40,1,,5,\n",
        "t");
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->surfaces[0].radius_mm, 50.0);
    EXPECT_EQ(lens->surfaces[0].thickness_mm, 5.0);
}

TEST(ParsePrescription, ErrorColumnPointsPastLeadingSpaces) {
    const auto lens =
        parsePrescription(std::string(kHeader) + "surface,  abc,5,1.5,50,10,550\n", "t");
    ASSERT_FALSE(lens);
    EXPECT_EQ(lens.error().message.rfind("t:2:11: ", 0), 0u) << lens.error().message;
}

TEST(ParsePrescription, FileWithoutFinalNewlineParses) {
    std::string text = std::string(kHeader) + kRows;
    text.pop_back();
    const auto lens = parsePrescription(text, "t");
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->surfaces.size(), 3u);
}

TEST(ParsePrescription, StopInsideGlassIsAcceptedWhenTheGlassContinues) {
    const auto lens = parsePrescription(
        std::string(kHeader) +
            "surface,40,3,1.6,40,10,\nstop,0,3,1.6,40,6,\nsurface,-40,45,1,,10,\n",
        "t");
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->stop_index, 1);
}

std::string flatRows(int surfaces) {
    std::string text = kHeader;
    for (int i = 0; i < surfaces - 1; ++i) text += "surface,0,1,1,,10,\n";
    return text + "stop,0,40,1,,5,\n";
}

TEST(ParsePrescription, AcceptsFiveHundredTwelveSurfacesAndRefusesOneMore) {
    const auto most = parsePrescription(flatRows(512), "t");
    ASSERT_TRUE(most) << most.error().message;
    EXPECT_EQ(most->surfaces.size(), 512u);
    const auto too_many = parsePrescription(flatRows(513), "t");
    ASSERT_FALSE(too_many);
    // The 513th row is on line 514 (the header is line 1).
    EXPECT_EQ(too_many.error().message.rfind("t:514:1: more than 512 surfaces", 0), 0u)
        << too_many.error().message;
}

TEST(ParsePrescription, HashInsideAFieldIsNotAComment) {
    const auto lens =
        parsePrescription(std::string(kHeader) + "surface,50#,5,1.5,50,10,550\n", "t");
    ASSERT_FALSE(lens);
    EXPECT_NE(lens.error().message.find("'50#'"), std::string::npos) << lens.error().message;
}

TEST(PrescriptionMetadata, ReadsKeyValueComments) {
    const auto lens = parsePrescription(
        std::string("# name: Test Lens\n# source_patent: US 1,234,567\n") + kHeader + kRows,
        "dir/test.csv");
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->metadata.at("name"), "Test Lens");
    EXPECT_EQ(lens->metadata.at("source_patent"), "US 1,234,567");
    EXPECT_EQ(lens->name, "Test Lens");
}

TEST(PrescriptionMetadata, SplitsSeveralPairsOnOneLineAtSemicolons) {
    const auto lens = parsePrescription(
        std::string("# focal_length_mm: 129 (upstream label); f_number: 11 (upstream label)\n") +
            kHeader + kRows,
        "t");
    ASSERT_TRUE(lens);
    EXPECT_EQ(lens->metadata.at("focal_length_mm"), "129 (upstream label)");
    EXPECT_EQ(lens->metadata.at("f_number"), "11 (upstream label)");
    EXPECT_EQ(lens->metadataNumber("focal_length_mm"), 129.0);
    EXPECT_EQ(lens->metadataNumber("f_number"), 11.0);
}

TEST(PrescriptionMetadata, KeepsSemicolonsThatDoNotStartAnotherPair) {
    const auto lens = parsePrescription(
        std::string("# name: a toy (three surfaces; surface 2 is inert) ; f_number: 11\n") +
            kHeader + kRows,
        "t");
    ASSERT_TRUE(lens);
    EXPECT_EQ(lens->name, "a toy (three surfaces; surface 2 is inert)");
    EXPECT_EQ(lens->metadataNumber("f_number"), 11.0);
}

TEST(PrescriptionMetadata, IgnoresProseAndKeepsTheFirstValueOfAKey) {
    const auto lens =
        parsePrescription(std::string("# flarelab lens prescription, format v1 (see README.md)\n"
                                      "# paraxial check (d-line, computed): EFL 99.24 mm\n"
                                      "# f_number: 16\n# f_number: 22\n") +
                              kHeader + kRows + "# late_key: after the header\n",
                          "t");
    ASSERT_TRUE(lens);
    EXPECT_EQ(lens->metadata.size(), 2u);
    EXPECT_EQ(lens->metadata.at("f_number"), "16");
    EXPECT_EQ(lens->metadata.at("late_key"), "after the header");
}

TEST(PrescriptionMetadata, NameFallsBackToTheFileStem) {
    const auto lens = parsePrescription(std::string(kHeader) + kRows, "some/dir/my-lens.v2.csv");
    ASSERT_TRUE(lens);
    EXPECT_EQ(lens->name, "my-lens.v2");
}

TEST(PrescriptionMetadata, NumberIsTheLeadingNumberOfTheValue) {
    Prescription p;
    p.metadata = {{"labelled", "100 (label in both upstream files)"},
                  {"plain", "2.8"},
                  {"signed", "+35"},
                  {"range", "28-75"},
                  {"unit", "50mm"},
                  {"absent", "not given (patent lens is f/2.8)"},
                  {"empty", ""},
                  {"not_finite", "nan"},
                  {"too_big", "1e400"}};
    EXPECT_EQ(p.metadataNumber("labelled"), 100.0);
    EXPECT_EQ(p.metadataNumber("plain"), 2.8);
    EXPECT_EQ(p.metadataNumber("signed"), 35.0);
    EXPECT_EQ(p.metadataNumber("range"), 28.0);
    EXPECT_EQ(p.metadataNumber("unit"), 50.0);
    EXPECT_EQ(p.metadataNumber("absent"), std::nullopt);
    EXPECT_EQ(p.metadataNumber("empty"), std::nullopt);
    EXPECT_EQ(p.metadataNumber("not_finite"), std::nullopt);
    EXPECT_EQ(p.metadataNumber("too_big"), std::nullopt);
    EXPECT_EQ(p.metadataNumber("missing"), std::nullopt);
}

TEST(PrescriptionMetadata, ShippedLensWithoutFNumberGivesNullopt) {
    const auto lens = loadPrescription(lensPath("nikon-28-75mm.csv"));
    ASSERT_TRUE(lens) << lens.error().message;
    EXPECT_EQ(lens->metadataNumber("f_number"), std::nullopt);
    EXPECT_EQ(lens->metadataNumber("focal_length_mm"), 28.9);
}

struct BadCamera {
    const char* field;
    CameraDescription camera;
};

std::vector<BadCamera> badCameras() {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    constexpr double kInf = std::numeric_limits<double>::infinity();
    std::vector<BadCamera> cases;
    const auto add = [&](const char* field, auto&& change) {
        CameraDescription camera;
        change(camera);
        cases.push_back({field, camera});
    };
    add("focal_length_mm", [](CameraDescription& c) { c.focal_length_mm = -50.0; });
    add("focal_length_mm", [&](CameraDescription& c) { c.focal_length_mm = kNaN; });
    add("f_number", [](CameraDescription& c) { c.f_number = -2.0; });
    add("f_number", [&](CameraDescription& c) { c.f_number = kInf; });
    add("f_number", [](CameraDescription& c) { c.f_number = 0.3; });
    add("sensor_width_mm", [](CameraDescription& c) { c.sensor_width_mm = 0.0; });
    add("sensor_width_mm", [&](CameraDescription& c) { c.sensor_width_mm = kNaN; });
    add("sensor_height_mm", [](CameraDescription& c) { c.sensor_height_mm = -24.0; });
    add("aperture_blades", [](CameraDescription& c) { c.aperture_blades = 2; });
    add("aperture_blades", [](CameraDescription& c) { c.aperture_blades = 65; });
    add("aperture_blades", [](CameraDescription& c) { c.aperture_blades = -6; });
    add("aperture_rotation_deg", [&](CameraDescription& c) { c.aperture_rotation_deg = kInf; });
    add("default_coating_wavelength_nm",
        [](CameraDescription& c) { c.default_coating_wavelength_nm = 50.0; });
    add("default_coating_wavelength_nm",
        [&](CameraDescription& c) { c.default_coating_wavelength_nm = kNaN; });
    return cases;
}

TEST(LensMake, RejectsEachInvalidCameraFieldByName) {
    const auto prescription = loadPrescription(lensPath("heliar-tronnier.csv"));
    ASSERT_TRUE(prescription) << prescription.error().message;
    for (const BadCamera& bad : badCameras()) {
        SCOPED_TRACE(bad.field);
        ASSERT_TRUE(bad.camera.invalidReason().has_value());
        const auto lens = Lens::make(*prescription, bad.camera);
        ASSERT_FALSE(lens);
        EXPECT_EQ(lens.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(lens.error().message.find(bad.field), std::string::npos) << lens.error().message;
    }
}

TEST(LensMake, AcceptsTheBoundaryCameraValues) {
    const auto prescription = loadPrescription(lensPath("heliar-tronnier.csv"));
    ASSERT_TRUE(prescription);
    CameraDescription camera;
    camera.f_number = 0.5;
    camera.aperture_blades = 3;
    camera.default_coating_wavelength_nm = 100.0;
    EXPECT_TRUE(Lens::make(*prescription, camera));
    camera.aperture_blades = 64;
    camera.default_coating_wavelength_nm = 5000.0;
    EXPECT_TRUE(Lens::make(*prescription, camera));
}

}  // namespace
}  // namespace flarelab::optics
