#include "render/ghost_shape.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>
#include <string>

namespace flarelab::render {
namespace {

using Vec2 = Eigen::Vector2d;

// A random shape inside the documented bounds, with sizes from 0.2 to 5 mm around +-10 mm.
GhostShapeParams randomShape(std::mt19937_64& rng) {
    std::uniform_real_distribution<double> centre(-10.0, 10.0);
    std::uniform_real_distribution<double> size(0.2, 5.0);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    GhostShapeParams p;
    p.centre_x_mm = centre(rng);
    p.centre_y_mm = centre(rng);
    p.half_height_mm = size(rng);
    p.left_mm = size(rng);
    p.right_mm = size(rng);
    p.left_handle_x_mm = unit(rng) * p.left_mm;
    p.left_handle_y_mm = unit(rng) * p.half_height_mm;
    p.right_handle_x_mm = unit(rng) * p.right_mm;
    p.right_handle_y_mm = unit(rng) * p.half_height_mm;
    return p;
}

// A query point near the shape's box: inside, on a ring around it, or far away.
Vec2 randomQuery(const GhostShapeParams& p, std::mt19937_64& rng) {
    const double extent = std::max({p.half_height_mm, p.left_mm, p.right_mm});
    std::uniform_real_distribution<double> spread(-3.0 * extent, 3.0 * extent);
    return Vec2(p.centre_x_mm + spread(rng), p.centre_y_mm + spread(rng));
}

TEST(GhostShape, CircleShapeMatchesTrueCircleDistance) {
    const double radius = 3.0;
    const BezierLoop loop = toBezierLoop(circleGhostShape(1.0, -2.0, radius));
    std::mt19937_64 rng(1);
    std::uniform_real_distribution<double> angle(0.0, 2.0 * std::numbers::pi);
    std::uniform_real_distribution<double> dist(0.0, 3.0 * radius);
    for (int i = 0; i < 2000; ++i) {
        const double a = angle(rng);
        const double r = dist(rng);
        const Vec2 q = Vec2(1.0, -2.0) + r * Vec2(std::cos(a), std::sin(a));
        // The four-arc circle deviates by at most 2e-4 of the radius from the true one.
        EXPECT_NEAR(signedDistanceExact(loop, q), r - radius, 2.1e-4 * radius) << "i=" << i;
    }
}

TEST(GhostShape, SignIsNegativeInsideAndPositiveOutside) {
    const BezierLoop loop = toBezierLoop(circleGhostShape(0.0, 0.0, 2.0));
    EXPECT_LT(signedDistanceExact(loop, Vec2(0.0, 0.0)), 0.0);
    EXPECT_LT(signedDistanceFast(loop, Vec2(1.9, 0.0)), 0.0);
    EXPECT_GT(signedDistanceExact(loop, Vec2(2.1, 0.0)), 0.0);
    EXPECT_GT(signedDistanceFast(loop, Vec2(0.0, -5.0)), 0.0);
    // The four-arc circle's radius varies by about 2e-4 of the radius around the true one.
    EXPECT_NEAR(signedDistanceExact(loop, Vec2(0.0, 0.0)), -2.0, 2.1e-4 * 2.0);
    // Points level with the joints: the winding count must not double-count a shared vertex.
    for (const double y : {-2.0, 0.0, 2.0}) {
        EXPECT_EQ(windingNumber(loop, Vec2(-7.0, y)), 0) << y;
        EXPECT_EQ(windingNumber(loop, Vec2(7.0, y)), 0) << y;
    }
    EXPECT_NE(windingNumber(loop, Vec2(0.5, 0.0)), 0);
}

TEST(GhostShape, SignMatchesContainmentOfAStarShapedPolygonWithCorners) {
    // Zero handles make every joint a corner; the shape is then the rhombus |x|/L + |y|/h <= 1
    // (with straight sides), so containment is known in closed form.
    GhostShapeParams p;
    p.half_height_mm = 2.0;
    p.left_mm = 3.0;
    p.right_mm = 3.0;
    p.left_handle_x_mm = p.left_handle_y_mm = p.right_handle_x_mm = p.right_handle_y_mm = 0.0;
    ASSERT_TRUE(validateGhostShape(p));
    // Handles of zero put the inner control points on the joints: each side is straight.
    const BezierLoop loop = toBezierLoop(p);
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> u(-4.0, 4.0);
    for (int i = 0; i < 5000; ++i) {
        const Vec2 q(u(rng), u(rng));
        const double level = std::abs(q.x()) / 3.0 + std::abs(q.y()) / 2.0;
        if (std::abs(level - 1.0) < 1e-9) continue;
        const bool inside = level < 1.0;
        EXPECT_EQ(windingNumber(loop, q) != 0, inside) << q.transpose();
        // Distance to the rhombus side through the quadrant of q (valid where the foot of the
        // perpendicular lies on the side, which holds for points inside).
        if (inside) {
            const double side_distance = (1.0 - level) / std::hypot(1.0 / 3.0, 1.0 / 2.0);
            EXPECT_NEAR(signedDistanceExact(loop, q), -side_distance, 1e-9) << q.transpose();
        }
    }
}

TEST(GhostShape, PointsOnTheCurveHaveZeroDistance) {
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    for (int i = 0; i < 200; ++i) {
        const BezierLoop loop = toBezierLoop(randomShape(rng));
        for (int s = 0; s < loop.segmentCount(); ++s) {
            const double t = unit(rng);
            const Vec2 q = loop.point(s, t);
            EXPECT_LT(std::abs(signedDistanceExact(loop, q)), 1e-9) << "i=" << i << " s=" << s;
            EXPECT_LT(std::abs(signedDistanceFast(loop, q, {8, 4})), 1e-9) << "i=" << i;
        }
    }
}

TEST(GhostShape, ExactDistanceIsNeverAboveDenseSampling) {
    // The reference must find a point at least as near, up to its 1e-9 mm tolerance, as any of
    // 4000 samples per segment; the point it reports lies on the curve.
    std::mt19937_64 rng(4);
    for (int i = 0; i < 50; ++i) {
        const GhostShapeParams p = randomShape(rng);
        const BezierLoop loop = toBezierLoop(p);
        for (int k = 0; k < 20; ++k) {
            const Vec2 q = randomQuery(p, rng);
            const ClosestPoint exact = closestPointExact(loop, q);
            double sampled = std::numeric_limits<double>::infinity();
            for (int s = 0; s < loop.segmentCount(); ++s)
                for (int j = 0; j <= 4000; ++j)
                    sampled = std::min(sampled, (loop.point(s, j / 4000.0) - q).norm());
            EXPECT_LE(exact.distance_mm, sampled + 1e-9) << "i=" << i << " k=" << k;
            EXPECT_NEAR((exact.point_mm - q).norm(), exact.distance_mm, 1e-12);
            EXPECT_NEAR((loop.point(exact.segment, exact.t) - exact.point_mm).norm(), 0.0, 1e-12);
        }
    }
}

TEST(GhostShape, FartherThanProvesOnlyTrueBoundsAndFindsLooseOnes) {
    // Random shapes, some with handles of no length (straight sides whose speed vanishes at both
    // ends, where Newton leaves the segment), against the exact distance.
    std::mt19937_64 rng(41);
    std::uniform_real_distribution<double> share(0.0, 1.5);
    int proven = 0;
    for (int i = 0; i < 200; ++i) {
        GhostShapeParams p = randomShape(rng);
        if (i % 3 == 0) p.right_handle_x_mm = p.right_handle_y_mm = 0.0;
        if (i % 5 == 0) p.left_handle_x_mm = p.left_handle_y_mm = 0.0;
        const BezierLoop loop = toBezierLoop(p);
        for (int k = 0; k < 20; ++k) {
            const Vec2 q = randomQuery(p, rng);
            const double exact = closestPointExact(loop, q, 1e-12).distance_mm;
            const double bound = share(rng) * exact;
            const bool farther = fartherThan(loop, q, bound);
            if (farther) {
                EXPECT_GE(exact, bound - 1e-12) << "i=" << i << " k=" << k;
                ++proven;
            }
            if (bound <= 0.8 * exact && exact > 1e-3) {  // a loose bound is proven
                EXPECT_TRUE(farther) << "i=" << i << " k=" << k << " " << bound << " " << exact;
            }
            if (bound > exact) {
                EXPECT_FALSE(farther) << "i=" << i << " k=" << k;
            }
        }
    }
    EXPECT_GT(proven, 1000);
    // A straight side with handles of no length: the fast distance lands on a corner, nine
    // times too far; the bound it would suggest is refused.
    BezierLoop side;
    side.control_points_mm = {{-7.8165, -16.4622}, {-20.1555, -16.4622}, {-30.1733, -9.4575},
                              {-30.1733, -0.8298}, {-30.1733, 7.7979},   {-20.1555, 14.8025},
                              {-7.8165, 14.8025},  {-7.8165, 14.8025},   {7.8333, -0.8298},
                              {7.8333, -0.8298},   {7.8333, -0.8298},    {-7.8165, -16.4622}};
    const Vec2 q(1.688, -8.066);
    const double fast = closestPointFast(side, q, {4, 2}).distance_mm;
    const double exact = closestPointExact(side, q).distance_mm;
    EXPECT_GT(fast, 5.0 * exact);
    EXPECT_FALSE(fartherThan(side, q, 0.5 * fast));
    EXPECT_TRUE(fartherThan(side, q, 0.8 * exact));
    // Degenerate asks answer no.
    EXPECT_FALSE(fartherThan(side, Vec2(std::nan(""), 0.0), 1.0));
    EXPECT_FALSE(fartherThan(side, q, -1.0));
    EXPECT_FALSE(fartherThan(BezierLoop{}, q, 1.0));
}

TEST(GhostShape, FastAgreesWithExactAfterEnoughIterations) {
    std::mt19937_64 rng(5);
    double worst = 0.0;
    for (int i = 0; i < 300; ++i) {
        const GhostShapeParams p = randomShape(rng);
        const BezierLoop loop = toBezierLoop(p);
        for (int k = 0; k < 30; ++k) {
            const Vec2 q = randomQuery(p, rng);
            const double exact = signedDistanceExact(loop, q);
            const double fast = signedDistanceFast(loop, q, {8, 4});
            worst = std::max(worst, std::abs(exact - fast));
            EXPECT_NEAR(fast, exact, 1e-6) << "i=" << i << " k=" << k << " q=" << q.transpose();
            // The fast method returns a point on the curve: never nearer than the reference.
            EXPECT_GE(std::abs(fast), std::abs(exact) - 1e-9);
        }
    }
    RecordProperty("worst_abs_error_mm", std::to_string(worst));
}

TEST(GhostShape, SeededRandomShapesSignAgreesBetweenMethodsAndWithCentre) {
    std::mt19937_64 rng(6);
    for (int i = 0; i < 500; ++i) {
        const GhostShapeParams p = randomShape(rng);
        ASSERT_TRUE(validateGhostShape(p));
        const BezierLoop loop = toBezierLoop(p);
        // The centre is inside every valid shape.
        EXPECT_LT(signedDistanceExact(loop, Vec2(p.centre_x_mm, p.centre_y_mm)), 0.0) << i;
        const Vec2 q = randomQuery(p, rng);
        const double exact = signedDistanceExact(loop, q);
        const double fast = signedDistanceFast(loop, q);
        if (std::abs(exact) > 1e-9) {
            EXPECT_EQ(exact < 0.0, fast < 0.0) << i;
        }
        // Outside the box of the shape is always outside.
        const Vec2 far(p.centre_x_mm + p.right_mm + 0.01, q.y());
        EXPECT_GT(signedDistanceFast(loop, far), 0.0) << i;
    }
}

TEST(GhostShape, DegenerateLoopsGiveFiniteDistances) {
    std::vector<BezierLoop> loops;
    loops.push_back({std::vector<Vec2>(3, Vec2(1.0, 1.0))});  // one segment, a single point
    loops.push_back({std::vector<Vec2>(12, Vec2::Zero())});   // four segments, a single point
    loops.push_back({{Vec2(0, 0), Vec2(1, 0), Vec2(2, 0), Vec2(3, 0), Vec2(2, 0), Vec2(1, 0)}});
    loops.push_back({{Vec2(0, 0), Vec2(0, 0), Vec2(3, 3), Vec2(3, 3), Vec2(3, 3), Vec2(0, 0)}});
    // Collinear control polygon that folds back on itself (a cusp on the line).
    loops.push_back({{Vec2(0, 0), Vec2(4, 0), Vec2(-1, 0), Vec2(2, 0), Vec2(2, 0), Vec2(0, 0)}});
    // The default shape at its limits: zero handles.
    GhostShapeParams corners;
    corners.left_handle_x_mm = corners.left_handle_y_mm = 0.0;
    corners.right_handle_x_mm = corners.right_handle_y_mm = 0.0;
    loops.push_back(toBezierLoop(corners));
    // And outside them: zero extents (a vertical line), which validation rejects but the
    // distance must survive.
    GhostShapeParams line = corners;
    line.left_mm = line.right_mm = 0.0;
    loops.push_back(toBezierLoop(line));
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> u(-5.0, 5.0);
    for (std::size_t l = 0; l < loops.size(); ++l) {
        for (int k = 0; k < 200; ++k) {
            // Include the control points themselves and points on the degenerate lines.
            const Vec2 q = k < static_cast<int>(loops[l].control_points_mm.size())
                               ? loops[l].control_points_mm[k]
                               : (k % 3 == 0 ? Vec2(u(rng), 0.0) : Vec2(u(rng), u(rng)));
            const double exact = signedDistanceExact(loops[l], q);
            const double fast = signedDistanceFast(loops[l], q, {8, 4});
            ASSERT_TRUE(std::isfinite(exact)) << "loop " << l << " q=" << q.transpose();
            ASSERT_TRUE(std::isfinite(fast)) << "loop " << l << " q=" << q.transpose();
            EXPECT_NEAR(std::abs(fast), std::abs(exact), 1e-6) << "loop " << l;
        }
    }
    // A single-point loop: the distance to the point, and outside.
    EXPECT_NEAR(signedDistanceExact(loops[0], Vec2(4.0, 5.0)), 5.0, 1e-12);
}

// The fast search skips segments whose control box is farther than the best point found, and
// starts with the nearest box; loops of more than 16 segments take the plain pass over all.
// Both must give the same closest point: the same loop with 16 zero-length segments appended at
// its first point takes the plain pass and, since those segments add only that point, has the
// same answer, bit for bit, from every query (near, far, inside, on the curve and on the
// points where two segments meet), but where one of the added segments wins by rounding.
TEST(GhostShape, SkippingFarSegmentsChangesNoClosestPoint) {
    std::mt19937_64 rng(21);
    std::uniform_real_distribution<double> u(-20.0, 20.0);
    for (int shape = 0; shape < 20; ++shape) {
        const BezierLoop loop = toBezierLoop(randomShape(rng));
        BezierLoop plain = loop;
        for (int k = 0; k < 48; ++k) plain.control_points_mm.push_back(loop.control_points_mm[0]);
        ASSERT_EQ(plain.segmentCount(), 20);
        for (int k = 0; k < 300; ++k) {
            const Vec2 q = k < 12
                               ? loop.control_points_mm[static_cast<size_t>(k)]
                               : (k < 40 ? loop.point(k % 4, (k % 7) / 6.0) : Vec2(u(rng), u(rng)));
            for (const FastDistanceOptions o : {FastDistanceOptions{}, FastDistanceOptions{1, 1}}) {
                const ClosestPoint a = closestPointFast(loop, q, o);
                const ClosestPoint b = closestPointFast(plain, q, o);
                if (b.segment < 4) {
                    ASSERT_EQ(a.distance_mm, b.distance_mm) << "shape " << shape << " q " << k;
                    EXPECT_EQ(a.segment, b.segment) << "shape " << shape << " q " << k;
                    EXPECT_EQ(a.t, b.t) << "shape " << shape << " q " << k;
                } else {
                    // A zero-length segment evaluates to its point only to rounding (Bernstein
                    // weights sum to 1 only to rounding), so it may win by an ulp.
                    EXPECT_EQ(a.segment, 0) << "shape " << shape << " q " << k;
                    EXPECT_NEAR(a.distance_mm, b.distance_mm, 1e-12 * (1.0 + b.distance_mm));
                }
            }
        }
    }
}

TEST(GhostShape, EmptyLoopAndNonFiniteQueryAreInfiniteNotNaN) {
    EXPECT_EQ(signedDistanceExact(BezierLoop{}, Vec2(0, 0)),
              std::numeric_limits<double>::infinity());
    const BezierLoop loop = toBezierLoop(circleGhostShape(0.0, 0.0, 1.0));
    const Vec2 nan(std::nan(""), 0.0);
    EXPECT_EQ(signedDistanceFast(loop, nan), std::numeric_limits<double>::infinity());
    EXPECT_EQ(windingNumber(loop, nan), 0);
}

TEST(GhostShapeParams, VectorRoundTripsAndControlPointsAreAxisAligned) {
    std::mt19937_64 rng(8);
    for (int i = 0; i < 100; ++i) {
        const GhostShapeParams p = randomShape(rng);
        const auto back = ghostShapeFromVector(toVector(p));
        ASSERT_TRUE(back) << back.error().message;
        EXPECT_EQ(*back, p);
        const BezierLoop loop = toBezierLoop(p);
        ASSERT_EQ(loop.segmentCount(), 4);
        const auto& c = loop.control_points_mm;
        // Handles at the top and bottom are horizontal, at the extremes vertical (G^1 joints).
        EXPECT_EQ(c[0].y(), c[1].y());
        EXPECT_EQ(c[11].y(), c[0].y());
        EXPECT_EQ(c[2].x(), c[3].x());
        EXPECT_EQ(c[3].x(), c[4].x());
        EXPECT_EQ(c[5].y(), c[6].y());
        EXPECT_EQ(c[6].y(), c[7].y());
        EXPECT_EQ(c[8].x(), c[9].x());
        EXPECT_EQ(c[9].x(), c[10].x());
        EXPECT_EQ(c[3], Vec2(p.centre_x_mm - p.left_mm, p.centre_y_mm));
        EXPECT_EQ(c[9], Vec2(p.centre_x_mm + p.right_mm, p.centre_y_mm));
    }
}

TEST(GhostShapeParams, OutOfBoundsValuesAreRejectedNamingTheParameter) {
    struct Case {
        int index;
        double value;
        const char* name;
    };
    const Case cases[] = {
        {0, std::nan(""), "centre_x_mm"},
        {1, std::numeric_limits<double>::infinity(), "centre_y_mm"},
        {2, 0.0, "half_height_mm"},
        {3, -1.0, "left_mm"},
        {4, 0.0, "right_mm"},
        {5, -0.1, "left_handle_x_mm"},
        {5, 1.5, "left_handle_x_mm"},     // beyond left_mm = 1
        {6, 1.0001, "left_handle_y_mm"},  // beyond half_height_mm = 1
        {7, 2.0, "right_handle_x_mm"},
        {8, -1e-12, "right_handle_y_mm"},
    };
    for (const Case& c : cases) {
        GhostShapeVector v = toVector(GhostShapeParams{});
        v[c.index] = c.value;
        const auto result = ghostShapeFromVector(v);
        ASSERT_FALSE(result) << c.name;
        EXPECT_EQ(result.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(result.error().message.find(c.name), std::string::npos) << result.error().message;
        EXPECT_STREQ(ghostShapeParamName(c.index), c.name);
    }
    EXPECT_TRUE(validateGhostShape(GhostShapeParams{}));
    EXPECT_TRUE(validateGhostShape(circleGhostShape(0.0, 0.0, 0.01)));
}

TEST(BezierLoop, VectorFormValidatesLengthAndFiniteness) {
    const std::vector<double> five = {0, 0, 1, 1, 2};
    EXPECT_FALSE(bezierLoopFromVector(five));
    EXPECT_FALSE(bezierLoopFromVector({}));
    std::vector<double> twelve_points(24, 0.0);
    twelve_points[7] = std::numeric_limits<double>::infinity();
    const auto bad = bezierLoopFromVector(twelve_points);
    ASSERT_FALSE(bad);
    EXPECT_NE(bad.error().message.find("control point 3 y"), std::string::npos)
        << bad.error().message;
    const BezierLoop circle = toBezierLoop(circleGhostShape(0.5, 0.5, 1.0));
    const auto back = bezierLoopFromVector(toVector(circle));
    ASSERT_TRUE(back);
    EXPECT_EQ(back->control_points_mm, circle.control_points_mm);
}

TEST(BezierLoop, EightSegmentOctagonHasKnownDistances) {
    // A regular octagon of circumradius 2 with straight sides (inner points on the chords),
    // the kind of loop a polygonal aperture needs.
    BezierLoop octagon;
    for (int i = 0; i < 8; ++i) {
        const double a0 = i * std::numbers::pi / 4.0;
        const double a1 = (i + 1) * std::numbers::pi / 4.0;
        const Vec2 p0 = 2.0 * Vec2(std::cos(a0), std::sin(a0));
        const Vec2 p1 = 2.0 * Vec2(std::cos(a1), std::sin(a1));
        octagon.control_points_mm.push_back(p0);
        octagon.control_points_mm.push_back(p0 + (p1 - p0) / 3.0);
        octagon.control_points_mm.push_back(p0 + 2.0 * (p1 - p0) / 3.0);
    }
    const double apothem = 2.0 * std::cos(std::numbers::pi / 8.0);
    EXPECT_NEAR(signedDistanceExact(octagon, Vec2::Zero()), -apothem, 1e-9);
    EXPECT_NEAR(signedDistanceFast(octagon, Vec2::Zero()), -apothem, 1e-9);
    EXPECT_NEAR(signedDistanceExact(octagon, Vec2(3.0, 0.0)), 1.0, 1e-9);  // nearest: a vertex
    EXPECT_NEAR(signedDistanceFast(octagon, Vec2(3.0, 0.0)), 1.0, 1e-12);
}

TEST(TransferIntensity, FollowsEquation64) {
    // Border value on the border, inner value deep inside, zero far outside.
    EXPECT_EQ(transferIntensity(0.0, 2.0, 0.5, 1.0, 1.0, 1.0, 1.0), 2.0);
    EXPECT_DOUBLE_EQ(transferIntensity(-5.0, 2.0, 0.5, 1.0, 1.0, 1.0, 1.0), 0.5);
    EXPECT_DOUBLE_EQ(transferIntensity(5.0, 2.0, 0.5, 1.0, 1.0, 1.0, 1.0), 0.0);
    // Halfway inside with E_i = 2: S = 0.5, S^2 = 0.25 -> lerp(2, 0.5, 0.25) = 1.625.
    EXPECT_DOUBLE_EQ(transferIntensity(-1.0, 2.0, 0.5, 2.0, 4.0, 2.0, 1.0), 1.625);
    // Outside with F_o = 4, E_o = 0.5: S = 0.25, sqrt = 0.5 -> lerp(2, 0, 0.5) = 1.
    EXPECT_DOUBLE_EQ(transferIntensity(1.0, 2.0, 0.5, 2.0, 4.0, 2.0, 0.5), 1.0);
    // Continuous at the border from both sides.
    EXPECT_NEAR(transferIntensity(1e-12, 2.0, 0.5, 1.0, 1.0, 1.0, 1.0), 2.0, 1e-11);
    EXPECT_NEAR(transferIntensity(-1e-12, 2.0, 0.5, 1.0, 1.0, 1.0, 1.0), 2.0, 1e-11);
}

TEST(TransferIntensity, ShadesEachChannelAndValidatesFields) {
    GhostShading s;
    s.border_rgb = {1.0, 0.5, 0.25};
    s.inner_rgb = {0.1, 0.2, 0.3};
    s.inner_falloff_mm = 0.5;
    s.outer_falloff_mm = 0.25;
    ASSERT_TRUE(validateShading(s));
    const BezierLoop loop = toBezierLoop(circleGhostShape(0.0, 0.0, 2.0));
    const auto centre = shadeGhost(loop, s, Vec2::Zero());
    EXPECT_DOUBLE_EQ(centre[0], 0.1);
    EXPECT_DOUBLE_EQ(centre[1], 0.2);
    EXPECT_DOUBLE_EQ(centre[2], 0.3);
    const auto far = shadeGhost(loop, s, Vec2(5.0, 0.0));
    EXPECT_EQ(far, (std::array<double, 3>{0.0, 0.0, 0.0}));
    const auto border = shadeGhost(loop, s, Vec2(2.0, 0.0));
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(border[c], s.border_rgb[c], 1e-9);

    GhostShading bad = s;
    bad.inner_rgb[1] = -0.1;
    const Status r1 = validateShading(bad);
    ASSERT_FALSE(r1);
    EXPECT_NE(r1.error().message.find("inner_rgb[1]"), std::string::npos) << r1.error().message;
    bad = s;
    bad.outer_falloff_mm = 0.0;
    const Status r2 = validateShading(bad);
    ASSERT_FALSE(r2);
    EXPECT_NE(r2.error().message.find("outer_falloff_mm"), std::string::npos);
    bad = s;
    bad.inner_exponent = std::nan("");
    EXPECT_FALSE(validateShading(bad));
}

// The mean of eq. 6.4 over a block of side w x h at a straight edge whose normal makes angle phi
// with the x axis, by a dense grid: what boxTransferWeights must give in closed form.
TransferWeights<double> denseBlockMean(
    double d, double w, double h, double phi, double fi, double fo, double ei, double eo) {
    const int n = 400;
    TransferWeights<double> sum{0.0, 0.0};
    for (int j = 0; j < n; ++j)
        for (int i = 0; i < n; ++i) {
            const double x = ((i + 0.5) / n - 0.5) * w, y = ((j + 0.5) / n - 0.5) * h;
            const double e = d + x * std::cos(phi) + y * std::sin(phi);
            sum.border += transferIntensity(e, 1.0, 0.0, fi, fo, ei, eo);
            sum.inner += transferIntensity(e, 0.0, 1.0, fi, fo, ei, eo);
        }
    return {sum.border / (n * n), sum.inner / (n * n)};
}

TEST(TransferIntensity, BlockMeanMatchesDenseAveragingAtAnyEdgeAngle) {
    struct Case {
        double fi, fo, ei, eo;
    };
    // Sharp edges (falloffs far below the block), wide ones, and exponents at their bounds.
    const Case cases[] = {{0.01, 0.01, 1.0, 1.0},
                          {3.0, 2.0, 0.25, 4.0},
                          {0.5, 1.5, 4.0, 0.25},
                          {1.0, 0.02, 2.0, 1.0}};
    const double w = 1.3, h = 0.9;
    for (const Case& k : cases)
        for (double phi : {0.0, 0.3, std::numbers::pi / 4.0, 1.2, std::numbers::pi / 2.0, 2.5})
            for (double d : {-4.0, -1.1, -0.5, -0.2, 0.0, 0.15, 0.4, 0.9, 3.0}) {
                const double a = 0.5 * w * std::abs(std::cos(phi));
                const double c = 0.5 * h * std::abs(std::sin(phi));
                const auto got = boxTransferWeights(d, a, c, k.fi, k.fo, k.ei, k.eo);
                const auto want = denseBlockMean(d, w, h, phi, k.fi, k.fo, k.ei, k.eo);
                EXPECT_NEAR(got.border, want.border, 2e-3)
                    << "d " << d << " phi " << phi << " fi " << k.fi << " fo " << k.fo;
                EXPECT_NEAR(got.inner, want.inner, 2e-3)
                    << "d " << d << " phi " << phi << " fi " << k.fi << " fo " << k.fo;
            }
}

TEST(TransferIntensity, BlockMeanOfAPointIsTheTransferAndFarRegionsAreExact) {
    for (double d : {-2.0, -0.3, 0.0, 0.2, 1.5}) {
        const auto w = boxTransferWeights(d, 0.0, 0.0, 1.0, 0.5, 2.0, 0.5);
        EXPECT_DOUBLE_EQ(w.border, transferIntensity(d, 1.0, 0.0, 1.0, 0.5, 2.0, 0.5));
        EXPECT_DOUBLE_EQ(w.inner, transferIntensity(d, 0.0, 1.0, 1.0, 0.5, 2.0, 0.5));
        // A vanishing block tends to the point value (exponents >= 1: no infinite slope at the
        // border, where an exponent below 1 makes the mean of a 1e-6 block differ by ~1e-3).
        const auto tiny = boxTransferWeights(d, 1e-6, 4e-7, 1.0, 0.5, 2.0, 1.0);
        EXPECT_NEAR(tiny.border, transferIntensity(d, 1.0, 0.0, 1.0, 0.5, 2.0, 1.0), 1e-5);
        EXPECT_NEAR(tiny.inner, transferIntensity(d, 0.0, 1.0, 1.0, 0.5, 2.0, 1.0), 1e-5);
    }
    // Far from the edge on either side: exact constants, whatever the block.
    const auto out = boxTransferWeights(50.0, 3.0, 2.0, 1.0, 0.5, 2.0, 0.5);
    EXPECT_EQ(out.border, 0.0);
    EXPECT_EQ(out.inner, 0.0);
    const auto in = boxTransferWeights(-50.0, 3.0, 2.0, 1.0, 0.5, 2.0, 0.5);
    EXPECT_EQ(in.border, 0.0);
    EXPECT_EQ(in.inner, 1.0);
    // Partition of unity deep inside a wide block: border + inner weights stay in [0, 1].
    for (double d = -3.0; d <= 3.0; d += 0.05) {
        const auto v = boxTransferWeights(d, 0.7, 0.4, 0.3, 0.2, 1.0, 1.0);
        EXPECT_TRUE(std::isfinite(v.border) && std::isfinite(v.inner)) << d;
        EXPECT_GE(v.border, -1e-12) << d;
        EXPECT_GE(v.inner, -1e-12) << d;
        EXPECT_LE(v.border + v.inner, 1.0 + 1e-12) << d;
    }
}

}  // namespace
}  // namespace flarelab::render
