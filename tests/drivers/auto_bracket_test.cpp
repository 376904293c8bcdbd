#include "drivers/auto_bracket.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "drivers/sim_camera.h"
#include "hdr/merge.h"
#include "optics/prescription.h"
#include "tests/test_lenses.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

using flarelab::testing::heliar;

// The Heliar's light on axis at 160 x 107 (small render grids). Its core reaches some 1e11 e-/s,
// so only a camera with a shortest exposure far below the simulated default 10 us keeps it from
// clipping.
SimCameraOptions scene(double min_exposure_s) {
    SimCameraOptions o;
    o.width_px = 160;
    o.height_px = 107;
    o.render.base_grid = 32;
    o.render.probe_grid = 6;
    o.render.starburst_options.mask_size = 64;
    o.render.starburst_options.fft_size = 256;
    o.min_exposure_s = min_exposure_s;
    return o;
}

std::unique_ptr<SimCamera> camera(const SimCameraOptions& o) {
    auto c = SimCamera::make(heliar(), o);
    EXPECT_TRUE(c) << c.error().message;
    return std::move(*c);
}

hdr::RawFrame shoot(Camera& c, double exposure_s) {
    EXPECT_TRUE(c.setExposure(exposure_s));
    auto frame = c.capture(exposure_s + 10.0);
    EXPECT_TRUE(frame) << frame.error().message;
    return std::move(*frame);
}

bool mentions(const BracketPlan& plan, const std::string& text) {
    return std::any_of(plan.reasons.begin(), plan.reasons.end(),
                       [&](const std::string& r) { return r.find(text) != std::string::npos; });
}

TEST(PlanBrackets, KeepsTheCoreUnclippedAndReachesTheFloor) {
    const SimCameraOptions o = scene(1e-9);
    auto c = camera(o);
    const BracketPlanOptions options;
    auto plan = planBrackets(*c, options);
    ASSERT_TRUE(plan) << plan.error().message;
    EXPECT_TRUE(plan->core_unclipped);
    EXPECT_TRUE(plan->floor_reached);
    const std::vector<double>& t = plan->exposure_times_s;
    ASSERT_GE(t.size(), 2u);
    EXPECT_TRUE(std::is_sorted(t.begin(), t.end()));
    for (size_t k = 1; k < t.size(); ++k) EXPECT_LE(t[k] / t[k - 1], options.max_ratio * 1.001);
    double total = 0.0;
    for (const double x : t) total += x;
    EXPECT_LE(total, options.budget_s);
    EXPECT_GE(plan->reasons.size(), 3u);
    EXPECT_TRUE(mentions(*plan, "shortest"));
    EXPECT_TRUE(mentions(*plan, "longest"));

    // Against the truth: the shortest keeps every pixel below saturation, the longest records
    // the scene's 5th percentile at a signal-to-noise ratio of 10 or more.
    const hdr::RawFrame shortest = shoot(*c, t.front());
    const auto top = *std::max_element(shortest.samples.begin(), shortest.samples.end());
    EXPECT_LT(top, shortest.white_level_dn - 0.01 * (shortest.white_level_dn - 64.0));
    auto rate = c->meanRate_e_s(0.0);
    ASSERT_TRUE(rate);
    std::vector<float> sorted = *rate;
    std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 20, sorted.end());
    const double floor_e = (sorted[sorted.size() / 20] + o.dark_current_e_s) * t.back();
    const double snr = floor_e / std::sqrt(floor_e + o.read_noise_e * o.read_noise_e);
    EXPECT_GE(snr, options.floor_snr * 0.95);
    EXPECT_NEAR(plan->read_noise_dn, 0.75, 1e-9);  // the camera's own figures
    EXPECT_NEAR(plan->electrons_per_dn, 4.0, 1e-9);
}

TEST(PlanBrackets, SaysPlainlyWhenTheShortestExposureClipsTheCore) {
    auto c = camera(scene(1e-5));  // the simulated camera's default
    auto plan = planBrackets(*c);
    ASSERT_TRUE(plan) << plan.error().message;
    EXPECT_FALSE(plan->core_unclipped);
    EXPECT_EQ(plan->exposure_times_s.front(), 1e-5);
    EXPECT_TRUE(mentions(*plan, "cannot keep the light's core from clipping")) << plan->reasons[0];
    EXPECT_TRUE(plan->floor_reached);  // the other goal is still met
}

// The lensbaby's light is a hard point and its ghosts a faint veil: core and floor lie further
// apart than the merge takes (hdr::kMaxExposureRatio), and the plan keeps the floor.
TEST(PlanBrackets, StaysWithinWhatTheMergeTakesAndKeepsTheFloor) {
    static const optics::Lens lensbaby = *optics::Lens::make(
        *optics::loadPrescription(flarelab::testing::lensPath("lensbaby-toy.csv")),
        optics::CameraDescription{});
    SimCameraOptions o = scene(1e-12);
    o.width_px = 640;  // as flarelab capture takes it: the floor per pixel is 16 times dimmer
    o.height_px = 427;
    auto c = SimCamera::make(lensbaby, o);
    ASSERT_TRUE(c) << c.error().message;
    auto plan = planBrackets(**c);
    ASSERT_TRUE(plan) << plan.error().message;
    const std::vector<double>& t = plan->exposure_times_s;
    ASSERT_GE(t.size(), 2u);
    EXPECT_LE(t.back() / t.front(), hdr::kMaxExposureRatio);
    EXPECT_TRUE(mentions(*plan, "the merge takes exposures at most"))
        << t.front() << " " << t.back();
    EXPECT_FALSE(plan->core_unclipped);
    // The core's end moved, not the floor's: the shortest lies well above the camera's 1 ps, the
    // longest stays seconds long.
    EXPECT_GT(t.front(), 1e-10);
    EXPECT_GT(t.back(), 1.0);
}

TEST(PlanBrackets, SaysPlainlyWhenTheBudgetStopsTheLongest) {
    auto c = camera(scene(1e-9));
    BracketPlanOptions options;
    options.budget_s = 0.01;
    auto plan = planBrackets(*c, options);
    ASSERT_TRUE(plan) << plan.error().message;
    EXPECT_TRUE(plan->core_unclipped);
    EXPECT_FALSE(plan->floor_reached);
    EXPECT_LT(plan->floor_snr, options.floor_snr);
    EXPECT_TRUE(mentions(*plan, "cannot reach the ghosts' noise floor")) << plan->reasons.back();
    double total = 0.0;
    for (const double x : plan->exposure_times_s) total += x;
    EXPECT_LE(total, options.budget_s);
}

// A camera that gives no noise figures (many V4L2 and libcamera sensors): the sim camera with
// read_noise_dn and electrons_per_dn taken out of its frames.
class SilentCamera final : public Camera {
public:
    explicit SilentCamera(Camera& inner) : inner_(inner) {}
    DeviceIdentity identity() const override { return inner_.identity(); }
    CameraCapabilities capabilities() const override { return inner_.capabilities(); }
    Status setExposure(double t) override { return inner_.setExposure(t); }
    double exposure_s() const override { return inner_.exposure_s(); }
    Status setGain(double g) override { return inner_.setGain(g); }
    double gain() const override { return inner_.gain(); }
    Status setFormat(hdr::RawFormat f) override { return inner_.setFormat(f); }
    hdr::RawFormat format() const override { return inner_.format(); }
    Result<hdr::RawFrame> capture(double timeout_s) override {
        auto frame = inner_.capture(timeout_s);
        if (frame) frame->read_noise_dn = frame->electrons_per_dn = 0.0;
        return frame;
    }
    void abort() override { inner_.abort(); }

private:
    Camera& inner_;
};

TEST(PlanBrackets, MeasuresTheNoiseFromAPairWhenTheCameraGivesNone) {
    auto inner = camera(scene(1e-9));
    SilentCamera c(*inner);
    auto plan = planBrackets(c);
    ASSERT_TRUE(plan) << plan.error().message;
    EXPECT_TRUE(mentions(*plan, "measured from a pair of probe frames")) << plan->reasons[1];
    EXPECT_NEAR(plan->electrons_per_dn, 4.0, 0.2 * 4.0);
    EXPECT_TRUE(plan->core_unclipped);
    EXPECT_TRUE(plan->floor_reached);
}

TEST(PlanBrackets, RefusesOptionsOutOfRangeNamingThem) {
    auto c = camera(scene(1e-9));
    const std::vector<std::pair<std::function<void(BracketPlanOptions&)>, std::string>> cases = {
        {[](BracketPlanOptions& o) { o.core_level = 1.0; }, "core_level"},
        {[](BracketPlanOptions& o) { o.floor_percentile = 0.0; }, "floor_percentile"},
        {[](BracketPlanOptions& o) { o.floor_snr = -1.0; }, "floor_snr"},
        {[](BracketPlanOptions& o) { o.floor_headroom = 0.5; }, "floor_headroom"},
        {[](BracketPlanOptions& o) { o.max_ratio = 1.0; }, "max_ratio"},
        {[](BracketPlanOptions& o) { o.max_exposures = 0; }, "max_exposures"},
        {[](BracketPlanOptions& o) { o.budget_s = std::nan(""); }, "budget_s"},
        {[](BracketPlanOptions& o) { o.max_probes = 2; }, "max_probes"},
    };
    for (const auto& [edit, field] : cases) {
        BracketPlanOptions options;
        edit(options);
        auto plan = planBrackets(*c, options);
        ASSERT_FALSE(plan) << field;
        EXPECT_EQ(plan.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(plan.error().message.find(field), std::string::npos) << plan.error().message;
    }
    // A camera that is gone: its error, with the probe named.
    c->setFaults({0, true});
    auto gone = planBrackets(*c);
    ASSERT_FALSE(gone);
    EXPECT_EQ(deviceFaultOf(gone.error()), DeviceFault::Disconnected);
    EXPECT_NE(gone.error().message.find("bracket probe"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::drivers
