#include "render/model_ghost.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <optional>
#include <utility>

#include "common/cpu.h"

#if defined(__x86_64__)
#include <immintrin.h>
#endif

namespace flarelab::render {
namespace {

using Vec2 = Eigen::Vector2d;
using Cubic = std::array<Vec2, 4>;

constexpr int kChunkChords = 8;

// The squared distances of the point (qx, qy) to chords a + t e, t in [0, 1], given relative to
// one origin in single precision (addGhostBlock's candidates), and the smallest of them. n is a
// multiple of kLanes (the candidates are padded with chords far away), so the loop runs in whole
// vectors; plain selects, not std::clamp or std::min (whose NaN order keeps them scalar): one
// SIMD lane per chord. AVX2 where the processor has it, chosen at run time like the row
// tracer's kernels; both give the same bits (no fused multiply-adds: -ffp-contract=off).
constexpr size_t kLanes = 8;
struct ChordArrays {
    const float* ax;
    const float* ay;
    const float* ex;
    const float* ey;
    const float* inv;  // 1 / |e|^2, or 0 for a chord of no length
};
using Float8 = float __attribute__((vector_size(32)));  // GCC's and Clang's vector extension
[[gnu::always_inline]] inline float chordDistances(
    const ChordArrays& c, size_t n, float qx, float qy, float* __restrict d2) {
    const Float8 zero = {}, one = zero + 1.0f;
    const Float8 x = zero + qx, y = zero + qy;
    Float8 lowest = zero + std::numeric_limits<float>::max();
    for (size_t k = 0; k < n; k += kLanes) {
        Float8 ax, ay, ex, ey, inv;
        __builtin_memcpy(&ax, c.ax + k, sizeof ax);
        __builtin_memcpy(&ay, c.ay + k, sizeof ay);
        __builtin_memcpy(&ex, c.ex + k, sizeof ex);
        __builtin_memcpy(&ey, c.ey + k, sizeof ey);
        __builtin_memcpy(&inv, c.inv + k, sizeof inv);
        const Float8 px = x - ax, py = y - ay;
        Float8 t = (px * ex + py * ey) * inv;
        t = t > zero ? t : zero;
        t = t < one ? t : one;
        const Float8 dx = px - t * ex, dy = py - t * ey;
        const Float8 v = dx * dx + dy * dy;
        __builtin_memcpy(d2 + k, &v, sizeof v);
        lowest = v < lowest ? v : lowest;
    }
    float m = lowest[0];
    for (size_t j = 1; j < kLanes; ++j) m = lowest[j] < m ? lowest[j] : m;
    return m;
}
using ChordKernel = float (*)(const ChordArrays&, size_t, float, float, float*);
float chordDistancesSse2(const ChordArrays& c, size_t n, float qx, float qy, float* d2) {
    return chordDistances(c, n, qx, qy, d2);
}
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
[[gnu::target("avx2")]] float chordDistancesAvx2(
    const ChordArrays& c, size_t n, float qx, float qy, float* d2) {
    return chordDistances(c, n, qx, qy, d2);
}
#endif
ChordKernel chordKernel() {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    return processorHasAvx2() ? &chordDistancesAvx2 : &chordDistancesSse2;
#else
    return &chordDistancesSse2;
#endif
}
// Past these the fast evaluation is not worth its memory (a pathological loop); the ghost is
// drawn exactly instead.
constexpr size_t kMaxChords = size_t{1} << 22;
constexpr size_t kMaxCrossings = size_t{1} << 26;
constexpr int kMaxDepth = 48;

// The largest distance of the inner control points from the chord c[0]-c[3]: the curve lies in
// their convex hull and runs from c[0] to c[3], so curve and chord are within this of each other
// (ghost_shape.cpp uses the same bound).
double flatness(const Cubic& c) {
    const Vec2 e = c[3] - c[0];
    const double len2 = e.squaredNorm();
    double worst = 0.0;
    for (int i = 1; i <= 2; ++i) {
        const double t = len2 > 0.0 ? std::clamp((c[i] - c[0]).dot(e) / len2, 0.0, 1.0) : 0.0;
        worst = std::max(worst, (c[i] - (c[0] + t * e)).norm());
    }
    return worst;
}

double boxGap(const Vec2& lo_a, const Vec2& hi_a, const Vec2& lo_b, const Vec2& hi_b) {
    const double dx = std::max({lo_a.x() - hi_b.x(), lo_b.x() - hi_a.x(), 0.0});
    const double dy = std::max({lo_a.y() - hi_b.y(), lo_b.y() - hi_a.y(), 0.0});
    return std::hypot(dx, dy);
}

struct Flattener {
    double tolerance_mm;
    Vec2 region_lo, region_hi;  // the image's pixel centres, mm
    double margin_mm;           // pieces farther than this from the region need no detail
    GhostOutline* out;
    bool overflow = false;

    // Appends the end points of the chords that replace c (its start is already there). A piece
    // far from the image is one chord whatever its flatness: curve and chord lie in the same box,
    // which holds no pixel centre, so the winding number of every pixel is the same for both, and
    // both are farther from every pixel than any falloff reaches.
    void run(const Cubic& c, int depth, int32_t segment, double t0, double t1) {
        if (overflow) return;
        Vec2 lo = c[0], hi = c[0];
        for (int i = 1; i < 4; ++i) {
            lo = lo.cwiseMin(c[i]);
            hi = hi.cwiseMax(c[i]);
        }
        const bool far = boxGap(lo, hi, region_lo, region_hi) > margin_mm;
        if (far || depth >= kMaxDepth || flatness(c) <= tolerance_mm) {
            out->vertices_mm.push_back(c[3]);
            out->chord_segment.push_back(segment);
            out->chord_t.push_back({t0, t1});
            if (out->vertices_mm.size() > kMaxChords) overflow = true;
            return;
        }
        const Vec2 p01 = 0.5 * (c[0] + c[1]), p12 = 0.5 * (c[1] + c[2]), p23 = 0.5 * (c[2] + c[3]);
        const Vec2 p012 = 0.5 * (p01 + p12), p123 = 0.5 * (p12 + p23);
        const Vec2 mid = 0.5 * (p012 + p123);
        const double t_mid = 0.5 * (t0 + t1);
        run({c[0], p01, p012, mid}, depth + 1, segment, t0, t_mid);
        run({mid, p123, p23, c[3]}, depth + 1, segment, t_mid, t1);
    }
};

// The spans of each pixel row of y0..y1 where the polyline winds around the pixel centre. A chord
// crosses the row y + 0.5 when it lies in [min y, max y) of the chord (half-open, so a shared
// vertex counts once), upward (+1) or downward (-1); the winding number of a point is the sum over
// the crossings to its right, so left of all crossings it is 0 and between crossings k and k + 1
// (sorted by x) it is minus the sum over crossings 0..k.
bool buildSpans(GhostOutline& o, const SensorToImage& m, int64_t y0, int64_t y1) {
    const int64_t rows = y1 - y0 + 1;
    const size_t n = o.vertices_mm.size() - 1;
    std::vector<Vec2> px(o.vertices_mm.size());
    for (size_t i = 0; i < px.size(); ++i)
        px[i] = m.toPixels(o.vertices_mm[i].x(), o.vertices_mm[i].y());
    const auto rowsOf = [&](const Vec2& a, const Vec2& b) {
        const double lo = std::min(a.y(), b.y()), hi = std::max(a.y(), b.y());
        const int64_t first = std::max<int64_t>(y0, static_cast<int64_t>(std::ceil(lo - 0.5)));
        const int64_t last = std::min<int64_t>(y1, static_cast<int64_t>(std::ceil(hi - 0.5)) - 1);
        return std::pair{first, last};
    };
    std::vector<int64_t> count(static_cast<size_t>(rows) + 1, 0);
    size_t total = 0;
    for (size_t i = 0; i < n; ++i) {
        if (px[i].y() == px[i + 1].y()) continue;
        const auto [first, last] = rowsOf(px[i], px[i + 1]);
        for (int64_t y = first; y <= last; ++y) ++count[static_cast<size_t>(y - y0 + 1)];
        if (last >= first) total += static_cast<size_t>(last - first + 1);
        if (total > kMaxCrossings) return false;
    }
    for (size_t r = 1; r < count.size(); ++r) count[r] += count[r - 1];
    std::vector<std::pair<double, int>> crossings(total);
    std::vector<int64_t> fill(count.begin(), count.end() - 1);
    for (size_t i = 0; i < n; ++i) {
        const Vec2& a = px[i];
        const Vec2& b = px[i + 1];
        if (a.y() == b.y()) continue;
        const auto [first, last] = rowsOf(a, b);
        const int dir = a.y() < b.y() ? 1 : -1;
        const double slope = (b.x() - a.x()) / (b.y() - a.y());
        for (int64_t y = first; y <= last; ++y) {
            const double yc = static_cast<double>(y) + 0.5;
            crossings[static_cast<size_t>(fill[static_cast<size_t>(y - y0)]++)] = {
                a.x() + (yc - a.y()) * slope, dir};
        }
    }
    o.row0 = y0;
    o.row_start.assign(static_cast<size_t>(rows) + 1, 0);
    o.spans_px.clear();
    for (int64_t r = 0; r < rows; ++r) {
        const auto begin = crossings.begin() + count[static_cast<size_t>(r)];
        const auto end = crossings.begin() + count[static_cast<size_t>(r) + 1];
        std::sort(begin, end);
        int prefix = 0;
        for (auto it = begin; it != end; ++it) {
            prefix += it->second;
            if (prefix == 0 || it + 1 == end) continue;
            const double from = it->first, to = (it + 1)->first;
            if (!o.spans_px.empty() &&
                o.row_start[static_cast<size_t>(r)] < static_cast<int64_t>(o.spans_px.size()) &&
                o.spans_px.back()[1] == from)
                o.spans_px.back()[1] = to;  // adjacent intervals of non-zero winding
            else
                o.spans_px.push_back({from, to});
        }
        o.row_start[static_cast<size_t>(r) + 1] = static_cast<int64_t>(o.spans_px.size());
    }
    return true;
}

std::shared_ptr<const GhostOutline> buildOutline(const BezierLoop& loop,
                                                 const GhostShading& shading,
                                                 const SensorToImage& m,
                                                 int64_t width,
                                                 int64_t height,
                                                 int64_t y0,
                                                 int64_t y1,
                                                 const GhostDrawOptions& options) {
    auto o = std::make_shared<GhostOutline>();
    const double mm_per_px = 1.0 / std::min(m.px_per_mm_x, m.px_per_mm_y);
    o->tolerance_mm = options.sagitta_px * mm_per_px;
    o->reach_mm = 0.5 * std::hypot(1.0 / m.px_per_mm_x, 1.0 / m.px_per_mm_y);
    o->tolerance =
        options.smooth_tolerance * std::max(shadingPeak(shading), options.tolerance_peak);
    Flattener f;
    f.tolerance_mm = o->tolerance_mm;
    f.region_lo = {(0.5 - m.centre_x_px) / m.px_per_mm_x, (0.5 - m.centre_y_px) / m.px_per_mm_y};
    f.region_hi = {(static_cast<double>(width) - 0.5 - m.centre_x_px) / m.px_per_mm_x,
                   (static_cast<double>(height) - 0.5 - m.centre_y_px) / m.px_per_mm_y};
    f.margin_mm = std::max(shading.inner_falloff_mm, shading.outer_falloff_mm) + o->reach_mm +
                  2.0 * o->tolerance_mm + mm_per_px;
    f.out = o.get();
    o->vertices_mm.push_back(loop.control_points_mm.front());
    for (int s = 0; s < loop.segmentCount(); ++s) f.run(loop.segment(s), 0, s, 0.0, 1.0);
    if (f.overflow) return nullptr;
    o->vertices_mm.back() = o->vertices_mm.front();  // closed exactly
    const int32_t chords = static_cast<int32_t>(o->vertices_mm.size() - 1);
    o->edges_mm.resize(static_cast<size_t>(chords));
    o->inverse_length2.resize(static_cast<size_t>(chords));
    for (size_t i = 0; i < static_cast<size_t>(chords); ++i) {
        o->edges_mm[i] = o->vertices_mm[i + 1] - o->vertices_mm[i];
        const double len2 = o->edges_mm[i].squaredNorm();
        o->inverse_length2[i] = len2 > 0.0 ? 1.0 / len2 : 0.0;
    }
    o->bend_angle.assign(static_cast<size_t>(chords), 0.0);
    o->bend_radius_mm.assign(static_cast<size_t>(chords), std::numeric_limits<double>::infinity());
    for (size_t i = 0; i < static_cast<size_t>(chords); ++i) {
        const Vec2& e0 = o->edges_mm[i];
        const Vec2& e1 = o->edges_mm[(i + 1) % static_cast<size_t>(chords)];
        const double angle = std::atan2(e0.x() * e1.y() - e0.y() * e1.x(), e0.dot(e1));
        o->bend_angle[i] = angle;
        if (angle != 0.0) o->bend_radius_mm[i] = 0.5 * (e0.norm() + e1.norm()) / std::abs(angle);
    }
    // A joint where the segments meet at an angle (a corner: the chords' turn there says little
    // of its sharpness) has no radius: on its inner side two points can be nearest.
    for (size_t i = 0; i < static_cast<size_t>(chords); ++i) {
        const size_t next = (i + 1) % static_cast<size_t>(chords);
        if (o->chord_segment[i] == o->chord_segment[next]) continue;
        const auto a = loop.segment(o->chord_segment[i]);
        const auto b = loop.segment(o->chord_segment[next]);
        Vec2 out = Vec2::Zero(), in = Vec2::Zero();
        for (int k = 2; k >= 0 && out.squaredNorm() == 0.0; --k)
            out = a[3] - a[static_cast<size_t>(k)];
        for (int k = 1; k <= 3 && in.squaredNorm() == 0.0; ++k)
            in = b[static_cast<size_t>(k)] - b[0];
        const double angle = std::atan2(out.x() * in.y() - out.y() * in.x(), out.dot(in));
        // A handle of no length at the joint: the curve's speed vanishes there and its
        // curvature grows without bound, a corner in all but the direction.
        const bool stops = (a[3] - a[2]).squaredNorm() == 0.0 || (b[1] - b[0]).squaredNorm() == 0.0;
        if (std::abs(angle) > 1e-9 || stops) o->bend_radius_mm[i] = 0.0;
    }
    {
        double left = 0.0, right = 0.0;
        for (const double bend : o->bend_angle) {
            if (bend > 0.0) left += bend;
            if (bend < 0.0) right -= bend;
        }
        const double slack = 1.75e-4, turn = 2.0 * std::numbers::pi;
        o->convex = (right <= slack && std::abs(left - turn) <= 1e-6 * turn) ||
                    (left <= slack && std::abs(right - turn) <= 1e-6 * turn);
        o->turns_left = left >= right;
    }
    for (int s = 0; s < loop.segmentCount(); ++s) {
        const auto c = loop.segment(s);
        o->segment_power.push_back({c[3] - 3.0 * c[2] + 3.0 * c[1] - c[0],
                                    3.0 * (c[2] - 2.0 * c[1] + c[0]), 3.0 * (c[1] - c[0]), c[0]});
    }
    for (int32_t begin = 0; begin < chords; begin += kChunkChords) {
        GhostOutline::Chunk chunk;
        chunk.begin = begin;
        chunk.end = std::min(chords, begin + kChunkChords);
        chunk.lo_mm = chunk.hi_mm = o->vertices_mm[static_cast<size_t>(begin)];
        for (int32_t i = begin + 1; i <= chunk.end; ++i) {
            chunk.lo_mm = chunk.lo_mm.cwiseMin(o->vertices_mm[static_cast<size_t>(i)]);
            chunk.hi_mm = chunk.hi_mm.cwiseMax(o->vertices_mm[static_cast<size_t>(i)]);
        }
        for (int32_t i = begin; i < chunk.end; ++i) {
            const double bend = o->bend_angle[static_cast<size_t>(i)];
            chunk.turn += std::abs(bend);
            if (bend > 0.0) chunk.left += bend;
            if (bend < 0.0) chunk.right -= bend;
            chunk.radius_mm = std::min(chunk.radius_mm, o->bend_radius_mm[static_cast<size_t>(i)]);
        }
        o->chunks.push_back(chunk);
    }
    std::vector<std::array<Vec2, 2>> below;
    for (const auto& chunk : o->chunks) below.push_back({chunk.lo_mm, chunk.hi_mm});
    while (below.size() > 1) {
        std::vector<std::array<Vec2, 2>> level((below.size() + 1) / 2);
        for (size_t i = 0; i < level.size(); ++i) {
            level[i] = below[2 * i];
            if (2 * i + 1 < below.size()) {
                level[i][0] = level[i][0].cwiseMin(below[2 * i + 1][0]);
                level[i][1] = level[i][1].cwiseMax(below[2 * i + 1][1]);
            }
        }
        o->levels.push_back(level);
        below = std::move(level);
    }
    if (!buildSpans(*o, m, y0, y1)) return nullptr;
    return o;
}

// ---------------------------------------------------------------------------
// Queries on the outline

struct Nearest {
    double distance_mm = std::numeric_limits<double>::infinity();
    Vec2 point_mm = Vec2::Zero();
    int32_t chord = 0;
    double u = 0.0;  // where on the chord, in [0, 1]
    // Set by refineOnCurve: the segment and parameter of point_mm on the curve.
    int32_t segment = 0;
    double t = 0.0;
};

double boxDistance2(const Vec2& lo, const Vec2& hi, const Vec2& q) {
    const double dx = std::max(std::max(lo.x() - q.x(), q.x() - hi.x()), 0.0);
    const double dy = std::max(std::max(lo.y() - q.y(), q.y() - hi.y()), 0.0);
    return dx * dx + dy * dy;
}
double boxDistance2(const GhostOutline::Chunk& c, const Vec2& q) {
    return boxDistance2(c.lo_mm, c.hi_mm, q);
}

void scanChunk(const GhostOutline& o,
               const GhostOutline::Chunk& c,
               const Vec2& q,
               double& best2,
               Nearest& best) {
    for (int32_t i = c.begin; i < c.end; ++i) {
        const size_t k = static_cast<size_t>(i);
        const Vec2& a = o.vertices_mm[k];
        const Vec2& e = o.edges_mm[k];
        const double t = std::clamp((q - a).dot(e) * o.inverse_length2[k], 0.0, 1.0);
        const Vec2 p = a + t * e;
        const double d2 = (p - q).squaredNorm();
        if (d2 < best2) {
            best2 = d2;
            best.point_mm = p;
            best.chord = i;
            best.u = t;
        }
    }
}

double boxDistance2(const std::array<Vec2, 2>& box, const Vec2& q) {
    return boxDistance2(box[0], box[1], q);
}

// The nearest chord point to q: best first down the box levels, never into a box farther than
// the best so far. `bound`, when finite, is known to be at least the distance (the distance is
// 1-Lipschitz, so a neighbour's distance plus the way to it is one) and prunes from the start.
// `hint`, when not negative, is a chunk to scan first (a neighbour's nearest): its distance, often
// near the answer, prunes the rest.
Nearest nearest(const GhostOutline& o,
                const Vec2& q,
                double bound = std::numeric_limits<double>::infinity(),
                int32_t hint = -1) {
    const double start2 = std::isfinite(bound) ? bound * bound * (1.0 + 1e-9) + 1e-300
                                               : std::numeric_limits<double>::infinity();
    double best2 = start2;
    Nearest best;
    best.point_mm = q;
    if (hint >= 0 && static_cast<size_t>(hint) < o.chunks.size())
        scanChunk(o, o.chunks[static_cast<size_t>(hint)], q, best2, best);
    struct Item {
        int level;  // -1: a chunk
        size_t index;
        double distance2;  // of its box from q, computed when it was pushed
    };
    const auto distance2 = [&](int level, size_t index) {
        return level < 0 ? boxDistance2(o.chunks[index], q)
                         : boxDistance2(o.levels[static_cast<size_t>(level)][index], q);
    };
    Item stack[160];
    int top = 0;
    const int root = o.levels.empty() ? -1 : static_cast<int>(o.levels.size()) - 1;
    stack[top++] = {root, 0, distance2(root, 0)};
    while (top > 0) {
        const Item item = stack[--top];
        if (item.distance2 > best2) continue;
        if (item.level < 0) {
            scanChunk(o, o.chunks[item.index], q, best2, best);
            continue;
        }
        const int child_level = item.level - 1;
        const size_t count =
            child_level < 0 ? o.chunks.size() : o.levels[static_cast<size_t>(child_level)].size();
        Item a{child_level, 2 * item.index, distance2(child_level, 2 * item.index)};
        if (2 * item.index + 1 >= count) {
            if (a.distance2 <= best2) stack[top++] = a;
            continue;
        }
        Item b{child_level, 2 * item.index + 1, distance2(child_level, 2 * item.index + 1)};
        if (a.distance2 < b.distance2) std::swap(a, b);  // the nearer one is popped first
        if (a.distance2 <= best2) stack[top++] = a;
        if (b.distance2 <= best2) stack[top++] = b;
    }
    if (best2 == start2 && std::isfinite(bound)) return nearest(o, q);  // rounding: search all
    best.distance_mm = std::sqrt(best2);
    return best;
}

bool inside(const GhostOutline& o, int64_t x, int64_t y) {
    const int64_t r = y - o.row0;
    if (r < 0 || r + 1 >= static_cast<int64_t>(o.row_start.size())) return false;
    const double xc = static_cast<double>(x) + 0.5;
    for (int64_t k = o.row_start[static_cast<size_t>(r)];
         k < o.row_start[static_cast<size_t>(r) + 1]; ++k) {
        const auto& span = o.spans_px[static_cast<size_t>(k)];
        if (xc <= span[0]) return false;
        if (xc < span[1]) return true;
    }
    return false;
}

Vec2 pixelCentreMm(const SensorToImage& m, int64_t x, int64_t y) {
    return {(static_cast<double>(x) + 0.5 - m.centre_x_px) / m.px_per_mm_x,
            (static_cast<double>(y) + 0.5 - m.centre_y_px) / m.px_per_mm_y};
}

// A block's middle pixel, its centre in sensor mm, and the farthest the block's corner pixels'
// centres lie from it.
struct BlockMiddle {
    int64_t x, y;
    Vec2 centre_mm;
    double radius_mm;
};
BlockMiddle blockMiddle(const GhostPrimitive& g, int64_t x0, int64_t y0, int64_t x1, int64_t y1) {
    BlockMiddle m{x0 + (x1 - x0) / 2, y0 + (y1 - y0) / 2, {}, 0.0};
    m.centre_mm = pixelCentreMm(g.mapping, m.x, m.y);
    for (const int64_t x : {x0, x1})
        for (const int64_t y : {y0, y1})
            m.radius_mm =
                std::max(m.radius_mm, (pixelCentreMm(g.mapping, x, y) - m.centre_mm).norm());
    return m;
}

// Eq. 6.4's mean over the pixel centred on q at unsigned distance `distance` from the chords,
// nearest at `point`, as shadeGhostBlock takes it from the curve.
std::array<double, 3> shadeFromNearest(
    const GhostPrimitive& g, const Vec2& q, double distance, const Vec2& point, bool in) {
    const Vec2 half(0.5 / g.mapping.px_per_mm_x, 0.5 / g.mapping.px_per_mm_y);
    const Vec2 spread = blockSpread(q, ClosestPoint{distance, 0, 0.0, point}, half);
    const GhostShading& s = g.shading;
    std::array<double, 3> out{};
    // Away from the edge and from the falloff's end, eq. 6.4 is smooth across the pixel and its
    // mean is the value plus half the variance of the distance over the pixel times the second
    // derivative: one power instead of the antiderivatives' four. The next term is below
    // |E (E-1) (E-2) (E-3)| / 120 (reach / d)^4 of the value, under 3e-5 at 4 reaches.
    const double reach = spread.x() + spread.y();
    const double f = in ? s.inner_falloff_mm : s.outer_falloff_mm;
    if (distance > 4.0 * reach && (distance + reach <= f || distance - reach >= f)) {
        double w = 1.0;
        if (distance + reach <= f) {
            const double e = in ? s.inner_exponent : s.outer_exponent;
            const double p = std::pow(distance / f, e);
            const double variance = (spread.x() * spread.x() + spread.y() * spread.y()) / 3.0;
            w = p + 0.5 * variance * e * (e - 1.0) * p / (distance * distance);
        }
        for (size_t c = 0; c < 3; ++c)
            out[c] = in ? s.border_rgb[c] + (s.inner_rgb[c] - s.border_rgb[c]) * w
                        : s.border_rgb[c] * (1.0 - w);
        return out;
    }
    const auto w = boxTransferWeights<double>(in ? -distance : distance, spread.x(), spread.y(),
                                              s.inner_falloff_mm, s.outer_falloff_mm,
                                              s.inner_exponent, s.outer_exponent);
    for (size_t c = 0; c < 3; ++c) out[c] = s.border_rgb[c] * w.border + s.inner_rgb[c] * w.inner;
    return out;
}

// Two Newton steps on the segment with power-basis coefficients c from t, kept in [0, 1]; the
// point reached.
// `steps` Newton steps; `moved`, when given, gets how far the last one moved the point (mm).
Vec2 newtonOnSegment(const std::array<Vec2, 4>& c,
                     const Vec2& q,
                     double& t,
                     int steps = 2,
                     double* moved = nullptr) {
    if (moved) *moved = 0.0;
    for (int step = 0; step < steps; ++step) {
        const Vec2 p = ((c[0] * t + c[1]) * t + c[2]) * t + c[3];
        const Vec2 d1 = (3.0 * t * c[0] + 2.0 * c[1]) * t + c[2];
        const Vec2 d2 = 6.0 * t * c[0] + 2.0 * c[1];
        const Vec2 r = p - q;
        const double gn = d1.squaredNorm();
        const double h = gn + r.dot(d2);
        const double curvature = h > 0.0 ? h : gn;
        if (!(curvature > 0.0)) break;
        const double next = std::clamp(t - r.dot(d1) / curvature, 0.0, 1.0);
        // How far the step moved the point, to second order (where C' nearly vanishes, at a
        // corner of coinciding control points, the first-order term alone would say nothing).
        const double dt = std::abs(next - t);
        if (moved) *moved = dt * (std::sqrt(gn) + 0.5 * dt * d2.norm());
        t = next;
    }
    return ((c[0] * t + c[1]) * t + c[2]) * t + c[3];
}

// The nearest curve point of q on a branch (GhostBranch): Newton, three steps, from the
// first-order prediction of its loop parameter, trying the neighbouring segment where it stops
// at a joint. `ok` when the point passes the checks below (the last step moved it by less than
// `settled_mm` among them); else the caller searches.
struct Followed {
    bool ok = false;
    double distance_mm = 0.0;
    Vec2 point_mm = Vec2::Zero();
    int32_t segment = 0;
    double t = 0.0;
};
Followed followBranch(const GhostOutline& o,
                      const GhostBranch& b,
                      const Vec2& q,
                      double settled_mm) {
    Followed f;
    const int segments = static_cast<int>(o.segment_power.size());
    double u = b.loop_u + b.gradient.dot(q - b.middle_mm);
    if (segments < 1 || !std::isfinite(u)) return f;
    const double length = static_cast<double>(segments);
    u -= length * std::floor(u / length);
    int segment = std::min(static_cast<int>(u), segments - 1);
    double t = std::clamp(u - segment, 0.0, 1.0);
    double moved = 0.0;
    Vec2 p = newtonOnSegment(o.segment_power[static_cast<size_t>(segment)], q, t, 3, &moved);
    if (segments > 1 && (t == 0.0 || t == 1.0)) {
        segment = t == 0.0 ? (segment + segments - 1) % segments : (segment + 1) % segments;
        t = t == 0.0 ? 1.0 : 0.0;
        p = newtonOnSegment(o.segment_power[static_cast<size_t>(segment)], q, t, 3, &moved);
    }
    // A nearest point: inside its segment (not stopped at a joint), where the curve's direction
    // is square to the way to q (to within `settled_mm` along it), no farther than the middle's
    // distance plus the way to it allows, and, where the branch asks, with q on its outer side.
    const auto& c = o.segment_power[static_cast<size_t>(segment)];
    const Vec2 d1 = (3.0 * t * c[0] + 2.0 * c[1]) * t + c[2];
    const Vec2 r = q - p;
    const double speed = d1.norm();
    f.ok = moved <= settled_mm && t > 0.0 && t < 1.0 && speed > 0.0 &&
           std::abs(r.dot(d1)) <= settled_mm * speed &&
           r.norm() <= b.distance_mm + (q - b.middle_mm).norm() + settled_mm &&
           (b.outward == 0 || (d1.x() * r.y() - d1.y() * r.x()) * b.outward > 0.0);
    f.distance_mm = (p - q).norm();
    f.point_mm = p;
    f.segment = segment;
    f.t = t;
    return f;
}

// The branch of the loop through segment/t seen from q: the derivative of the nearest point's
// parameter across the sensor, from (C(t) - q) . C'(t) = 0. nullopt where the nearest point does
// not move smoothly (q at or beyond the centre of curvature, a cusp).
std::optional<GhostBranch> branchAt(const GhostOutline& o,
                                    int32_t segment,
                                    double t,
                                    const Vec2& q) {
    const auto& c = o.segment_power[static_cast<size_t>(segment)];
    const Vec2 point = ((c[0] * t + c[1]) * t + c[2]) * t + c[3];
    const Vec2 d1 = (3.0 * t * c[0] + 2.0 * c[1]) * t + c[2];
    const Vec2 d2 = 6.0 * t * c[0] + 2.0 * c[1];
    const double curvature = d1.squaredNorm() + (point - q).dot(d2);
    if (!(curvature > 1e-3 * d1.squaredNorm()) || !std::isfinite(curvature)) return std::nullopt;
    GhostBranch b;
    b.loop_u = static_cast<double>(segment) + t;
    b.middle_mm = q;
    b.gradient = d1 / curvature;
    b.distance_mm = (point - q).norm();
    return b;
}

// The end of the single-branch tests: the stretch from chord `first` turns by `turn` in all
// (`left` and `right` of it to each side), nowhere more sharply than `radius`. Gently enough for
// every point within `farthest` of it: either side (0). Else, when it bends one way by less than
// a half turn, for points on the outer side of the bend (the right of a left-turning stretch: -1;
// the left of a right-turning one: +1), where the outward normals of a convex arc never cross, so
// that a point lies on the outward normal of one point of it at most. nullopt otherwise.
std::optional<int> branchKind(const GhostOutline& o,
                              int32_t first,
                              double turn,
                              double left,
                              double right,
                              double radius,
                              const Vec2& c,
                              double farthest) {
    if (turn <= 0.5 * std::numbers::pi && radius >= 2.0 * farthest) return 0;
    if (!(turn < std::numbers::pi)) return std::nullopt;
    // Only where the region lies on the outer side (judged at c from the first chord; each point
    // is checked again where Newton lands).
    const Vec2& e = o.edges_mm[static_cast<size_t>(first)];
    const Vec2 towards = c - o.vertices_mm[static_cast<size_t>(first)];
    const double side = e.x() * towards.y() - e.y() * towards.x();
    const double slack = 1.75e-4;  // a hundredth of a degree the other way in all
    if (right <= slack && side < 0.0) return -1;
    if (left <= slack && side > 0.0) return +1;
    return std::nullopt;
}

// Whether the candidate chords of a region (every chord that can be nearest to one of its
// points; chord indices ascending) form one branch for it: they run along the loop without a gap,
// and either the region lies on the outer side of a stretch that turns one way by less than a
// half turn, or the stretch turns by at most a right angle and nowhere more sharply than twice
// the farthest point's distance from the curve (`farthest`) allows. Then every point's nearest
// point lies on that stretch and is the only point there where the distance stops changing. `c`
// is a point of the region, which lies on one side of the stretch.
// Returns nullopt when they do not, else the side a point must lie on (GhostBranch::outward).
std::optional<int> singleBranch(
    const GhostOutline& o, const int32_t* index, size_t count, const Vec2& c, double farthest) {
    if (count == 0) return std::nullopt;
    const int32_t total = static_cast<int32_t>(o.edges_mm.size());
    int gaps = 0;
    size_t gap_at = 0;
    for (size_t k = 1; k < count; ++k)
        if (index[k] != index[k - 1] + 1) {
            ++gaps;
            gap_at = k;
        }
    if (!(gaps == 0 || (gaps == 1 && index[0] == 0 && index[count - 1] == total - 1)))
        return std::nullopt;
    const int32_t first = gaps == 0 ? index[0] : index[gap_at];
    double turn = 0.0, left = 0.0, right = 0.0;
    double radius = std::numeric_limits<double>::infinity();
    for (size_t k = 0; k + 1 < count; ++k) {
        const size_t i = static_cast<size_t>((first + static_cast<int32_t>(k)) % total);
        const double bend = o.bend_angle[i];
        turn += std::abs(bend);
        if (bend > 0.0) left += bend;
        if (bend < 0.0) right -= bend;
        radius = std::min(radius, o.bend_radius_mm[i]);
    }
    return branchKind(o, first, turn, left, right, radius, c, farthest);
}

// singleBranch on whole chunks: the chunks whose boxes lie within `reach` of c (a superset of the
// chords within reach, so a stricter test), their turns summed per chunk. A few box tests per
// chunk of the loop, no chord's.
std::optional<int> singleBranchOfChunks(const GhostOutline& o,
                                        const Vec2& c,
                                        double reach,
                                        double farthest) {
    const double reach2 = reach * reach * (1.0 + 1e-12) + 1e-300;
    const size_t n = o.chunks.size();
    int64_t first = -1, previous = -1;
    int gaps = 0;
    size_t found = 0;
    bool has_zero = false, has_last = false;
    double turn = 0.0, left = 0.0, right = 0.0;
    double radius = std::numeric_limits<double>::infinity();
    for (size_t k = 0; k < n; ++k) {
        const auto& chunk = o.chunks[k];
        if (boxDistance2(chunk, c) > reach2) continue;
        if (previous >= 0 && static_cast<int64_t>(k) != previous + 1) {
            ++gaps;
            first = static_cast<int64_t>(k);
        }
        if (previous < 0) first = static_cast<int64_t>(k);
        has_zero = has_zero || k == 0;
        has_last = has_last || k + 1 == n;
        previous = static_cast<int64_t>(k);
        ++found;
        turn += chunk.turn;
        left += chunk.left;
        right += chunk.right;
        radius = std::min(radius, chunk.radius_mm);
        if (gaps > 1) return std::nullopt;
    }
    if (found == 0 || !(gaps == 0 || (gaps == 1 && has_zero && has_last))) return std::nullopt;
    return branchKind(o, o.chunks[static_cast<size_t>(first)].begin, turn, left, right, radius, c,
                      farthest);
}

// The curve's own distance near the chord's: Newton on (C(t) - q) . C'(t) = 0 from the chord
// point's parameter, two steps (the start is within the sagitta, so they converge far below it).
// The chords put the distance within their sagitta of the curve's, which at an edge sharper than
// a pixel moves the pixel's mean by up to the sagitta's share of the pixel (1 % at 0.01 px); this
// takes that away. Kept only when it is a point of the curve no farther than the chord's plus the
// sagitta (else the chord's stands). Within two sagittas of the chords, where they and the curve
// may disagree about the side, the side is the curve's winding number.
void refineOnCurve(const GhostPrimitive& g, const Vec2& q, Nearest& n, bool& in) {
    const GhostOutline& o = *g.outline;
    const size_t i = static_cast<size_t>(n.chord);
    const int segment = o.chord_segment[i];
    double t = o.chord_t[i][0] + n.u * (o.chord_t[i][1] - o.chord_t[i][0]);
    const double t_chord = t;
    Vec2 p = newtonOnSegment(o.segment_power[static_cast<size_t>(segment)], q, t);
    double d = (p - q).norm();
    int at_segment = segment;
    double at_t = t;
    // Stopped at a joint: the nearest point may lie just across it, on the neighbouring segment
    // (the chords on both sides of a joint are equally near a point whose foot is the joint, and
    // either may be the one found).
    const int segments = static_cast<int>(o.segment_power.size());
    if (segments > 1 && (t == 0.0 || t == 1.0)) {
        const int other = t == 0.0 ? (segment + segments - 1) % segments : (segment + 1) % segments;
        double u = t == 0.0 ? 1.0 : 0.0;
        const Vec2 p2 = newtonOnSegment(o.segment_power[static_cast<size_t>(other)], q, u);
        const double d2 = (p2 - q).norm();
        if (d2 < d) {
            d = d2;
            p = p2;
            at_segment = other;
            at_t = u;
        }
    }
    if (d <= n.distance_mm + o.tolerance_mm) {
        n.distance_mm = d;
        n.point_mm = p;
        n.segment = at_segment;
        n.t = at_t;
    } else {
        n.segment = segment;
        n.t = t_chord;
    }
    if (n.distance_mm <= 2.0 * o.tolerance_mm) in = windingNumber(g.loop_mm, q) != 0;
}

std::array<double, 3> fastValue(const GhostPrimitive& g, int64_t x, int64_t y) {
    const Vec2 q = pixelCentreMm(g.mapping, x, y);
    Nearest n = nearest(*g.outline, q);
    bool in = inside(*g.outline, x, y);
    refineOnCurve(g, q, n, in);
    return shadeFromNearest(g, q, n.distance_mm, n.point_mm, in);
}

// ---------------------------------------------------------------------------
// Edge tiles along one branch of the curve, four pixels at a time

// Where the nearest points of a tile's pixels all lie on one short run of the loop (one branch,
// gently curved), each pixel's nearest point is found by Newton on that segment of the curve from
// a prediction, with no search of the chords; the pixel means follow in vectors of four. Lanes
// Newton cannot settle (a joint, no convergence) are left to the per-pixel path.
// Four-double vectors stay inside always-inlined functions and the kernels compiled for them, so
// the ABI note GCC gives for AVX-sized values is moot here.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wpsabi"
#endif
using Double4 = double __attribute__((vector_size(32)));  // GCC's and Clang's vector extension
using Mask4 = long long __attribute__((vector_size(32)));

struct BranchTile {
    // The middle's segment and the ones before and after it, C(t) = ((a t + b) t + c) t + d with
    // the origin at the middle: power[1] is the middle's; a pixel whose predicted parameter runs
    // off its ends starts on the neighbour.
    std::array<std::array<Vec2, 4>, 3> power;
    double t_m = 0.0;                   // the middle's nearest point's parameter
    Vec2 gradient_t = Vec2::Zero();     // d t / d q at the middle
    double px_x = 1.0, px_y = 1.0;      // pixels per mm
    double first_x = 0.0;               // the row's first pixel centre, mm from the middle
    double row_y = 0.0;                 // the row's pixel centres, mm from the middle
    double half_x = 0.0, half_y = 0.0;  // half a pixel, mm
    double converged_mm = 0.0;          // the last Newton step moves the point less than this
    double mm_per_px = 0.0;
    double near_mm = 0.0;      // within this of the curve the side needs the winding number
    int outward = 0;           // GhostBranch::outward
    double distance_mm = 0.0;  // GhostBranch::distance_mm
};

// s^e = exp(e ln s) for four s in [0, 1] and e > 0 (0 at s = 0), through glibc's vector math
// library (libmvec): its AVX2 variants where the processor has AVX2 (called out of line, by
// pointer, so that no AVX vector crosses a call compiled without AVX), its SSE ones otherwise.
#if defined(__x86_64__) && defined(__GLIBC__)
extern "C" {
// Declared with AVX2 as their definitions are: Clang refuses an AVX vector passed to a function
// it believes is compiled without AVX (the ABI would differ), even from an AVX2 caller.
[[gnu::target("avx2")]] __m256d _ZGVdN4v_log(__m256d);
[[gnu::target("avx2")]] __m256d _ZGVdN4v_exp(__m256d);
__m128d _ZGVbN2v_log(__m128d);
__m128d _ZGVbN2v_exp(__m128d);
}
[[gnu::target("avx2")]] void powUnitAvx2(const double* s, const double* e, double* out) {
    const __m256d v = _mm256_loadu_pd(s);
    const __m256d one = _mm256_set1_pd(1.0);
    const __m256d positive = _mm256_cmp_pd(v, _mm256_setzero_pd(), _CMP_GT_OQ);
    const __m256d safe = _mm256_blendv_pd(one, v, positive);
    const __m256d r = _ZGVdN4v_exp(_mm256_mul_pd(_mm256_loadu_pd(e), _ZGVdN4v_log(safe)));
    _mm256_storeu_pd(out, _mm256_and_pd(r, positive));
}
void powUnitSse(const double* s, const double* e, double* out) {
    for (int h = 0; h < 4; h += 2) {
        double safe[2];
        for (int j = 0; j < 2; ++j) safe[j] = s[h + j] > 0.0 ? s[h + j] : 1.0;
        const __m128d r =
            _ZGVbN2v_exp(_mm_mul_pd(_mm_loadu_pd(e + h), _ZGVbN2v_log(_mm_loadu_pd(safe))));
        _mm_storeu_pd(out + h, r);
        for (int j = 0; j < 2; ++j)
            if (!(s[h + j] > 0.0)) out[h + j] = 0.0;
    }
}
struct Avx2Math {
    static constexpr auto pow = &powUnitAvx2;
};
struct BaseMath {
    static constexpr auto pow = &powUnitSse;
};
#else
void powUnitScalar(const double* s, const double* e, double* out) {
    for (int j = 0; j < 4; ++j) out[j] = s[j] > 0.0 ? std::pow(s[j], e[j]) : 0.0;
}
struct BaseMath {
    static constexpr auto pow = &powUnitScalar;
};
#endif

// Square roots of four doubles (SSE2, which every x86-64 has; one lane at a time elsewhere).
[[gnu::always_inline]] inline Double4 sqrt4(Double4 x) {
#if defined(__x86_64__)
    using Half = double __attribute__((vector_size(16)));
    Half lo, hi;
    __builtin_memcpy(&lo, &x, sizeof lo);
    __builtin_memcpy(&hi, reinterpret_cast<const char*>(&x) + sizeof lo, sizeof hi);
    lo = (Half)_mm_sqrt_pd((__m128d)lo);
    hi = (Half)_mm_sqrt_pd((__m128d)hi);
    Double4 out;
    __builtin_memcpy(&out, &lo, sizeof lo);
    __builtin_memcpy(reinterpret_cast<char*>(&out) + sizeof lo, &hi, sizeof hi);
    return out;
#else
    for (int j = 0; j < 4; ++j) x[j] = std::sqrt(x[j]);
    return x;
#endif
}

// s^e for s in [0, 1] and e > 0 (0 at s = 0).
template <typename Math>
[[gnu::always_inline]] inline Double4 powUnit(Double4 s, Double4 e) {
    double in[4], exponent[4], out[4];
    __builtin_memcpy(in, &s, sizeof in);
    __builtin_memcpy(exponent, &e, sizeof exponent);
    Math::pow(in, exponent, out);
    Double4 r;
    __builtin_memcpy(&r, out, sizeof out);
    return r;
}

struct VectorShading {
    Double4 fo, fi, eo, ei;
};

// Eq. 6.4's second antiderivatives (transferAntiderivatives' `second`) at x, both weights.
template <typename Math>
[[gnu::always_inline]] inline void secondAntiderivative(const VectorShading& v,
                                                        Double4 x,
                                                        Double4& border,
                                                        Double4& inner) {
    const Double4 zero = {}, one = zero + 1.0, half = zero + 0.5;
    const Mask4 out = x > zero;
    const Double4 y = out ? x : -x;
    const Double4 f = out ? v.fo : v.fi, e = out ? v.eo : v.ei;
    const Double4 e1 = e + one, e2 = e + 2.0;
    Double4 s = y / f;
    s = s < one ? s : one;
    const Double4 p = powUnit<Math>(s, e2);
    const Double4 k = f * f / (e1 * e2);
    const Double4 r = y - f;
    const Mask4 within = y < f;
    const Double4 p2 = k * p;
    const Double4 beyond_border = half * f * f - k + f * e / e1 * r;
    const Double4 b = within ? half * y * y - p2 : beyond_border;
    const Double4 i = within ? p2 : k + f / e1 * r + half * r * r;
    border = b;
    inner = out ? zero : i;
}

// The pixel means' weights on the border and inner intensities (boxTransferWeights, or the
// variance form shadeFromNearest uses away from the edge and the falloffs' ends) for signed
// distances sd and half spreads a, c.
template <typename Math>
[[gnu::always_inline]] inline void pixelWeights(
    const VectorShading& v, Double4 sd, Double4 a, Double4 c, Double4& w_border, Double4& w_inner) {
    const Double4 zero = {}, one = zero + 1.0;
    const Mask4 in = sd < zero;
    const Double4 dist = in ? -sd : sd;
    const Double4 reach = a + c;
    const Double4 fs = in ? v.fi : v.fo, es = in ? v.ei : v.eo;
    // Away from the edge and the falloff's end: one power.
    const Mask4 within = dist + reach <= fs;
    Double4 q = dist / fs;
    q = q < one ? q : one;
    const Double4 p = powUnit<Math>(q, es);
    const Double4 variance = (a * a + c * c) / 3.0;
    const Double4 safe = dist > zero ? dist : one;
    Double4 w = within ? p + 0.5 * variance * es * (es - one) * p / (safe * safe) : one;
    Double4 wb = one - w, wi = in ? w : zero;
    const Mask4 far = (dist > 4.0 * reach) & (within | (dist - reach >= fs));
    const Mask4 all_out = sd - reach >= v.fo;
    const Mask4 all_in = sd + reach <= -v.fi;
    const Mask4 box = ~far & ~all_out & ~all_in;
    bool any_box = false;
    for (int j = 0; j < 4; ++j) any_box = any_box || box[j] != 0;
    if (any_box) {
        const Double4 big = a > c ? a : c;
        Double4 small = a > c ? c : a;
        small = small > 1e-6 * big ? small : 1e-6 * big;
        Double4 b1, i1, b2, i2, b3, i3, b4, i4;
        secondAntiderivative<Math>(v, sd + big + small, b1, i1);
        secondAntiderivative<Math>(v, sd + big - small, b2, i2);
        secondAntiderivative<Math>(v, sd - big + small, b3, i3);
        secondAntiderivative<Math>(v, sd - big - small, b4, i4);
        const Double4 scale = 0.25 / (big * small);
        wb = box ? (b1 - b2 - b3 + b4) * scale : wb;
        wi = box ? (i1 - i2 - i3 + i4) * scale : wi;
    }
    w_border = all_out ? zero : (all_in ? zero : wb);
    w_inner = all_out ? zero : (all_in ? one : wi);
}

// One row of a branch tile (BranchTile::row_y): pixels x0..x1, whose sides (inside the loop or not)
// are `in`; adds the pixel means to rgb (pixel x0 first) and sets done[x - x0] for the pixels it
// drew (the rest are left to the caller).
template <typename Math>
[[gnu::always_inline]] inline void branchRowBody(const BranchTile& b,
                                                 const GhostShading& shading,
                                                 int64_t x0,
                                                 int64_t x1,
                                                 const uint8_t* in,
                                                 float* rgb,
                                                 uint8_t* done) {
    const Double4 zero = {}, one = zero + 1.0;
    const VectorShading v{zero + shading.outer_falloff_mm, zero + shading.inner_falloff_mm,
                          zero + shading.outer_exponent, zero + shading.inner_exponent};
    const Double4 qy = zero + b.row_y;
    for (int64_t x = x0; x <= x1; x += 4) {
        Double4 qx;
        for (int j = 0; j < 4; ++j)
            qx[j] = b.first_x + static_cast<double>(std::min(x + j, x1) - x0) / b.px_x;
        Double4 t = b.t_m + b.gradient_t.x() * qx + b.gradient_t.y() * qy;
        // Each lane on the segment its prediction names: the middle's, or the one before or
        // after it.
        const Mask4 before = t<zero, after = t> one;
        t = before ? t + one : (after ? t - one : t);
        bool all_middle = true;
        for (int j = 0; j < 4; ++j) all_middle = all_middle && !before[j] && !after[j];
        const auto pick = [&](int k, bool xs) {
            const auto component = [&](size_t segment) {
                const Vec2& v = b.power[segment][static_cast<size_t>(k)];
                return xs ? v.x() : v.y();
            };
            Double4 v = zero + component(1);
            if (all_middle) return v;
            for (int j = 0; j < 4; ++j)
                if (before[j] || after[j]) v[j] = component(before[j] ? 0 : 2);
            return v;
        };
        const Double4 ax = pick(0, true), ay = pick(0, false);
        const Double4 bx = pick(1, true), by = pick(1, false);
        const Double4 cx = pick(2, true), cy = pick(2, false);
        const Double4 dx = pick(3, true), dy = pick(3, false);
        t = t > zero ? t : zero;
        t = t < one ? t : one;
        const Double4 sx = ((ax * t + bx) * t + cx) * t + dx;
        const Double4 sy = ((ay * t + by) * t + cy) * t + dy;
        Double4 last_dt = zero, last_speed2 = zero, last_bend2 = zero;
        for (int step = 0; step < 3; ++step) {
            const Double4 px = ((ax * t + bx) * t + cx) * t + dx;
            const Double4 py = ((ay * t + by) * t + cy) * t + dy;
            const Double4 d1x = (3.0 * ax * t + 2.0 * bx) * t + cx;
            const Double4 d1y = (3.0 * ay * t + 2.0 * by) * t + cy;
            const Double4 d2x = 6.0 * ax * t + 2.0 * bx, d2y = 6.0 * ay * t + 2.0 * by;
            const Double4 rx = px - qx, ry = py - qy;
            const Double4 gn = d1x * d1x + d1y * d1y;
            const Double4 h = gn + rx * d2x + ry * d2y;
            const Double4 curvature = h > zero ? h : gn;
            const Double4 safe = curvature > zero ? curvature : one;
            Double4 next = t - (rx * d1x + ry * d1y) / safe;
            next = curvature > zero ? next : t;
            next = next > zero ? next : zero;
            next = next < one ? next : one;
            last_dt = next > t ? next - t : t - next;
            last_speed2 = gn;
            last_bend2 = d2x * d2x + d2y * d2y;
            t = next;
        }
        // How far the last step moved the point, to second order.
        const Double4 move = last_dt * (sqrt4(last_speed2) + 0.5 * last_dt * sqrt4(last_bend2));
        const Double4 px = ((ax * t + bx) * t + cx) * t + dx;
        const Double4 py = ((ay * t + by) * t + cy) * t + dy;
        const Double4 rx = qx - px, ry = qy - py;
        const Double4 d2 = rx * rx + ry * ry;
        const Double4 dist = sqrt4(d2);
        const Double4 wander = (px - sx) * (px - sx) + (py - sy) * (py - sy);
        const Double4 from_middle = sqrt4(qx * qx + qy * qy);
        Mask4 ok = (move <= b.converged_mm) & (t > zero) & (t < one) &
                   (wander <= b.mm_per_px * b.mm_per_px) & (dist > b.near_mm) &
                   (dist <= b.distance_mm + from_middle + b.converged_mm);
        // Square to the curve at the point (rx, ry run from it to the pixel), and on the outer
        // side where the branch asks.
        const Double4 tx = (3.0 * ax * t + 2.0 * bx) * t + cx;
        const Double4 ty = (3.0 * ay * t + 2.0 * by) * t + cy;
        Double4 along = tx * rx + ty * ry;
        along = along < zero ? -along : along;
        const Double4 speed = sqrt4(tx * tx + ty * ty);
        ok &= (speed > zero) & (along <= b.converged_mm * speed);
        if (b.outward != 0) ok &= (tx * ry - ty * rx) * static_cast<double>(b.outward) > zero;
        const Double4 safe = dist > zero ? dist : one;
        Double4 a = b.half_x * (rx / safe), c = b.half_y * (ry / safe);
        a = a < zero ? -a : a;
        c = c < zero ? -c : c;
        Double4 sd;
        for (int j = 0; j < 4; ++j) sd[j] = x + j <= x1 && in[x + j - x0] ? -dist[j] : dist[j];
        Double4 wb, wi;
        pixelWeights<Math>(v, sd, a, c, wb, wi);
        for (int j = 0; j < 4 && x + j <= x1; ++j) {
            if (!ok[j]) continue;
            float* pixel = rgb + (x + j - x0) * 3;
            for (size_t k = 0; k < 3; ++k)
                pixel[k] += static_cast<float>(shading.border_rgb[k] * wb[j] +
                                               shading.inner_rgb[k] * wi[j]);
            done[x + j - x0] = 1;
        }
    }
}

using BranchRow = void (*)(
    const BranchTile&, const GhostShading&, int64_t, int64_t, const uint8_t*, float*, uint8_t*);
void branchRowBase(const BranchTile& b,
                   const GhostShading& s,
                   int64_t x0,
                   int64_t x1,
                   const uint8_t* in,
                   float* rgb,
                   uint8_t* done) {
    branchRowBody<BaseMath>(b, s, x0, x1, in, rgb, done);
}
#if defined(__x86_64__) && defined(__GLIBC__)
[[gnu::target("avx2")]] void branchRowAvx2(const BranchTile& b,
                                           const GhostShading& s,
                                           int64_t x0,
                                           int64_t x1,
                                           const uint8_t* in,
                                           float* rgb,
                                           uint8_t* done) {
    branchRowBody<Avx2Math>(b, s, x0, x1, in, rgb, done);
}
#endif
BranchRow branchRow() {
#if defined(__x86_64__) && defined(__GLIBC__)
    return processorHasAvx2() ? &branchRowAvx2 : &branchRowBase;
#else
    return &branchRowBase;
#endif
}

}  // namespace

std::optional<GhostPrimitive> prepareGhostPrimitive(const BezierLoop& loop_mm,
                                                    const GhostShading& shading,
                                                    const SensorToImage& mapping,
                                                    int64_t width,
                                                    int64_t height,
                                                    const GhostDrawOptions& options) {
    if (loop_mm.segmentCount() < 1 || width < 1 || height < 1) return std::nullopt;
    if (!validateShading(shading)) return std::nullopt;
    if (!(mapping.px_per_mm_x > 0.0) || !(mapping.px_per_mm_y > 0.0) ||
        !std::isfinite(mapping.px_per_mm_x) || !std::isfinite(mapping.px_per_mm_y) ||
        !std::isfinite(mapping.centre_x_px) || !std::isfinite(mapping.centre_y_px))
        return std::nullopt;
    const FastDistanceOptions& distance = options.distance;
    if (distance.iterations < 0 || distance.seeds_per_segment < 1) return std::nullopt;
    if (!(options.sagitta_px > 0.0 && options.sagitta_px <= 1.0) ||
        !(options.smooth_tolerance > 0.0 && options.smooth_tolerance <= 0.1) ||
        !(options.tolerance_peak >= 0.0) || !std::isfinite(options.tolerance_peak))
        return std::nullopt;
    bool lit = false;
    for (int c = 0; c < 3; ++c)
        lit = lit || shading.border_rgb[c] > 0.0 || shading.inner_rgb[c] > 0.0;
    if (!lit) return std::nullopt;

    double lo_x = std::numeric_limits<double>::infinity(), hi_x = -lo_x;
    double lo_y = lo_x, hi_y = -lo_x;
    for (const auto& p : loop_mm.control_points_mm) {
        if (!std::isfinite(p.x()) || !std::isfinite(p.y())) return std::nullopt;
        lo_x = std::min(lo_x, p.x());
        hi_x = std::max(hi_x, p.x());
        lo_y = std::min(lo_y, p.y());
        hi_y = std::max(hi_y, p.y());
    }
    // Beyond the outer falloff the ghost is zero; the curve lies in its control points' box. A
    // pixel's mean reaches half its diagonal further.
    const double grow = shading.outer_falloff_mm +
                        0.5 * std::hypot(1.0 / mapping.px_per_mm_x, 1.0 / mapping.px_per_mm_y);
    const Eigen::Vector2d a = mapping.toPixels(lo_x - grow, lo_y - grow);
    const Eigen::Vector2d b = mapping.toPixels(hi_x + grow, hi_y + grow);
    if (!std::isfinite(a.x()) || !std::isfinite(a.y()) || !std::isfinite(b.x()) ||
        !std::isfinite(b.y()))
        return std::nullopt;
    // Pixel x is sampled at x + 0.5: the range holds the centres inside [a, b].
    const double fx0 = std::ceil(a.x() - 0.5), fx1 = std::floor(b.x() - 0.5);
    const double fy0 = std::ceil(a.y() - 0.5), fy1 = std::floor(b.y() - 0.5);
    const double w = static_cast<double>(width), h = static_cast<double>(height);
    if (fx1 < 0.0 || fy1 < 0.0 || fx0 > w - 1.0 || fy0 > h - 1.0 || fx0 > fx1 || fy0 > fy1)
        return std::nullopt;
    GhostPrimitive g;
    g.loop_mm = loop_mm;
    g.shading = shading;
    g.mapping = mapping;
    g.distance = distance;
    g.x0 = static_cast<int64_t>(std::max(0.0, fx0));
    g.x1 = static_cast<int64_t>(std::min(w - 1.0, fx1));
    g.y0 = static_cast<int64_t>(std::max(0.0, fy0));
    g.y1 = static_cast<int64_t>(std::min(h - 1.0, fy1));
    if (options.evaluation == GhostEvaluation::Fast)
        g.outline = buildOutline(loop_mm, shading, mapping, width, height, g.y0, g.y1, options);
    return g;
}

void addGhostRow(const GhostPrimitive& g, int64_t y, int64_t x0, int64_t x1, float* rgb) {
    const double qy =
        (static_cast<double>(y) + 0.5 - g.mapping.centre_y_px) / g.mapping.px_per_mm_y;
    const Eigen::Vector2d half(0.5 / g.mapping.px_per_mm_x, 0.5 / g.mapping.px_per_mm_y);
    for (int64_t x = x0; x <= x1; ++x, rgb += 3) {
        const double qx =
            (static_cast<double>(x) + 0.5 - g.mapping.centre_x_px) / g.mapping.px_per_mm_x;
        const std::array<double, 3> v =
            shadeGhostBlock(g.loop_mm, g.shading, {qx, qy}, half, g.distance);
        for (int c = 0; c < 3; ++c)
            if (std::isfinite(v[c])) rgb[c] += static_cast<float>(v[c]);
    }
}

std::array<double, 3> ghostPixelValue(const GhostPrimitive& g, int64_t x, int64_t y) {
    if (g.outline) return fastValue(g, x, y);
    const Eigen::Vector2d half(0.5 / g.mapping.px_per_mm_x, 0.5 / g.mapping.px_per_mm_y);
    return shadeGhostBlock(g.loop_mm, g.shading, pixelCentreMm(g.mapping, x, y), half, g.distance);
}

void GhostSampleMemo::reset(const GhostPrimitive* ghost,
                            int64_t origin_x,
                            int64_t origin_y,
                            int64_t cells_x,
                            int64_t cells_y,
                            int64_t spacing_px) {
    ghost_ = ghost;
    origin_x_ = origin_x;
    origin_y_ = origin_y;
    cells_x_ = std::max<int64_t>(0, cells_x);
    cells_y_ = std::max<int64_t>(0, cells_y);
    spacing_ = std::max<int64_t>(1, spacing_px);
    const size_t n = static_cast<size_t>((cells_x_ + 1) * (cells_y_ + 1));
    if (slots_.size() < n) slots_.resize(n);  // new slots carry stamp 0, never current
    if (++stamp_ == 0) {
        for (auto& slot : slots_) slot.stamp = 0;
        stamp_ = 1;
    }
}

GhostSampleMemo::Entry* GhostSampleMemo::find(const GhostPrimitive& ghost, double x, double y) {
    if (&ghost != ghost_) return nullptr;
    const double fx = (x + 0.5 - static_cast<double>(origin_x_)) / static_cast<double>(spacing_);
    const double fy = (y + 0.5 - static_cast<double>(origin_y_)) / static_cast<double>(spacing_);
    const double ix = std::nearbyint(fx), iy = std::nearbyint(fy);
    if (!(std::abs(fx - ix) <= 1e-9 && std::abs(fy - iy) <= 1e-9)) return nullptr;
    if (ix < 0.0 || iy < 0.0 || ix > static_cast<double>(cells_x_) ||
        iy > static_cast<double>(cells_y_))
        return nullptr;
    Slot& slot = slots_[static_cast<size_t>(static_cast<int64_t>(iy) * (cells_x_ + 1) +
                                            static_cast<int64_t>(ix))];
    if (slot.stamp != stamp_) {
        slot.stamp = stamp_;
        slot.entry = Entry{};
        ++misses;
    } else {
        ++hits;
    }
    return &slot.entry;
}

GhostBlockCover coverGhostBlock(const GhostPrimitive& g,
                                int64_t x0,
                                int64_t y0,
                                int64_t x1,
                                int64_t y1,
                                bool finest,
                                GhostSampleMemo* memo,
                                const GhostBranch* branch) {
    GhostBlockCover cover;
    const auto fx0 = static_cast<double>(x0), fx1 = static_cast<double>(x1);
    const auto fy0 = static_cast<double>(y0), fy1 = static_cast<double>(y1);
    cover.node_x = {fx0 - 0.5, 0.5 * (fx0 + fx1), fx1 + 0.5};
    cover.node_y = {fy0 - 0.5, 0.5 * (fy0 + fy1), fy1 + 0.5};
    if (x1 < g.x0 || x0 > g.x1 || y1 < g.y0 || y0 > g.y1) {
        cover.kind = GhostBlockKind::Outside;
        return cover;
    }
    if (!g.outline) return cover;  // Edge: every pixel exactly
    const GhostOutline& o = *g.outline;
    const GhostShading& s = g.shading;
    const SensorToImage& m = g.mapping;
    const auto point = [&](double x, double y) {
        return Vec2((x + 0.5 - m.centre_x_px) / m.px_per_mm_x,
                    (y + 0.5 - m.centre_y_px) / m.px_per_mm_y);
    };
    const auto entryAt = [&](double x, double y, GhostSampleMemo::Entry& local) {
        GhostSampleMemo::Entry* e = memo ? memo->find(g, x, y) : nullptr;
        return e ? e : &local;
    };
    // The signed distance is 1-Lipschitz and a pixel's mean reaches reach_mm beyond its centre,
    // so the value at the block's middle bounds every pixel's within r of it (r: to the
    // corner nodes, which lie farther than any pixel centre of the block).
    const Vec2 c = point(cover.node_x[1], cover.node_y[1]);
    const double r = std::hypot(0.5 * (fx1 - fx0 + 1.0) / m.px_per_mm_x,
                                0.5 * (fy1 - fy0 + 1.0) / m.px_per_mm_y);
    // Pixels take the curve's distance where Newton finds it, the chords' (within a sagitta)
    // where not: two sagittas of slack on the bound.
    const double h = o.reach_mm + 2.0 * o.tolerance_mm;
    GhostSampleMemo::Entry local_mid;
    GhostSampleMemo::Entry& mid = *entryAt(cover.node_x[1], cover.node_y[1], local_mid);
    const double settled_mm = 1e-3 * o.tolerance_mm;
    if (!mid.has_distance) {
        // The middle is a pixel centre, a pixel edge or a corner; its side is that of the
        // nearest pixel centre (from the spans) unless the outline passes between them, which
        // it can only within half a pixel's diagonal (and the chords' sagitta) of the middle.
        bool in = inside(o, static_cast<int64_t>(std::floor(cover.node_x[1] + 0.5)),
                         static_cast<int64_t>(std::floor(cover.node_y[1] + 0.5)));
        Nearest n;
        const Followed f = branch ? followBranch(o, *branch, c, settled_mm) : Followed{};
        if (f.ok) {  // on the enclosing block's branch: Newton found it
            n.distance_mm = f.distance_mm;
            n.point_mm = f.point_mm;
            n.segment = f.segment;
            n.t = f.t;
            if (n.distance_mm <= 2.0 * o.tolerance_mm) in = windingNumber(g.loop_mm, c) != 0;
        } else {
            n = nearest(o, c);
            refineOnCurve(g, c, n, in);
        }
        mid.has_distance = true;
        mid.chord = n.chord;
        mid.segment = n.segment;
        mid.t = n.t;
        mid.side_known = n.distance_mm > h || n.distance_mm <= 2.0 * o.tolerance_mm;
        mid.signed_distance_mm = in ? -n.distance_mm : n.distance_mm;
        if (mid.side_known) mid.value = shadeFromNearest(g, c, n.distance_mm, n.point_mm, in);
    }
    // Whether the block lies on one branch of the loop (passed on to its parts, and used for its
    // own samples): within a block on one branch, from the middle's nearest point; else from the
    // chords near the block. Not for the smallest blocks that will be drawn per pixel, which have
    // no parts.
    const auto findBranch = [&] {
        if (cover.branch) return;
        const double distance = std::abs(mid.signed_distance_mm);
        if (branch) {
            cover.branch = branchAt(o, mid.segment, mid.t, c);
            if (cover.branch)
                cover.branch->outward = branch->outward;
            else
                cover.branch = *branch;
            return;
        }
        const double slack = 2.0 * o.tolerance_mm;
        // Outside a convex loop every point has one nearest point (the block lies outside when
        // its middle does, farther than the block's radius).
        std::optional<int> kind;
        if (o.convex && mid.signed_distance_mm > r + slack)
            kind = o.turns_left ? -1 : +1;  // outside is to the right of a left-turning loop
        else
            kind = singleBranchOfChunks(o, c, distance + 2.0 * r + slack, distance + r + slack);
        if (kind) {
            cover.branch = branchAt(o, mid.segment, mid.t, c);
            if (cover.branch) cover.branch->outward = *kind;
        }
    };
    // Unknown side: the middle lies within h of the outline, where no block is Outside or
    // inside the inner falloff (r is at least the half pixel diagonal) and every block is Edge.
    if (!mid.side_known) {
        if (!finest || branch) findBranch();
        return cover;
    }
    const double d = mid.signed_distance_mm;
    if (d - r >= s.outer_falloff_mm + h) {
        cover.kind = GhostBlockKind::Outside;
        return cover;
    }
    if (d + r <= -(s.inner_falloff_mm + h)) {
        bool lit = false;
        for (size_t k = 0; k < 3; ++k) lit = lit || s.inner_rgb[k] > 0.0;
        cover.kind = lit ? GhostBlockKind::Smooth : GhostBlockKind::Outside;
        for (auto& row : cover.nodes)
            for (auto& node : row)
                for (size_t k = 0; k < 3; ++k) node[k] = static_cast<float>(s.inner_rgb[k]);
        return cover;
    }
    // The edge, where a pixel's mean bends the value within a pixel, is drawn per pixel; so are
    // the ends of the falloffs, where eq. 6.4's slope jumps, except in the smallest blocks.
    if (std::abs(d) - r <= 2.0 * h) {
        if (!finest || branch) findBranch();
        return cover;
    }
    const bool in = d < 0.0;
    if (!finest) {
        const double f = in ? s.inner_falloff_mm : s.outer_falloff_mm;
        if (std::abs(d) - r <= f + h && std::abs(d) + r >= f - h) {
            findBranch();
            return cover;
        }
    }
    findBranch();
    // Nine nodes carry the block, four points between them check it. Every one lies on the
    // middle's side, more than 2 h from the outline.
    const double bound = std::abs(d) + o.tolerance_mm;
    const auto sample = [&](double x, double y) {
        GhostSampleMemo::Entry local;
        GhostSampleMemo::Entry& e = *entryAt(x, y, local);
        if (!e.has_distance || !e.side_known) {
            const Vec2 q = point(x, y);
            if (cover.branch) {
                // Newton on the block's branch; a point no nearer than the middle's distance
                // plus the way to it allows is not the nearest, and is searched after all.
                const Followed f = followBranch(o, *cover.branch, q, settled_mm);
                if (f.ok && f.distance_mm <= std::abs(d) + (q - c).norm() + o.tolerance_mm) {
                    e.has_distance = e.side_known = true;
                    e.segment = f.segment;
                    e.t = f.t;
                    e.signed_distance_mm = in ? -f.distance_mm : f.distance_mm;
                    e.value = shadeFromNearest(g, q, f.distance_mm, f.point_mm, in);
                    return e.value;
                }
            }
            Nearest n = nearest(o, q, bound + (q - c).norm(), mid.chord / kChunkChords);
            bool side = in;
            refineOnCurve(g, q, n, side);
            e.has_distance = e.side_known = true;
            e.chord = n.chord;
            e.segment = n.segment;
            e.t = n.t;
            e.signed_distance_mm = side ? -n.distance_mm : n.distance_mm;
            e.value = shadeFromNearest(g, q, n.distance_mm, n.point_mm, side);
        }
        return e.value;
    };
    std::array<double, 3> v[3][3];
    for (size_t j = 0; j < 3; ++j)
        for (size_t i = 0; i < 3; ++i)
            v[j][i] = (i == 1 && j == 1) ? mid.value : sample(cover.node_x[i], cover.node_y[j]);
    for (const double y :
         {0.5 * (cover.node_y[0] + cover.node_y[1]), 0.5 * (cover.node_y[1] + cover.node_y[2])}) {
        const auto wy = quadraticWeights(cover.node_y[0], cover.node_y[1], cover.node_y[2], y);
        for (const double x : {0.5 * (cover.node_x[0] + cover.node_x[1]),
                               0.5 * (cover.node_x[1] + cover.node_x[2])}) {
            const auto wx = quadraticWeights(cover.node_x[0], cover.node_x[1], cover.node_x[2], x);
            const std::array<double, 3> truth = sample(x, y);
            for (size_t k = 0; k < 3; ++k) {
                double interpolated = 0.0;
                for (size_t j = 0; j < 3; ++j)
                    for (size_t i = 0; i < 3; ++i) interpolated += wy[j] * wx[i] * v[j][i][k];
                if (!(std::abs(interpolated - truth[k]) <= o.tolerance)) return cover;
            }
        }
    }
    cover.kind = GhostBlockKind::Smooth;
    for (size_t j = 0; j < 3; ++j)
        for (size_t i = 0; i < 3; ++i)
            for (size_t k = 0; k < 3; ++k) cover.nodes[j][i][k] = static_cast<float>(v[j][i][k]);
    return cover;
}

void addGhostBlock(const GhostPrimitive& g,
                   int64_t x0,
                   int64_t y0,
                   int64_t x1,
                   int64_t y1,
                   float* rgb,
                   int64_t row_stride,
                   const GhostBranch* given) {
    if (!g.outline) {
        for (int64_t y = y0; y <= y1; ++y) addGhostRow(g, y, x0, x1, rgb + (y - y0) * row_stride);
        return;
    }
    const GhostOutline& o = *g.outline;
    const BlockMiddle mid = blockMiddle(g, x0, y0, x1, y1);
    const Vec2 c = mid.centre_mm;
    const double r = mid.radius_mm;
    // The chords that can be nearest to some pixel of the block: within the middle pixel's
    // distance plus twice the block's radius of it. In single precision relative to the block's
    // middle pixel (a few pixels of millimetres: rounding far below the sagitta), in arrays the
    // compiler vectorizes; only the nearest one is recomputed in double. Gathered when a pixel
    // first needs them.
    thread_local std::vector<float> ax, ay, ex, ey, inv, d2;
    thread_local std::vector<int32_t> index;
    bool gathered = false;
    size_t count = 0, padded = 0;
    double reach = 0.0;
    const auto gather = [&] {
        if (gathered) return;
        gathered = true;
        reach = nearest(o, c).distance_mm + 2.0 * r;
        const double reach2 = reach * reach * (1.0 + 1e-12) + 1e-300;
        ax.clear(), ay.clear(), ex.clear(), ey.clear(), inv.clear(), index.clear();
        for (const auto& chunk : o.chunks) {
            if (boxDistance2(chunk, c) > reach2) continue;
            for (int32_t i = chunk.begin; i < chunk.end; ++i) {
                const Vec2& a = o.vertices_mm[static_cast<size_t>(i)];
                const Vec2& e = o.edges_mm[static_cast<size_t>(i)];
                const double t = std::clamp(
                    (c - a).dot(e) * o.inverse_length2[static_cast<size_t>(i)], 0.0, 1.0);
                if ((a + t * e - c).squaredNorm() > reach2) continue;
                ax.push_back(static_cast<float>(a.x() - c.x()));
                ay.push_back(static_cast<float>(a.y() - c.y()));
                ex.push_back(static_cast<float>(e.x()));
                ey.push_back(static_cast<float>(e.y()));
                const float len2f = ex.back() * ex.back() + ey.back() * ey.back();
                inv.push_back(len2f > 0.0f ? 1.0f / len2f : 0.0f);
                index.push_back(i);
            }
        }
        count = index.size();
        // Padded to whole vectors with chords of no length far away (squared distance about
        // 1e36, finite, never the nearest).
        padded = (count + kLanes - 1) / kLanes * kLanes;
        ax.resize(padded, 1e18f), ay.resize(padded, 1e18f), ex.resize(padded, 0.0f);
        ey.resize(padded, 0.0f), inv.resize(padded, 0.0f);
        d2.resize(padded);
    };
    const ChordKernel kernel = chordKernel();
    // A pixel the slow way: the nearest of the candidates, refined on the curve, its side.
    const auto exactAt = [&](int64_t x, int64_t y, const Vec2& q, Nearest& n, bool& in) {
        gather();
        const ChordArrays chords{ax.data(), ay.data(), ex.data(), ey.data(), inv.data()};
        const float lowest = kernel(chords, padded, static_cast<float>(q.x() - c.x()),
                                    static_cast<float>(q.y() - c.y()), d2.data());
        size_t best = 0;  // the first that is the nearest
        while (best + 1 < count && d2[best] != lowest) ++best;
        n = Nearest{};
        n.chord = index[best];
        const Vec2& a = o.vertices_mm[static_cast<size_t>(n.chord)];
        const Vec2& e = o.edges_mm[static_cast<size_t>(n.chord)];
        n.u =
            std::clamp((q - a).dot(e) * o.inverse_length2[static_cast<size_t>(n.chord)], 0.0, 1.0);
        n.point_mm = a + n.u * e;
        n.distance_mm = (n.point_mm - q).norm();
        in = inside(o, x, y);
        refineOnCurve(g, q, n, in);
    };
    const auto addExact = [&](int64_t x, int64_t y) {
        const Vec2 q = pixelCentreMm(g.mapping, x, y);
        Nearest n;
        bool in = false;
        exactAt(x, y, q, n, in);
        const auto v = shadeFromNearest(g, q, n.distance_mm, n.point_mm, in);
        float* pixel = rgb + (y - y0) * row_stride + (x - x0) * 3;
        for (size_t k = 0; k < 3; ++k) pixel[k] += static_cast<float>(v[k]);
    };
    const auto perPixel = [&] {
        for (int64_t y = y0; y <= y1; ++y)
            for (int64_t x = x0; x <= x1; ++x) addExact(x, y);
    };
    // On one branch (given by the classification of the tile, or found here from the
    // candidates), every pixel's nearest point is found by Newton from a prediction, four pixels
    // at a time; the pixels Newton does not settle are searched.
    std::optional<GhostBranch> branch;
    if (given) {
        branch = *given;
    } else {
        gather();
        if (count == 0) return perPixel();
        const std::optional<int> kind = singleBranch(o, index.data(), count, c, reach - r);
        if (!kind) return perPixel();
        Nearest middle;
        bool in = false;
        exactAt(mid.x, mid.y, c, middle, in);
        branch = branchAt(o, middle.segment, middle.t, c);
        if (!branch) return perPixel();
        branch->outward = *kind;
    }
    const int segments = static_cast<int>(o.segment_power.size());
    const int64_t width = x1 - x0 + 1;
    if (segments < 1 || width > 256 || !std::isfinite(branch->loop_u)) return perPixel();
    BranchTile b;
    {
        const double length = static_cast<double>(segments);
        const double u = branch->loop_u - length * std::floor(branch->loop_u / length);
        const int segment = std::min(static_cast<int>(u), segments - 1);
        b.t_m = std::clamp(u - segment, 0.0, 1.0);
        for (int k = 0; k < 3; ++k) {
            const auto& p =
                o.segment_power[static_cast<size_t>((segment + segments - 1 + k) % segments)];
            b.power[static_cast<size_t>(k)] = {p[0], p[1], p[2], p[3] - branch->middle_mm};
        }
    }
    b.gradient_t = branch->gradient;
    b.outward = branch->outward;
    b.distance_mm = branch->distance_mm;
    b.px_x = g.mapping.px_per_mm_x;
    b.px_y = g.mapping.px_per_mm_y;
    b.half_x = 0.5 / b.px_x;
    b.half_y = 0.5 / b.px_y;
    b.converged_mm = 1e-3 * o.tolerance_mm;
    b.mm_per_px = 1.0 / std::min(b.px_x, b.px_y);
    b.near_mm = 2.0 * o.tolerance_mm;
    const BranchRow row_kernel = branchRow();
    std::array<uint8_t, 256> in{}, done{};
    for (int64_t y = y0; y <= y1; ++y) {
        for (int64_t x = x0; x <= x1; ++x) {
            in[static_cast<size_t>(x - x0)] = inside(o, x, y) ? 1 : 0;
            done[static_cast<size_t>(x - x0)] = 0;
        }
        const Vec2 first = pixelCentreMm(g.mapping, x0, y) - branch->middle_mm;
        b.first_x = first.x();
        b.row_y = first.y();
        row_kernel(b, g.shading, x0, x1, in.data(), rgb + (y - y0) * row_stride, done.data());
        for (int64_t x = x0; x <= x1; ++x)
            if (!done[static_cast<size_t>(x - x0)]) addExact(x, y);
    }
}

}  // namespace flarelab::render
