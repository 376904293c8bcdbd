// ============================================================================
//  flarelab render: Quad, quadBarycentrics, orientation
// ============================================================================
//
// The renderer's primitive (Bodonyi & Kunkli 2023 §4.1): the image of one cell of a ray grid, four
// corners in pixel coordinates with the attributes the per-pixel accumulation interpolates. The
// corners keep grid order (i, j), (i+1, j), (i+1, j+1), (i, j+1), so a quad is a closed polygon
// with edges 0-1, 1-2, 2-3, 3-0.
//
// quadBarycentrics answers whether a pixel lies in the quad and with which weights the corner
// attributes mix there (§3.4 and §4.5 of the paper):
//   - strictly convex quads (every ray-grid cell of a smooth lens away from caustics) use
//     Wachspress coordinates, eq. 8 and 9: rational, smooth, cheap;
//   - simple non-convex quads use mean value coordinates (Floater 2003; eq. 7, in the form of
//     Hormann & Floater 2006 that stays finite up to the boundary);
//   - everything else (coincident corners, all corners on one line, bow-ties where the grid
//     folds over at a caustic) is split into triangles, or a segment, with ordinary barycentrics.
// All three reproduce linear functions (sum w_i corner_i = p, sum w_i = 1), and on an edge all of
// them reduce to linear interpolation between that edge's two corners, so neighbouring quads that
// share an edge agree on it.
//
// Every decision (inside or outside, which class a quad is in) is taken with `orientation`, an
// exact predicate: a point that lies exactly on a shared edge belongs to both quads, never to
// neither.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <optional>

namespace flarelab::render {

struct QuadCorner {
    Eigen::Vector2d position_px = Eigen::Vector2d::Zero();  // image space, DESIGN.md
    float throughput = 0.0f;
    float stop_u = 0.0f;  // stop coordinates as in optics::GridSample
    float stop_v = 0.0f;
    float aperture_ratio = 0.0f;  // optics::GridSample::aperture_ratio: above 1, vignetted
};

struct Quad {
    std::array<QuadCorner, 4> corners;  // grid order (i,j), (i+1,j), (i+1,j+1), (i,j+1)
    // Bit k: the edge from corner k to corner k+1 is an interior edge of a smooth stretch of the
    // ghost (render/ghost_quads.h MergeOptions::centre_edge_jump), drawn by the pixel centre's
    // side instead of cut by area. 0 for every quad not made by quadsFromGrid with that option.
    uint8_t centre_edges = 0;
};

// The sign of the cross product (b - a) x (c - a) = (bx - ax)(cy - ay) - (by - ay)(cx - ax),
// computed exactly: +1, 0 or -1, whatever the magnitudes. In image space (y down) +1 is a
// clockwise turn on screen. A double evaluation of the formula decides when its value clears an
// error bound (Shewchuk 1997, orient2d's first stage); below the bound the six products are
// expanded into exact sums of doubles (FMA two-products and two-sums) whose sign is the sign of
// the largest term. Exact for all finite inputs whose products neither overflow nor fall below
// 1e-290 in magnitude (pixel coordinates are far inside that range).
int orientation(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Eigen::Vector2d& c);

// True when all four corner turns have the same non-zero sign. For four points that means the
// quad is simple and strictly convex (its exterior angles, all of one sign and each below pi,
// must add up to exactly one turn). Flat corners, coincident corners and bow-ties are not convex.
bool quadIsConvex(const Quad& quad);

// Generalized barycentric coordinates of p with respect to the quad's corners, in corner order,
// or nullopt when p is outside. "Inside" is the closed region the boundary winds around (non-zero
// winding number) together with the boundary itself; for a degenerate quad of zero area only its
// edges are inside. The weights are finite, non-negative for convex quads, and sum to 1; a point
// on an edge gets weight only on that edge's corners. Non-finite corners or p give nullopt.
std::optional<std::array<double, 4>> quadBarycentrics(const Quad& quad, const Eigen::Vector2d& p);

// The corner attributes mixed with barycentric weights (from quadBarycentrics).
struct QuadSample {
    float throughput = 0.0f;
    float stop_u = 0.0f;
    float stop_v = 0.0f;
    float aperture_ratio = 0.0f;
};
QuadSample interpolateQuad(const Quad& quad, const std::array<double, 4>& weights);

}  // namespace flarelab::render
