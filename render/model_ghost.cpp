#include "render/model_ghost.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

namespace flarelab::render {
namespace {

using Vec2 = Eigen::Vector2d;
using Cubic = std::array<Vec2, 4>;

constexpr int kChunkChords = 8;
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
    double peak = 0.0;
    for (int c = 0; c < 3; ++c)
        peak = std::max({peak, shading.border_rgb[c], shading.inner_rgb[c]});
    o->tolerance = options.smooth_tolerance * peak;
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
    for (int32_t begin = 0; begin < chords; begin += kChunkChords) {
        GhostOutline::Chunk chunk;
        chunk.begin = begin;
        chunk.end = std::min(chords, begin + kChunkChords);
        chunk.lo_mm = chunk.hi_mm = o->vertices_mm[static_cast<size_t>(begin)];
        for (int32_t i = begin + 1; i <= chunk.end; ++i) {
            chunk.lo_mm = chunk.lo_mm.cwiseMin(o->vertices_mm[static_cast<size_t>(i)]);
            chunk.hi_mm = chunk.hi_mm.cwiseMax(o->vertices_mm[static_cast<size_t>(i)]);
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
};

double boxDistance2(const GhostOutline::Chunk& c, const Vec2& q) {
    const double dx = std::max({c.lo_mm.x() - q.x(), 0.0, q.x() - c.hi_mm.x()});
    const double dy = std::max({c.lo_mm.y() - q.y(), 0.0, q.y() - c.hi_mm.y()});
    return dx * dx + dy * dy;
}

void scanChunk(const GhostOutline& o,
               const GhostOutline::Chunk& c,
               const Vec2& q,
               double& best2,
               Nearest& best) {
    for (int32_t i = c.begin; i < c.end; ++i) {
        const Vec2& a = o.vertices_mm[static_cast<size_t>(i)];
        const Vec2 e = o.vertices_mm[static_cast<size_t>(i) + 1] - a;
        const double len2 = e.squaredNorm();
        const double t = len2 > 0.0 ? std::clamp((q - a).dot(e) / len2, 0.0, 1.0) : 0.0;
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
    const double dx = std::max({box[0].x() - q.x(), 0.0, q.x() - box[1].x()});
    const double dy = std::max({box[0].y() - q.y(), 0.0, q.y() - box[1].y()});
    return dx * dx + dy * dy;
}

// The nearest chord point to q: best first down the box levels, never into a box farther than
// the best so far. `bound`, when finite, is known to be at least the distance (the distance is
// 1-Lipschitz, so a neighbour's distance plus the way to it is one) and prunes from the start.
Nearest nearest(const GhostOutline& o,
                const Vec2& q,
                double bound = std::numeric_limits<double>::infinity()) {
    const double start2 = std::isfinite(bound) ? bound * bound * (1.0 + 1e-9) + 1e-300
                                               : std::numeric_limits<double>::infinity();
    double best2 = start2;
    Nearest best;
    best.point_mm = q;
    struct Item {
        int level;  // -1: a chunk
        size_t index;
    };
    Item stack[160];
    int top = 0;
    if (o.levels.empty())
        stack[top++] = {-1, 0};
    else
        stack[top++] = {static_cast<int>(o.levels.size()) - 1, 0};
    const auto distance2 = [&](const Item& item) {
        return item.level < 0
                   ? boxDistance2(o.chunks[item.index], q)
                   : boxDistance2(o.levels[static_cast<size_t>(item.level)][item.index], q);
    };
    while (top > 0) {
        const Item item = stack[--top];
        if (distance2(item) > best2) continue;
        if (item.level < 0) {
            scanChunk(o, o.chunks[item.index], q, best2, best);
            continue;
        }
        const int child_level = item.level - 1;
        const size_t count =
            child_level < 0 ? o.chunks.size() : o.levels[static_cast<size_t>(child_level)].size();
        Item a{child_level, 2 * item.index}, b{child_level, 2 * item.index + 1};
        if (b.index >= count) {
            stack[top++] = a;
            continue;
        }
        if (distance2(a) < distance2(b)) std::swap(a, b);  // the nearer one is popped first
        stack[top++] = a;
        stack[top++] = b;
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
    const auto c = g.loop_mm.segment(o.chord_segment[i]);
    double t = o.chord_t[i][0] + n.u * (o.chord_t[i][1] - o.chord_t[i][0]);
    for (int step = 0; step < 2; ++step) {
        const double s = 1.0 - t;
        const Vec2 p = (s * s * s) * c[0] + (3.0 * s * s * t) * c[1] + (3.0 * s * t * t) * c[2] +
                       (t * t * t) * c[3];
        const Vec2 d1 = (3.0 * s * s) * (c[1] - c[0]) + (6.0 * s * t) * (c[2] - c[1]) +
                        (3.0 * t * t) * (c[3] - c[2]);
        const Vec2 d2 =
            (6.0 * s) * (c[2] - 2.0 * c[1] + c[0]) + (6.0 * t) * (c[3] - 2.0 * c[2] + c[1]);
        const Vec2 r = p - q;
        const double gn = d1.squaredNorm();
        const double h = gn + r.dot(d2);
        const double curvature = h > 0.0 ? h : gn;
        if (!(curvature > 0.0)) break;
        t = std::clamp(t - r.dot(d1) / curvature, 0.0, 1.0);
    }
    const double s = 1.0 - t;
    const Vec2 p = (s * s * s) * c[0] + (3.0 * s * s * t) * c[1] + (3.0 * s * t * t) * c[2] +
                   (t * t * t) * c[3];
    const double d = (p - q).norm();
    if (d <= n.distance_mm + o.tolerance_mm) {
        n.distance_mm = d;
        n.point_mm = p;
    }
    if (n.distance_mm <= 2.0 * o.tolerance_mm) in = windingNumber(g.loop_mm, q) != 0;
}

std::array<double, 3> fastValue(const GhostPrimitive& g,
                                int64_t x,
                                int64_t y,
                                double bound = std::numeric_limits<double>::infinity()) {
    const Vec2 q = pixelCentreMm(g.mapping, x, y);
    Nearest n = nearest(*g.outline, q, bound);
    bool in = inside(*g.outline, x, y);
    refineOnCurve(g, q, n, in);
    return shadeFromNearest(g, q, n.distance_mm, n.point_mm, in);
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
        !(options.smooth_tolerance > 0.0 && options.smooth_tolerance <= 0.1))
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

GhostBlockCover coverGhostBlock(
    const GhostPrimitive& g, int64_t x0, int64_t y0, int64_t x1, int64_t y1, bool finest) {
    GhostBlockCover cover;
    if (x1 < g.x0 || x0 > g.x1 || y1 < g.y0 || y0 > g.y1) {
        cover.kind = GhostBlockKind::Outside;
        return cover;
    }
    if (!g.outline) return cover;  // Edge: every pixel exactly
    const GhostOutline& o = *g.outline;
    const GhostShading& s = g.shading;
    // The signed distance is 1-Lipschitz and a pixel's mean reaches reach_mm beyond its centre,
    // so the value at the block's middle pixel bounds every pixel's within r of it.
    const BlockMiddle mid = blockMiddle(g, x0, y0, x1, y1);
    const int64_t mx = mid.x, my = mid.y;
    const Vec2 c = mid.centre_mm;
    const double r = mid.radius_mm;
    Nearest nc = nearest(o, c);
    bool in = inside(o, mx, my);
    refineOnCurve(g, c, nc, in);
    const double d = in ? -nc.distance_mm : nc.distance_mm;
    // Pixels take the curve's distance where Newton finds it, the chords' (within a sagitta)
    // where not: two sagittas of slack on the bound.
    const double h = o.reach_mm + 2.0 * o.tolerance_mm;
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
    if (std::abs(d) - r <= 2.0 * h) return cover;
    if (!finest) {
        const double f = in ? s.inner_falloff_mm : s.outer_falloff_mm;
        if (std::abs(d) - r <= f + h && std::abs(d) + r >= f - h) return cover;
    }
    // Nine nodes carry the block, four points between them check it.
    const int64_t xs[3] = {x0, mx, x1}, ys[3] = {y0, my, y1};
    const auto sample = [&](int64_t x, int64_t y) {
        return fastValue(
            g, x, y, nc.distance_mm + o.tolerance_mm + (pixelCentreMm(g.mapping, x, y) - c).norm());
    };
    std::array<double, 3> v[3][3];
    for (int j = 0; j < 3; ++j)
        for (int i = 0; i < 3; ++i)
            v[j][i] = (i == 1 && j == 1) ? shadeFromNearest(g, c, nc.distance_mm, nc.point_mm, in)
                                         : sample(xs[i], ys[j]);
    const int64_t check_x[2] = {midPixel(x0, mx), midPixel(mx, x1)};
    const int64_t check_y[2] = {midPixel(y0, my), midPixel(my, y1)};
    for (const int64_t y : check_y) {
        const auto wy = quadraticWeights(static_cast<double>(y0), static_cast<double>(my),
                                         static_cast<double>(y1), static_cast<double>(y));
        for (const int64_t x : check_x) {
            const auto wx = quadraticWeights(static_cast<double>(x0), static_cast<double>(mx),
                                             static_cast<double>(x1), static_cast<double>(x));
            const std::array<double, 3> truth = sample(x, y);
            for (size_t k = 0; k < 3; ++k) {
                double interpolated = 0.0;
                for (int j = 0; j < 3; ++j)
                    for (int i = 0; i < 3; ++i) interpolated += wy[j] * wx[i] * v[j][i][k];
                if (!(std::abs(interpolated - truth[k]) <= o.tolerance)) return cover;
            }
        }
    }
    cover.kind = GhostBlockKind::Smooth;
    for (int j = 0; j < 3; ++j)
        for (int i = 0; i < 3; ++i)
            for (size_t k = 0; k < 3; ++k) cover.nodes[j][i][k] = static_cast<float>(v[j][i][k]);
    return cover;
}

void addGhostBlock(const GhostPrimitive& g,
                   int64_t x0,
                   int64_t y0,
                   int64_t x1,
                   int64_t y1,
                   float* rgb,
                   int64_t row_stride) {
    if (!g.outline) {
        for (int64_t y = y0; y <= y1; ++y) addGhostRow(g, y, x0, x1, rgb + (y - y0) * row_stride);
        return;
    }
    const GhostOutline& o = *g.outline;
    // The chords that can be nearest to some pixel of the block: within the middle pixel's
    // distance plus twice the block's radius of it.
    const BlockMiddle mid = blockMiddle(g, x0, y0, x1, y1);
    const Vec2 c = mid.centre_mm;
    const double r = mid.radius_mm;
    const double reach = nearest(o, c).distance_mm + 2.0 * r;
    const double reach2 = reach * reach * (1.0 + 1e-12) + 1e-300;
    // The candidates in single precision relative to the block's middle pixel (a few pixels of
    // millimetres: rounding far below the sagitta), in arrays the compiler vectorizes; only the
    // nearest one is recomputed in double.
    thread_local std::vector<float> ax, ay, ex, ey, inv, d2;
    thread_local std::vector<int32_t> index;
    ax.clear(), ay.clear(), ex.clear(), ey.clear(), inv.clear(), index.clear();
    for (const auto& chunk : o.chunks) {
        if (boxDistance2(chunk, c) > reach2) continue;
        for (int32_t i = chunk.begin; i < chunk.end; ++i) {
            const Vec2& a = o.vertices_mm[static_cast<size_t>(i)];
            const Vec2 e = o.vertices_mm[static_cast<size_t>(i) + 1] - a;
            const double len2 = e.squaredNorm();
            const double t = len2 > 0.0 ? std::clamp((c - a).dot(e) / len2, 0.0, 1.0) : 0.0;
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
    const size_t count = index.size();
    d2.resize(count);
    for (int64_t y = y0; y <= y1; ++y) {
        float* row = rgb + (y - y0) * row_stride;
        for (int64_t x = x0; x <= x1; ++x, row += 3) {
            const Vec2 q = pixelCentreMm(g.mapping, x, y);
            const float qx = static_cast<float>(q.x() - c.x());
            const float qy = static_cast<float>(q.y() - c.y());
            {
                // Plain selects, not std::clamp (whose NaN order keeps it scalar): one SIMD lane
                // per chord.
                const float* __restrict pax = ax.data();
                const float* __restrict pay = ay.data();
                const float* __restrict pex = ex.data();
                const float* __restrict pey = ey.data();
                const float* __restrict pinv = inv.data();
                float* __restrict pd2 = d2.data();
                for (size_t k = 0; k < count; ++k) {
                    const float px = qx - pax[k], py = qy - pay[k];
                    float t = (px * pex[k] + py * pey[k]) * pinv[k];
                    t = t > 0.0f ? t : 0.0f;
                    t = t < 1.0f ? t : 1.0f;
                    const float dx = px - t * pex[k], dy = py - t * pey[k];
                    pd2[k] = dx * dx + dy * dy;
                }
            }
            size_t best = 0;
            float best_d2 = d2[0];
            for (size_t k = 1; k < count; ++k)
                if (d2[k] < best_d2) best_d2 = d2[best = k];
            Nearest n;
            n.chord = index[best];
            const Vec2& a = o.vertices_mm[static_cast<size_t>(n.chord)];
            const Vec2 e = o.vertices_mm[static_cast<size_t>(n.chord) + 1] - a;
            const double len2 = e.squaredNorm();
            n.u = len2 > 0.0 ? std::clamp((q - a).dot(e) / len2, 0.0, 1.0) : 0.0;
            n.point_mm = a + n.u * e;
            n.distance_mm = (n.point_mm - q).norm();
            bool in = inside(o, x, y);
            refineOnCurve(g, q, n, in);
            const auto v = shadeFromNearest(g, q, n.distance_mm, n.point_mm, in);
            for (size_t k = 0; k < 3; ++k) row[k] += static_cast<float>(v[k]);
        }
    }
}

}  // namespace flarelab::render
