// The flarelab command line's client of the daemon (apps/daemon_commands.h), against a daemon in
// the test process: sweep start with and without --watch, job list, control, rig status, and the
// errors a user sees when the daemon is not there or refuses.
#include <gtest/gtest.h>

#include "apps/daemon_commands.h"
#include "apps/sweep_command.h"
#include "tests/apps/command_runner.h"
#include "tests/daemon/daemon_fixture.h"

namespace flarelab::daemon {
namespace {

using namespace testing;
using apps::testing::runCommand;

auto sweepCommands = [](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
    apps::addSweepCommands(app, out, err, code);
};
auto jobCommands = [](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
    apps::addJobCommands(app, out, err, code);
};
auto rigCommands = [](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
    apps::addRigCommands(app, out, err, code);
};

TEST(Client, StartsAWatchedSweepListsItAndReportsTheRig) {
    TempDir dir;
    Daemon daemon(dir.path);
    const std::string output = daemon.output_root + "/cli";
    const auto run = runCommand(
        sweepCommands,
        {"sweep",      "start",   "--socket",   daemon.socket,
         "--sim",      "--fast",  "--lens",     flarelab::testing::lensPath("heliar-tronnier.csv"),
         "--from",     "0",       "--to",       "0.6",
         "--step",     "0.2",     "--brackets", "0.01,0.04",
         "--width",    "64",      "--height",   "43",
         "--previews", "--watch", "-o",         output});
    EXPECT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("job-000001 queued: 4 frames of heliar-tronnier.csv -> " + output),
              std::string::npos)
        << run.out;
    EXPECT_NE(run.out.find("job-000001 succeeded: 4 frames in " + output), std::string::npos)
        << run.out;
    EXPECT_NE(run.err.find("capture [##############################] 4/4 frames"),
              std::string::npos)
        << run.err;
    EXPECT_TRUE(fs::exists(output + "/previews"));

    const auto list = runCommand(jobCommands, {"job", "list", "--socket", daemon.socket});
    EXPECT_EQ(list.code, 0) << list.err;
    EXPECT_NE(list.out.find("job-000001  succeeded"), std::string::npos) << list.out;
    const auto json = runCommand(jobCommands, {"job", "list", "--socket", daemon.socket, "--json"});
    EXPECT_NE(json.out.find("\"state\": \"SUCCEEDED\""), std::string::npos) << json.out;

    const auto rig = runCommand(rigCommands, {"rig", "status", "--socket", daemon.socket});
    EXPECT_EQ(rig.code, 0) << rig.err;
    EXPECT_NE(rig.out.find("output root: " + daemon.output_root), std::string::npos) << rig.out;
    EXPECT_NE(rig.out.find("running: nothing"), std::string::npos) << rig.out;
}

TEST(Client, WithoutWatchItReturnsOnceAcceptedAndControlsTheJob) {
    TempDir dir;
    Daemon daemon(dir.path);
    const auto start =
        runCommand(sweepCommands, {"sweep",
                                   "start",
                                   "--socket",
                                   daemon.socket,
                                   "--sim",
                                   "--lens",
                                   flarelab::testing::lensPath("heliar-tronnier.csv"),
                                   "--from",
                                   "0",
                                   "--to",
                                   "4",
                                   "--step",
                                   "0.2",
                                   "--brackets",
                                   "0.01",
                                   "--width",
                                   "64",
                                   "--height",
                                   "43",
                                   "-o",
                                   daemon.output_root + "/slow"});
    ASSERT_EQ(start.code, 0) << start.err;
    const auto pause =
        runCommand(jobCommands, {"job", "pause", "job-000001", "--socket", daemon.socket});
    EXPECT_EQ(pause.code, 0) << pause.err;
    EXPECT_NE(pause.out.find("paused"), std::string::npos) << pause.out;
    const auto cancel =
        runCommand(jobCommands, {"job", "cancel", "job-000001", "--socket", daemon.socket});
    EXPECT_EQ(cancel.code, 0) << cancel.err;
    const auto watch =
        runCommand(jobCommands, {"job", "watch", "job-000001", "--socket", daemon.socket});
    EXPECT_EQ(watch.code, 3) << watch.out << watch.err;
    EXPECT_NE(watch.out.find("job-000001 cancelled"), std::string::npos) << watch.out;
}

TEST(Client, ErrorsSayWhatIsWrong) {
    TempDir dir;
    Daemon daemon(dir.path);
    const auto unknown =
        runCommand(jobCommands, {"job", "cancel", "job-000042", "--socket", daemon.socket});
    EXPECT_EQ(unknown.code, 1);
    EXPECT_NE(unknown.err.find("job cancel: job_id: no job 'job-000042'"), std::string::npos)
        << unknown.err;
    const auto refused =
        runCommand(sweepCommands, {"sweep", "start", "--socket", daemon.socket, "--sim", "--lens",
                                   flarelab::testing::lensPath("heliar-tronnier.csv"), "--step",
                                   "-1", "-o", daemon.output_root + "/x"});
    EXPECT_EQ(refused.code, 1);
    EXPECT_NE(refused.err.find("sweep start: config.step_deg"), std::string::npos) << refused.err;
    const auto outside = runCommand(
        sweepCommands, {"sweep", "start", "--socket", daemon.socket, "--sim", "--lens",
                        flarelab::testing::lensPath("heliar-tronnier.csv"), "-o", dir.path + "/x"});
    EXPECT_EQ(outside.code, 1);
    EXPECT_NE(outside.err.find("is not below the output root"), std::string::npos) << outside.err;
    const auto no_lens =
        runCommand(sweepCommands, {"sweep", "start", "--socket", daemon.socket, "--sim", "--lens",
                                   dir.path + "/missing.csv", "-o", daemon.output_root + "/y"});
    EXPECT_EQ(no_lens.code, 1);
    EXPECT_NE(no_lens.err.find("cannot open it"), std::string::npos) << no_lens.err;
    const auto gone =
        runCommand(jobCommands, {"job", "list", "--socket", dir.path + "/no-such.sock"});
    EXPECT_EQ(gone.code, 1);
    EXPECT_NE(gone.err.find("is flarelabd running"), std::string::npos) << gone.err;
    ::unsetenv("FLARELAB_SOCKET");
    ::unsetenv("FLARELAB_ADDRESS");
    const auto nowhere = runCommand(jobCommands, {"job", "list"});
    EXPECT_EQ(nowhere.code, 2);
    EXPECT_NE(nowhere.err.find("no daemon named"), std::string::npos) << nowhere.err;
}

}  // namespace
}  // namespace flarelab::daemon
