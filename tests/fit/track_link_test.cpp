#include "fit/track_link.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "fit/sweep_fit.h"

namespace flarelab::fit {
namespace {

// A ghost moving along a line with the angle: centre, radius and brightness linear in it.
struct Motion {
    double x0_mm, x_rate, y_mm;
    double radius0_mm, radius_rate;
    double border;
};

GhostState stateAt(const Motion& m, double angle_deg) {
    GhostState g;
    g.shape = render::circleGhostShape(m.x0_mm + m.x_rate * angle_deg, m.y_mm,
                                       m.radius0_mm + m.radius_rate * angle_deg);
    g.shading.border_rgb = {m.border, m.border, m.border};
    g.shading.inner_rgb = {0.5 * m.border, 0.5 * m.border, 0.5 * m.border};
    g.shading.inner_falloff_mm = 0.3;
    g.shading.outer_falloff_mm = 0.1;
    return g;
}

// Linking as `flarelab fit --link` turns it on, the other options at their defaults.
const TrackLinkOptions kOn = [] {
    TrackLinkOptions o;
    o.enabled = true;
    return o;
}();

std::vector<double> sweepAngles(int frames, double step_deg) {
    std::vector<double> angles;
    for (int i = 0; i < frames; ++i) angles.push_back(step_deg * i);
    return angles;
}

// Frames first..last (inclusive) of a ghost as one track.
GhostTrack fragment(int64_t id,
                    const Motion& m,
                    const std::vector<double>& angles,
                    int first,
                    int last,
                    double cost = 1.0) {
    GhostTrack t;
    t.id = id;
    for (int i = first; i <= last; ++i)
        t.samples.push_back(
            {angles[static_cast<size_t>(i)], stateAt(m, angles[static_cast<size_t>(i)]), cost});
    return t;
}

// Which motion a track's samples follow (index into `motions`), or -1 when they follow none or
// more than one.
int followedMotion(const GhostTrack& t, const std::vector<Motion>& motions) {
    int which = -1;
    for (const TrackSample& s : t.samples) {
        int here = -1;
        for (size_t k = 0; k < motions.size(); ++k) {
            const GhostState truth = stateAt(motions[k], s.angle_deg);
            if (std::abs(truth.shape.centre_x_mm - s.state.shape.centre_x_mm) < 1e-9 &&
                std::abs(truth.shape.centre_y_mm - s.state.shape.centre_y_mm) < 1e-9)
                here = static_cast<int>(k);
        }
        if (here < 0 || (which >= 0 && here != which)) return -1;
        which = here;
    }
    return which;
}

TEST(TrackLink, FragmentsOfOneGhostBecomeOneTrackEach) {
    const auto angles = sweepAngles(51, 0.2);
    // Two ghosts that cross the frame at different speeds and sizes; each broken where it faded
    // for a few frames.
    const std::vector<Motion> motions = {{0.5, 0.4, 0.0, 1.0, 0.05, 100.0},
                                         {-2.0, -0.3, 1.0, 2.5, -0.02, 30.0}};
    std::vector<GhostTrack> tracks = {
        fragment(7, motions[0], angles, 0, 14),  fragment(3, motions[0], angles, 17, 30),
        fragment(9, motions[0], angles, 34, 50), fragment(4, motions[1], angles, 5, 24),
        fragment(2, motions[1], angles, 28, 45),
    };
    std::mt19937_64 rng(3);
    std::shuffle(tracks.begin(), tracks.end(), rng);
    TrackLinkStats stats;
    const auto linked = linkTracks(tracks, angles, kOn, &stats);
    ASSERT_EQ(linked.size(), 2u);
    EXPECT_EQ(stats.fragments, 5);
    EXPECT_EQ(stats.links, 3);
    // By id, each the id of its earliest fragment, each following one ghost over all its frames.
    EXPECT_EQ(linked[0].id, 4);
    EXPECT_EQ(linked[1].id, 7);
    EXPECT_EQ(followedMotion(linked[0], motions), 1);
    EXPECT_EQ(followedMotion(linked[1], motions), 0);
    EXPECT_EQ(linked[0].samples.size(), 20u + 18u);
    EXPECT_EQ(linked[1].samples.size(), 15u + 14u + 17u);
    EXPECT_TRUE(std::is_sorted(
        linked[1].samples.begin(), linked[1].samples.end(),
        [](const TrackSample& a, const TrackSample& b) { return a.angle_deg < b.angle_deg; }));
}

TEST(TrackLink, AGhostOfAnotherSizePlaceOrBrightnessIsNotLinked) {
    const auto angles = sweepAngles(40, 0.2);
    const Motion a{0.0, 0.5, 0.0, 1.0, 0.0, 50.0};
    const GhostTrack before = fragment(1, a, angles, 0, 15);
    Motion larger = a, elsewhere = a, brighter = a, same = a;
    larger.radius0_mm = 2.0;        // twice the size
    elsewhere.y_mm = 1.5;           // 1.5 radii off the line
    brighter.border = 50.0 * 10.0;  // ten times the light
    for (const Motion& other : {larger, elsewhere, brighter}) {
        const GhostTrack after = fragment(2, other, angles, 18, 39);
        EXPECT_FALSE(trackLinkCost(before, after, angles, kOn).value_or(2.0) < 1.0);
        TrackLinkStats stats;
        EXPECT_EQ(linkTracks({before, after}, angles, kOn, &stats).size(), 2u);
        EXPECT_EQ(stats.links, 0);
    }
    // The same ghost is, and its cost is far below the gate.
    const GhostTrack after = fragment(2, same, angles, 18, 39);
    ASSERT_TRUE(trackLinkCost(before, after, angles, kOn).has_value());
    EXPECT_LT(*trackLinkCost(before, after, angles, kOn), 1e-6);
    EXPECT_EQ(linkTracks({before, after}, angles, kOn).size(), 1u);
}

TEST(TrackLink, GapsAndOverlapsBeyondTheLimitsAreNotLinked) {
    const auto angles = sweepAngles(60, 0.2);
    const Motion a{0.0, 0.5, 0.0, 1.0, 0.0, 50.0};
    TrackLinkOptions o = kOn;
    o.max_gap_frames = 8;
    o.max_overlap_frames = 3;
    const GhostTrack before = fragment(1, a, angles, 0, 20);
    EXPECT_TRUE(trackLinkCost(before, fragment(2, a, angles, 29, 59), angles, o));   // gap 8
    EXPECT_FALSE(trackLinkCost(before, fragment(2, a, angles, 30, 59), angles, o));  // gap 9
    EXPECT_TRUE(trackLinkCost(before, fragment(2, a, angles, 18, 59), angles, o));   // 3 shared
    EXPECT_FALSE(trackLinkCost(before, fragment(2, a, angles, 17, 59), angles, o));  // 4 shared
    // Never backwards, nor into a fragment that ends first.
    EXPECT_FALSE(trackLinkCost(fragment(2, a, angles, 25, 59), before, angles, o));
    EXPECT_FALSE(trackLinkCost(before, fragment(2, a, angles, 5, 19), angles, o));
}

TEST(TrackLink, OverlappingFramesKeepTheSampleOfLowerCost) {
    const auto angles = sweepAngles(30, 0.2);
    const Motion a{0.0, 0.5, 0.0, 1.0, 0.0, 50.0};
    // The later fragment was followed back two frames over the first's end, with lower costs.
    const auto linked = linkTracks(
        {fragment(1, a, angles, 0, 14, 2.0), fragment(2, a, angles, 13, 29, 1.0)}, angles, kOn);
    ASSERT_EQ(linked.size(), 1u);
    ASSERT_EQ(linked[0].samples.size(), 30u);
    for (const TrackSample& s : linked[0].samples)
        EXPECT_EQ(s.cost, s.angle_deg < 13 * 0.2 - 1e-9 ? 2.0 : 1.0) << s.angle_deg;
}

TEST(TrackLink, TwoEndsNeverShareOneStart) {
    // Two ghosts that fade out at the same frame, side by side, and one that comes back where
    // the first would be: one link, to the first.
    const auto angles = sweepAngles(40, 0.2);
    const Motion a{0.0, 0.5, 0.0, 1.0, 0.0, 50.0}, b{0.0, 0.5, 0.45, 1.0, 0.0, 50.0};
    TrackLinkStats stats;
    const auto linked = linkTracks({fragment(1, a, angles, 0, 15), fragment(2, b, angles, 0, 15),
                                    fragment(3, a, angles, 18, 39)},
                                   angles, kOn, &stats);
    EXPECT_EQ(stats.links, 1);
    ASSERT_EQ(linked.size(), 2u);
    EXPECT_EQ(linked[0].id, 1);
    EXPECT_EQ(linked[0].samples.size(), 16u + 22u);
    EXPECT_EQ(followedMotion(linked[0], {a}), 0);
}

TEST(TrackLink, TheAssignmentIsTheCheapestOverAllLinks) {
    // End 1 is nearest to start 3, but end 2 can reach only start 3, and end 1 can reach start 4
    // as well: linking 1 -> 3 first (the cheapest single link) would leave two fragments
    // unlinked; the assignment gives 1 -> 4 and 2 -> 3.
    const auto angles = sweepAngles(40, 0.2);
    const Motion base{0.0, 0.0, 0.0, 1.0, 0.0, 50.0};
    Motion m1 = base, m2 = base, m3 = base, m4 = base;
    // Costs, in position tolerances (0.6 radii): 1 -> 3 0.33, 1 -> 4 0.5, 2 -> 3 0.5, 2 -> 4 1.33
    // (beyond the gate). 1 -> 3 alone: 0.33 + half a gate for each of 2 and 4 left = 1.33; the
    // assignment: 0.5 + 0.5 = 1.0.
    m2.y_mm = 0.5;
    m3.y_mm = 0.2;
    m4.y_mm = -0.3;
    const GhostTrack e1 = fragment(1, m1, angles, 0, 15), e2 = fragment(2, m2, angles, 0, 15);
    const GhostTrack s3 = fragment(3, m3, angles, 18, 39), s4 = fragment(4, m4, angles, 18, 39);
    EXPECT_LT(*trackLinkCost(e1, s3, angles, kOn), *trackLinkCost(e1, s4, angles, kOn));
    EXPECT_LT(*trackLinkCost(e2, s3, angles, kOn), 1.0);
    EXPECT_GT(*trackLinkCost(e2, s4, angles, kOn), 1.0);
    TrackLinkStats stats;
    const auto linked = linkTracks({e1, e2, s3, s4}, angles, kOn, &stats);
    EXPECT_EQ(stats.links, 2);
    ASSERT_EQ(linked.size(), 2u);
    EXPECT_EQ(followedMotion(linked[0], {m1, m2, m3, m4}), -1);  // 1 then 4
    EXPECT_EQ(linked[0].samples.back().state.shape.centre_y_mm, -0.3);
    EXPECT_EQ(linked[1].samples.back().state.shape.centre_y_mm, 0.2);
}

TEST(TrackLink, PathTracksAndLinkingOffPassUnchanged) {
    const auto angles = sweepAngles(40, 0.2);
    const Motion a{0.0, 0.5, 0.0, 1.0, 0.0, 50.0};
    GhostTrack p1 = fragment(1, a, angles, 0, 15), p2 = fragment(2, a, angles, 18, 39);
    p1.path = 5;
    p2.path = 6;
    EXPECT_EQ(linkTracks({p1, p2}, angles, kOn).size(), 2u);
    // Off unless asked for.
    EXPECT_EQ(linkTracks({fragment(1, a, angles, 0, 15), fragment(2, a, angles, 18, 39)}, angles,
                         TrackLinkOptions{})
                  .size(),
              2u);
    TrackLinkOptions off = kOn;
    off.enabled = false;
    EXPECT_EQ(
        linkTracks({fragment(1, a, angles, 0, 15), fragment(2, a, angles, 18, 39)}, angles, off)
            .size(),
        2u);
    EXPECT_TRUE(linkTracks({}, angles, kOn).empty());
    EXPECT_EQ(linkTracks({fragment(1, a, angles, 0, 15)}, angles, kOn).size(), 1u);
}

TEST(TrackLink, AGhostWithNoLightIsNeverLinkedToALitOne) {
    const auto angles = sweepAngles(40, 0.2);
    Motion dark{0.0, 0.5, 0.0, 1.0, 0.0, 0.0};
    const Motion lit{0.0, 0.5, 0.0, 1.0, 0.0, 50.0};
    const auto cost = trackLinkCost(fragment(1, dark, angles, 0, 15),
                                    fragment(2, lit, angles, 18, 39), angles, kOn);
    EXPECT_FALSE(cost.value_or(2.0) < 1.0);
    EXPECT_EQ(linkTracks({fragment(1, dark, angles, 0, 15), fragment(2, lit, angles, 18, 39)},
                         angles, kOn)
                  .size(),
              2u);
}

TEST(TrackLink, OptionsOutOfRangeAreNamed) {
    const auto expectError = [](TrackLinkOptions o, const char* field) {
        const Status s = checkTrackLinkOptions(o);
        ASSERT_FALSE(s);
        EXPECT_NE(s.error().message.find(field), std::string::npos) << s.error().message;
        SweepFitOptions sweep;
        sweep.link = o;
        EXPECT_FALSE(checkSweepFitOptions(sweep));
    };
    TrackLinkOptions o;
    EXPECT_TRUE(checkTrackLinkOptions(o));
    o.max_gap_frames = -1;
    expectError(o, "max_gap_frames");
    o = {};
    o.max_overlap_frames = -2;
    expectError(o, "max_overlap_frames");
    o = {};
    o.history = 0;
    expectError(o, "history");
    o = {};
    o.position_radii = std::nan("");
    expectError(o, "position_radii");
    o = {};
    o.size_ratio = 1.0;
    expectError(o, "size_ratio");
    o = {};
    o.energy_ratio = std::numeric_limits<double>::infinity();
    expectError(o, "energy_ratio");
    o = {};
    o.gate = 0.0;
    expectError(o, "gate");
}

}  // namespace
}  // namespace flarelab::fit
