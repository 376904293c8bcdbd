#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "apps/bench_command.h"
#include "tests/apps/command_runner.h"

namespace flarelab::apps {
namespace {

using testing::CommandRun;

CommandRun benchMerge(std::vector<std::string> args) {
    args.insert(args.begin(), "bench");
    return testing::runCommand(addBenchCommands, args);
}

TEST(BenchMerge, QuickRunWritesTheTablesAndEveryJsonKey) {
    const auto json_path =
        (std::filesystem::temp_directory_path() / "flarelab_bench_merge_test.json").string();
    std::filesystem::remove(json_path);
    const CommandRun run = benchMerge({"merge", "--quick", "--width", "96", "--height", "64",
                                       "--repeat", "1", "--json", json_path});
    ASSERT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("## HDR bracket merge: speed"), std::string::npos) << run.out;
    EXPECT_NE(run.out.find("## HDR bracket merge: accuracy"), std::string::npos) << run.out;
    EXPECT_NE(run.out.find("| OpenCV MergeDebevec (8-bit) |"), std::string::npos) << run.out;
    std::ifstream file(json_path);
    const nlohmann::json doc = nlohmann::json::parse(file);
    for (const char* key : {"ours_ms", "debevec_ms", "robertson_ms", "copy_ms", "ours_rel_err",
                            "debevec_rel_err", "robertson_rel_err"}) {
        ASSERT_TRUE(doc.contains(key)) << key;
        ASSERT_TRUE(doc[key].is_number()) << key << ": " << doc[key];
        EXPECT_GE(doc[key].get<double>(), 0.0) << key;
    }
    EXPECT_EQ(doc["settings"]["width"], 96);
    EXPECT_EQ(doc["settings"]["height"], 64);
    EXPECT_GT(doc["settings"]["dynamic_range"].get<double>(), 1e6);
    // Even this small, the noise-weighted 12-bit merge beats OpenCV's on 8 bits.
    EXPECT_LT(doc["ours_rel_err"].get<double>(), doc["debevec_rel_err"].get<double>());
    EXPECT_LT(doc["ours_rel_err"].get<double>(), doc["robertson_rel_err"].get<double>());
}

TEST(BenchMerge, RejectsAnImageTooSmall) {
    const CommandRun run = benchMerge({"merge", "--quick", "--width", "4"});
    EXPECT_NE(run.code, 0);
    EXPECT_NE(run.err.find("--width"), std::string::npos) << run.err;
}

}  // namespace
}  // namespace flarelab::apps
