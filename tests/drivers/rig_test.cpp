#include "drivers/rig.h"

#include <gtest/gtest.h>

#include <set>

#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

RigOptions tinyRig() {
    RigOptions o;
    o.sim_camera.width_px = 48;
    o.sim_camera.height_px = 32;
    o.sim_camera.render.base_grid = 16;
    o.sim_camera.render.probe_grid = 6;
    o.sim_camera.render.starburst_options.mask_size = 32;
    o.sim_camera.render.starburst_options.fft_size = 128;
    o.sim_clock = std::make_shared<SimClock>(SimTime::Fast);
    return o;
}

TEST(SimHeadBackend, OpensByUriWithItsParametersAndNamesTheBadOne) {
    HeadRegistry heads;
    ASSERT_TRUE(addSimHeadBackend(heads));
    auto head = heads.open("sim:?speed_deg_s=45&settle_s=0&time=fast&seed=3");
    ASSERT_TRUE(head) << head.error().message;
    EXPECT_EQ((*head)->speed_deg_s(), 45.0);
    ASSERT_TRUE((*head)->home(10.0));
    EXPECT_EQ(*(*head)->moveTo(2.5, 10.0), 2.5);

    for (const auto& [uri, named] : std::vector<std::pair<std::string, std::string>>{
             {"sim:?speed=4", "unknown parameter 'speed'"},
             {"sim:?speed_deg_s=fast", "speed_deg_s"},
             {"sim:?speed_deg_s=-1", "speed_deg_s"},
             {"sim:?time=slow", "time must be fast or real"},
             {"sim:?seed=1.5", "seed"},
         }) {
        const auto bad = heads.open(uri);
        ASSERT_FALSE(bad) << uri;
        EXPECT_NE(bad.error().message.find(named), std::string::npos) << bad.error().message;
    }
    const auto listed = heads.enumerate();
    ASSERT_EQ(listed.size(), 1u);
    EXPECT_EQ(listed[0].kind, "head");
}

TEST(OpenRig, BindsTheSimulatedCameraToTheOpenedHead) {
    const RigOptions options = tinyRig();
    auto registries = makeRigRegistries(options);
    ASSERT_TRUE(registries) << registries.error().message;
    auto rig =
        openRig(*registries, "sim:?lens=" + flarelab::testing::lensPath("heliar-tronnier.csv"),
                "sim:", options);
    ASSERT_TRUE(rig) << rig.error().message;
    ASSERT_NE(rig->sim_head, nullptr);
    ASSERT_NE(rig->sim_camera, nullptr);
    ASSERT_TRUE(rig->head->home(10.0));
    ASSERT_TRUE(rig->head->moveTo(7.0, 10.0));
    auto frame = rig->camera->capture(10.0);
    ASSERT_TRUE(frame) << frame.error().message;
    EXPECT_EQ(frame->angle_deg, 7.0);  // stamped with where the head stands
    EXPECT_EQ(frame->width, 48);
    EXPECT_EQ(frame->timestamp_marks, hdr::TimestampMark::ExposureStart);
}

TEST(OpenRig, NamesTheDeviceThatCouldNotBeOpened) {
    const RigOptions options = tinyRig();
    auto registries = makeRigRegistries(options);
    ASSERT_TRUE(registries);
    const auto no_lens = openRig(*registries, "sim:", "sim:", options);
    ASSERT_FALSE(no_lens);
    EXPECT_NE(no_lens.error().message.find("camera 'sim:'"), std::string::npos);
    EXPECT_NE(no_lens.error().message.find("lens"), std::string::npos);
    const auto no_head = openRig(*registries, "sim:", "warp:drive", options);
    ASSERT_FALSE(no_head);
    EXPECT_NE(no_head.error().message.find("head 'warp:drive'"), std::string::npos);
    EXPECT_EQ(no_head.error().code, ErrorCode::NotFound);
}

TEST(UnavailableBackend, AnswersUnsupportedNamingTheMissingLibrary) {
    CameraRegistry cameras;
    ASSERT_TRUE(addUnavailableBackend(cameras, "aravis", "GigE Vision cameras", "aravis-0.8"));
    const auto opened = cameras.open("aravis:Basler-123");
    ASSERT_FALSE(opened);
    EXPECT_EQ(opened.error().code, ErrorCode::Unsupported);
    EXPECT_NE(opened.error().message.find("no aravis backend: aravis-0.8 was not installed"),
              std::string::npos)
        << opened.error().message;
    EXPECT_NE(cameras.backends()[0].second.find("not in this build"), std::string::npos);
    EXPECT_TRUE(cameras.enumerate().empty());
}

TEST(BackendStatus, NamesEverySchemeOfTheIssueAndTheLibraryAMissingOneNeeds) {
    std::set<std::string> schemes;
    for (const BackendStatus& b : backendStatus()) {
        schemes.insert(b.kind + ":" + b.scheme);
        if (!b.built) {
            EXPECT_FALSE(b.missing.empty()) << b.scheme;
        }
    }
    EXPECT_EQ(schemes,
              (std::set<std::string>{"camera:sim", "camera:aravis", "camera:v4l2",
                                     "camera:libcamera", "head:sim", "head:zaber", "head:apt"}));
}

}  // namespace
}  // namespace flarelab::drivers
