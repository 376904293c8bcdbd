#include "apps/lens_commands.h"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>
#include <sstream>

#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

struct CommandRun {
    int code = -1;
    std::string out, err;
};

CommandRun runFlarelab(std::vector<std::string> args) {
    CLI::App app;
    app.require_subcommand(1);
    std::ostringstream out, err;
    int code = 0;
    addLensCommands(app, out, err, code);
    std::vector<const char*> argv{"flarelab"};
    for (const auto& a : args) argv.push_back(a.c_str());
    try {
        app.parse(static_cast<int>(argv.size()), argv.data());
    } catch (const CLI::ParseError& e) {
        return {app.exit(e, out, err), out.str(), err.str()};
    }
    return {code, out.str(), err.str()};
}

TEST(LensShow, JsonHasEflAndBflOfTheLens) {
    const CommandRun run =
        runFlarelab({"lens", "show", testing::lensPath("heliar-tronnier.csv"), "--json"});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto doc = nlohmann::json::parse(run.out);
    EXPECT_NEAR(doc["efl_mm"].get<double>(), 99.24, 0.01);
    EXPECT_NEAR(doc["bfl_mm"].get<double>(), 81.32, 0.01);
    EXPECT_EQ(doc["label_focal_length_mm"].get<double>(), 100.0);
}

TEST(LensShow, TextPrintsEflBesideTheLabel) {
    const CommandRun run = runFlarelab({"lens", "show", testing::lensPath("heliar-tronnier.csv")});
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
