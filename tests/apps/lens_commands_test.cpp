#include "apps/lens_commands.h"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>
#include <sstream>

#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun runFlarelab(const std::vector<std::string>& args) {
    return testing::runCommand(addLensCommands, args);
}

TEST(LensShow, JsonHasEflAndBflOfTheLens) {
    const CommandRun run =
        runFlarelab({"lens", "show", flarelab::testing::lensPath("heliar-tronnier.csv"), "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto doc = nlohmann::json::parse(run.out);
    EXPECT_NEAR(doc["efl_mm"].get<double>(), 99.24, 0.01);
    EXPECT_NEAR(doc["bfl_mm"].get<double>(), 81.32, 0.01);
    EXPECT_EQ(doc["label_focal_length_mm"].get<double>(), 100.0);
}

TEST(LensShow, TextPrintsEflBesideTheLabel) {
    const CommandRun run =
        runFlarelab({"lens", "show", flarelab::testing::lensPath("heliar-tronnier.csv")});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("99.236 mm   (source's label: 100.0 mm)"), std::string::npos) << run.out;
}

TEST(LensShow, MissingFileIsAClearError) {
    const CommandRun run = runFlarelab({"lens", "show", "/nonexistent/lens.csv"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("/nonexistent/lens.csv"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::apps
