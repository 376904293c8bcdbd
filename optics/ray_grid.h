// ============================================================================
//  flarelab optics: RayGrid (sparse ray grids through one path)
// ============================================================================
//
// The input of the tiled renderer (Bodonyi & Kunkli 2023 §3.3, after Hullin et al. 2011): an
// n x n grid of parallel rays from one light, traced through one path at one wavelength. The grid
// covers the square that bounds the part of the beam that passes the stop on this path (the
// path's own entrance pupil, found with real rays, plus a margin), clipped to the front lens.
//
// Each sample keeps where the ray met the sensor, its throughput, and where it crossed the stop in
// stop-normalized coordinates. The stop does not invalidate rays: the renderer applies the
// aperture shape to interpolated stop coordinates, so ghost edges come out sharp however coarse
// the grid. `valid` is false for rays that miss a surface, leave a clear aperture or are totally
// reflected; they carry no light (throughput 0). Where the geometry still exists (a ray cut by a
// clear aperture, traced on as if the lens were wider) such a ray keeps its sensor position and
// stop coordinates (`has_position`), so a quad with some cut corners can fade its light to zero
// across the cut instead of being dropped (Bodonyi & Kunkli 2023 §3.3).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <utility>
#include <vector>

#include "common/large_pages.h"
#include "common/result.h"
#include "optics/aim.h"
#include "optics/lens.h"

namespace flarelab::optics {

struct GridSample {
    float sensor_x_mm = 0.0f;
    float sensor_y_mm = 0.0f;
    float throughput = 0.0f;
    float stop_u = 0.0f;  // stop crossing / stop semi-aperture; inside when aperture().contains
    float stop_v = 0.0f;
    bool valid = false;         // reached the sensor through every clear aperture
    bool has_position = false;  // position and stop coordinates are meaningful (valid or cut)
    // TracedRay::aperture_ratio (above 1: cut) and the throughput the ray would carry if no clear
    // aperture cut it, so a renderer can place the vignetting edge between rays instead of
    // fading the light over a whole cell. Both meaningful where has_position is.
    float aperture_ratio = 0.0f;
    float open_throughput = 0.0f;
};

// The square of the entry plane a grid covers.
struct EntrySquare {
    Eigen::Vector2d centre_mm = Eigen::Vector2d::Zero();
    double half_width_mm = 0.0;
};

struct RayGrid {
    GhostPath path;
    int n = 0;  // rays per side
    double theta_rad = 0.0;
    double phi_rad = 0.0;
    double wavelength_nm = 0.0;
    EntryPlane plane;
    Eigen::Vector2d entry_centre_mm = Eigen::Vector2d::Zero();  // of the square on the entry plane
    double entry_half_width_mm = 0.0;
    LargePageVector<GridSample> samples;  // n * n, row-major: samples[iy * n + ix]

    const GridSample& at(int ix, int iy) const {
        return samples[static_cast<size_t>(iy) * static_cast<size_t>(n) + static_cast<size_t>(ix)];
    }
    // Entry-plane position of grid point (ix, iy): corners of the square for n >= 2, its centre
    // for n = 1.
    Eigen::Vector2d entryPoint(int ix, int iy) const;
    int64_t validCount() const;
    EntrySquare square() const { return {entry_centre_mm, entry_half_width_mm}; }
};

// Which tracer fills the grid: the row tracer (row_tracer.h) in float where a probe (a sub-grid of
// about 2 sqrt(n) rays a side) shows float within float_tolerance_mm of double, else in double
// (Auto, the default; grids up to 32 x 32 are traced in double without a probe); the row tracer in
// float or double regardless; or PathTracer ray by ray in double (the reference the others are
// measured against).
enum class GridTracer { Auto, RowFloat, RowDouble, Exact };

struct RayGridOptions {
    double margin = 0.1;  // the square's half-width beyond the aimed pupil, as a fraction
    bool fresnel = true;
    GridTracer tracer = GridTracer::Auto;
    // 1e-4 mm is 0.005 px of a 1920-pixel-wide image of a 36 mm sensor (0.02 px at 8K).
    double float_tolerance_mm = 1e-4;
    bool clip_apertures = true;
    // The square to cover, taken from an earlier grid of the same light, path and wavelength
    // (RayGrid::square()) instead of aiming the path's beam again; it must have a positive,
    // finite half-width.
    std::optional<EntrySquare> square;
};

// theta in [0, pi/2), n in 1..8192, wavelength in 200..3000 nm, a valid path of `lens`;
// anything else is an InvalidArgument error. A light too far off axis for any ray to get
// through gives a grid with no valid sample, not an error.
Result<RayGrid> traceRayGrid(const Lens& lens,
                             const GhostPath& path,
                             double theta_rad,
                             double phi_rad,
                             double wavelength_nm,
                             int n,
                             const RayGridOptions& options = {});

// A grid traced where it is asked to be (adaptive refinement, render/ghost_quads.h): open() sets up
// the square, the launch plane and the tracer (its precision chosen by the same probe) as
// traceRayGrid does and traces nothing; trace() fills the samples of the points given, each once.
// Samples not traced stay GridSample{} (invalid, without position). Row tracer only: an Exact
// tracer is refused.
class GridFiller {
public:
    static Result<GridFiller> open(const Lens& lens,
                                   const GhostPath& path,
                                   double theta_rad,
                                   double phi_rad,
                                   double wavelength_nm,
                                   int n,
                                   const RayGridOptions& options = {});
    GridFiller(GridFiller&&) noexcept;
    GridFiller& operator=(GridFiller&&) noexcept;
    ~GridFiller();

    const RayGrid& grid() const { return grid_; }
    bool traced(int ix, int iy) const {
        return traced_[static_cast<size_t>(iy) * static_cast<size_t>(grid_.n) +
                       static_cast<size_t>(ix)] != 0;
    }
    // Grid points (ix, iy) with 0 <= ix, iy < n (checked: another is a programming error); those
    // traced already are skipped.
    void trace(std::span<const std::pair<int, int>> points);
    void traceAll();
    int64_t tracedCount() const { return traced_count_; }
    RayGrid take() && { return std::move(grid_); }

private:
    struct Impl;
    GridFiller(RayGrid grid, std::unique_ptr<Impl> impl);
    RayGrid grid_;
    std::vector<uint8_t> traced_;
    int64_t traced_count_ = 0;
    std::unique_ptr<Impl> impl_;
};

// How far a grid traced with `options` lands from the reference grid (GridTracer::Exact) over the
// same entry square. Samples whose validity differs (a ray grazing a surface or a clear aperture's
// rim, where rounding decides) are counted, not compared.
struct GridAgreement {
    int64_t samples = 0;  // valid in both
    int64_t validity_differs = 0;
    double max_position_error_mm = 0.0;
    double max_stop_error = 0.0;     // in stop semi-apertures
    double max_stop_shift_mm = 0.0;  // that times the footprint's half-size: the stop edge's shift
    double max_throughput_rel_error = 0.0;  // over samples carrying >= 1e-3 of the largest
    double power_rel_error = 0.0;           // of the sum of throughput over valid samples
};
Result<GridAgreement> compareWithExactGrid(const Lens& lens,
                                           const GhostPath& path,
                                           double theta_rad,
                                           double phi_rad,
                                           double wavelength_nm,
                                           int n,
                                           const RayGridOptions& options);

}  // namespace flarelab::optics
