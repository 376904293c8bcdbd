#include "render/quad.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace flarelab::render {
namespace {

using Vec2 = Eigen::Vector2d;

// a + b = sum + err exactly (Knuth's two-sum; no assumption on the magnitudes).
void twoSum(double a, double b, double& sum, double& err) {
    sum = a + b;
    const double b_virtual = sum - a;
    const double a_virtual = sum - b_virtual;
    err = (a - a_virtual) + (b - b_virtual);
}

// Adds t to a non-overlapping expansion stored in increasing magnitude, dropping zero terms
// (GROW-EXPANSION with zero elimination, Shewchuk 1997 §2.4). The result keeps both properties,
// so its sign is the sign of its last term.
void growExpansion(double* terms, int& count, double t) {
    double q = t;
    int kept = 0;
    for (int i = 0; i < count; ++i) {
        double sum = 0.0, err = 0.0;
        twoSum(q, terms[i], sum, err);
        q = sum;
        if (err != 0.0) terms[kept++] = err;
    }
    if (q != 0.0) terms[kept++] = q;
    count = kept;
}

// The determinant expanded into six products ax*by - ay*bx + bx*cy - by*cx + cx*ay - cy*ax, each
// split exactly into a rounded product and its FMA residual, and summed without error.
int exactOrientation(const Vec2& a, const Vec2& b, const Vec2& c) {
    const double factors[6][2] = {{a.x(), b.y()},  {-a.y(), b.x()}, {b.x(), c.y()},
                                  {-b.y(), c.x()}, {c.x(), a.y()},  {-c.y(), a.x()}};
    double terms[12];
    int count = 0;
    for (const auto& f : factors) {
        const double product = f[0] * f[1];
        growExpansion(terms, count, std::fma(f[0], f[1], -product));
        growExpansion(terms, count, product);
    }
    if (count == 0) return 0;
    return terms[count - 1] > 0.0 ? 1 : -1;
}

double cross(const Vec2& a, const Vec2& b) { return a.x() * b.y() - a.y() * b.x(); }

bool lexicographicLess(const Vec2& a, const Vec2& b) {
    return a.x() < b.x() || (a.x() == b.x() && a.y() < b.y());
}

// p is known to lie on the line through a and b; true when it is also between them. Coordinate
// comparisons are exact, so together with an exact orientation this decides the closed segment.
bool withinBox(const Vec2& a, const Vec2& b, const Vec2& p) {
    return std::min(a.x(), b.x()) <= p.x() && p.x() <= std::max(a.x(), b.x()) &&
           std::min(a.y(), b.y()) <= p.y() && p.y() <= std::max(a.y(), b.y());
}

// Closed segments ab and cd share at least one point.
bool segmentsTouch(const Vec2& a, const Vec2& b, const Vec2& c, const Vec2& d) {
    const int o1 = orientation(a, b, c), o2 = orientation(a, b, d);
    const int o3 = orientation(c, d, a), o4 = orientation(c, d, b);
    if (o1 * o2 < 0 && o3 * o4 < 0) return true;
    return (o1 == 0 && withinBox(a, b, c)) || (o2 == 0 && withinBox(a, b, d)) ||
           (o3 == 0 && withinBox(c, d, a)) || (o4 == 0 && withinBox(c, d, b));
}

using Weights = std::array<double, 4>;

// Linear interpolation along edge (i, i+1) for a point on it. The parameter is measured from the
// lexicographically smaller end, so the two quads sharing an edge compute identical weights.
Weights edgeWeights(const std::array<Vec2, 4>& v, int i, const Vec2& p) {
    const int j = (i + 1) % 4;
    const bool swap = lexicographicLess(v[j], v[i]);
    const int first = swap ? j : i, second = swap ? i : j;
    const Vec2 edge = v[second] - v[first];
    const double length2 = edge.squaredNorm();
    double t = 0.0;
    if (length2 > 0.0) t = std::clamp((p - v[first]).dot(edge) / length2, 0.0, 1.0);
    Weights w{0.0, 0.0, 0.0, 0.0};
    w[first] += 1.0 - t;
    w[second] += t;
    return w;
}

bool allFinite(const Weights& w) {
    return std::all_of(w.begin(), w.end(), [](double x) { return std::isfinite(x); });
}

// Wachspress coordinates, eq. 8 and 9 of Bodonyi & Kunkli 2023, for a strictly convex quad whose
// corner turns have sign `sign` and a point strictly inside. Written as products of areas (no
// division by a vanishing area), so the weights stay bounded up to the boundary. Areas that
// rounding pushes below zero for a point a few ulps from an edge are clamped to that edge.
std::optional<Weights> wachspress(const std::array<Vec2, 4>& v, int sign, const Vec2& p) {
    std::array<double, 4> edge_area{};  // A(p, v_j, v_{j+1}), made positive by `sign`
    std::array<double, 4> corner_area{};
    for (int j = 0; j < 4; ++j) {
        const Vec2 dj = v[j] - p;
        const Vec2 dk = v[(j + 1) % 4] - p;
        edge_area[j] = std::max(0.0, sign * 0.5 * cross(dj, dk));
        const Vec2 in = v[j] - v[(j + 3) % 4];
        const Vec2 out = v[(j + 1) % 4] - v[j];
        corner_area[j] = std::max(0.0, sign * 0.5 * cross(in, out));
    }
    Weights w{};
    double total = 0.0;
    for (int i = 0; i < 4; ++i) {
        w[i] = corner_area[i] * edge_area[(i + 1) % 4] * edge_area[(i + 2) % 4];
        total += w[i];
    }
    if (!(total > 0.0) || !std::isfinite(total)) return std::nullopt;
    for (double& x : w) x /= total;
    if (!allFinite(w)) return std::nullopt;
    return w;
}

// Mean value coordinates (eq. 7; Floater 2003) for a simple quad and a point strictly inside.
// tan(alpha_i / 2) is taken as A / (r r' + D) while the edge subtends less than a right angle and
// as (r r' - D) / A beyond, where A and D are the cross and dot products of the corner vectors:
// each form divides by a quantity bounded away from zero in its range (Hormann & Floater 2006).
// A point so close to an edge that A drowns in rounding is treated as on it.
std::optional<Weights> meanValue(const std::array<Vec2, 4>& v, const Vec2& p) {
    std::array<Vec2, 4> d;
    std::array<double, 4> r{};
    for (int i = 0; i < 4; ++i) {
        d[i] = v[i] - p;
        r[i] = d[i].norm();
        if (!(r[i] > 0.0)) return std::nullopt;
    }
    std::array<double, 4> half_tan{};
    for (int i = 0; i < 4; ++i) {
        const int j = (i + 1) % 4;
        const double a = cross(d[i], d[j]);
        const double dot = d[i].dot(d[j]);
        const double rr = r[i] * r[j];
        if (dot >= 0.0) {
            half_tan[i] = a / (rr + dot);
        } else {
            if (std::abs(a) <= 1e-13 * rr) return edgeWeights(v, i, p);
            half_tan[i] = (rr - dot) / a;
        }
    }
    Weights w{};
    double total = 0.0;
    for (int i = 0; i < 4; ++i) {
        w[i] = (half_tan[(i + 3) % 4] + half_tan[i]) / r[i];
        total += w[i];
    }
    if (!(std::abs(total) > 0.0) || !std::isfinite(total)) return std::nullopt;
    for (double& x : w) x /= total;
    if (!allFinite(w)) return std::nullopt;
    return w;
}

// Ordinary barycentrics in the first non-degenerate corner triangle that holds p. The two fan
// triangles (0,1,2) and (0,2,3) cover every point of non-zero winding number of any quad; the
// other two only matter when rounding defeats both.
std::optional<Weights> triangleFallback(const std::array<Vec2, 4>& v, const Vec2& p) {
    static constexpr int kTriangles[4][3] = {{0, 1, 2}, {0, 2, 3}, {0, 1, 3}, {1, 2, 3}};
    for (const auto& tri : kTriangles) {
        const Vec2& a = v[tri[0]];
        const Vec2& b = v[tri[1]];
        const Vec2& c = v[tri[2]];
        const int o = orientation(a, b, c);
        if (o == 0) continue;
        if (orientation(a, b, p) * o < 0 || orientation(b, c, p) * o < 0 ||
            orientation(c, a, p) * o < 0)
            continue;
        // Sub-triangle areas around p, clamped: p is inside, so a negative one is rounding.
        const double la = std::max(0.0, o * cross(b - p, c - p));
        const double lb = std::max(0.0, o * cross(c - p, a - p));
        const double lc = std::max(0.0, o * cross(a - p, b - p));
        const double total = la + lb + lc;
        if (!(total > 0.0) || !std::isfinite(total)) continue;
        Weights w{0.0, 0.0, 0.0, 0.0};
        w[tri[0]] = la / total;
        w[tri[1]] = lb / total;
        w[tri[2]] = lc / total;
        return w;
    }
    return std::nullopt;
}

// The last resort when even the triangles fail to produce weights for a point inside: linear
// interpolation on the nearest edge. Always finite.
Weights nearestEdgeWeights(const std::array<Vec2, 4>& v, const Vec2& p) {
    int best = 0;
    double best_distance = std::numeric_limits<double>::infinity();
    for (int i = 0; i < 4; ++i) {
        const Vec2& a = v[i];
        const Vec2& b = v[(i + 1) % 4];
        const Vec2 edge = b - a;
        const double length2 = edge.squaredNorm();
        const double t = length2 > 0.0 ? std::clamp((p - a).dot(edge) / length2, 0.0, 1.0) : 0.0;
        const double distance = (a + t * edge - p).squaredNorm();
        if (distance < best_distance) {
            best_distance = distance;
            best = i;
        }
    }
    const Weights w = edgeWeights(v, best, p);
    return allFinite(w) ? w : Weights{0.25, 0.25, 0.25, 0.25};
}

enum class QuadKind { Convex, Simple, Degenerate };

QuadKind classify(const std::array<Vec2, 4>& v, int& convex_sign) {
    std::array<int, 4> turn{};
    for (int i = 0; i < 4; ++i) turn[i] = orientation(v[(i + 3) % 4], v[i], v[(i + 1) % 4]);
    if (turn[0] != 0 && turn[0] == turn[1] && turn[1] == turn[2] && turn[2] == turn[3]) {
        convex_sign = turn[0];
        return QuadKind::Convex;
    }
    for (int i = 0; i < 4; ++i)
        for (int j = i + 1; j < 4; ++j)
            if (v[i] == v[j]) return QuadKind::Degenerate;
    if (std::all_of(turn.begin(), turn.end(), [](int t) { return t == 0; }))
        return QuadKind::Degenerate;
    // Opposite edges that touch: a bow-tie, or a corner folded back onto the quad.
    if (segmentsTouch(v[0], v[1], v[2], v[3]) || segmentsTouch(v[1], v[2], v[3], v[0]))
        return QuadKind::Degenerate;
    return QuadKind::Simple;
}

}  // namespace

int orientation(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Eigen::Vector2d& c) {
    // Shewchuk's orient2d filter: with c as origin the rounded determinant differs from the exact
    // one by at most (3 + 16 eps) eps (|left| + |right|), eps = 2^-53.
    const double left = (a.x() - c.x()) * (b.y() - c.y());
    const double right = (a.y() - c.y()) * (b.x() - c.x());
    const double det = left - right;
    constexpr double kEps = std::numeric_limits<double>::epsilon() / 2.0;
    constexpr double kBound = (3.0 + 16.0 * kEps) * kEps;
    const double bound = kBound * (std::abs(left) + std::abs(right));
    if (det > bound) return 1;
    if (-det > bound) return -1;
    if (!std::isfinite(det)) return 0;
    return exactOrientation(a, b, c);
}

bool quadIsConvex(const Quad& quad) {
    std::array<Vec2, 4> v;
    for (int i = 0; i < 4; ++i) v[i] = quad.corners[i].position_px;
    int sign = 0;
    return classify(v, sign) == QuadKind::Convex;
}

std::optional<std::array<double, 4>> quadBarycentrics(const Quad& quad, const Eigen::Vector2d& p) {
    std::array<Vec2, 4> v;
    for (int i = 0; i < 4; ++i) {
        v[i] = quad.corners[i].position_px;
        if (!v[i].allFinite()) return std::nullopt;
    }
    if (!p.allFinite()) return std::nullopt;

    // Boundary and winding number (Sunday's crossing rule) from one exact orientation per edge.
    int winding = 0;
    for (int i = 0; i < 4; ++i) {
        const Vec2& a = v[i];
        const Vec2& b = v[(i + 1) % 4];
        const int side = orientation(a, b, p);
        if (side == 0 && withinBox(a, b, p)) return edgeWeights(v, i, p);
        if (a.y() <= p.y()) {
            if (b.y() > p.y() && side > 0) ++winding;
        } else if (b.y() <= p.y() && side < 0) {
            --winding;
        }
    }
    if (winding == 0) return std::nullopt;

    int sign = 0;
    const QuadKind kind = classify(v, sign);
    std::optional<Weights> w;
    if (kind == QuadKind::Convex) w = wachspress(v, sign, p);
    if (kind == QuadKind::Simple) w = meanValue(v, p);
    if (!w) w = triangleFallback(v, p);
    if (!w) w = nearestEdgeWeights(v, p);
    return w;
}

QuadSample interpolateQuad(const Quad& quad, const std::array<double, 4>& weights) {
    double throughput = 0.0, u = 0.0, v = 0.0, ratio = 0.0;
    for (int i = 0; i < 4; ++i) {
        throughput += weights[i] * quad.corners[i].throughput;
        u += weights[i] * quad.corners[i].stop_u;
        v += weights[i] * quad.corners[i].stop_v;
        ratio += weights[i] * quad.corners[i].aperture_ratio;
    }
    return QuadSample{static_cast<float>(throughput), static_cast<float>(u), static_cast<float>(v),
                      static_cast<float>(ratio)};
}

}  // namespace flarelab::render
