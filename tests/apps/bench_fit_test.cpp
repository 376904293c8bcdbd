#include <gtest/gtest.h>

#include "apps/bench_command.h"
#include "bench/fit_bench.h"
#include "tests/apps/command_runner.h"

namespace flarelab::apps {
namespace {

// A whole trade fits a sweep per row (minutes each); here only what decides which rows run.
TEST(BenchFit, AnUnknownKnobIsRefusedByNameBeforeAnythingIsLoaded) {
    const testing::CommandRun run =
        testing::runCommand(addBenchCommands, {"bench", "fit", "--sweep", "/nonexistent/sweep",
                                               "--lens", "/nonexistent/lens.csv", "--knob",
                                               "shading refit passes", "--knob", "refit passes"});
    EXPECT_NE(run.code, 0);
    EXPECT_NE(run.err.find("unknown knob 'refit passes'"), std::string::npos) << run.err;
    for (const std::string& knob : bench::tradeKnobs())
        EXPECT_NE(run.err.find(knob), std::string::npos) << knob << "\n" << run.err;
    EXPECT_EQ(run.err.find("/nonexistent"), std::string::npos) << run.err;
}

}  // namespace
}  // namespace flarelab::apps
