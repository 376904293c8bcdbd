#include "optics/aim.h"

#include <algorithm>
#include <cmath>

#include <Eigen/LU>

#include "optics/paraxial.h"

namespace flarelab::optics {

EntryPlane defaultEntryPlane(const Lens& lens) {
    EntryPlane plane;
    double front = 0.0;
    for (const LensSurface& s : lens.surfaces()) {
        // The cap of a surface reaches from its vertex by at most its sag at the clear aperture.
        double sag = 0.0;
        if (s.curvature != 0.0) {
            const double r = 1.0 / s.curvature;
            const double h = std::min(s.semi_aperture_mm, std::abs(r));
            sag = r - std::copysign(std::sqrt(std::max(0.0, r * r - h * h)), r);
        }
        front = std::min(front, s.z_mm + std::min(0.0, sag));
    }
    plane.launch_z_mm = front - 1.0;
    const auto paraxial = paraxialProperties(lens, kLambdaD_nm);
    plane.entry_z_mm = paraxial ? paraxial->entrance_pupil_z_mm : 0.0;
    if (!std::isfinite(plane.entry_z_mm) || std::abs(plane.entry_z_mm) > 1e5)
        plane.entry_z_mm = 0.0;
    return plane;
}

Ray rayThroughEntry(const EntryPlane& plane,
                    const Eigen::Vector2d& entry_mm,
                    const Eigen::Vector3d& direction,
                    double wavelength_nm) {
    Ray ray;
    const double back = (plane.entry_z_mm - plane.launch_z_mm) / direction.z();
    ray.position = Eigen::Vector3d(entry_mm.x(), entry_mm.y(), plane.entry_z_mm) - back * direction;
    ray.direction = direction;
    ray.wavelength_nm = wavelength_nm;
    return ray;
}

std::optional<Eigen::Vector2d> aimAtStop(const PathTracer& tracer,
                                         const EntryPlane& plane,
                                         const Eigen::Vector3d& direction,
                                         const Eigen::Vector2d& target_stop_mm,
                                         const Eigen::Vector2d& initial_entry_mm) {
    if (!(direction.z() > 0.0)) return std::nullopt;
    const auto stop_at = [&](const Eigen::Vector2d& entry) -> std::optional<Eigen::Vector2d> {
        const Ray ray = rayThroughEntry(plane, entry, direction, tracer.wavelength_nm());
        return tracer.traceToStop(ray.position, ray.direction);
    };
    Eigen::Vector2d entry = initial_entry_mm;
    std::optional<Eigen::Vector2d> hit = stop_at(entry);
    if (!hit) return std::nullopt;
    const double scale = std::max(1.0, initial_entry_mm.norm() + target_stop_mm.norm());
    for (int iteration = 0; iteration < 50; ++iteration) {
        const Eigen::Vector2d residual = *hit - target_stop_mm;
        if (residual.norm() < 1e-9 * scale) return entry;
        // Jacobian by central differences.
        const double h = 1e-6 * scale;
        Eigen::Matrix2d jacobian;
        for (int axis = 0; axis < 2; ++axis) {
            Eigen::Vector2d step = Eigen::Vector2d::Zero();
            step[axis] = h;
            const auto plus = stop_at(entry + step);
            const auto minus = stop_at(entry - step);
            if (!plus || !minus) return std::nullopt;
            jacobian.col(axis) = (*plus - *minus) / (2.0 * h);
        }
        if (!(std::abs(jacobian.determinant()) > 1e-14)) return std::nullopt;
        const Eigen::Vector2d delta = jacobian.partialPivLu().solve(residual);
        // Backtrack when the full step leaves the region where the ray is defined or gets worse.
        double lambda = 1.0;
        bool moved = false;
        for (int halving = 0; halving < 30; ++halving, lambda *= 0.5) {
            const Eigen::Vector2d candidate = entry - lambda * delta;
            const auto candidate_hit = stop_at(candidate);
            if (candidate_hit && (*candidate_hit - target_stop_mm).norm() < residual.norm()) {
                entry = candidate;
                hit = candidate_hit;
                moved = true;
                break;
            }
        }
        if (!moved) return std::nullopt;
    }
    return std::nullopt;
}

std::optional<Eigen::Vector2d> paraxialEntry(const Lens& lens,
                                             const GhostPath& path,
                                             double wavelength_nm,
                                             const EntryPlane& plane,
                                             const Eigen::Vector3d& direction,
                                             const Eigen::Vector2d& target_stop_mm) {
    const PathMatrices m = pathMatrices(lens, path, wavelength_nm);
    const double a = m.to_stop(0, 0), b = m.to_stop(0, 1);
    if (!(std::abs(a) > 1e-12) || !(direction.z() > 0.0)) return std::nullopt;
    const Eigen::Vector2d slope(direction.x() / direction.z(), direction.y() / direction.z());
    // Height at the first vertex (z = 0), then carried along the ray to the entry plane.
    const Eigen::Vector2d at_vertex = (target_stop_mm - b * slope) / a;
    return Eigen::Vector2d(at_vertex + slope * plane.entry_z_mm);
}

}  // namespace flarelab::optics
