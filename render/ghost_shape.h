// ============================================================================
//  flarelab render: BezierLoop, GhostShapeParams, signed distance, GhostShading
// ============================================================================
//
// The shape and shading of one model ghost (chapter 6.3 of the thesis).
//
// Shape. A ghost's border is a closed loop of cubic Bézier segments (eq. 6.1 of the thesis) in
// sensor millimetres. The default model has four segments: the left and right halves of the
// ghost meet at a common top and bottom point (height h above and below the centre M), each half
// reaches out to its own extent (L, R), and each half's curvature is set by one axis-aligned
// control offset C = (C.x, C.y): the handle at the top and bottom points is horizontal and C.x
// long, the handle at the half's extreme point is vertical and C.y long. Handles at a joint are
// collinear, so the loop is G^1 (C^1 where the handle lengths match) as §6.3.1 asks. With
// L = R = h = r and C = (k r, k r), k = 0.5519..., the loop is the usual four-arc approximation
// of a circle of radius r. Any other closed loop (more segments, e.g. for polygonal apertures)
// is a BezierLoop built from its control points.
//
// Distance. signedDistance* is the Euclidean distance from a point to the loop, NEGATIVE INSIDE
// and positive outside (the thesis writes it the other way round; see transferIntensity). Inside
// means a non-zero winding number, decided with an exact orientation predicate on a chord
// polygon that provably winds around the point as the curve does, so it is robust at joints and
// corners, where the tangent test of eq. 6.3 is not. Two ways to the unsigned distance:
//   - closestPointExact: branch and bound over de Casteljau halves. A piece's lower bound is the
//     larger of its control box's distance and its chord's distance less its flatness; a piece
//     is dropped once that bound is within the tolerance (1e-9 mm by default) of the best point
//     found on the curve so far. The reference.
//   - closestPointFast: a fixed number of Newton steps on (C(t) - Q) . C'(t) = 0 from a few
//     seeds per segment, what a renderer evaluates per pixel; bench/bezier_distance_bench.cpp
//     measures its error against the reference.
// Degenerate segments (collinear or coincident control points, zero length) give finite
// results; no input of finite control points and a finite query yields NaN.
//
// Shading. transferIntensity is eq. 6.4 of the thesis: the border intensity I_b fades to the
// inner intensity I_i inside over F_i with exponent E_i, and to zero outside over F_o with
// exponent E_o, per colour channel.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>
#include <span>
#include <utility>
#include <vector>

#include "common/result.h"

namespace flarelab::render {

// ---------------------------------------------------------------------------
// A closed loop of cubic Bézier segments
// ---------------------------------------------------------------------------

// 3N control points for N segments: segment i runs through points 3i, 3i+1, 3i+2 and 3i+3, the
// last index taken modulo 3N, so the loop closes on point 0. Points 3i are on the curve.
struct BezierLoop {
    std::vector<Eigen::Vector2d> control_points_mm;

    int segmentCount() const { return static_cast<int>(control_points_mm.size() / 3); }
    // The four control points of segment i, 0 <= i < segmentCount().
    std::array<Eigen::Vector2d, 4> segment(int i) const;
    // The point of segment i at t in [0, 1] (eq. 6.1 of the thesis).
    Eigen::Vector2d point(int i, double t) const;
};

// The parameter vector form of a general loop, for optimizers: x0, y0, x1, y1, ... of the 3N
// control points (6N values). Errors: a length that is not a positive multiple of 6, or a
// non-finite value (named by index and coordinate). No simplicity is checked or implied.
Result<BezierLoop> bezierLoopFromVector(std::span<const double> values_mm);
std::vector<double> toVector(const BezierLoop& loop);

// ---------------------------------------------------------------------------
// The default four-segment ghost shape (§6.3.1 of the thesis)
// ---------------------------------------------------------------------------

// Bounds, checked by validateGhostShape:
//   all finite; half_height_mm, left_mm, right_mm > 0;
//   0 <= left_handle_x_mm <= left_mm,  0 <= left_handle_y_mm <= half_height_mm,
//   0 <= right_handle_x_mm <= right_mm, 0 <= right_handle_y_mm <= half_height_mm.
// Guarantee inside these bounds: every segment's control polygon is monotone in x and y, so the
// segment is strictly monotone in both and stays in its own quadrant around the centre, touching
// the axes only at its end points. The loop is therefore simple (no self-intersections), passes
// through the four points (M.x, M.y +- h), (M.x - L, M.y), (M.x + R, M.y), and its interior is
// orthogonally convex (every horizontal or vertical line meets it in one interval). A handle of
// 0 gives a corner; handles equal to the extents give a rectangle-like rounded shape.
struct GhostShapeParams {
    double centre_x_mm = 0.0;                       // M_x
    double centre_y_mm = 0.0;                       // M_y
    double half_height_mm = 1.0;                    // h: the halves meet at M.y - h and M.y + h
    double left_mm = 1.0;                           // L: extent of the left half from the centre
    double right_mm = 1.0;                          // R: extent of the right half
    double left_handle_x_mm = 0.5519150244935106;   // C_l.x: horizontal handle at top and bottom
    double left_handle_y_mm = 0.5519150244935106;   // C_l.y: vertical handle at the left extreme
    double right_handle_x_mm = 0.5519150244935106;  // C_r.x
    double right_handle_y_mm = 0.5519150244935106;  // C_r.y
    bool operator==(const GhostShapeParams&) const = default;
};

// The handle length, as a fraction of the radius, of the four-arc circle with the smallest
// radial error (about 2e-4 of the radius; spencermortensen.com/articles/bezier-circle, cited as
// [2] in the thesis).
inline constexpr double kCircleHandle = 0.5519150244935106;

// Indices of the parameter vector, in the order of the struct's fields.
inline constexpr int kGhostShapeParamCount = 9;
using GhostShapeVector = Eigen::Matrix<double, kGhostShapeParamCount, 1>;
// The field name of parameter `index` ("left_handle_x_mm"), or "?" out of range.
const char* ghostShapeParamName(int index);

GhostShapeVector toVector(const GhostShapeParams& params);
// Validates the bounds above; the error names the parameter, its value and the violated bound.
Result<GhostShapeParams> ghostShapeFromVector(const Eigen::Ref<const GhostShapeVector>& values);
Status validateGhostShape(const GhostShapeParams& params);

// The circle of the given radius (> 0) around (x, y), as the default shape.
GhostShapeParams circleGhostShape(double centre_x_mm, double centre_y_mm, double radius_mm);

// The 12 control points of the default shape from its parameter vector (in field order),
// templated so a Ceres Jet can pass through. Segments run top -> left -> bottom -> right -> top
// (with y down, the image convention, that is counter-clockwise on screen). Not validated: out
// of bounds the loop may self-intersect.
template <typename T>
std::array<Eigen::Matrix<T, 2, 1>, 12> ghostShapeControlPoints(const T* params) {
    using V = Eigen::Matrix<T, 2, 1>;
    const T& mx = params[0];
    const T& my = params[1];
    const T& h = params[2];
    const T& l = params[3];
    const T& r = params[4];
    const T& lx = params[5];
    const T& ly = params[6];
    const T& rx = params[7];
    const T& ry = params[8];
    return {
        V(mx, my - h), V(mx - lx, my - h), V(mx - l, my - ly),  // top -> left
        V(mx - l, my), V(mx - l, my + ly), V(mx - lx, my + h),  // left -> bottom
        V(mx, my + h), V(mx + rx, my + h), V(mx + r, my + ry),  // bottom -> right
        V(mx + r, my), V(mx + r, my - ry), V(mx + rx, my - h),  // right -> top
    };
}

// The loop of a shape (not validated; see ghostShapeControlPoints).
BezierLoop toBezierLoop(const GhostShapeParams& params);

// ---------------------------------------------------------------------------
// Distance
// ---------------------------------------------------------------------------

struct ClosestPoint {
    double distance_mm = 0.0;  // unsigned, >= 0
    int segment = 0;           // which segment holds the closest point found
    double t = 0.0;            // its parameter on that segment, in [0, 1]
    Eigen::Vector2d point_mm = Eigen::Vector2d::Zero();
};

// The closest point of the loop to q within tolerance_mm (> 0): the returned distance is the
// distance to a point on the curve and exceeds the true minimum by at most tolerance_mm (plus
// rounding). A loop without segments or a non-finite q gives distance +infinity.
ClosestPoint closestPointExact(const BezierLoop& loop,
                               const Eigen::Vector2d& q,
                               double tolerance_mm = 1e-9);

// Whether every point of the loop lies at least bound_mm from q, proven from the control points
// (de Casteljau halves, each bounded by its control box and its chord less its flatness): true
// is a certainty; false means a point nearer was found or no proof came within 12 halvings per
// segment. Far cheaper than a closest point when the bound is well below the distance. False for
// a non-finite q, a negative or NaN bound, or a loop without segments.
bool fartherThan(const BezierLoop& loop, const Eigen::Vector2d& q, double bound_mm);

struct FastDistanceOptions {
    int iterations = 4;         // Newton steps per seed, >= 0
    int seeds_per_segment = 4;  // seeds at t = (k + 1/2) / seeds, >= 1; end points always tried
};

// The closest point found by Newton's method on (C(t) - Q) . C'(t) = 0, clamped to [0, 1],
// falling back to a Gauss-Newton step where the second derivative would make the step uphill.
// Always a point on the curve, so never below the true distance. Same misses as the exact one.
ClosestPoint closestPointFast(const BezierLoop& loop,
                              const Eigen::Vector2d& q,
                              const FastDistanceOptions& options = {});

// The winding number of the loop around q (0 outside; +-1 inside a simple loop, the sign
// following the loop's direction). Correct for points farther than about 1e-13 (1 + |q|) mm from
// the curve (the chord polygon it counts on comes from rounded subdivision); nearer, it may be
// either value, which the distance, zero to that precision, makes harmless. Non-finite q gives 0.
int windingNumber(const BezierLoop& loop, const Eigen::Vector2d& q);

// Signed distances: negative where windingNumber != 0 (inside), positive outside.
double signedDistanceExact(const BezierLoop& loop,
                           const Eigen::Vector2d& q,
                           double tolerance_mm = 1e-9);
double signedDistanceFast(const BezierLoop& loop,
                          const Eigen::Vector2d& q,
                          const FastDistanceOptions& options = {});

// ---------------------------------------------------------------------------
// Intensity (§6.3.2 of the thesis)
// ---------------------------------------------------------------------------

// The intensity transfer function, eq. 6.4 of the thesis, on this file's sign convention
// (negative inside): with S = |d| / F,
//   inside  (d < 0): I = lerp(I_b, I_i, clamp(S^E_i, 0, 1)), F = F_i;
//   outside (d > 0): I = lerp(I_b, 0,   clamp(S^E_o, 0, 1)), F = F_o;
//   on the border (d = 0): I = I_b.
// The thesis sets S = 1 at d = 0, which would give I_i on the border and contradict its own
// figure 6.3 (the border is the brightest); we take the limit S -> 0 so that I is continuous.
// Falloffs and exponents must be > 0 (validateShading); d = 0 is returned before any pow, so no
// derivative of 0^E is taken.
template <typename T>
T transferIntensity(const T& signed_distance_mm,
                    const T& border,
                    const T& inner,
                    const T& inner_falloff_mm,
                    const T& outer_falloff_mm,
                    const T& inner_exponent,
                    const T& outer_exponent) {
    using std::abs, std::pow;
    if (signed_distance_mm == T(0.0)) return border;
    const bool inside = signed_distance_mm < T(0.0);
    const T s = abs(signed_distance_mm) / (inside ? inner_falloff_mm : outer_falloff_mm);
    T w = pow(s, inside ? inner_exponent : outer_exponent);
    if (w > T(1.0)) w = T(1.0);
    const T target = inside ? inner : T(0.0);
    return border + (target - border) * w;
}

// Eq. 6.4 as weights on the two intensities: I = I_b * border + I_i * inner.
template <typename T>
struct TransferWeights {
    T border;
    T inner;
};

namespace detail {

// The first (F) and second (G) antiderivatives of eq. 6.4's weights in d, both zero at d = 0:
// F' = w, G' = F. Outside, with s = d / F_o < 1: F = d - F_o s^(E+1) / (E+1) and
// G = d^2 / 2 - F_o^2 s^(E+2) / ((E+1)(E+2)) on the border weight, then linear (F) and
// quadratic (G) continuations where w is constant; inside likewise with F_i, E_i, mirrored.
template <typename T>
void transferAntiderivatives(const T& d,
                             const T& inner_falloff_mm,
                             const T& outer_falloff_mm,
                             const T& inner_exponent,
                             const T& outer_exponent,
                             TransferWeights<T>& first,
                             TransferWeights<T>& second) {
    using std::pow;
    if (d == T(0.0)) {  // F = d, G = d^2 / 2 on the border weight (carries d's derivatives)
        first = {d, T(0.0)};
        second = {T(0.5) * d * d, T(0.0)};
        return;
    }
    if (d > T(0.0)) {
        const T& f = outer_falloff_mm;
        const T e1 = outer_exponent + T(1.0), e2 = outer_exponent + T(2.0);
        if (d < f) {
            const T s = d / f;
            const T p1 = pow(s, e1);
            first = {d - f * p1 / e1, T(0.0)};
            second = {T(0.5) * d * d - f * f * p1 * s / (e1 * e2), T(0.0)};
        } else {
            const T f_end = f * outer_exponent / e1;
            first = {f_end, T(0.0)};
            second = {T(0.5) * f * f - f * f / (e1 * e2) + f_end * (d - f), T(0.0)};
        }
        return;
    }
    // Inside: y = -d; H(y) = integral of w over [-y, 0], F(d) = -H(y), G(d) = integral of H.
    const T y = -d;
    const T& f = inner_falloff_mm;
    const T e1 = inner_exponent + T(1.0), e2 = inner_exponent + T(2.0);
    TransferWeights<T> h, g;
    if (y < f) {
        const T s = y / f;
        const T power = pow(s, e1);
        const T p1 = f * power / e1, p2 = f * f * power * s / (e1 * e2);
        h = {y - p1, p1};
        g = {T(0.5) * y * y - p2, p2};
    } else {
        const T k = f * f / (e1 * e2), r = y - f;
        const TransferWeights<T> h_end = {f * inner_exponent / e1, f / e1};
        h = {h_end.border, h_end.inner + r};
        g = {T(0.5) * f * f - k + h_end.border * r, k + h_end.inner * r + T(0.5) * r * r};
    }
    first = {-h.border, -h.inner};
    second = g;
}

}  // namespace detail

// Eq. 6.4's weights averaged over a rectangle of pixels around the point at signed distance d,
// in the linear approximation of the distance across it (a straight edge): the distance over the
// rectangle is d + u, u the sum of two uniform variables on [-a, a] and [-c, c], where a and c
// (>= 0, mm) are the rectangle's half width and height times the distance gradient's |x| and
// |y| components. This is what a pixel, or a block mean of pixels, records of a ghost whose
// edges are sharper than it: the point value at the block's centre would be a blur the model
// then learns as a wide falloff. Exact for the convolution of two boxes:
//   (G(d+a+c) - G(d+a-c) - G(d-a+c) + G(d-a-c)) / (4ac);   c -> 0: (F(d+a) - F(d-a)) / 2a;
// a, c -> 0: eq. 6.4 itself. Constant regions short-cut, so no rounding of the differences
// enters far from the edge.
template <typename T>
TransferWeights<T> boxTransferWeights(const T& d,
                                      double a,
                                      double c,
                                      const T& inner_falloff_mm,
                                      const T& outer_falloff_mm,
                                      const T& inner_exponent,
                                      const T& outer_exponent) {
    if (a < c) std::swap(a, c);
    const double reach = a + c;
    if (d - T(reach) >= outer_falloff_mm) return {T(0.0), T(0.0)};
    if (d + T(reach) <= -inner_falloff_mm) return {T(0.0), T(1.0)};
    if (a <= 1e-9) {
        const T w_border = transferIntensity<T>(d, T(1.0), T(0.0), inner_falloff_mm,
                                                outer_falloff_mm, inner_exponent, outer_exponent);
        const T w_inner = transferIntensity<T>(d, T(0.0), T(1.0), inner_falloff_mm,
                                               outer_falloff_mm, inner_exponent, outer_exponent);
        return {w_border, w_inner};
    }
    TransferWeights<T> f[4], g[4];
    const auto at = [&](int k, const T& x) {
        detail::transferAntiderivatives<T>(x, inner_falloff_mm, outer_falloff_mm, inner_exponent,
                                           outer_exponent, f[k], g[k]);
    };
    if (c <= 1e-3 * a) {
        at(0, d + T(a));
        at(1, d - T(a));
        const double scale = 0.5 / a;
        return {(f[0].border - f[1].border) * scale, (f[0].inner - f[1].inner) * scale};
    }
    at(0, d + T(a + c));
    at(1, d + T(a - c));
    at(2, d - T(a - c));
    at(3, d - T(a + c));
    const double scale = 0.25 / (a * c);
    return {(g[0].border - g[1].border - g[2].border + g[3].border) * scale,
            (g[0].inner - g[1].inner - g[2].inner + g[3].inner) * scale};
}

struct GhostShading {
    std::array<double, 3> border_rgb = {1.0, 1.0, 1.0};  // I_b per channel, >= 0
    std::array<double, 3> inner_rgb = {0.0, 0.0, 0.0};   // I_i per channel, >= 0
    double inner_falloff_mm = 1.0;                       // F_i > 0
    double outer_falloff_mm = 1.0;                       // F_o > 0
    double inner_exponent = 1.0;                         // E_i > 0
    double outer_exponent = 1.0;                         // E_o > 0
    bool operator==(const GhostShading&) const = default;
};

// Errors name the field ("inner_rgb[1]") and the violated bound.
Status validateShading(const GhostShading& shading);

// The ghost's peak: its largest border or inner value over the channels (0 for none above 0).
inline double shadingPeak(const GhostShading& shading) {
    double peak = 0.0;
    for (size_t c = 0; c < 3; ++c)
        peak = std::max({peak, shading.border_rgb[c], shading.inner_rgb[c]});
    return peak;
}

// The RGB value at a given signed distance (eq. 6.4 per channel).
std::array<double, 3> shadeAtDistance(const GhostShading& shading, double signed_distance_mm);

// The RGB value of the ghost at point q: the fast signed distance, then eq. 6.4.
std::array<double, 3> shadeGhost(const BezierLoop& loop,
                                 const GhostShading& shading,
                                 const Eigen::Vector2d& q_mm,
                                 const FastDistanceOptions& options = {});

// A rectangle of the sensor (a pixel, or a block of pixels a fit samples) seen from a loop: the
// signed distance at its centre and the half spreads of the distance across it along x and y
// (boxTransferWeights' a and c): the half size times the distance gradient's components, the
// gradient being the unit vector from the closest curve point (on the curve, where it is
// undefined, the diagonal's).
struct BlockDistance {
    double distance_mm = 0.0;
    double spread_x_mm = 0.0;
    double spread_y_mm = 0.0;
};
Eigen::Vector2d blockSpread(const Eigen::Vector2d& centre_mm,
                            const ClosestPoint& closest,
                            const Eigen::Vector2d& half_size_mm);
BlockDistance blockDistance(const BezierLoop& loop,
                            const Eigen::Vector2d& centre_mm,
                            const Eigen::Vector2d& half_size_mm,
                            const FastDistanceOptions& options = {});

// The ghost's mean RGB value over the rectangle centred on q with half size `half_size_mm`
// (boxTransferWeights): what a pixel, which integrates the light over its area, records.
std::array<double, 3> shadeGhostBlock(const BezierLoop& loop,
                                      const GhostShading& shading,
                                      const Eigen::Vector2d& centre_mm,
                                      const Eigen::Vector2d& half_size_mm,
                                      const FastDistanceOptions& options = {});

}  // namespace flarelab::render
