#include "render/ghost_shape.h"

#include <cstddef>
#include <limits>
#include <sstream>
#include <string>

#include "common/check.h"
#include "render/quad.h"

namespace flarelab::render {
namespace {

using Vec2 = Eigen::Vector2d;
using Cubic = std::array<Vec2, 4>;

constexpr double kInfinity = std::numeric_limits<double>::infinity();

[[gnu::always_inline]] inline Vec2 evalCubic(const Cubic& c, double t) {
    const double s = 1.0 - t;
    return (s * s * s) * c[0] + (3.0 * s * s * t) * c[1] + (3.0 * s * t * t) * c[2] +
           (t * t * t) * c[3];
}

[[gnu::always_inline]] inline Vec2 firstDerivative(const Cubic& c, double t) {
    const double s = 1.0 - t;
    return (3.0 * s * s) * (c[1] - c[0]) + (6.0 * s * t) * (c[2] - c[1]) +
           (3.0 * t * t) * (c[3] - c[2]);
}

[[gnu::always_inline]] inline Vec2 secondDerivative(const Cubic& c, double t) {
    return (6.0 * (1.0 - t)) * (c[2] - 2.0 * c[1] + c[0]) + (6.0 * t) * (c[3] - 2.0 * c[2] + c[1]);
}

// de Casteljau at t = 1/2: exact in binary floating point up to the halving's rounding.
void splitHalf(const Cubic& c, Cubic& left, Cubic& right) {
    const Vec2 p01 = 0.5 * (c[0] + c[1]);
    const Vec2 p12 = 0.5 * (c[1] + c[2]);
    const Vec2 p23 = 0.5 * (c[2] + c[3]);
    const Vec2 p012 = 0.5 * (p01 + p12);
    const Vec2 p123 = 0.5 * (p12 + p23);
    const Vec2 mid = 0.5 * (p012 + p123);
    left = {c[0], p01, p012, mid};
    right = {mid, p123, p23, c[3]};
}

struct Box {
    Vec2 lo;
    Vec2 hi;
};

Box controlBox(const Cubic& c) {
    Box b{c[0], c[0]};
    for (int i = 1; i < 4; ++i) {
        b.lo = b.lo.cwiseMin(c[i]);
        b.hi = b.hi.cwiseMax(c[i]);
    }
    return b;
}

double distanceToBox(const Box& b, const Vec2& q) {
    const double dx = std::max({b.lo.x() - q.x(), 0.0, q.x() - b.hi.x()});
    const double dy = std::max({b.lo.y() - q.y(), 0.0, q.y() - b.hi.y()});
    return std::hypot(dx, dy);
}

// The parameter in [0, 1] of the point of segment a-b closest to q; 0 for a zero-length segment.
double projectOnChord(const Vec2& a, const Vec2& b, const Vec2& q) {
    const Vec2 ab = b - a;
    const double len2 = ab.squaredNorm();
    if (!(len2 > 0.0)) return 0.0;
    return std::clamp((q - a).dot(ab) / len2, 0.0, 1.0);
}

// The largest distance of the inner control points from the chord segment c[0]-c[3]. The curve
// lies in the control points' convex hull, so within this distance of the chord; being connected
// from c[0] to c[3], it also comes within this distance of every chord point. Hence the curve's
// and the chord's distances to any point differ by at most this flatness.
double flatness(const Cubic& c) {
    double worst = 0.0;
    for (int i = 1; i <= 2; ++i) {
        const double u = projectOnChord(c[0], c[3], c[i]);
        const Vec2 on_chord = c[0] + u * (c[3] - c[0]);
        worst = std::max(worst, (c[i] - on_chord).norm());
    }
    return worst;
}

struct Piece {
    Cubic cubic;
    double t0 = 0.0;  // parameter range of the piece on its segment
    double t1 = 1.0;
    double lower = 0.0;  // lower bound on the distance from q to the piece
};

void consider(ClosestPoint& best, const BezierLoop& loop, int segment, double t, const Vec2& q) {
    const Vec2 p = loop.point(segment, t);
    const double d = (p - q).norm();
    if (d < best.distance_mm) best = ClosestPoint{d, segment, t, p};
}

bool isFinite(const Vec2& v) { return std::isfinite(v.x()) && std::isfinite(v.y()); }

// Sunday's winding rule for one chord a -> b (half-open in y, so a vertex shared by two chords
// is counted once), with the exact orientation predicate.
int chordWinding(const Vec2& a, const Vec2& b, const Vec2& q) {
    if (a.y() <= q.y()) {
        if (b.y() > q.y() && render::orientation(a, b, q) > 0) return 1;
    } else if (b.y() <= q.y() && render::orientation(a, b, q) < 0) {
        return -1;
    }
    return 0;
}

// Winding contribution of one cubic piece: a piece whose control box excludes q is replaced by
// its chord (curve and chord stay inside the same convex box without q, so one deforms into the
// other without crossing q); otherwise it is halved. Only pieces whose box holds q are halved,
// so the work grows with the depth, not exponentially, unless the curve passes through q.
int cubicWinding(const Cubic& c, const Vec2& q, int depth) {
    const Box b = controlBox(c);
    const bool excludes =
        q.x() < b.lo.x() || q.x() > b.hi.x() || q.y() < b.lo.y() || q.y() > b.hi.y();
    // A piece shrunk below about 1e-13 of its coordinates (or a segment of coincident points)
    // holds q on the curve to rounding: either answer is right, and halving it again is not.
    const double tiny = 1e-13 * (1.0 + q.cwiseAbs().maxCoeff());
    const bool point_like = (b.hi - b.lo).maxCoeff() <= tiny;
    if (excludes || point_like || depth >= 44) return chordWinding(c[0], c[3], q);
    Cubic left, right;
    splitHalf(c, left, right);
    return cubicWinding(left, q, depth + 1) + cubicWinding(right, q, depth + 1);
}

std::string formatDouble(double v) {
    std::ostringstream out;
    out.precision(17);
    out << v;
    return out.str();
}

Error paramError(const char* name, double value, const std::string& bound) {
    return makeError(ErrorCode::InvalidArgument, std::string("ghost shape parameter ") + name +
                                                     " = " + formatDouble(value) + " must be " +
                                                     bound);
}

}  // namespace

// ---------------------------------------------------------------------------
// BezierLoop
// ---------------------------------------------------------------------------

std::array<Vec2, 4> BezierLoop::segment(int i) const {
    const int n = static_cast<int>(control_points_mm.size());
    FLARELAB_DCHECK(i >= 0 && 3 * i + 2 < n);
    return {control_points_mm[3 * i], control_points_mm[3 * i + 1], control_points_mm[3 * i + 2],
            control_points_mm[(3 * i + 3) % n]};
}

Vec2 BezierLoop::point(int i, double t) const { return evalCubic(segment(i), t); }

Result<BezierLoop> bezierLoopFromVector(std::span<const double> values_mm) {
    if (values_mm.empty() || values_mm.size() % 6 != 0)
        return makeError(ErrorCode::InvalidArgument,
                         "Bézier loop vector has " + std::to_string(values_mm.size()) +
                             " values; it needs a positive multiple of 6 (3 points per segment)");
    BezierLoop loop;
    loop.control_points_mm.reserve(values_mm.size() / 2);
    for (std::size_t i = 0; i < values_mm.size(); i += 2) {
        for (std::size_t k = 0; k < 2; ++k) {
            if (!std::isfinite(values_mm[i + k]))
                return makeError(ErrorCode::InvalidArgument,
                                 "Bézier loop control point " + std::to_string(i / 2) + " " +
                                     (k == 0 ? "x" : "y") + " = " + formatDouble(values_mm[i + k]) +
                                     " is not finite");
        }
        loop.control_points_mm.emplace_back(values_mm[i], values_mm[i + 1]);
    }
    return loop;
}

std::vector<double> toVector(const BezierLoop& loop) {
    std::vector<double> out;
    out.reserve(2 * loop.control_points_mm.size());
    for (const Vec2& p : loop.control_points_mm) {
        out.push_back(p.x());
        out.push_back(p.y());
    }
    return out;
}

// ---------------------------------------------------------------------------
// Default shape
// ---------------------------------------------------------------------------

const char* ghostShapeParamName(int index) {
    static constexpr const char* kNames[kGhostShapeParamCount] = {
        "centre_x_mm",      "centre_y_mm",      "half_height_mm",    "left_mm",          "right_mm",
        "left_handle_x_mm", "left_handle_y_mm", "right_handle_x_mm", "right_handle_y_mm"};
    if (index < 0 || index >= kGhostShapeParamCount) return "?";
    return kNames[index];
}

GhostShapeVector toVector(const GhostShapeParams& p) {
    GhostShapeVector v;
    v << p.centre_x_mm, p.centre_y_mm, p.half_height_mm, p.left_mm, p.right_mm, p.left_handle_x_mm,
        p.left_handle_y_mm, p.right_handle_x_mm, p.right_handle_y_mm;
    return v;
}

Status validateGhostShape(const GhostShapeParams& p) {
    const GhostShapeVector v = toVector(p);
    for (int i = 0; i < kGhostShapeParamCount; ++i)
        if (!std::isfinite(v[i])) return paramError(ghostShapeParamName(i), v[i], "finite");
    for (int i : {2, 3, 4})
        if (!(v[i] > 0.0)) return paramError(ghostShapeParamName(i), v[i], "> 0");
    // Handles: each within [0, the extent it lies along].
    struct HandleBound {
        int handle;
        int extent;
    };
    for (const HandleBound hb :
         {HandleBound{5, 3}, HandleBound{6, 2}, HandleBound{7, 4}, HandleBound{8, 2}}) {
        const double value = v[hb.handle];
        if (!(value >= 0.0 && value <= v[hb.extent]))
            return paramError(ghostShapeParamName(hb.handle), value,
                              std::string("in [0, ") + ghostShapeParamName(hb.extent) + " = " +
                                  formatDouble(v[hb.extent]) + "]");
    }
    return Ok{};
}

Result<GhostShapeParams> ghostShapeFromVector(const Eigen::Ref<const GhostShapeVector>& v) {
    const GhostShapeParams p{v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]};
    const Status status = validateGhostShape(p);
    if (!status) return status.error();
    return p;
}

GhostShapeParams circleGhostShape(double centre_x_mm, double centre_y_mm, double radius_mm) {
    const double k = kCircleHandle * radius_mm;
    return GhostShapeParams{centre_x_mm, centre_y_mm, radius_mm, radius_mm, radius_mm, k, k, k, k};
}

BezierLoop toBezierLoop(const GhostShapeParams& params) {
    const GhostShapeVector v = toVector(params);
    const auto points = ghostShapeControlPoints<double>(v.data());
    BezierLoop loop;
    loop.control_points_mm.assign(points.begin(), points.end());
    return loop;
}

// ---------------------------------------------------------------------------
// Distance
// ---------------------------------------------------------------------------

ClosestPoint closestPointExact(const BezierLoop& loop, const Vec2& q, double tolerance_mm) {
    FLARELAB_CHECK_GT(tolerance_mm, 0.0);
    ClosestPoint best{kInfinity, 0, 0.0, q};
    if (!isFinite(q)) return best;
    const int n = loop.segmentCount();
    // Upper bound first: every segment's end points, so that pruning starts tight.
    for (int s = 0; s < n; ++s) {
        consider(best, loop, s, 0.0, q);
        consider(best, loop, s, 1.0, q);
    }
    std::vector<Piece> stack;
    stack.reserve(128);
    for (int s = 0; s < n; ++s) {
        const Cubic segment = loop.segment(s);
        stack.push_back(Piece{segment, 0.0, 1.0, 0.0});
        while (!stack.empty()) {
            const Piece piece = stack.back();
            stack.pop_back();
            // The best point may have improved since the piece was pushed.
            if (best.distance_mm - piece.lower <= tolerance_mm) continue;
            const Cubic& c = piece.cubic;
            const double flat = flatness(c);
            const double u = projectOnChord(c[0], c[3], q);
            const double chord_distance = (c[0] + u * (c[3] - c[0]) - q).norm();
            // The point of the piece at the chord projection's parameter: on the curve, so an
            // upper bound, and the piece's nearest point once the piece is flat.
            const double t_mid = piece.t0 + u * (piece.t1 - piece.t0);
            const Vec2 p_mid = evalCubic(segment, t_mid);
            const double d_mid = (p_mid - q).norm();
            if (d_mid < best.distance_mm) best = ClosestPoint{d_mid, s, t_mid, p_mid};
            const double lower = std::max(distanceToBox(controlBox(c), q), chord_distance - flat);
            // Done with the piece once it cannot beat the best point by more than the tolerance.
            // The width test stops pieces that rounding keeps from shrinking further.
            if (best.distance_mm - lower <= tolerance_mm || piece.t1 - piece.t0 < 1e-15) continue;
            Cubic left, right;
            splitHalf(c, left, right);
            const double t_half = 0.5 * (piece.t0 + piece.t1);
            Piece a{left, piece.t0, t_half, std::max(lower, distanceToBox(controlBox(left), q))};
            Piece b{right, t_half, piece.t1, std::max(lower, distanceToBox(controlBox(right), q))};
            // Visit the nearer half first so the bound tightens early.
            if (a.lower < b.lower) std::swap(a, b);
            stack.push_back(a);
            stack.push_back(b);
        }
    }
    return best;
}

bool fartherThan(const BezierLoop& loop, const Vec2& q, double bound_mm) {
    if (!isFinite(q) || !(bound_mm >= 0.0) || loop.segmentCount() == 0) return false;
    // Pieces whose lower bound reaches the bound are done; a curve point nearer than it ends the
    // search. Each segment's pieces are halved at most kDepth times (a 2^-kDepth share of the
    // segment), past which a piece still in doubt answers no.
    constexpr int kDepth = 12;
    struct Open {
        Cubic cubic;
        int depth;
    };
    Open stack[2 * kDepth + 2];
    for (int s = 0; s < loop.segmentCount(); ++s) {
        int top = 0;
        stack[top++] = Open{loop.segment(s), 0};
        while (top > 0) {
            const Open piece = stack[--top];
            const Cubic& c = piece.cubic;
            if (distanceToBox(controlBox(c), q) >= bound_mm) continue;
            if ((c[0] - q).norm() < bound_mm || (c[3] - q).norm() < bound_mm) return false;
            const double u = projectOnChord(c[0], c[3], q);
            if ((c[0] + u * (c[3] - c[0]) - q).norm() - flatness(c) >= bound_mm) continue;
            if (piece.depth == kDepth) return false;
            Cubic left, right;
            splitHalf(c, left, right);
            stack[top++] = Open{left, piece.depth + 1};
            stack[top++] = Open{right, piece.depth + 1};
        }
    }
    return true;
}

ClosestPoint closestPointFast(const BezierLoop& loop,
                              const Vec2& q,
                              const FastDistanceOptions& options) {
    FLARELAB_DCHECK(options.iterations >= 0 && options.seeds_per_segment >= 1);
    ClosestPoint best{kInfinity, 0, 0.0, q};
    if (!isFinite(q)) return best;
    const int n = loop.segmentCount();
    const int seeds = std::max(options.seeds_per_segment, 1);
    // A segment lies in its control polygon's box, so one whose box is farther than the best
    // point so far cannot improve it and is skipped. The segment whose box is nearest goes first
    // to set a small bound. The answer is the one the plain loop over all segments in order gives:
    // a tie goes to the lower segment, and the bound has a margin far above rounding.
    constexpr int kStackSegments = 16;
    double box_distance[kStackSegments];
    const bool cull = n <= kStackSegments;
    int first = 0;
    if (cull) {
        for (int s = 0; s < n; ++s) {
            const Cubic c = loop.segment(s);
            Vec2 lo = c[0], hi = c[0];
            for (int k = 1; k < 4; ++k) {
                lo = lo.cwiseMin(c[k]);
                hi = hi.cwiseMax(c[k]);
            }
            const Vec2 gap = (lo - q).cwiseMax(q - hi).cwiseMax(Vec2::Zero());
            box_distance[s] = gap.norm();
            if (box_distance[s] < box_distance[first]) first = s;
        }
    }
    const auto better = [&best](double d, int s) {
        return d < best.distance_mm || (d == best.distance_mm && s < best.segment);
    };
    for (int step = 0; step < n; ++step) {
        const int s = cull ? (step == 0 ? first : (step <= first ? step - 1 : step)) : step;
        if (cull && step > 0 && box_distance[s] > best.distance_mm * (1.0 + 1e-9) + 1e-300)
            continue;
        const Cubic c = loop.segment(s);
        for (const double t_end : {0.0, 1.0}) {
            const Vec2& p = t_end == 0.0 ? c[0] : c[3];
            const double d = (p - q).norm();
            if (better(d, s)) best = ClosestPoint{d, s, t_end, p};
        }
        for (int k = 0; k < seeds; ++k) {
            double t = (k + 0.5) / seeds;
            for (int it = 0; it < options.iterations; ++it) {
                const Vec2 r = evalCubic(c, t) - q;
                const Vec2 d1 = firstDerivative(c, t);
                const double g = r.dot(d1);          // half the derivative of |C(t) - q|^2
                const double gn = d1.squaredNorm();  // Gauss-Newton curvature, >= 0
                const double h = gn + r.dot(secondDerivative(c, t));
                // Newton where it heads for a minimum, Gauss-Newton (always downhill) elsewhere;
                // a stationary control polygon (zero derivative) leaves t where it is.
                const double curvature = h > 0.0 ? h : gn;
                if (!(curvature > 0.0)) break;
                const double next = std::clamp(t - g / curvature, 0.0, 1.0);
                if (next == t) break;
                t = next;
            }
            const Vec2 p = evalCubic(c, t);
            const double d = (p - q).norm();
            if (better(d, s)) best = ClosestPoint{d, s, t, p};
        }
    }
    return best;
}

int windingNumber(const BezierLoop& loop, const Vec2& q) {
    if (!isFinite(q)) return 0;
    int winding = 0;
    for (int s = 0; s < loop.segmentCount(); ++s) winding += cubicWinding(loop.segment(s), q, 0);
    return winding;
}

double signedDistanceExact(const BezierLoop& loop, const Vec2& q, double tolerance_mm) {
    const double d = closestPointExact(loop, q, tolerance_mm).distance_mm;
    return windingNumber(loop, q) != 0 ? -d : d;
}

double signedDistanceFast(const BezierLoop& loop,
                          const Vec2& q,
                          const FastDistanceOptions& options) {
    const double d = closestPointFast(loop, q, options).distance_mm;
    return windingNumber(loop, q) != 0 ? -d : d;
}

// ---------------------------------------------------------------------------
// Intensity
// ---------------------------------------------------------------------------

Status validateShading(const GhostShading& s) {
    const auto bad = [](const std::string& field, double value, const char* bound) {
        return Status(makeError(
            ErrorCode::InvalidArgument,
            "ghost shading " + field + " = " + formatDouble(value) + " must be " + bound));
    };
    for (int c = 0; c < 3; ++c) {
        if (!(std::isfinite(s.border_rgb[c]) && s.border_rgb[c] >= 0.0))
            return bad("border_rgb[" + std::to_string(c) + "]", s.border_rgb[c], "finite and >= 0");
        if (!(std::isfinite(s.inner_rgb[c]) && s.inner_rgb[c] >= 0.0))
            return bad("inner_rgb[" + std::to_string(c) + "]", s.inner_rgb[c], "finite and >= 0");
    }
    const std::pair<const char*, double> positive[] = {{"inner_falloff_mm", s.inner_falloff_mm},
                                                       {"outer_falloff_mm", s.outer_falloff_mm},
                                                       {"inner_exponent", s.inner_exponent},
                                                       {"outer_exponent", s.outer_exponent}};
    for (const auto& [name, value] : positive)
        if (!(std::isfinite(value) && value > 0.0)) return bad(name, value, "finite and > 0");
    return Ok{};
}

std::array<double, 3> shadeAtDistance(const GhostShading& s, double signed_distance_mm) {
    std::array<double, 3> out{};
    for (int c = 0; c < 3; ++c)
        out[c] = transferIntensity(signed_distance_mm, s.border_rgb[c], s.inner_rgb[c],
                                   s.inner_falloff_mm, s.outer_falloff_mm, s.inner_exponent,
                                   s.outer_exponent);
    return out;
}

std::array<double, 3> shadeGhost(const BezierLoop& loop,
                                 const GhostShading& shading,
                                 const Vec2& q_mm,
                                 const FastDistanceOptions& options) {
    return shadeAtDistance(shading, signedDistanceFast(loop, q_mm, options));
}

Vec2 blockSpread(const Vec2& centre_mm, const ClosestPoint& closest, const Vec2& half_size_mm) {
    if (!(closest.distance_mm > 1e-12) || !std::isfinite(closest.distance_mm))
        return half_size_mm * std::sqrt(0.5);
    const Vec2 u = (centre_mm - closest.point_mm) / closest.distance_mm;
    return {half_size_mm.x() * std::abs(u.x()), half_size_mm.y() * std::abs(u.y())};
}

BlockDistance blockDistance(const BezierLoop& loop,
                            const Vec2& centre_mm,
                            const Vec2& half_size_mm,
                            const FastDistanceOptions& options) {
    const ClosestPoint cp = closestPointFast(loop, centre_mm, options);
    const double sign = windingNumber(loop, centre_mm) != 0 ? -1.0 : 1.0;
    const Vec2 spread = blockSpread(centre_mm, cp, half_size_mm);
    return {sign * cp.distance_mm, spread.x(), spread.y()};
}

std::array<double, 3> shadeGhostBlock(const BezierLoop& loop,
                                      const GhostShading& shading,
                                      const Vec2& centre_mm,
                                      const Vec2& half_size_mm,
                                      const FastDistanceOptions& options) {
    const BlockDistance b = blockDistance(loop, centre_mm, half_size_mm, options);
    const auto w = boxTransferWeights<double>(b.distance_mm, b.spread_x_mm, b.spread_y_mm,
                                              shading.inner_falloff_mm, shading.outer_falloff_mm,
                                              shading.inner_exponent, shading.outer_exponent);
    std::array<double, 3> out{};
    for (int c = 0; c < 3; ++c)
        out[static_cast<size_t>(c)] = shading.border_rgb[static_cast<size_t>(c)] * w.border +
                                      shading.inner_rgb[static_cast<size_t>(c)] * w.inner;
    return out;
}

}  // namespace flarelab::render
