// ============================================================================
//  flarelab render: SensorToImage, adaptiveGridSize, GhostQuads, rasterizeReference
// ============================================================================
//
// From traced ray grids to pixels, the plain way: each 2 x 2 block of neighbouring rays of a grid
// becomes a quad (Bodonyi & Kunkli 2023 §4.1), and the reference rasterizer draws the quads of
// one ghost after another into the frame buffer, as Hullin et al. 2011 do ("the previous method"
// of the paper). It is the baseline the tiled renderer is measured against, and on dense grids the
// reference image for its PSNR.
//
// Radiometry. A grid ray stands for the light crossing one cell of the entry plane, of area
// cell_area_mm2 (perpendicular to the axis). Landing in a quad of area A on the sensor, that light
// spreads over A: a point inside receives throughput * cell_area / A (per unit of the light's
// irradiance, per pixel area). Summed over the image, a quad therefore delivers exactly its
// throughput times its cell area, the power that entered through its cell: the drawing conserves
// energy whatever the grid size.
//
// Pixels integrate over their area, as a sensor's do (and as the model ghosts of model_ghost.h
// are drawn). A pixel gets the integral of the quad's light over the part of the pixel that lies
// inside the quad, inside the stop and inside every clear aperture:
//   - the quad's straight edges cut the pixel square exactly (polygon clipping);
//   - the stop's outline and the vignetting edge are placed from the stop coordinates and the
//     clear-aperture ratio interpolated across the quad, linearized over the pixel (their value
//     and gradient at the centroid of what is left), and cut the same way: a circle of radius R
//     pixels is replaced by its tangent over one pixel, an area error below 1 / (12 R) of it;
//   - the throughput is taken at the centroid of the covered part (exact for a linear one).
// Pixels wholly inside all of these cost one interpolation, like a point sample. Quads that are
// not convex (folds at caustics) are point-sampled on a 4 x 4 grid per pixel. For tests and
// truth images, RasterOptions::supersample draws every quad by point sampling N x N per pixel
// instead, with the same interpolation.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "optics/aperture.h"
#include "optics/prescription.h"
#include "optics/ray_grid.h"
#include "render/quad.h"

namespace flarelab::render {

// Sensor millimetres to image pixels (DESIGN.md): the optical axis at the image centre, the
// sensor's width and height spread over the image's width and height.
struct SensorToImage {
    double px_per_mm_x = 1.0;
    double px_per_mm_y = 1.0;
    double centre_x_px = 0.0;
    double centre_y_px = 0.0;

    Eigen::Vector2d toPixels(double x_mm, double y_mm) const {
        return {centre_x_px + x_mm * px_per_mm_x, centre_y_px + y_mm * px_per_mm_y};
    }
};
SensorToImage sensorToImage(const optics::CameraDescription& camera, int64_t width, int64_t height);

// The grid size for a ghost, eq. 13 of Bodonyi & Kunkli 2023: the base size times
// min(max((G / S * sigma)^phi, 0.05), 1), where G and S are the areas of the ghost's and the
// sensor's bounding rectangles; at least 2 (one quad). sigma = 1, phi = 1/2 in the paper.
int adaptiveGridSize(int base_size,
                     double ghost_area_mm2,
                     double sensor_area_mm2,
                     double sigma = 1.0,
                     double phi = 0.5);

// Primitive merge (Bodonyi & Kunkli 2023 §4.2): where a ghost's grid maps to the sensor almost
// affinely, 2 x 2 blocks of quads become one quad with the block's outer corners, `steps` times
// over (a block of 2^k x 2^k cells after k steps; only blocks of the same level merge). A block
// merges when all its cells are fully lit (four valid rays) and convex, the merged quad is convex,
// and each of the six lines through the block (its four sides and two midlines, two quad edges
// each) keeps its direction: the two edges e_A, e_B of a line satisfy
//     e_A . e_B > 0  and  |e_A x e_B| <= gamma |e_A| |e_B|,
// gamma being the sine of the largest angle allowed between them. The paper's printed test,
// (x1 - x2) + (y1 - y2) < gamma, is a signed sum: differences of opposite signs cancel, so two
// edges at right angles can pass it; the sine cannot cancel, does not depend on the edges'
// lengths, and is exact for edges of any size. Merged quads interpolate their attributes from
// the block's corner rays; energy is kept (a merged quad stands for 4^k cells).
//
// Interior edges. Where two quads of a grid meet along a whole edge (the same two corner rays),
// both convex and turning the same way (so they lie on either side of it), the light on either
// side is the same interpolated throughput, and differs only by the light's density, each quad's
// cell area over its area on the sensor. Where those densities differ by at most
// centre_edge_jump (relative), a pixel the edge crosses goes whole to the quad that holds its
// centre instead of being cut in two by area: it costs what a pixel inside costs, and the error
// is that jump times the part of the pixel on the other side, with either sign along the edge.
// Both quads must be at least a pixel wide (area over longest edge), so that a pixel meets few
// quads and the one holding its centre stands for them. The outline of the ghost, edges where a
// merged quad meets smaller ones, folds, quads under a pixel wide, and steep changes of density
// keep the exact cut. 0 cuts every edge by area (the truth the others are
// measured against).
struct MergeOptions {
    int steps = 0;         // 0: no merge; the paper's light and heavy merges use 4
    double gamma = 0.001;  // sine of the largest angle between edges of a line (0.001 ~ 0.06 deg)
    double centre_edge_jump = 0.0;  // see above; 0: every edge cut by area
    // A merged quad keeps its corners inside every clear aperture and within this radius in stop
    // coordinates (StopMask::inscribedRadius, 1 for a round stop): a quad that the stop's outline
    // or vignetting crosses is cut per pixel over all of its pixels, so only single cells are.
    double clear_stop_radius = 1.0;
};

// The paper's settings, as the benchmark names them, and the interior edges' rule with them.
inline constexpr double kCentreEdgeJump = 0.01;
inline constexpr MergeOptions kNoMerge{0, 0.0, 0.0, 1.0};
inline constexpr MergeOptions kLightMerge{4, 0.001, kCentreEdgeJump, 1.0};
inline constexpr MergeOptions kHeavyMerge{4, 0.1, kCentreEdgeJump, 1.0};

// The quads of one traced grid, in pixels. A quad is kept when at least one of its corners is a
// valid ray and all four have a position; quads with a corner that has no geometry at all (a ray
// that missed a surface or was totally reflected) are dropped. A corner cut by a clear aperture
// keeps the throughput it would have had (GridSample::open_throughput) and its aperture ratio
// above 1: the rasterizer cuts the light where the interpolated ratio crosses 1.
struct GhostQuads {
    LargePageVector<Quad> quads;
    std::vector<uint16_t> cells;  // grid cells each quad stands for (4^k); empty: all 1
    double cell_area_mm2 = 0.0;   // entry-plane area one ray stands for
    double cellArea(size_t i) const {
        return cells.empty() ? cell_area_mm2 : cell_area_mm2 * static_cast<double>(cells[i]);
    }
};
GhostQuads quadsFromGrid(const optics::RayGrid& grid,
                         const SensorToImage& mapping,
                         const MergeOptions& merge = {});

// Adaptive grids: the merged quads of quadsFromGrid without tracing the whole grid. The grid is
// looked at in blocks of 2^steps cells, each traced at its corners, side middles and centre (nine
// rays). A block whose nine rays are all valid, whose six lines (sides and midlines) keep their
// direction within gamma both on the sensor and in stop coordinates, and whose quad and four
// half-size quads are convex is one merged quad; any other block is split in four and looked at
// again the same way, down to blocks of one cell, which become quads as quadsFromGrid makes them
// (all four corners traced). Where the grid is not lit at all it is therefore traced whole, as
// it must be to find what light there is.
// It sees less than tracing the grid and merging: a block whose lines stay straight at half its
// size while its quarters bend is merged here and not there (bench/adaptive_grid_bench.cpp
// measures what that costs in the image). With merge.steps = 0 it traces the whole grid.
// The tracer is GridFiller's (the row tracer; options.tracer Exact is refused).
struct AdaptiveQuads {
    GhostQuads quads;
    int64_t rays = 0;  // traced
};
Result<AdaptiveQuads> adaptiveQuads(const optics::Lens& lens,
                                    const optics::GhostPath& path,
                                    double theta_rad,
                                    double phi_rad,
                                    double wavelength_nm,
                                    int n,
                                    const optics::RayGridOptions& options,
                                    const SensorToImage& mapping,
                                    const MergeOptions& merge);

struct RasterOptions {
    // Quads that are not convex and below this area (px^2) are added whole to the pixel under
    // their centre. With supersample N, every quad below min_quad_area_px / N^2 is.
    double min_quad_area_px = 1.0;
    // 0: pixel-area integration (the header's comment). N in 1..64: N x N point samples per
    // pixel, the slow reference the integration is tested against (1: the pixel centre only).
    int supersample = 0;
};

// The stop shape as the renderers look it up, many millions of times per image: the circle, or
// the blades' edge normals computed once. Same shape as optics::ApertureShape::contains, without
// trigonometry per lookup.
class StopMask {
public:
    explicit StopMask(const optics::ApertureShape& shape);
    int blades() const { return blades_; }                        // 0: circle
    double inscribedRadius() const { return inscribed_radius_; }  // 1, or the blades' apothem
    // Blade k's edge normal over the apothem: inside when (u, v) . normal <= 1.
    double normalU(int k) const { return normal_u_[static_cast<size_t>(k)]; }
    double normalV(int k) const { return normal_v_[static_cast<size_t>(k)]; }
    bool contains(double u, double v) const {
        if (blades_ == 0) return u * u + v * v <= 1.0;
        double ratio = -1.0;
        for (int k = 0; k < blades_; ++k)
            ratio = std::max(ratio, u * normal_u_[k] + v * normal_v_[k]);
        return ratio <= 1.0;
    }

private:
    int blades_ = 0;  // 0: circle
    double inscribed_radius_ = 1.0;
    std::vector<double> normal_u_, normal_v_;  // edge normals over the apothem
};

// One edge of a convex quad as a line function, (c + gy py) + gx px, positive inside the quad.
// The two quads that share an edge compute its coefficients from the same endpoints in the same
// (canonical) order and differ only in their sign, so their values are exact negatives; a pixel
// centre exactly on the edge belongs to the quad for which `closed` is true, so it is counted
// once (a fill rule), never twice and never not at all. Along a row, c + gy py is fixed: a
// pixel costs one product and one sum per edge.
struct EdgeFunction {
    double c = 0.0, gx = 0.0, gy = 0.0;
    bool closed = true;
    // An interior edge (Quad::centre_edges): a pixel is on the side its centre is on (with the
    // fill rule above), never cut.
    bool by_centre = false;
    double reach = 0.0;  // how far `at` changes from a pixel's centre to its corners
    double at(double px, double py) const { return (c + gy * py) + gx * px; }
    double gradX() const { return gx; }
    double gradY() const { return gy; }
};

// A quad ready to draw into one channel of a width x height image: the range of pixels it can
// touch, its light per unit of interpolated throughput, and, for a strictly convex quad (every
// cell of a smooth ghost away from its caustics), its evaluation set up once. Both renderers draw
// the same primitives with primitiveValueAt, so they agree bit for bit.
struct Primitive {
    Quad quad;
    int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;  // inclusive pixel range (a splat: one pixel)
    double scale = 0.0;  // irradiance x cell area / quad area; for a splat irradiance x cell area
    int channel = 0;
    bool splat = false;   // below min_quad_area_px: drawn whole at the pixel under its centre
    bool convex = false;  // edge and corner_area hold the set-up below
    // 0: area-integrated (convex quads); N > 0: N x N point samples per pixel.
    int supersample = 0;
    // Convex quads interpolate convex mixtures of their corners' values: when all four corners
    // lie inside a convex shape, every point of the quad does. stop_radius is the corners'
    // largest |(stop_u, stop_v)| (inside the stop's inscribed circle: no stop edge in the quad),
    // vignette_clear whether every corner passes every clear aperture.
    double stop_radius = 0.0;
    bool vignette_clear = false;
    // Convex quads: edge i runs from corner i to i+1. With A_i(p) = edge[i].at(p) and C_i the
    // area of the corner triangle (i-1, i, i+1), the Wachspress weight of corner i (eq. 8-9 of
    // Bodonyi & Kunkli 2023) is C_i / (A_{i-1} A_i); multiplied through by the product of all
    // four A it is C_i A_{i+1} A_{i+2}, free of division, and one division normalizes the four.
    std::array<EdgeFunction, 4> edge;
    std::array<double, 4> corner_area{};
    // Convex quads: the corners' least and greatest throughput, which bound every interpolated
    // one.
    double throughput_low = 0.0, throughput_high = 0.0;
    // Convex quads: the sum of the four Wachspress weights above at the pixel centre (x + 1/2,
    // y + 1/2), and the throughput-weighted sum, as polynomials of u = x - x0 and v = y - y0:
    // c0 + v (c1 + v c2) + u (c3 + v c4) + u^2 c5. Quadratic in each because the weights are
    // products of two edge functions; the inside of a pixel no edge cuts costs two of them and a
    // division (set up by preparePrimitive once x0 and y0 are known).
    std::array<double, 6> inside_total{}, inside_sum{};
};

// The primitives of one grid, as the renderer keeps them until they are drawn.
using PrimitiveArray = LargePageVector<Primitive>;

// nullopt when the quad cannot put light in the image (outside it, non-finite, no irradiance, no
// throughput, or a convex quad wholly outside the stop or a clear aperture). cell_area_mm2 is the
// entry-plane area the quad stands for (GhostQuads::cellArea).
std::optional<Primitive> preparePrimitive(const Quad& quad,
                                          double cell_area_mm2,
                                          int channel,
                                          float irradiance,
                                          int64_t width,
                                          int64_t height,
                                          const RasterOptions& options = {});

// Adds static_cast<float>(primitiveValueAt(p, x, y, stop)) to out[pixel_step * (x - x0)] for x
// in x0..x1 (pixel_step 3: one channel of an interleaved RGB row; 1: a row of one channel's
// plane): the same values, bit for bit, with the pixels that lie wholly inside a convex primitive
// (the common pixel of a ghost) evaluated a row at a time, four at once.
void addPrimitiveRow(const Primitive& p,
                     int64_t x0,
                     int64_t x1,
                     int64_t y,
                     const StopMask& stop,
                     float* out,
                     int64_t pixel_step = 3);

// addPrimitiveRow for the rows y0..y1 (out: pixel (x0, y0)'s channel, rows `stride` floats
// apart), the same values bit for bit; a block wholly inside an unmasked convex primitive (the
// common case) skips the per-pixel tests.
void addPrimitiveBlock(const Primitive& p,
                       int64_t x0,
                       int64_t y0,
                       int64_t x1,
                       int64_t y1,
                       const StopMask& stop,
                       float* out,
                       int64_t stride,
                       int64_t pixel_step = 3);

// The light of a convex primitive at the point (px, py), per pixel area: 0 outside the quad, the
// stop shape or a clear aperture; a point exactly on an edge shared by two quads belongs to one
// of them (EdgeFunction::closed). What RasterOptions::supersample samples.
inline double convexValueAt(const Primitive& p, double px, double py, const StopMask& stop) {
    double a[4];
    for (int i = 0; i < 4; ++i) {
        a[i] = p.edge[i].at(px, py);
        if (!(a[i] > 0.0 || (a[i] == 0.0 && p.edge[i].closed))) return 0.0;
    }
    const double w[4] = {p.corner_area[0] * a[1] * a[2], p.corner_area[1] * a[2] * a[3],
                         p.corner_area[2] * a[3] * a[0], p.corner_area[3] * a[0] * a[1]};
    const double total = w[0] + w[1] + w[2] + w[3];
    if (!(total > 0.0)) return 0.0;
    double t = 0.0, u = 0.0, v = 0.0, ratio = 0.0;
    for (int i = 0; i < 4; ++i) {
        t += w[i] * p.quad.corners[i].throughput;
        u += w[i] * p.quad.corners[i].stop_u;
        v += w[i] * p.quad.corners[i].stop_v;
        ratio += w[i] * p.quad.corners[i].aperture_ratio;
    }
    if (!(t > 0.0) || !(ratio <= total) || !stop.contains(u / total, v / total)) return 0.0;
    const double value = p.scale * (t / total);
    return std::isfinite(value) ? value : 0.0;
}

// What the primitive adds to pixel (x, y) of its range: its light integrated over the pixel
// (per pixel area), or the mean of its point samples, or for a splat its whole light masked at
// its centre. Finite and >= 0.
double primitiveValueAt(const Primitive& primitive, int64_t x, int64_t y, const StopMask& stop);

// Adds one ghost's quads to `channel` (0 red, 1 green, 2 blue) of `image`, scaled by the light's
// irradiance in that channel, the stop shape applied to the interpolated stop coordinates. Pixels
// integrate over their area (or are supersampled, options.supersample). Quads partly or wholly
// outside the image are clipped; nothing non-finite is ever written.
void rasterizeReference(ImageRGB& image,
                        const GhostQuads& ghost,
                        int channel,
                        float irradiance,
                        const optics::ApertureShape& aperture,
                        const RasterOptions& options = {});

// The power a traced grid of the imaging path carries to the sensor per unit of the light's
// irradiance (mm^2: the effective area of the entrance pupil), integrated as the ghosts are:
// across each cell of the grid the four rays' throughput, stop coordinates and clear-aperture
// ratio are interpolated bilinearly, cells wholly inside the stop and every clear aperture count
// their mean throughput, and cells that an edge crosses are sampled 16 x 16. Cells with a ray
// that has no geometry count their corners that pass. 0 for a grid of fewer than 2 x 2 rays.
double imagingPower(const optics::RayGrid& grid, const optics::ApertureShape& aperture);

}  // namespace flarelab::render
