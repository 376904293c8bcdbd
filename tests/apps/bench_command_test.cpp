#include "apps/bench_command.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "tests/apps/command_runner.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun bench(std::vector<std::string> args) {
    args.insert(args.begin(), "bench");
    return testing::runCommand(addBenchCommands, args);
}

TEST(BenchRender, WritesTheTablesAndAJsonDocumentWithEveryLens) {
    const auto json_path =
        (std::filesystem::temp_directory_path() / "flarelab_bench_render_test.json").string();
    std::filesystem::remove(json_path);
    const CommandRun run =
        bench({"render", "--quick", "--lens", flarelab::testing::lensPath("lensbaby-toy.csv"),
               "--lens", flarelab::testing::lensPath("heliar-tronnier.csv"), "--lights", "1",
               "--width", "96", "--height", "64", "--grid", "16", "--json", json_path});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("| lensbaby-toy | 1 |"), std::string::npos) << run.out;
    EXPECT_NE(run.out.find("Tables 5-7"), std::string::npos);
    std::ifstream file(json_path);
    const nlohmann::json doc = nlohmann::json::parse(file);
    ASSERT_EQ(doc["lenses"].size(), 2u);
    for (const auto& lens : doc["lenses"]) {
        for (const char* key : {"name", "tiled_ms", "reference_ms", "speedup", "psnr_db"})
            EXPECT_TRUE(lens.contains(key)) << key;
        EXPECT_GT(lens["tiled_ms"].get<double>(), 0.0);
        EXPECT_GT(lens["reference_ms"].get<double>(), 0.0);
        // Light merge against the unmerged reference: close, never identical by accident of a
        // missing image.
        if (!lens["psnr_db"].is_null()) {
            EXPECT_GT(lens["psnr_db"].get<double>(), 40.0);
        }
    }
    EXPECT_EQ(doc["merge"].size(), 6u);  // two lenses x three merge levels
    EXPECT_EQ(doc["lenses"][0]["name"], "lensbaby-toy");
}

TEST(BenchRender, RejectsAMissingLensNamingIt) {
    const CommandRun run = bench({"render", "--quick", "--lens", "/nonexistent/lens.csv"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("/nonexistent/lens.csv"), std::string::npos) << run.err;
}

}  // namespace
}  // namespace flarelab::apps
