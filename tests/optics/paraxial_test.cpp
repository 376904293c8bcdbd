#include "optics/paraxial.h"

#include <gtest/gtest.h>

#include <fstream>
#include <regex>
#include <sstream>

#include "common/units.h"
#include "optics/prescription.h"
#include "tests/test_paths.h"

namespace flarelab::optics {
namespace {

using flarelab::testing::kShippedLenses;
using flarelab::testing::lensPath;

// The independent paraxial check each shipped file carries in its header:
// "# paraxial check (...): EFL 99.24 mm, back focal distance 81.32 mm, ..."
struct HeaderCheck {
    double efl_mm = 0.0;
    double bfl_mm = 0.0;
    double stop_mm = 0.0;  // "stop semi-aperture giving f/N ...: X mm", 0 if absent
};
HeaderCheck readHeaderCheck(const std::string& path) {
    std::ifstream in(path);
    std::string line;
    HeaderCheck check;
    const std::regex paraxial(R"(EFL ([0-9.]+) mm, back focal distance ([0-9.]+) mm)");
    const std::regex stop(R"(stop semi-aperture giving .*: ([0-9.]+) mm)");
    std::smatch m;
    while (std::getline(in, line)) {
        if (std::regex_search(line, m, paraxial)) {
            check.efl_mm = std::stod(m[1]);
            check.bfl_mm = std::stod(m[2]);
        }
        if (std::regex_search(line, m, stop)) check.stop_mm = std::stod(m[1]);
    }
    return check;
}

TEST(ParaxialProperties, MatchIndependentCheckOfEveryShippedLensToOneThousandth) {
    for (const char* file : kShippedLenses) {
        SCOPED_TRACE(file);
        const HeaderCheck check = readHeaderCheck(lensPath(file));
        ASSERT_GT(check.efl_mm, 0.0);
        const auto prescription = loadPrescription(lensPath(file));
        ASSERT_TRUE(prescription) << prescription.error().message;
        const auto lens = Lens::make(*prescription, CameraDescription{});
        ASSERT_TRUE(lens) << lens.error().message;
        const auto p = paraxialProperties(*lens, kLambdaD_nm);
        ASSERT_TRUE(p);
        EXPECT_NEAR(p->efl_mm, check.efl_mm, 1e-3 * check.efl_mm);
        EXPECT_NEAR(p->bfl_mm, check.bfl_mm, 1e-3 * check.bfl_mm);
    }
}

TEST(LensMake, ScalesStopToTheHeaderFNumberCheck) {
    for (const char* file : kShippedLenses) {
        SCOPED_TRACE(file);
        const HeaderCheck check = readHeaderCheck(lensPath(file));
        if (check.stop_mm == 0.0) continue;
        const auto lens = Lens::make(*loadPrescription(lensPath(file)), CameraDescription{});
        ASSERT_TRUE(lens);
        EXPECT_NEAR(lens->surfaces()[lens->stopIndex()].semi_aperture_mm, check.stop_mm,
                    2e-3 * check.stop_mm);
    }
}

}  // namespace
}  // namespace flarelab::optics

namespace flarelab::optics {
namespace {

TEST(LensMake, RejectsHeaderLabelsOutsideTheCameraRangeAndNamesThem) {
    for (const char* file :
         {"label-focal-length-overflows-stop.csv", "label-values-close-the-stop.csv"}) {
        SCOPED_TRACE(file);
        const auto prescription = loadPrescription(
            flarelab::testing::sourcePath(std::string("fuzz/corpus/prescription/") + file));
        ASSERT_TRUE(prescription);
        const auto lens = Lens::make(*prescription, CameraDescription{});
        ASSERT_FALSE(lens);
        EXPECT_NE(lens.error().message.find("header label focal_length_mm"), std::string::npos)
            << lens.error().message;
        // The camera's own values override the labels and make the lens usable.
        CameraDescription camera;
        camera.focal_length_mm = 50.0;
        camera.f_number = 8.0;
        EXPECT_TRUE(Lens::make(*prescription, camera));
    }
}

TEST(LensMake, RejectsAnFNumberWhoseStopWouldBeAbsurd) {
    const auto prescription = loadPrescription(flarelab::testing::lensPath("heliar-tronnier.csv"));
    CameraDescription camera;
    camera.f_number = 9000.0;
    camera.focal_length_mm = 0.02;
    const auto lens = Lens::make(*prescription, camera);
    ASSERT_FALSE(lens);
    EXPECT_NE(lens.error().message.find("stop semi-aperture"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::optics
