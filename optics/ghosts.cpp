#include "optics/ghosts.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "common/units.h"
#include "optics/aim.h"
#include "optics/paraxial.h"
#include "optics/ray_grid.h"
#include "optics/tracer.h"

namespace flarelab::optics {
namespace {

constexpr double kRgb_nm[3] = {kLambdaRed_nm, kLambdaGreen_nm, kLambdaBlue_nm};

// Power of a traced grid: sum of throughputs of rays inside the stop shape (and, if asked, on
// the sensor) times the area one ray stands for.
struct GridPower {
    double power = 0.0;
    double through_stop = 0.0;  // same without the sensor condition
};
GridPower gridPower(const Lens& lens, const RayGrid& grid, bool require_on_sensor) {
    const double half_w = 0.5 * lens.camera().sensor_width_mm;
    const double half_h = 0.5 * lens.camera().sensor_height_mm;
    const double cell =
        grid.n > 1 ? 2.0 * grid.entry_half_width_mm / (grid.n - 1) : 2.0 * grid.entry_half_width_mm;
    GridPower result;
    for (const GridSample& s : grid.samples) {
        if (!s.valid || !lens.aperture().contains(s.stop_u, s.stop_v)) continue;
        result.through_stop += s.throughput;
        if (!require_on_sensor ||
            (std::abs(s.sensor_x_mm) <= half_w && std::abs(s.sensor_y_mm) <= half_h))
            result.power += s.throughput;
    }
    result.power *= cell * cell;
    result.through_stop *= cell * cell;
    return result;
}

}  // namespace

Result<ImagingPower> imagingPower(const Lens& lens, const LightDirectionDeg& light, int grid) {
    ImagingPower result;
    result.grid = grid;
    for (int c = 0; c < 3; ++c) {
        auto imaging = traceRayGrid(lens, GhostPath{}, degToRad(light.theta_deg),
                                    degToRad(light.phi_deg), kRgb_nm[c], grid);
        if (!imaging) return imaging.error();
        result.rgb[c] = gridPower(lens, *imaging, false).power;
    }
    return result;
}

Result<GhostIntensity> ghostIntensity(const Lens& lens,
                                      const GhostPath& path,
                                      const LightDirectionDeg& light,
                                      const ImagingPower& reference) {
    if (path.isImaging() || !lens.isValidPath(path))
        return makeError(ErrorCode::InvalidArgument,
                         "ghost intensity: " + pathLabel(path) + " is not a ghost of this lens");
    GhostIntensity result;
    double on_sensor = 0.0, through_stop = 0.0;
    for (int c = 0; c < 3; ++c) {
        auto ghost = traceRayGrid(lens, path, degToRad(light.theta_deg), degToRad(light.phi_deg),
                                  kRgb_nm[c], reference.grid);
        if (!ghost) return ghost.error();
        const GridPower g = gridPower(lens, *ghost, true);
        result.relative_power_rgb[c] = reference.rgb[c] > 0.0 ? g.power / reference.rgb[c] : 0.0;
        result.relative_power += result.relative_power_rgb[c] / 3.0;
        on_sensor += g.power;
        through_stop += g.through_stop;
    }
    result.on_sensor_fraction = through_stop > 0.0 ? on_sensor / through_stop : 0.0;
    return result;
}

Result<GhostIntensity> ghostIntensity(const Lens& lens,
                                      const GhostPath& path,
                                      const LightDirectionDeg& light,
                                      int grid) {
    auto reference = imagingPower(lens, light, grid);
    if (!reference) return reference.error();
    return ghostIntensity(lens, path, light, *reference);
}

Result<GhostEnumeration> enumerateGhosts(const Lens& lens, const EnumerationOptions& options) {
    if (!(options.min_relative_power >= 0.0) || !std::isfinite(options.min_relative_power))
        return makeError(ErrorCode::InvalidArgument,
                         "ghost enumeration: min_relative_power must be finite and >= 0");
    GhostEnumeration result;
    std::optional<ImagingPower> reference;
    if (options.min_relative_power > 0.0) {
        auto power = imagingPower(lens, options.cull_light, options.cull_grid);
        if (!power) return power.error();
        reference = *power;
    }
    const int n = static_cast<int>(lens.surfaces().size());
    for (int i = 0; i < n; ++i) {
        for (int j = i + 1; j < n; ++j) {
            const GhostPath path{i, j};
            if (!lens.isValidPath(path)) continue;  // the stop does not reflect
            ++result.all_pairs;
            if (options.skip_double_stop_crossing && lens.stopCrossings(path) > 1) {
                ++result.double_stop_skipped;
                continue;
            }
            if (!options.include_last_surface && j == n - 1) {
                ++result.last_surface_skipped;
                continue;
            }
            if (options.min_relative_power > 0.0) {
                auto intensity = ghostIntensity(lens, path, options.cull_light, *reference);
                if (!intensity) return intensity.error();
                if (intensity->relative_power < options.min_relative_power) {
                    std::ostringstream reason;
                    reason << (intensity->relative_power == 0.0
                                   ? "no light reaches the sensor"
                                   : "relative power below the threshold");
                    result.culled.push_back({path, reason.str(), intensity->relative_power});
                    continue;
                }
            }
            result.ghosts.push_back(path);
        }
    }
    return result;
}

std::optional<ExactGhost> exactGhost(const Lens& lens,
                                     const GhostPath& path,
                                     const LightDirectionDeg& light,
                                     double wavelength_nm,
                                     int rim_points) {
    if (!lens.isValidPath(path) || rim_points < 0 || !(light.theta_deg >= 0.0) ||
        !(light.theta_deg < 90.0))
        return std::nullopt;
    const Eigen::Vector3d direction =
        lightDirection(degToRad(light.theta_deg), degToRad(light.phi_deg));
    const EntryPlane plane = defaultEntryPlane(lens);
    const PathTracer geometric(
        lens, path, wavelength_nm,
        TraceOptions{.clip_apertures = false, .clip_stop = false, .fresnel = false});
    const auto to_sensor = [&](const Eigen::Vector2d& entry) -> std::optional<Eigen::Vector2d> {
        const auto traced =
            geometric.trace(rayThroughEntry(plane, entry, direction, wavelength_nm));
        if (!traced) return std::nullopt;
        return Eigen::Vector2d(traced->ray.position.x(), traced->ray.position.y());
    };
    const std::optional<AimedBeam> beam =
        aimBeam(lens, path, wavelength_nm, plane, direction, rim_points);
    if (!beam || !beam->centre_entry) return std::nullopt;
    const auto centre = to_sensor(*beam->centre_entry);
    if (!centre) return std::nullopt;

    ExactGhost ghost;
    ghost.centre_mm = *centre;
    ghost.extent_mm << centre->x(), centre->y(), centre->x(), centre->y();
    double radius_sum = 0.0;
    for (const Eigen::Vector2d& entry : beam->rim_entries) {
        const auto rim = to_sensor(entry);
        if (!rim) continue;
        radius_sum += (*rim - *centre).norm();
        ghost.extent_mm[0] = std::min(ghost.extent_mm[0], rim->x());
        ghost.extent_mm[1] = std::min(ghost.extent_mm[1], rim->y());
        ghost.extent_mm[2] = std::max(ghost.extent_mm[2], rim->x());
        ghost.extent_mm[3] = std::max(ghost.extent_mm[3], rim->y());
        ++ghost.rim_points;
    }
    ghost.radius_mm = ghost.rim_points > 0 ? radius_sum / ghost.rim_points : 0.0;
    return ghost;
}

}  // namespace flarelab::optics
