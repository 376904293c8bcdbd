// ============================================================================
//  flarelab render: GhostEvaluation, GhostDrawOptions, GhostOutline, GhostPrimitive,
//                   prepareGhostPrimitive, addGhostRow, coverGhostBlock, addGhostBlock,
//                   ghostPixelValue
// ============================================================================
//
// The second primitive kind of the tile engine (tiles.h): a model ghost, a closed loop of cubic
// Béziers in sensor millimetres shaded by the transfer function of its signed distance
// (ghost_shape.h). A pixel gets the ghost's mean over its area (shadeGhostBlock), as a sensor's
// pixel integrates the light: an edge sharper than a pixel is drawn anti-aliased, as the
// simulator and a camera record it. Its pixel range is the loop's control-point box (which holds
// the curve) grown by the outer falloff, past which the ghost is zero, and by half a pixel,
// clipped to the image; the tile engine visits only the dense tiles that range touches.
//
// Two evaluations of the same image:
//   - Exact (the reference): every pixel of the range runs shadeGhostBlock, Newton's distance to
//     the Béziers, the winding test and eq. 6.4's box mean. Seconds per 1080p frame of a fitted
//     model, whose falloffs are often hundreds of pixels wide.
//   - Fast (the default): the loop is flattened once into chords that stay within `sagitta_px`
//     (0.01 px) of the curve, grouped in runs of 8 with bounding boxes; the inside test is a table
//     of spans per pixel row (where the chords' winding number is not zero). The signed distance
//     to the chords is within the sagitta of the curve's and, like it, 1-Lipschitz, so one value
//     at a block's centre bounds it over the block (coverGhostBlock): a block beyond the outer
//     falloff is skipped, one deep inside is the constant inner value, and one away from the edge
//     that the biquadratic through its 3 x 3 nodes matches to within `smooth_tolerance` of the
//     ghost's peak at four check points is drawn by that interpolation. Only the dense tiles left,
//     those an edge crosses, are evaluated per pixel (addGhostBlock): the distance over the
//     chords near the tile, the sign from the spans, and eq. 6.4's box mean (the powers) as in
//     the exact evaluation. bench/playback_bench.cpp measures both and their difference.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "render/ghost_quads.h"
#include "render/ghost_shape.h"

namespace flarelab::render {

enum class GhostEvaluation { Fast, Exact };

struct GhostDrawOptions {
    FastDistanceOptions distance;  // the exact evaluation's Newton distance
    GhostEvaluation evaluation = GhostEvaluation::Fast;
    double sagitta_px = 0.01;  // fast: chords within this of the curve, in (0, 1]
    // fast: a block drawn by interpolation is off by at most this fraction of the ghost's peak
    // (its largest border or inner value) at its check points, in (0, 0.1]
    double smooth_tolerance = 1e-4;
    // fast: when larger than the ghost's peak, the peak the tolerance is a fraction of: a frame's
    // brightest ghost, so that the frame's error budget, not each ghost's, sets how finely a dim
    // ghost is drawn. Finite and >= 0.
    double tolerance_peak = 0.0;
};

// The fast evaluation's flattened loop (see above). Built by prepareGhostPrimitive.
struct GhostOutline {
    struct Chunk {
        Eigen::Vector2d lo_mm, hi_mm;  // box of the chunk's chords
        int32_t begin = 0, end = 0;    // chords begin..end-1; chord i runs vertex i -> i + 1
        // Over the chunk's chords' ends (bend_angle): the sum of the turns' sizes, of the left
        // and of the right turns, and the smallest radius.
        double turn = 0.0, left = 0.0, right = 0.0;
        double radius_mm = std::numeric_limits<double>::infinity();
    };
    std::vector<Eigen::Vector2d> vertices_mm;  // closed: the last vertex repeats the first
    std::vector<Eigen::Vector2d> edges_mm;     // chord i: vertex i + 1 minus vertex i
    std::vector<double> inverse_length2;       // 1 / |edge i|^2, 0 for a chord of no length
    // The loop's segments in the power basis, C(t) = ((a t + b) t + c) t + d as {a, b, c, d},
    // for Newton's steps on the curve.
    std::vector<std::array<Eigen::Vector2d, 4>> segment_power;
    // Chord i replaces segment chord_segment[i] of the loop from t = chord_t[i][0] to [1]: where
    // a pixel needs the distance to the curve itself, Newton starts there.
    std::vector<int32_t> chord_segment;
    std::vector<std::array<double, 2>> chord_t;
    std::vector<Chunk> chunks;
    // Where chord i meets chord i + 1 (the last meets the first): the angle it turns (radians,
    // positive to the left) and the radius of curvature that implies, half their lengths' sum
    // over the angle's size (infinite where it runs straight on; zero at a joint where the
    // segments meet at an angle or a handle of no length stops the curve). The single-branch
    // tests read them.
    std::vector<double> bend_angle;
    std::vector<double> bend_radius_mm;
    // The loop turns one way only, once around (a convex outline): every point outside it has
    // one nearest point.
    bool convex = false;
    bool turns_left = true;  // the loop's turns sum to a left turn (counter-clockwise)
    // Boxes over runs of chunks, for the nearest-chord search: levels[l][i] bounds chunks
    // i 2^(l+1) .. (i + 1) 2^(l+1) - 1; the last level is one box.
    std::vector<std::vector<std::array<Eigen::Vector2d, 2>>> levels;
    // Row y (in [row0, row0 + rows)) is inside the loop (non-zero winding) at pixel x exactly
    // where x + 0.5 lies in one of spans_px[row_start[y - row0] .. row_start[y - row0 + 1]).
    int64_t row0 = 0;
    std::vector<int32_t> row_start;
    std::vector<std::array<double, 2>> spans_px;
    double tolerance_mm = 0.0;  // the chords' largest distance from the curve
    double reach_mm = 0.0;      // half a pixel's diagonal: how far a pixel's mean looks
    double tolerance = 0.0;     // smooth_tolerance times the peak, in the shading's unit
};

struct GhostPrimitive {
    BezierLoop loop_mm;
    GhostShading shading;
    SensorToImage mapping;  // sensor mm to pixels of the image it is drawn into
    FastDistanceOptions distance;
    int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;     // inclusive pixel range
    std::shared_ptr<const GhostOutline> outline;  // null: the exact evaluation
};

// nullopt when the ghost cannot put light in a width x height image: its range misses the image,
// it is black in every channel, or anything about it is not finite or out of bounds (an empty
// loop, a shading validateShading refuses, options out of their ranges).
std::optional<GhostPrimitive> prepareGhostPrimitive(const BezierLoop& loop_mm,
                                                    const GhostShading& shading,
                                                    const SensorToImage& mapping,
                                                    int64_t width,
                                                    int64_t height,
                                                    const GhostDrawOptions& options = {});

// Adds the ghost's exact mean over the pixels (x, y) for x in [x0, x1] to rgb, three floats
// per pixel starting with pixel x0. The caller keeps x0..x1 and y inside the ghost's range.
void addGhostRow(const GhostPrimitive& ghost, int64_t y, int64_t x0, int64_t x1, float* rgb);

// What a block of pixels (x0..x1, y0..y1, inclusive, inside the image) holds of a ghost.
enum class GhostBlockKind {
    Outside,  // nothing: the block is beyond the outer falloff or the range
    Smooth,   // the biquadratic through `nodes` (constant inside the inner falloff)
    Edge,     // neither: smaller blocks, or per pixel
};
// Pixel x of a row has its centre at x in the coordinates below (pixel-centre coordinates); a
// block of pixels x0..x1 spans x0 - 0.5 .. x1 + 0.5.
inline int64_t midPixel(int64_t a, int64_t b) { return a + (b - a) / 2; }
// The weights of the quadratic through nodes n0 <= n1 <= n2 at x (Lagrange); linear between n0
// and n2 when the middle node coincides with one of them, constant when all do.
inline std::array<double, 3> quadraticWeights(double n0, double n1, double n2, double x) {
    if (!(n2 > n0)) return {1.0, 0.0, 0.0};
    if (!(n1 > n0) || !(n2 > n1)) {
        const double t = (x - n0) / (n2 - n0);
        return {1.0 - t, 0.0, t};
    }
    return {(x - n1) * (x - n2) / ((n0 - n1) * (n0 - n2)),
            (x - n0) * (x - n2) / ((n1 - n0) * (n1 - n2)),
            (x - n0) * (x - n1) / ((n2 - n0) * (n2 - n1))};
}
// A block whose pixels' nearest curve points all lie on one branch of the loop, where each has
// one point at which the distance stops changing (coverGhostBlock checks it from the chords near
// the block): the loop parameter (segment + t) of the block middle's nearest point and its
// derivative across the sensor there. Newton from the first-order prediction
// loop_u + gradient . (q - middle) then finds the nearest point of any point of the block with no
// search. It holds in every part of the block.
// Where the branch is one only for points on the outer side of its bend (`outward` +1: left of
// the curve's direction, -1: right; 0: either side), a point Newton reaches with the point on the
// other side is a local minimum of the distance on the far side, not the nearest.
struct GhostBranch {
    double loop_u = 0.0;
    Eigen::Vector2d middle_mm = Eigen::Vector2d::Zero();
    Eigen::Vector2d gradient = Eigen::Vector2d::Zero();  // per mm
    int outward = 0;
    // The middle's distance from the curve: no point q is farther than this plus |q - middle|
    // (the distance is 1-Lipschitz), so a point Newton reaches beyond that is not the nearest.
    double distance_mm = 0.0;
};

struct GhostBlockCover {
    GhostBlockKind kind = GhostBlockKind::Edge;
    // The nodes, in pixel-centre coordinates: the block's outer edges and its middle,
    // {x0 - 0.5, (x0 + x1) / 2, x1 + 0.5} (and the same in y). Nodes on the block's edges are
    // shared with its neighbours and its halves, so a GhostSampleMemo serves them once.
    std::array<double, 3> node_x{}, node_y{};
    // RGB at the nodes when Smooth: nodes[j][i] at (node_x[i], node_y[j])
    std::array<std::array<std::array<float, 3>, 3>, 3> nodes{};
    // Set when the block (or the enclosing one whose branch was passed in) lies on one branch;
    // the caller passes it on to the block's parts.
    std::optional<GhostBranch> branch;
};

// The fast evaluation's values at points of a lattice, kept while one thread classifies one
// ghost over one region: every node and check point of the blocks coverGhostBlock is asked about
// there, when the blocks are whole dense tiles of a size divisible by 4 (their edges, middles and
// quarter points fall on a lattice of a quarter tile), is evaluated once. Values are what
// coverGhostBlock would compute without it, to rounding (where two chords are equally near a
// point, the searches may meet either first). Forgetting is O(1) (a stamp per slot).
class GhostSampleMemo {
public:
    // Forget everything; remember points of the lattice of `spacing_px` (> 0) pixels whose
    // origin is the pixel edge (origin_x, origin_y) (pixel-centre coordinate origin - 0.5),
    // `cells_x` x `cells_y` cells, for `ghost`.
    void reset(const GhostPrimitive* ghost,
               int64_t origin_x,
               int64_t origin_y,
               int64_t cells_x,
               int64_t cells_y,
               int64_t spacing_px);
    struct Entry {
        bool has_distance = false;
        bool side_known = false;  // false: too near the outline to take the side from a pixel
        int32_t chord = 0;        // the nearest chord of the outline
        double signed_distance_mm = 0.0;
        int32_t segment = 0;  // the nearest curve point: segment and parameter
        double t = 0.0;
        std::array<double, 3> value{};  // when side_known
    };
    // The entry of the point at pixel-centre coordinates (x, y), or null when it is not on the
    // lattice or `ghost` is not the one set.
    Entry* find(const GhostPrimitive& ghost, double x, double y);
    int64_t hits = 0, misses = 0;  // lookups of a known point and of a new one, ever

private:
    struct Slot {
        uint32_t stamp = 0;
        Entry entry;
    };
    const GhostPrimitive* ghost_ = nullptr;
    int64_t origin_x_ = 0, origin_y_ = 0, cells_x_ = 0, cells_y_ = 0, spacing_ = 1;
    uint32_t stamp_ = 0;
    std::vector<Slot> slots_;
};

// `finest`: the caller cannot split the block further, so it may be interpolated although the
// outer or inner falloff's end crosses it (checked all the same). An exact ghost is never Smooth.
// `memo`, when given, is set for this ghost (else ignored) and shares samples between calls.
// `branch`, when given, is the cover.branch of a block that holds this one: the samples are then
// found by Newton from it instead of searched (the same values, to rounding).
GhostBlockCover coverGhostBlock(const GhostPrimitive& ghost,
                                int64_t x0,
                                int64_t y0,
                                int64_t x1,
                                int64_t y1,
                                bool finest,
                                GhostSampleMemo* memo = nullptr,
                                const GhostBranch* branch = nullptr);

// Adds the ghost's mean over the pixels x0..x1, y0..y1 (inside the ghost's range) to rgb: pixel
// (x, y) at rgb + (y - y0) * row_stride + (x - x0) * 3. Fast or exact as the ghost was prepared.
// `branch`, when given, is the block's GhostBranch from coverGhostBlock (the block's pixels lie
// in the region it holds for); else the block finds whether it lies on one.
void addGhostBlock(const GhostPrimitive& ghost,
                   int64_t x0,
                   int64_t y0,
                   int64_t x1,
                   int64_t y1,
                   float* rgb,
                   int64_t row_stride,
                   const GhostBranch* branch = nullptr);

// The fast evaluation of one pixel (any pixel of the image; zero outside the range). For an
// exact ghost, the exact value.
std::array<double, 3> ghostPixelValue(const GhostPrimitive& ghost, int64_t x, int64_t y);

}  // namespace flarelab::render
