#include "optics/ray_grid.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "common/check.h"
#include "common/units.h"
#include "optics/paraxial.h"
#include "optics/row_tracer.h"
#include "optics/tracer.h"

namespace flarelab::optics {
namespace {

struct Square {
    Eigen::Vector2d centre;
    double half_width;
};

// The square on the entry plane that bounds the beam passing the stop on this path.
Square pupilSquare(const Lens& lens,
                   const GhostPath& path,
                   double wavelength_nm,
                   const EntryPlane& plane,
                   const Eigen::Vector3d& direction,
                   double margin) {
    const Eigen::Vector2d slope(direction.x() / direction.z(), direction.y() / direction.z());
    // The front lens's clear aperture projected along the beam onto the entry plane: no ray
    // outside it gets in, so the grid never needs to be larger.
    const LensSurface& front = lens.surfaces().front();
    const Eigen::Vector2d front_centre = slope * (plane.entry_z_mm - front.z_mm);
    const double front_r = front.semi_aperture_mm;

    Square square{front_centre, front_r};
    // The square is padded by `margin` anyway: a rim to 1e-3 of the front lens is plenty.
    constexpr int kRim = 16;
    const std::optional<AimedBeam> beam =
        aimBeam(lens, path, wavelength_nm, plane, direction, kRim, 1e-3);
    if (beam && !beam->rim_entries.empty()) {
        Eigen::Vector2d lo = beam->rim_entries.front(), hi = lo;
        for (const Eigen::Vector2d& e : beam->rim_entries) {
            lo = lo.cwiseMin(e);
            hi = hi.cwiseMax(e);
        }
        square.centre = 0.5 * (lo + hi);
        square.half_width = 0.5 * (hi - lo).maxCoeff() * (1.0 + margin);
    } else if (beam) {
        // No real ray gets through (light far off axis, TIR on the way): the paraxial beam of
        // the path, so that the grid still shows where the light would be.
        square.centre = beam->paraxial_centre_entry;
        square.half_width = beam->paraxial_beam_radius_mm * (1.0 + margin);
    }
    // Clip to the square around the front lens.
    const Eigen::Vector2d sq_lo = (square.centre.array() - square.half_width).matrix();
    const Eigen::Vector2d sq_hi = (square.centre.array() + square.half_width).matrix();
    const Eigen::Vector2d fr_lo = (front_centre.array() - front_r).matrix();
    const Eigen::Vector2d fr_hi = (front_centre.array() + front_r).matrix();
    const Eigen::Vector2d c_lo = sq_lo.cwiseMax(fr_lo);
    const Eigen::Vector2d c_hi = sq_hi.cwiseMin(fr_hi);
    if ((c_hi - c_lo).minCoeff() > 0.0) {
        square.centre = 0.5 * (c_lo + c_hi);
        square.half_width = 0.5 * (c_hi - c_lo).maxCoeff();
    }
    if (!(square.half_width > 0.0) || !std::isfinite(square.half_width)) {
        square.centre = front_centre;
        square.half_width = front_r;
    }
    return square;
}

}  // namespace

Eigen::Vector2d RayGrid::entryPoint(int ix, int iy) const {
    if (n == 1) return entry_centre_mm;
    const double step = 2.0 * entry_half_width_mm / (n - 1);
    return entry_centre_mm +
           Eigen::Vector2d(-entry_half_width_mm + step * ix, -entry_half_width_mm + step * iy);
}

int64_t RayGrid::validCount() const {
    return std::count_if(samples.begin(), samples.end(),
                         [](const GridSample& s) { return s.valid; });
}

namespace {

// Checks the arguments and sets up the grid: its square, entry plane and n x n empty samples.
Result<RayGrid> emptyGrid(const Lens& lens,
                          const GhostPath& path,
                          double theta_rad,
                          double phi_rad,
                          double wavelength_nm,
                          int n,
                          const RayGridOptions& options) {
    const auto invalid = [](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "ray grid: " + what);
    };
    if (!std::isfinite(theta_rad) || theta_rad < 0.0 || theta_rad >= 0.5 * kPi)
        return invalid("theta must lie in [0, 90) degrees (the light must be in front)");
    if (!std::isfinite(phi_rad)) return invalid("phi must be finite");
    if (!(wavelength_nm >= 200.0 && wavelength_nm <= 3000.0))
        return invalid("wavelength must lie in 200..3000 nm");
    if (n < 1 || n > 8192) return invalid("grid size must lie in 1..8192");
    if (!lens.isValidPath(path)) return invalid("path " + pathLabel(path) + " is not in this lens");
    if (!(options.margin >= 0.0 && options.margin <= 10.0))
        return invalid("margin must lie in 0..10");
    if (!(options.float_tolerance_mm >= 0.0))
        return invalid("float tolerance must be a non-negative length");

    RayGrid grid;
    grid.path = path;
    grid.n = n;
    grid.theta_rad = theta_rad;
    grid.phi_rad = phi_rad;
    grid.wavelength_nm = wavelength_nm;
    grid.plane = defaultEntryPlane(lens);
    const Eigen::Vector3d direction = lightDirection(theta_rad, phi_rad);

    if (options.square &&
        !(options.square->half_width_mm > 0.0 && std::isfinite(options.square->half_width_mm) &&
          options.square->centre_mm.allFinite()))
        return invalid("a given entry square must have a positive, finite size");
    const Square square =
        options.square
            ? Square{options.square->centre_mm, options.square->half_width_mm}
            : pupilSquare(lens, path, wavelength_nm, grid.plane, direction, options.margin);
    grid.entry_centre_mm = square.centre;
    grid.entry_half_width_mm = square.half_width;
    grid.samples.assign(static_cast<size_t>(n) * static_cast<size_t>(n), GridSample{});
    return grid;
}

// Clear apertures are not clipped but recorded, so a cut ray keeps the geometry it would have had
// in a wider lens and carries no light.
void store(GridSample& s,
           bool clip_apertures,
           double x,
           double y,
           double throughput,
           double u,
           double v,
           bool cut_by_aperture,
           double aperture_ratio) {
    const bool cut = clip_apertures && cut_by_aperture;
    s.sensor_x_mm = static_cast<float>(x);
    s.sensor_y_mm = static_cast<float>(y);
    s.open_throughput = static_cast<float>(throughput);
    s.throughput = cut ? 0.0f : s.open_throughput;
    s.aperture_ratio = clip_apertures ? static_cast<float>(aperture_ratio) : 0.0f;
    s.stop_u = static_cast<float>(u);
    s.stop_v = static_cast<float>(v);
    s.has_position = std::isfinite(s.sensor_x_mm) && std::isfinite(s.sensor_y_mm) &&
                     std::isfinite(s.stop_u) && std::isfinite(s.stop_v) &&
                     std::isfinite(s.throughput) && std::isfinite(s.open_throughput) &&
                     std::isfinite(s.aperture_ratio);
    s.valid = !cut && s.has_position;
    if (!s.has_position) s = GridSample{};
}

}  // namespace

struct GridFiller::Impl {
    RowTracer tracer;
    Eigen::Vector3d direction;
    double back = 0.0;  // every ray starts this far behind its entry point, along the light
    double launch_z = 0.0;
    bool clip_apertures = true;
    // Lanes waiting to be traced, reused from batch to batch.
    std::vector<double> xs{}, ys{};
    std::vector<size_t> at{};  // the sample each lane fills
    TracedRow row{};
};

GridFiller::GridFiller(RayGrid grid, std::unique_ptr<Impl> impl)
    : grid_(std::move(grid)), traced_(grid_.samples.size(), 0), impl_(std::move(impl)) {}
GridFiller::GridFiller(GridFiller&&) noexcept = default;
GridFiller& GridFiller::operator=(GridFiller&&) noexcept = default;
GridFiller::~GridFiller() = default;

Result<GridFiller> GridFiller::open(const Lens& lens,
                                    const GhostPath& path,
                                    double theta_rad,
                                    double phi_rad,
                                    double wavelength_nm,
                                    int n,
                                    const RayGridOptions& options) {
    if (options.tracer == GridTracer::Exact)
        return makeError(ErrorCode::InvalidArgument,
                         "ray grid: a grid traced point by point uses the row tracer, not Exact");
    auto grid = emptyGrid(lens, path, theta_rad, phi_rad, wavelength_nm, n, options);
    if (!grid) return grid.error();
    RowTracer::Options row_options;
    row_options.precision = options.tracer == GridTracer::RowDouble ? RowTracer::Precision::Double
                                                                    : RowTracer::Precision::Float;
    row_options.fresnel = options.fresnel;
    const Eigen::Vector3d direction = lightDirection(theta_rad, phi_rad);
    // Every ray of the grid starts on the launch plane, direction times the same distance behind
    // its entry point.
    const double back = (grid->plane.entry_z_mm - grid->plane.launch_z_mm) / direction.z();
    auto impl = std::make_unique<Impl>(Impl{
        .tracer = RowTracer(lens, path, wavelength_nm, row_options),
        .direction = direction,
        .back = back,
        .launch_z = grid->plane.entry_z_mm - back * direction.z(),
        .clip_apertures = options.clip_apertures,
    });
    if (options.tracer == GridTracer::Auto && n <= 32) {
        // A probe would cost as much as tracing the grid in double.
        impl->tracer.setPrecision(RowTracer::Precision::Double);
    } else if (options.tracer == GridTracer::Auto) {
        // The probe: a sub-grid over the whole square, about 2 sqrt(n) rays a side (every ray
        // of a grid up to 4 x 4 ... 16 x 16; 1.6 % of a 256 x 256 grid).
        const int stride = std::max(1, static_cast<int>(std::lround(std::sqrt(n / 4.0))));
        std::vector<double> px, py;
        for (int iy = 0; iy < n; iy += stride)
            for (int ix = 0; ix < n; ix += stride) {
                const Eigen::Vector2d e = grid->entryPoint(ix, iy);
                px.push_back(e.x() - back * direction.x());
                py.push_back(e.y() - back * direction.y());
            }
        impl->tracer.choosePrecision(px, py, impl->launch_z, direction, options.float_tolerance_mm);
    }
    return GridFiller(std::move(*grid), std::move(impl));
}

void GridFiller::trace(std::span<const std::pair<int, int>> points) {
    // In batches of lanes, like a grid row.
    constexpr size_t kBatch = 512;
    Impl& t = *impl_;
    const size_t n = static_cast<size_t>(grid_.n);
    const auto flush = [&] {
        if (t.at.empty()) return;
        t.tracer.trace(t.xs, t.ys, t.launch_z, t.direction, t.row);
        for (size_t i = 0; i < t.at.size(); ++i) {
            if (t.row.status[i] == 0) continue;
            store(grid_.samples[t.at[i]], t.clip_apertures, t.row.x_mm[i], t.row.y_mm[i],
                  t.row.throughput[i], t.row.stop_u[i], t.row.stop_v[i], t.row.status[i] == 2,
                  t.row.aperture_ratio[i]);
        }
        t.xs.clear();
        t.ys.clear();
        t.at.clear();
    };
    for (const auto& [ix, iy] : points) {
        FLARELAB_CHECK(ix >= 0 && iy >= 0 && ix < grid_.n && iy < grid_.n);
        const size_t at = static_cast<size_t>(iy) * n + static_cast<size_t>(ix);
        if (traced_[at]) continue;
        traced_[at] = 1;
        ++traced_count_;
        const Eigen::Vector2d e = grid_.entryPoint(ix, iy);
        t.xs.push_back(e.x() - t.back * t.direction.x());
        t.ys.push_back(e.y() - t.back * t.direction.y());
        t.at.push_back(at);
        if (t.at.size() == kBatch) flush();
    }
    flush();
}

void GridFiller::traceAll() {
    std::vector<std::pair<int, int>> row(static_cast<size_t>(grid_.n));
    for (int iy = 0; iy < grid_.n; ++iy) {
        for (int ix = 0; ix < grid_.n; ++ix) row[static_cast<size_t>(ix)] = {ix, iy};
        trace(row);
    }
}

Result<RayGrid> traceRayGrid(const Lens& lens,
                             const GhostPath& path,
                             double theta_rad,
                             double phi_rad,
                             double wavelength_nm,
                             int n,
                             const RayGridOptions& options) {
    if (options.tracer != GridTracer::Exact) {
        auto filler = GridFiller::open(lens, path, theta_rad, phi_rad, wavelength_nm, n, options);
        if (!filler) return filler.error();
        filler->traceAll();
        return std::move(*filler).take();
    }
    auto grid = emptyGrid(lens, path, theta_rad, phi_rad, wavelength_nm, n, options);
    if (!grid) return grid.error();
    // Ray by ray in double, a row at a time through traceBatch (the same bits as trace()).
    const Eigen::Vector3d direction = lightDirection(theta_rad, phi_rad);
    const PathTracer tracer(
        lens, path, wavelength_nm,
        TraceOptions{.clip_apertures = false, .clip_stop = false, .fresnel = options.fresnel});
    std::vector<Ray> rays(static_cast<size_t>(n));
    std::vector<std::optional<TracedRay>> traced(static_cast<size_t>(n));
    for (int iy = 0; iy < n; ++iy) {
        for (int ix = 0; ix < n; ++ix)
            rays[static_cast<size_t>(ix)] =
                rayThroughEntry(grid->plane, grid->entryPoint(ix, iy), direction, wavelength_nm);
        tracer.traceBatch(rays, traced);
        for (int ix = 0; ix < n; ++ix) {
            if (!traced[static_cast<size_t>(ix)]) continue;  // missed or totally reflected
            const TracedRay& t = *traced[static_cast<size_t>(ix)];
            store(grid->samples[static_cast<size_t>(iy) * n + ix], options.clip_apertures,
                  t.ray.position.x(), t.ray.position.y(), t.ray.throughput, t.stop_u, t.stop_v,
                  t.cut, t.aperture_ratio);
        }
    }
    return grid;
}

Result<GridAgreement> compareWithExactGrid(const Lens& lens,
                                           const GhostPath& path,
                                           double theta_rad,
                                           double phi_rad,
                                           double wavelength_nm,
                                           int n,
                                           const RayGridOptions& options) {
    auto tested = traceRayGrid(lens, path, theta_rad, phi_rad, wavelength_nm, n, options);
    if (!tested) return tested.error();
    RayGridOptions reference_options = options;
    reference_options.tracer = GridTracer::Exact;
    reference_options.square = tested->square();
    auto reference =
        traceRayGrid(lens, path, theta_rad, phi_rad, wavelength_nm, n, reference_options);
    if (!reference) return reference.error();
    GridAgreement a;
    double largest = 0.0, power_tested = 0.0, power_reference = 0.0;
    for (const GridSample& s : reference->samples)
        if (s.valid) largest = std::max(largest, static_cast<double>(s.throughput));
    for (size_t i = 0; i < tested->samples.size(); ++i) {
        const GridSample& t = tested->samples[i];
        const GridSample& r = reference->samples[i];
        if (t.valid) power_tested += t.throughput;
        if (r.valid) power_reference += r.throughput;
        if (t.valid != r.valid) {
            ++a.validity_differs;
            continue;
        }
        if (!r.valid) continue;
        ++a.samples;
        a.max_position_error_mm =
            std::max(a.max_position_error_mm, std::hypot(double{t.sensor_x_mm} - r.sensor_x_mm,
                                                         double{t.sensor_y_mm} - r.sensor_y_mm));
        a.max_stop_error = std::max(
            a.max_stop_error, std::hypot(double{t.stop_u} - r.stop_u, double{t.stop_v} - r.stop_v));
        if (r.throughput >= 1e-3 * largest && r.throughput > 0.0f)
            a.max_throughput_rel_error =
                std::max(a.max_throughput_rel_error,
                         std::abs(double{t.throughput} - r.throughput) / r.throughput);
    }
    float lo_x = 0.0f, hi_x = 0.0f, lo_y = 0.0f, hi_y = 0.0f;
    bool any = false;
    for (const GridSample& r : reference->samples) {
        if (!r.valid) continue;
        lo_x = any ? std::min(lo_x, r.sensor_x_mm) : r.sensor_x_mm;
        hi_x = any ? std::max(hi_x, r.sensor_x_mm) : r.sensor_x_mm;
        lo_y = any ? std::min(lo_y, r.sensor_y_mm) : r.sensor_y_mm;
        hi_y = any ? std::max(hi_y, r.sensor_y_mm) : r.sensor_y_mm;
        any = true;
    }
    a.max_stop_shift_mm = a.max_stop_error * 0.5 * std::max(hi_x - lo_x, hi_y - lo_y);
    a.power_rel_error =
        power_reference > 0.0 ? std::abs(power_tested - power_reference) / power_reference : 0.0;
    return a;
}

}  // namespace flarelab::optics
