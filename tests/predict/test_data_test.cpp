// The model file the report's browser test, the daemon's Predict tests and the Python client
// predict with, tests/data/models/moving-disc.flm, is movingDiscModel(2) with its per-frame values
// kept and a light power, so that the report holds every kind of plot (fitted dots, PST). This
// checks that the file is that model, and writes it again when asked:
//
//     FLARELAB_WRITE_TEST_DATA=1 build/release/tests/predict_test
//         --gtest_filter='TestData.*' --gtest_also_run_disabled_tests
// (one command line).
#include <gtest/gtest.h>

#include <cstdlib>

#include "fit/model_file.h"
#include "tests/predict/moving_disc_model.h"
#include "tests/test_paths.h"

namespace flarelab::predict {
namespace {

fit::FlareModel reportTestModel() {
    fit::FlareModel model = testing::movingDiscModel(2, true);
    model.capture.light_power_dn_s = 5.0e6;
    model.created_utc.clear();
    return model;
}

const std::string kPath = "tests/data/models/moving-disc.flm";

TEST(TestData, TheReportTestModelIsTheMovingDiscWithSamplesAndLightPower) {
    auto read = fit::readModel(flarelab::testing::sourcePath(kPath));
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(*read, reportTestModel()) << "rewrite " << kPath << " (see the top of this file)";
}

TEST(TestData, DISABLED_WriteTheReportTestModel) {
    if (std::getenv("FLARELAB_WRITE_TEST_DATA") == nullptr) GTEST_SKIP();
    ASSERT_TRUE(fit::writeModel(flarelab::testing::sourcePath(kPath), reportTestModel()));
}

}  // namespace
}  // namespace flarelab::predict
