// The daemon on a recorded sweep played back (flarelabd --replay): the same pipeline, the same
// job, the recording's data. Replaying the raw brackets recorded with a sweep must give back the
// recorded frames exactly.
#include <gtest/gtest.h>

#include "hdr/exr.h"
#include "hdr/sweep.h"
#include "tests/daemon/daemon_fixture.h"

namespace flarelab::daemon {
namespace {

using namespace testing;

ManagerOptions replayOf(const std::string& recorded_dir) {
    auto recorded = hdr::readSweep(recorded_dir);
    EXPECT_TRUE(recorded) << recorded.error().message;
    ManagerOptions options;
    auto sweep = std::make_shared<const hdr::Sweep>(std::move(*recorded));
    options.runner.limits.replay = sweep;
    options.runner.limits.head_min_deg = 0.0;
    options.runner.limits.head_max_deg = sweep->frames.back().angle_deg;
    return options;
}

v1::SweepConfig replayConfig(const std::string& output, double to_deg, double step_deg) {
    v1::SweepConfig c;
    c.set_from_deg(0.0);
    c.set_to_deg(to_deg);
    c.set_step_deg(step_deg);
    for (const double t : {0.25, 1.0, 4.0}) c.add_exposure_times_s(t);
    c.set_output_dir(output);
    return c;
}

TEST(Replay, RecordedRawBracketsReplayedThroughTheDaemonGiveBackTheRecordedFramesExactly) {
    TempDir dir;
    const std::string recorded = flarelab::testing::sourcePath("tests/data/sweeps/heliar-raw");
    Daemon daemon(dir.path, replayOf(recorded));
    auto stub = daemon.stub();
    v1::SweepConfig config = replayConfig("replayed", 2.0, 0.5);
    config.set_fit(true);
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, config, &job).ok());
    const auto events = watchToEnd(*stub, job.id());
    // This recording does not say its pixel pitch, so no model can be fitted in sensor mm: the
    // job fails at the fit, saying so, with every frame written.
    const v1::Job& last = events.back().job();
    ASSERT_EQ(last.state(), v1::FAILED) << last.reason();
    EXPECT_NE(last.reason().find("fit: "), std::string::npos) << last.reason();
    EXPECT_NE(last.reason().find("pixel_pitch_um"), std::string::npos) << last.reason();
    EXPECT_EQ(last.frames_done(), 5u);
    auto original = hdr::readSweep(recorded);
    auto replayed = hdr::readSweep(job.output_dir(), strictRead());
    ASSERT_TRUE(original && replayed) << (replayed ? "" : replayed.error().message);
    EXPECT_EQ(replayed->header.lens, original->header.lens);
    ASSERT_EQ(replayed->frames.size(), original->frames.size());
    for (size_t i = 0; i < original->frames.size(); ++i) {
        EXPECT_EQ(replayed->frames[i].angle_deg, original->frames[i].angle_deg);
        EXPECT_EQ(replayed->frames[i].brackets.size(), 3u);  // the recording predates them
        auto a = hdr::loadFrame(*original, i);
        auto b = hdr::loadFrame(*replayed, i);
        ASSERT_TRUE(a && b);
        EXPECT_EQ(a->image.pixels, b->image.pixels) << "frame " << i;
    }
    EXPECT_FALSE(fs::exists(job.output_dir() + "/model.flm"));
}

TEST(Replay, AnHdrOnlyRecordingIsExposedAgainAndConfigsMustFitTheRecording) {
    TempDir dir;
    Daemon daemon(dir.path, replayOf(flarelab::testing::sourcePath("tests/data/sweeps/nikon-hdr")));
    auto stub = daemon.stub();
    v1::Job job;
    ASSERT_TRUE(startSweep(*stub, replayConfig("hdr", 1.0, 0.5), &job).ok());
    const auto events = watchToEnd(*stub, job.id());
    EXPECT_EQ(events.back().job().state(), v1::SUCCEEDED) << events.back().job().reason();
    EXPECT_EQ(events.back().job().frames_done(), 3u);

    const grpc::Status off_grid = startSweep(*stub, replayConfig("grid", 1.0, 0.2), &job);
    EXPECT_EQ(off_grid.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(off_grid.error_message().find("config.step_deg: the recorded sweep has no frame at "
                                            "0.2 deg (it has 0, 0.5, 1)"),
              std::string::npos)
        << off_grid.error_message();
    v1::SweepConfig with_sim = simConfig("sim", 0.0, 1.0, 0.5);
    const grpc::Status sim = startSweep(*stub, with_sim, &job);
    EXPECT_EQ(sim.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_EQ(sim.error_message().rfind("config.sim: this daemon replays", 0), 0u);
    v1::SweepConfig size = replayConfig("size", 1.0, 0.5);
    size.set_width_px(640);
    EXPECT_EQ(startSweep(*stub, size, &job).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    v1::SweepConfig beyond = replayConfig("beyond", 2.0, 0.5);
    EXPECT_EQ(startSweep(*stub, beyond, &job).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    v1::RigDescription rig;
    auto ctx = context();
    ASSERT_TRUE(stub->DescribeRig(ctx.get(), {}, &rig).ok());
}

}  // namespace
}  // namespace flarelab::daemon
