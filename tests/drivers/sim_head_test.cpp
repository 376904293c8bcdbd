#include "drivers/sim_head.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <thread>

namespace flarelab::drivers {
namespace {

SimHeadOptions quick() {
    SimHeadOptions o;
    o.homed = true;
    o.speed_deg_s = 10.0;
    o.acceleration_deg_s2 = 20.0;
    o.settle_s = 0.2;
    return o;
}

std::unique_ptr<SimHead> head(const SimHeadOptions& o) {
    auto h = SimHead::make(o);
    EXPECT_TRUE(h);
    return std::move(*h);
}

DeviceFault headFaultOf(const Error& e) {
    const auto fault = deviceFaultOf(e);
    EXPECT_TRUE(fault) << e.message;
    return fault.value_or(DeviceFault::Busy);
}

TEST(SimHeadProfile, TrapezoidAndTriangleDurations) {
    // Ramps take v / a = 0.5 s and cover v^2 / a = 5 deg together.
    EXPECT_DOUBLE_EQ(SimHead::moveDuration_s(30.0, 10.0, 20.0), 3.0 + 0.5);
    EXPECT_DOUBLE_EQ(SimHead::moveDuration_s(5.0, 10.0, 20.0), 1.0);
    EXPECT_DOUBLE_EQ(SimHead::moveDuration_s(1.25, 10.0, 20.0), 0.5);  // triangle: 2 sqrt(d / a)
    EXPECT_DOUBLE_EQ(SimHead::moveDuration_s(3.0, 10.0, 0.0), 0.3);
    EXPECT_EQ(SimHead::moveDuration_s(0.0, 10.0, 20.0), 0.0);
}

TEST(SimHeadProfile, DistanceRisesMonotonicallyToTheTarget) {
    for (double d : {0.2, 1.25, 5.0, 30.0})
        for (double a : {0.0, 20.0}) {
            const double total = SimHead::moveDuration_s(d, 10.0, a);
            double last = 0.0;
            for (int i = 0; i <= 1000; ++i) {
                const double s = SimHead::moveDistance_deg(total * i / 1000.0, d, 10.0, a);
                ASSERT_GE(s, last - 1e-12) << d << " " << a << " " << i;
                ASSERT_LE(s, d + 1e-12);
                last = s;
            }
            EXPECT_NEAR(last, d, 1e-12);
        }
}

TEST(SimHead, MustBeHomedBeforeItMoves) {
    SimHeadOptions o = quick();
    o.homed = false;
    o.start_deg = 12.0;
    auto h = head(o);
    EXPECT_EQ(headFaultOf(h->position().error()), DeviceFault::NotHomed);
    EXPECT_EQ(headFaultOf(h->moveTo(1.0, 10.0).error()), DeviceFault::NotHomed);
    EXPECT_DOUBLE_EQ(h->trueAngle_deg(), 12.0);
    const int64_t before = h->clock()->now_ns();
    ASSERT_TRUE(h->home(10.0));
    // 12 deg: ramps cover 5 deg in 1 s, 7 deg cruise 0.7 s, settle 0.2 s.
    EXPECT_NEAR((h->clock()->now_ns() - before) * 1e-9, 1.9, 1e-6);
    EXPECT_EQ(*h->position(), 0.0);
    EXPECT_EQ(h->trueAngle_deg(), 0.0);
}

TEST(SimHead, MoveTakesProfileTimePlusSettleOnTheSimulatedClock) {
    auto h = head(quick());
    const auto wall = std::chrono::steady_clock::now();
    const int64_t before = h->clock()->now_ns();
    const auto at = h->moveTo(30.0, 10.0);
    ASSERT_TRUE(at);
    EXPECT_EQ(*at, 30.0);
    EXPECT_NEAR((h->clock()->now_ns() - before) * 1e-9, 3.5 + 0.2, 1e-6);
    EXPECT_NEAR(h->lastMoveDuration_s(), 3.7, 1e-6);
    // Fast mode does not sleep.
    EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - wall).count(), 0.5);
    // A 0.2 deg step: a triangle of 2 sqrt(0.2 / 20) = 0.2 s, plus settling.
    const int64_t step = h->clock()->now_ns();
    ASSERT_TRUE(h->moveTo(30.2, 10.0));
    EXPECT_NEAR((h->clock()->now_ns() - step) * 1e-9, 0.4, 1e-6);
}

TEST(SimHead, RejectsTargetsSpeedsAndTimeoutsOutOfRangeNamingTheField) {
    auto h = head(quick());
    for (double bad : {-91.0, 90.5, std::nan("")}) {
        const auto r = h->moveTo(bad, 10.0);
        ASSERT_FALSE(r) << bad;
        EXPECT_EQ(headFaultOf(r.error()), DeviceFault::OutOfRange);
        EXPECT_NE(r.error().message.find("angle_deg"), std::string::npos);
    }
    const auto t = h->moveTo(1.0, 0.0);
    ASSERT_FALSE(t);
    EXPECT_NE(t.error().message.find("timeout_s"), std::string::npos);
    for (double bad : {0.0, -1.0, 91.0}) {
        const Status s = h->setSpeed(bad);
        ASSERT_FALSE(s);
        EXPECT_NE(s.error().message.find("speed_deg_s"), std::string::npos);
    }
    EXPECT_TRUE(h->setSpeed(45.0));
    EXPECT_EQ(h->speed_deg_s(), 45.0);
    EXPECT_EQ(*h->position(), 0.0);  // nothing moved
    SimHeadOptions o = quick();
    o.min_deg = 5.0;
    o.max_deg = 1.0;
    const auto made = SimHead::make(o);
    ASSERT_FALSE(made);
    EXPECT_NE(made.error().message.find("min_deg"), std::string::npos);
}

TEST(SimHead, BacklashMakesTheApproachDirectionShow) {
    SimHeadOptions o = quick();
    o.backlash_deg = 0.4;
    auto h = head(o);
    ASSERT_TRUE(h->moveTo(10.0, 10.0));
    EXPECT_NEAR(h->trueAngle_deg(), 9.8, 1e-12);  // from below: trails by half the band
    ASSERT_TRUE(h->moveTo(12.0, 10.0));
    ASSERT_TRUE(h->moveTo(10.0, 10.0));
    EXPECT_NEAR(h->trueAngle_deg(), 10.2, 1e-12);  // from above
    EXPECT_EQ(*h->position(), 10.0);               // the report does not know
    // A reversal shorter than the band does not move the camera at all.
    ASSERT_TRUE(h->moveTo(9.8, 10.0));
    EXPECT_NEAR(h->trueAngle_deg(), 10.0, 1e-12);
    ASSERT_TRUE(h->moveTo(9.9, 10.0));
    EXPECT_NEAR(h->trueAngle_deg(), 10.0, 1e-12);
    ASSERT_TRUE(h->home(30.0));
    EXPECT_EQ(h->trueAngle_deg(), 0.0);
}

TEST(SimHead, PositionNoiseIsSeededWithTheGivenSpread) {
    SimHeadOptions o = quick();
    o.position_noise_deg = 0.05;
    o.seed = 11;
    auto a = head(o), b = head(o);
    double sum = 0.0, sum2 = 0.0;
    const int n = 400;
    for (int i = 0; i < n; ++i) {
        const double target = (i % 2) ? 5.0 : 6.0;
        ASSERT_TRUE(a->moveTo(target, 10.0));
        ASSERT_TRUE(b->moveTo(target, 10.0));
        ASSERT_EQ(a->trueAngle_deg(), b->trueAngle_deg());
        ASSERT_EQ(*a->position(), target);
        // Without backlash the camera follows the motor, so each move's error is a fresh draw.
        const double err = a->trueAngle_deg() - target;
        sum += err;
        sum2 += err * err;
    }
    const double mean = sum / n;
    EXPECT_NEAR(mean, 0.0, 4.0 * 0.05 / std::sqrt(n));
    EXPECT_NEAR(std::sqrt(sum2 / n - mean * mean), 0.05, 0.008);
    o.seed = 12;
    auto c = head(o);
    ASSERT_TRUE(c->moveTo(6.0, 10.0));
    o.seed = 11;
    auto d = head(o);
    ASSERT_TRUE(d->moveTo(6.0, 10.0));
    EXPECT_NE(c->trueAngle_deg(), d->trueAngle_deg());
}

TEST(SimHead, StallStopsAtTheObstacleAndStaysHomed) {
    SimHeadOptions o = quick();
    o.faults.stall_at_deg = 7.0;
    auto h = head(o);
    const auto r = h->moveTo(20.0, 10.0);
    ASSERT_FALSE(r);
    EXPECT_EQ(headFaultOf(r.error()), DeviceFault::Stalled);
    EXPECT_NEAR(*h->position(), 7.0, 0.01);
    EXPECT_EQ(headFaultOf(h->moveTo(8.0, 10.0).error()), DeviceFault::Stalled);  // still blocked
    EXPECT_TRUE(h->moveTo(2.0, 10.0));                                           // away is free
    h->setFaults({});
    EXPECT_TRUE(h->moveTo(20.0, 10.0));
}

TEST(SimHead, HangingMoveWaitsOutItsTimeout) {
    SimHeadOptions o = quick();
    o.faults.hang_moves = 1;
    auto h = head(o);
    const int64_t before = h->clock()->now_ns();
    const auto r = h->moveTo(5.0, 2.5);
    ASSERT_FALSE(r);
    EXPECT_EQ(headFaultOf(r.error()), DeviceFault::Timeout);
    EXPECT_NEAR((h->clock()->now_ns() - before) * 1e-9, 2.5, 1e-6);
    EXPECT_EQ(*h->position(), 0.0);
    EXPECT_TRUE(h->moveTo(5.0, 10.0));  // only one move hangs
}

TEST(SimHead, MoveLongerThanItsTimeoutStopsPartway) {
    auto h = head(quick());
    const auto r = h->moveTo(30.0, 1.0);  // needs 3.7 s
    ASSERT_FALSE(r);
    EXPECT_EQ(headFaultOf(r.error()), DeviceFault::Timeout);
    // One second in: 2.5 deg of ramp plus 5 deg of cruise.
    EXPECT_NEAR(*h->position(), 7.5, 1e-9);
}

TEST(SimHead, LostPositionNeedsRehoming) {
    SimHeadOptions o = quick();
    o.faults.lose_position_in_moves = 2;
    auto h = head(o);
    ASSERT_TRUE(h->moveTo(5.0, 10.0));
    const auto r = h->moveTo(15.0, 10.0);
    ASSERT_FALSE(r);
    EXPECT_EQ(headFaultOf(r.error()), DeviceFault::LostPosition);
    EXPECT_NEAR(h->trueAngle_deg(), 12.0, 1e-9);  // 30 % short
    EXPECT_EQ(headFaultOf(h->position().error()), DeviceFault::NotHomed);
    EXPECT_EQ(headFaultOf(h->moveTo(15.0, 10.0).error()), DeviceFault::NotHomed);
    ASSERT_TRUE(h->home(10.0));
    EXPECT_TRUE(h->moveTo(15.0, 10.0));
}

TEST(SimHead, DisconnectedHeadAnswersEveryCall) {
    auto h = head(quick());
    SimHeadFaults gone;
    gone.disconnected = true;
    h->setFaults(gone);
    EXPECT_EQ(headFaultOf(h->moveTo(1.0, 10.0).error()), DeviceFault::Disconnected);
    EXPECT_EQ(headFaultOf(h->position().error()), DeviceFault::Disconnected);
    EXPECT_EQ(headFaultOf(h->home(10.0).error()), DeviceFault::Disconnected);
    EXPECT_EQ(headFaultOf(h->setSpeed(1.0).error()), DeviceFault::Disconnected);
    EXPECT_EQ(headFaultOf(h->stop().error()), DeviceFault::Disconnected);
}

TEST(SimHead, RealTimeModeSleepsAndStopInterrupts) {
    SimHeadOptions o = quick();
    o.acceleration_deg_s2 = 0.0;
    o.settle_s = 0.0;
    o.speed_deg_s = 20.0;
    auto h = SimHead::make(o, std::make_shared<SimClock>(SimTime::RealTime)).value();
    auto wall = std::chrono::steady_clock::now();
    ASSERT_TRUE(h->moveTo(1.0, 5.0));  // 0.05 s
    EXPECT_GE(std::chrono::duration<double>(std::chrono::steady_clock::now() - wall).count(),
              0.045);

    Result<double> result = 0.0;
    wall = std::chrono::steady_clock::now();
    std::thread mover([&] { result = h->moveTo(41.0, 5.0); });  // 2 s
    std::this_thread::sleep_for(std::chrono::milliseconds(150));
    const auto midway = h->position();
    ASSERT_TRUE(midway);
    EXPECT_GT(*midway, 1.5);
    EXPECT_LT(*midway, 41.0);
    EXPECT_EQ(headFaultOf(h->moveTo(3.0, 5.0).error()), DeviceFault::Busy);
    ASSERT_TRUE(h->stop());
    mover.join();
    EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - wall).count(), 1.5);
    ASSERT_FALSE(result);
    EXPECT_EQ(headFaultOf(result.error()), DeviceFault::Stopped);
    EXPECT_LT(*h->position(), 41.0);
    EXPECT_EQ(*h->position(), h->trueAngle_deg());
}

}  // namespace
}  // namespace flarelab::drivers
