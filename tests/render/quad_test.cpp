#include "render/quad.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>

namespace flarelab::render {
namespace {

using Vec2 = Eigen::Vector2d;
using Weights = std::array<double, 4>;

Quad makeQuad(const Vec2& a, const Vec2& b, const Vec2& c, const Vec2& d) {
    Quad q;
    const Vec2 corners[4] = {a, b, c, d};
    for (int i = 0; i < 4; ++i) {
        q.corners[i].position_px = corners[i];
        q.corners[i].throughput = static_cast<float>(i + 1);
        q.corners[i].stop_u = static_cast<float>(0.1 * i);
        q.corners[i].stop_v = static_cast<float>(-0.2 * i);
    }
    return q;
}

// Checks sum w = 1 and sum w_i corner_i = p, both in the frame of corner 0 so that the tolerance
// is relative to the quad's size, not to its distance from the origin.
void expectLinearPrecision(const Quad& q, const Vec2& p, const Weights& w, double tolerance) {
    double total = 0.0;
    Vec2 local = Vec2::Zero();
    const Vec2 origin = q.corners[0].position_px;
    for (int i = 0; i < 4; ++i) {
        ASSERT_TRUE(std::isfinite(w[i]));
        total += w[i];
        local += w[i] * (q.corners[i].position_px - origin);
    }
    double size = 0.0;
    for (int i = 1; i < 4; ++i)
        size = std::max(size, (q.corners[i].position_px - origin).cwiseAbs().maxCoeff());
    ASSERT_NEAR(total, 1.0, 1e-12);
    ASSERT_NEAR(local.x(), p.x() - origin.x(), tolerance * size) << p.transpose();
    ASSERT_NEAR(local.y(), p.y() - origin.y(), tolerance * size) << p.transpose();
}

double naiveDeterminant(const Vec2& a, const Vec2& b, const Vec2& c) {
    return (b.x() - a.x()) * (c.y() - a.y()) - (b.y() - a.y()) * (c.x() - a.x());
}

int sign(__int128 x) { return x > 0 ? 1 : (x < 0 ? -1 : 0); }

TEST(Orientation, GivesTheSignOfTheCrossProduct) {
    EXPECT_EQ(orientation({0, 0}, {1, 0}, {0, 1}), 1);
    EXPECT_EQ(orientation({0, 0}, {0, 1}, {1, 0}), -1);
    EXPECT_EQ(orientation({0, 0}, {1, 1}, {3, 3}), 0);
    EXPECT_EQ(orientation({1, 1}, {1, 1}, {1, 1}), 0);
}

// Kettner et al.'s classroom example: p near the line through (12, 12) and (24, 24), moved by
// a few ulps. Every coordinate is a multiple of 2^-53 below 2^5, so 2^53 times the determinant is
// an exact 128-bit integer computation, the ground truth.
TEST(Orientation, IsExactWhereTheNaiveDoubleFormulaGetsTheSignWrong) {
    const Vec2 q(12.0, 12.0), r(24.0, 24.0);
    const double ulp = std::ldexp(1.0, -53);
    int naive_wrong = 0;
    for (int i = 0; i < 256; ++i) {
        for (int j = 0; j < 256; ++j) {
            const Vec2 p(0.5 + i * ulp, 0.5 + j * ulp);
            const auto scaled = [](double x) { return static_cast<__int128>(std::ldexp(x, 53)); };
            const __int128 det = (scaled(q.x()) - scaled(p.x())) * (scaled(r.y()) - scaled(p.y())) -
                                 (scaled(q.y()) - scaled(p.y())) * (scaled(r.x()) - scaled(p.x()));
            const int truth = sign(det);
            ASSERT_EQ(orientation(p, q, r), truth) << i << " " << j;
            ASSERT_EQ(orientation(q, r, p), truth) << i << " " << j;
            ASSERT_EQ(orientation(r, q, p), -truth) << i << " " << j;
            const double naive = naiveDeterminant(p, q, r);
            if ((naive > 0) - (naive < 0) != truth) ++naive_wrong;
        }
    }
    EXPECT_GT(naive_wrong, 1000);  // the naive formula fails often here; ours never does
}

TEST(Orientation, IsAntisymmetricAndCyclicOnRandomNearlyCollinearPoints) {
    std::mt19937_64 rng(11);
    std::uniform_real_distribution<double> coord(-1e3, 1e3), t(-2.0, 3.0), tiny(-1e-12, 1e-12);
    for (int k = 0; k < 100000; ++k) {
        const Vec2 a(coord(rng), coord(rng)), b(coord(rng), coord(rng));
        const double s = t(rng);
        const Vec2 c = a + s * (b - a) + Vec2(tiny(rng), tiny(rng));
        const int o = orientation(a, b, c);
        ASSERT_EQ(orientation(b, c, a), o);
        ASSERT_EQ(orientation(c, a, b), o);
        ASSERT_EQ(orientation(b, a, c), -o);
        ASSERT_EQ(orientation(a, c, b), -o);
    }
}

TEST(QuadIsConvex, ClassifiesConvexNonConvexAndDegenerateQuads) {
    EXPECT_TRUE(quadIsConvex(makeQuad({0, 0}, {1, 0}, {1, 1}, {0, 1})));
    EXPECT_TRUE(quadIsConvex(makeQuad({0, 0}, {0, 1}, {1, 1}, {1, 0})));  // other winding
    EXPECT_FALSE(quadIsConvex(makeQuad({0, 0}, {2, 0}, {0.5, 0.5}, {0, 2})));
    EXPECT_FALSE(quadIsConvex(makeQuad({0, 0}, {1, 1}, {1, 0}, {0, 1})));  // bow-tie
    EXPECT_FALSE(quadIsConvex(makeQuad({0, 0}, {1, 0}, {2, 0}, {1, 1})));  // flat corner
    EXPECT_FALSE(quadIsConvex(makeQuad({1, 1}, {1, 1}, {1, 1}, {1, 1})));
}

TEST(QuadBarycentrics, ReproducesCornersAsUnitVectors) {
    const Quad quads[] = {
        makeQuad({0, 0}, {4, 0.5}, {3.5, 3}, {-0.5, 2}),  // convex
        makeQuad({0, 0}, {4, 0}, {1, 1}, {0, 4}),         // arrowhead, reflex corner 2
        makeQuad({0, 0}, {2, 2}, {2, 0}, {0, 2}),         // bow-tie
        makeQuad({0, 0}, {1, 0}, {2, 0}, {1, 1}),         // flat corner 1
    };
    for (const Quad& q : quads) {
        for (int i = 0; i < 4; ++i) {
            const auto w = quadBarycentrics(q, q.corners[i].position_px);
            ASSERT_TRUE(w.has_value()) << i;
            for (int k = 0; k < 4; ++k) EXPECT_EQ((*w)[k], k == i ? 1.0 : 0.0) << i << " " << k;
        }
    }
}

// A random strictly convex quad: four points on an ellipse at sorted random angles.
Quad randomConvexQuad(std::mt19937_64& rng, const Vec2& centre, double size) {
    std::uniform_real_distribution<double> angle(0.0, 2.0 * std::numbers::pi), axis(0.3, 1.0);
    for (;;) {
        std::array<double, 4> a{angle(rng), angle(rng), angle(rng), angle(rng)};
        std::sort(a.begin(), a.end());
        const double rx = axis(rng) * size, ry = axis(rng) * size;
        Vec2 v[4];
        for (int i = 0; i < 4; ++i) v[i] = centre + Vec2(rx * std::cos(a[i]), ry * std::sin(a[i]));
        const Quad q = makeQuad(v[0], v[1], v[2], v[3]);
        if (quadIsConvex(q)) return q;
    }
}

TEST(QuadBarycentrics, HasLinearPrecisionAndNonNegativeWeightsInRandomConvexQuads) {
    std::mt19937_64 rng(1);
    std::uniform_real_distribution<double> unit(-1.2, 1.2);
    int inside = 0;
    for (int k = 0; k < 2000; ++k) {
        const Quad q = randomConvexQuad(rng, Vec2(100.0, 50.0), 10.0);
        for (int s = 0; s < 20; ++s) {
            const Vec2 p = Vec2(100.0, 50.0) + 10.0 * Vec2(unit(rng), unit(rng));
            // Independent inside test, away from the boundary: all edges see p on one side.
            int positive = 0, negative = 0;
            for (int i = 0; i < 4; ++i) {
                const double c = naiveDeterminant(q.corners[i].position_px,
                                                  q.corners[(i + 1) % 4].position_px, p);
                positive += c > 1e-9;
                negative += c < -1e-9;
            }
            const auto w = quadBarycentrics(q, p);
            if (positive == 4 || negative == 4) {
                ASSERT_TRUE(w.has_value());
            }
            if (positive > 0 && negative > 0) {
                ASSERT_FALSE(w.has_value());
            }
            if (!w) continue;
            ++inside;
            expectLinearPrecision(q, p, *w, 1e-12);
            for (double x : *w) ASSERT_GE(x, 0.0);
        }
    }
    EXPECT_GT(inside, 2000);
}

// A random arrowhead: corner `reflex` lies inside the triangle of the other three, so the quad is
// simple with exactly one reflex corner; the notch is the triangle it cuts away.
TEST(QuadBarycentrics, HasLinearPrecisionInRandomNonConvexQuads) {
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> coord(-10.0, 10.0), unit(0.05, 1.0);
    int inside = 0;
    for (int k = 0; k < 2000; ++k) {
        Vec2 a(coord(rng), coord(rng)), b(coord(rng), coord(rng)), c(coord(rng), coord(rng));
        if (std::abs(naiveDeterminant(a, b, c)) < 5.0) continue;
        const double l0 = unit(rng), l1 = unit(rng), l2 = unit(rng);
        const Vec2 r = (l0 * a + l1 * b + l2 * c) / (l0 + l1 + l2);
        std::array<Vec2, 4> v{a, b, c, r};
        std::rotate(v.begin(), v.begin() + (k % 4), v.end());
        const Quad q = makeQuad(v[0], v[1], v[2], v[3]);
        ASSERT_FALSE(quadIsConvex(q));
        for (int s = 0; s < 20; ++s) {
            const Vec2 p(coord(rng), coord(rng));
            const auto w = quadBarycentrics(q, p);
            const auto strictlyInside = [&](const Vec2& x, const Vec2& y, const Vec2& z) {
                const double d0 = naiveDeterminant(x, y, p), d1 = naiveDeterminant(y, z, p);
                const double d2 = naiveDeterminant(z, x, p);
                return (d0 > 1e-9 && d1 > 1e-9 && d2 > 1e-9) ||
                       (d0 < -1e-9 && d1 < -1e-9 && d2 < -1e-9);
            };
            if (strictlyInside(c, r, a)) {
                ASSERT_FALSE(w.has_value()) << p.transpose();
            }
            if (!w) continue;
            ++inside;
            expectLinearPrecision(q, p, *w, 1e-12);
        }
    }
    EXPECT_GT(inside, 2000);
}

TEST(QuadBarycentrics, NeighbouringQuadsAgreeOnTheirSharedEdge) {
    // Grid cells (i, j) and (i + 1, j): the left quad's edge 1-2 is the right quad's edge 3-0.
    const Vec2 p00(0, 0), p10(4, 0.5), p11(4.5, 4), p01(0, 3.5), p20(8, 1), p21(8.5, 4.5);
    const Quad left = makeQuad(p00, p10, p11, p01);
    const Quad right = makeQuad(p10, p20, p21, p11);
    for (int k = 0; k <= 16; ++k) {
        const Vec2 on_edge = p10 + (k / 16.0) * (p11 - p10);  // exact: dyadic steps
        const auto wl = quadBarycentrics(left, on_edge);
        const auto wr = quadBarycentrics(right, on_edge);
        ASSERT_TRUE(wl && wr) << k;
        EXPECT_EQ((*wl)[1], (*wr)[0]) << k;
        EXPECT_EQ((*wl)[2], (*wr)[3]) << k;
        EXPECT_EQ((*wl)[0] + (*wl)[3], 0.0);
        EXPECT_EQ((*wr)[1] + (*wr)[2], 0.0);
        // Just off the edge on either side the weights approach the edge's.
        const Vec2 normal = Vec2(p11.y() - p10.y(), p10.x() - p11.x()).normalized();
        for (double h : {1e-6, 1e-9}) {
            const Vec2 in_left = on_edge - h * normal;
            const Vec2 in_right = on_edge + h * normal;
            const auto l = quadBarycentrics(left, in_left);
            const auto r = quadBarycentrics(right, in_right);
            if (k == 0 || k == 16) continue;  // at the corners one side may be outside
            ASSERT_TRUE(l && r) << k << " " << h;
            EXPECT_NEAR((*l)[1], (*wl)[1], 10 * h) << k;
            EXPECT_NEAR((*r)[0], (*wr)[0], 10 * h) << k;
            EXPECT_NEAR((*l)[0] + (*l)[3], 0.0, 10 * h);
            EXPECT_FALSE(quadBarycentrics(left, in_right).has_value());
            EXPECT_FALSE(quadBarycentrics(right, in_left).has_value());
        }
    }
}

TEST(QuadBarycentrics, InterpolatesLinearlyOnEdges) {
    const Quad q = makeQuad({0, 0}, {8, 0}, {8, 8}, {0, 8});
    const auto w = quadBarycentrics(q, {2, 0});
    ASSERT_TRUE(w);
    EXPECT_EQ((*w)[0], 0.75);
    EXPECT_EQ((*w)[1], 0.25);
    EXPECT_EQ((*w)[2], 0.0);
    EXPECT_EQ((*w)[3], 0.0);
    const auto centre = quadBarycentrics(q, {4, 4});
    ASSERT_TRUE(centre);
    for (double x : *centre) EXPECT_NEAR(x, 0.25, 1e-15);
    EXPECT_FALSE(quadBarycentrics(q, {8.0000001, 4}).has_value());
    EXPECT_FALSE(quadBarycentrics(q, {4, std::nextafter(0.0, -1.0)}).has_value());
    EXPECT_TRUE(quadBarycentrics(q, {4, std::nextafter(0.0, 1.0)}).has_value());
}

TEST(QuadBarycentrics, AllCornersEqualIsAPoint) {
    const Quad q = makeQuad({3, 3}, {3, 3}, {3, 3}, {3, 3});
    const auto w = quadBarycentrics(q, {3, 3});
    ASSERT_TRUE(w);
    expectLinearPrecision(q, {3, 3}, *w, 0.0);
    EXPECT_FALSE(quadBarycentrics(q, {3, std::nextafter(3.0, 4.0)}).has_value());
    EXPECT_FALSE(quadBarycentrics(q, {0, 0}).has_value());
}

TEST(QuadBarycentrics, CollinearQuadIsASegment) {
    const Quad q = makeQuad({0, 0}, {1, 1}, {4, 4}, {2, 2});  // zero area, folded on itself
    for (double t : {0.0, 0.5, 1.5, 3.0, 4.0}) {
        const auto w = quadBarycentrics(q, {t, t});
        ASSERT_TRUE(w) << t;
        expectLinearPrecision(q, {t, t}, *w, 1e-15);
    }
    EXPECT_FALSE(quadBarycentrics(q, {1, 1.5}).has_value());
    EXPECT_FALSE(quadBarycentrics(q, {5, 5}).has_value());
}

TEST(QuadBarycentrics, QuadWithTwoCoincidentCornersIsATriangle) {
    const Quad q = makeQuad({0, 0}, {4, 0}, {4, 0}, {0, 4});
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<double> coord(-1.0, 5.0);
    for (int k = 0; k < 10000; ++k) {
        const Vec2 p(coord(rng), coord(rng));
        const auto w = quadBarycentrics(q, p);
        const bool inside = p.x() >= 0 && p.y() >= 0 && p.x() + p.y() <= 4.0;
        ASSERT_EQ(w.has_value(), inside) << p.transpose();
        if (w) expectLinearPrecision(q, p, *w, 1e-12);
    }
}

TEST(QuadBarycentrics, FlatCornerKeepsLinearPrecision) {
    const Quad q = makeQuad({0, 0}, {2, 0}, {4, 0}, {2, 3});  // corner 1 on edge 0-2
    std::mt19937_64 rng(4);
    std::uniform_real_distribution<double> x(0.0, 4.0), y(0.0, 3.0);
    int inside = 0;
    for (int k = 0; k < 10000; ++k) {
        const Vec2 p(x(rng), y(rng));
        const auto w = quadBarycentrics(q, p);
        if (!w) continue;
        ++inside;
        expectLinearPrecision(q, p, *w, 1e-12);
    }
    EXPECT_GT(inside, 4000);
}

TEST(QuadBarycentrics, BowTieCoversItsTwoLobesOnly) {
    // Edges 0-1 and 2-3 cross at (2, 2); the lobes are the left and right triangles.
    const Quad q = makeQuad({0, 0}, {4, 4}, {4, 0}, {0, 4});
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> coord(0.0, 4.0);
    for (int k = 0; k < 10000; ++k) {
        const Vec2 p(coord(rng), coord(rng));
        const double dx = std::abs(p.x() - 2.0), dy = std::abs(p.y() - 2.0);
        const auto w = quadBarycentrics(q, p);
        if (dx > dy + 1e-12) {
            ASSERT_TRUE(w) << p.transpose();
            expectLinearPrecision(q, p, *w, 1e-12);
        } else if (dy > dx + 1e-12) {
            ASSERT_FALSE(w) << p.transpose();
        }
    }
    const auto crossing = quadBarycentrics(q, {2, 2});
    ASSERT_TRUE(crossing);
    expectLinearPrecision(q, {2, 2}, *crossing, 1e-15);
}

TEST(QuadBarycentrics, HugeCoordinatesKeepPrecisionRelativeToTheQuad) {
    // Corners and points are 1e7 plus multiples of 2^-20, so differences are exact in double.
    std::mt19937_64 rng(6);
    std::uniform_int_distribution<int> offset(0, 4 << 20);
    const Vec2 base(1e7, 1e7);
    const auto at = [&](int ix, int iy) {
        return Vec2(base.x() + std::ldexp(ix, -20), base.y() + std::ldexp(iy, -20));
    };
    const Quad q =
        makeQuad(at(0, 0), at(3 << 20, 1 << 18), at(7 << 19, 3 << 20), at(1 << 17, 7 << 19));
    ASSERT_TRUE(quadIsConvex(q));
    int inside = 0;
    for (int k = 0; k < 10000; ++k) {
        const Vec2 p = at(offset(rng), offset(rng));
        const auto w = quadBarycentrics(q, p);
        if (!w) continue;
        ++inside;
        expectLinearPrecision(q, p, *w, 1e-12);
    }
    EXPECT_GT(inside, 3000);
    // A quad 1e7 pixels across, far larger than any image.
    const Quad big = makeQuad({-1e7, -1e7}, {1e7, -1e7}, {1e7, 1e7}, {-1e7, 1e7});
    const auto w = quadBarycentrics(big, {0.5, 0.5});
    ASSERT_TRUE(w);
    expectLinearPrecision(big, {0.5, 0.5}, *w, 1e-12);
}

TEST(QuadBarycentrics, TinyQuadsKeepPrecision) {
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> unit(-1.2, 1.2);
    int inside = 0;
    for (int k = 0; k < 500; ++k) {
        const Quad q = randomConvexQuad(rng, Vec2(640.5, 360.5), 1e-6);
        for (int s = 0; s < 20; ++s) {
            const Vec2 p = Vec2(640.5, 360.5) + 1e-6 * Vec2(unit(rng), unit(rng));
            const auto w = quadBarycentrics(q, p);
            if (!w) continue;
            ++inside;
            // A 1e-6 px quad at 640 px has coordinates good to ~1e-13 px: 1e-7 of its size.
            expectLinearPrecision(q, p, *w, 1e-6);
        }
    }
    EXPECT_GT(inside, 400);
}

TEST(QuadBarycentrics, NonFiniteInputIsOutside) {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const double inf = std::numeric_limits<double>::infinity();
    const Quad q = makeQuad({0, 0}, {1, 0}, {1, 1}, {0, 1});
    EXPECT_FALSE(quadBarycentrics(q, {nan, 0.5}).has_value());
    EXPECT_FALSE(quadBarycentrics(q, {0.5, inf}).has_value());
    EXPECT_FALSE(quadBarycentrics(makeQuad({0, 0}, {nan, 0}, {1, 1}, {0, 1}), {0.5, 0.5}));
}

TEST(InterpolateQuad, MixesCornerAttributes) {
    const Quad q = makeQuad({0, 0}, {2, 0}, {2, 2}, {0, 2});
    const auto w = quadBarycentrics(q, {1, 1});
    ASSERT_TRUE(w);
    const QuadSample s = interpolateQuad(q, *w);
    EXPECT_FLOAT_EQ(s.throughput, 2.5f);
    EXPECT_FLOAT_EQ(s.stop_u, 0.15f);
    EXPECT_FLOAT_EQ(s.stop_v, -0.3f);
    const QuadSample corner = interpolateQuad(q, {0.0, 0.0, 1.0, 0.0});
    EXPECT_EQ(corner.throughput, 3.0f);
}

}  // namespace
}  // namespace flarelab::render
