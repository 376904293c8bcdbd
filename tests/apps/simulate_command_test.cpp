#include "apps/simulate_command.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <sstream>

#include "hdr/exr.h"
#include "tests/test_paths.h"

namespace flarelab::apps {
namespace {

struct SimulateRun {
    int code = -1;
    std::string out, err;
};

SimulateRun simulate(std::vector<std::string> args) {
    CLI::App app;
    app.require_subcommand(1);
    std::ostringstream out, err;
    int code = 0;
    addSimulateCommand(app, out, err, code);
    std::vector<const char*> argv{"flarelab", "simulate"};
    for (const auto& a : args) argv.push_back(a.c_str());
    try {
        app.parse(static_cast<int>(argv.size()), argv.data());
    } catch (const CLI::ParseError& e) {
        return {app.exit(e, out, err), out.str(), err.str()};
    }
    return {code, out.str(), err.str()};
}

TEST(Simulate, WritesAnExrWithTheLightsAngleAndAPngPreview) {
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_simulate_test";
    std::filesystem::create_directories(dir);
    const std::string exr = (dir / "flare.exr").string(), png = (dir / "flare.png").string();
    const SimulateRun run = simulate({"--lens", flarelab::testing::lensPath("heliar-tronnier.csv"),
                                      "--angle", "4", "--roll", "10", "--width", "64", "--height",
                                      "48", "--grid", "16", "-o", exr, "--png", png});
    ASSERT_EQ(run.code, 0) << run.err;
    const auto image = hdr::readExr(exr);
    ASSERT_TRUE(image) << image.error().message;
    EXPECT_EQ(image->image.width, 64);
    EXPECT_EQ(image->meta.angle_deg, 4.0);
    EXPECT_TRUE(std::filesystem::exists(png));
    std::filesystem::remove_all(dir);
}

TEST(Simulate, BadLightAndMissingLightAreClearErrors) {
    const std::string lens = flarelab::testing::lensPath("heliar-tronnier.csv");
    SimulateRun run = simulate({"--lens", lens, "--light", "5,x", "-o", "/tmp/unused.exr"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("--light '5,x'"), std::string::npos);
    run = simulate({"--lens", lens, "-o", "/tmp/unused.exr"});
    EXPECT_EQ(run.code, 1);
    EXPECT_NE(run.err.find("needs --angle"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::apps
