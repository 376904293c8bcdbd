#include "optics/aim.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>

#include "common/units.h"
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
            sag = h * h / (r + std::copysign(std::sqrt(std::max(0.0, r * r - h * h)), r));
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

std::optional<Eigen::Vector2d> aimAtCrossing(const PathTracer& tracer,
                                             int crossing,
                                             const EntryPlane& plane,
                                             const Eigen::Vector3d& direction,
                                             const Eigen::Vector2d& target_mm,
                                             const Eigen::Vector2d& initial_entry_mm) {
    if (!(direction.z() > 0.0)) return std::nullopt;
    const auto crossing_at = [&](const Eigen::Vector2d& entry) -> std::optional<Eigen::Vector2d> {
        const Ray ray = rayThroughEntry(plane, entry, direction, tracer.wavelength_nm());
        return tracer.traceToCrossing(crossing, ray.position, ray.direction);
    };
    Eigen::Vector2d entry = initial_entry_mm;
    std::optional<Eigen::Vector2d> hit = crossing_at(entry);
    if (!hit) return std::nullopt;
    const double scale = std::max(1.0, initial_entry_mm.norm() + target_mm.norm());
    for (int iteration = 0; iteration < 50; ++iteration) {
        const Eigen::Vector2d residual = *hit - target_mm;
        if (residual.norm() < 1e-9 * scale) return entry;
        // Jacobian by central differences.
        const double h = 1e-6 * scale;
        Eigen::Matrix2d jacobian;
        for (int axis = 0; axis < 2; ++axis) {
            Eigen::Vector2d step = Eigen::Vector2d::Zero();
            step[axis] = h;
            const auto plus = crossing_at(entry + step);
            const auto minus = crossing_at(entry - step);
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
            const auto candidate_hit = crossing_at(candidate);
            if (candidate_hit && (*candidate_hit - target_mm).norm() < residual.norm()) {
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

std::optional<Eigen::Vector2d> aimAtStop(const PathTracer& tracer,
                                         const EntryPlane& plane,
                                         const Eigen::Vector3d& direction,
                                         const Eigen::Vector2d& target_mm,
                                         const Eigen::Vector2d& initial_entry_mm) {
    return aimAtCrossing(tracer, tracer.firstStopCrossing(), plane, direction, target_mm,
                         initial_entry_mm);
}

std::optional<Eigen::Vector2d> paraxialEntry(const Eigen::Matrix2d& to_here,
                                             const EntryPlane& plane,
                                             const Eigen::Vector3d& direction,
                                             const Eigen::Vector2d& target_mm) {
    const double a = to_here(0, 0), b = to_here(0, 1);
    if (!(std::abs(a) > 1e-12) || !(direction.z() > 0.0)) return std::nullopt;
    const Eigen::Vector2d slope(direction.x() / direction.z(), direction.y() / direction.z());
    // Height at the first vertex (z = 0), then carried along the ray to the entry plane.
    const Eigen::Vector2d at_vertex = (target_mm - b * slope) / a;
    return Eigen::Vector2d(at_vertex + slope * plane.entry_z_mm);
}

namespace {

// The centre ray of a beam found by continuation from the axis, where it is the axis itself:
// the light is moved off in steps and each aim starts from the previous answer. A path with an
// internal focus can have several rays through the same aperture point; this picks the one that
// joins the paraxial chief ray continuously, instead of whichever Newton's method happens on.
std::optional<Eigen::Vector2d> aimCentreByContinuation(const PathTracer& tracer,
                                                       int crossing,
                                                       const EntryPlane& plane,
                                                       const Eigen::Vector3d& direction,
                                                       const Eigen::Matrix2d& to_here,
                                                       double beam_radius_mm) {
    const double theta = std::acos(std::clamp(direction.z(), -1.0, 1.0));
    const double phi = std::atan2(direction.y(), direction.x());
    constexpr double kMaxStep = degToRad(1.0), kMinStep = degToRad(1e-3);
    double reached = 0.0, step = std::min(kMaxStep, theta);
    Eigen::Vector2d entry = Eigen::Vector2d::Zero();     // on the axis the centre ray is the axis
    Eigen::Vector2d velocity = Eigen::Vector2d::Zero();  // d entry / d theta, for the next guess
    while (reached < theta) {
        const double next = std::min(theta, reached + step);
        const Eigen::Vector3d d = lightDirection(next, phi);
        Eigen::Vector2d guess = entry + velocity * (next - reached);
        if (reached == 0.0) {
            if (const auto paraxial = paraxialEntry(to_here, plane, d, Eigen::Vector2d::Zero()))
                guess = *paraxial;
        }
        const auto aimed =
            aimAtCrossing(tracer, crossing, plane, d, Eigen::Vector2d::Zero(), guess);
        // Accept only an answer near the prediction: a far one is another branch of the path, and
        // a step that needs it has run into a fold, which smaller steps then locate. "Near" is a
        // quarter of the predicted move, or a twentieth of the beam where the chief ray hardly
        // moves (an entry plane at the path's own pupil).
        const double predicted_move = (guess - entry).norm();
        const double tolerance = 0.25 * predicted_move + 0.05 * beam_radius_mm;
        if (!aimed || (*aimed - guess).norm() > tolerance) {
            step *= 0.5;
            if (step < kMinStep) return std::nullopt;
            continue;
        }
        velocity = (*aimed - entry) / (next - reached);
        entry = *aimed;
        reached = next;
        step = std::min(kMaxStep, step * 2.0);
    }
    if (theta == 0.0) {
        return aimAtCrossing(tracer, crossing, plane, direction, Eigen::Vector2d::Zero(), entry);
    }
    return entry;
}

}  // namespace

std::optional<AimedBeam> aimBeam(const Lens& lens,
                                 const GhostPath& path,
                                 double wavelength_nm,
                                 const EntryPlane& plane,
                                 const Eigen::Vector3d& direction,
                                 int rim_points,
                                 double rim_tolerance) {
    const PathTransfer transfer = pathTransfer(lens, path, wavelength_nm);
    const auto ghost = paraxialGhost(transfer);
    if (!ghost) return std::nullopt;
    const PathCrossing& lim = transfer.crossings[ghost->limiting_crossing];
    AimedBeam beam;
    beam.crossing = ghost->limiting_crossing;
    beam.paraxial_beam_radius_mm = ghost->beam_radius_mm;
    const auto paraxial_centre =
        paraxialEntry(lim.to_here, plane, direction, Eigen::Vector2d::Zero());
    if (!paraxial_centre) return std::nullopt;
    beam.paraxial_centre_entry = *paraxial_centre;
    const PathTracer geometric(
        lens, path, wavelength_nm,
        TraceOptions{.clip_apertures = false, .clip_stop = false, .fresnel = false});
    beam.centre_entry = aimCentreByContinuation(geometric, beam.crossing, plane, direction,
                                                lim.to_here, ghost->beam_radius_mm);

    // The rim, by bisection between a ray that passes and one beyond the front lens.
    const PathTracer clipping(
        lens, path, wavelength_nm,
        TraceOptions{.clip_apertures = true, .clip_stop = true, .fresnel = false});
    const auto passes = [&](const Eigen::Vector2d& entry) {
        return clipping.trace(rayThroughEntry(plane, entry, direction, wavelength_nm)).has_value();
    };
    Eigen::Vector2d inside = beam.centre_entry.value_or(*paraxial_centre);
    if (!passes(inside)) {
        if (passes(*paraxial_centre)) {
            inside = *paraxial_centre;
        } else {
            return beam;  // fully vignetted (or the centre cannot be found): no rim
        }
    }
    const LensSurface& front = lens.surfaces().front();
    const Eigen::Vector2d slope(direction.x() / direction.z(), direction.y() / direction.z());
    const Eigen::Vector2d front_centre = slope * (plane.entry_z_mm - front.z_mm);
    // Every entry point farther than this from `inside` misses the front lens.
    const double reach = (inside - front_centre).norm() + 2.0 * front.semi_aperture_mm + 1.0;
    for (int k = 0; k < rim_points; ++k) {
        const double angle = 2.0 * kPi * k / rim_points;
        const Eigen::Vector2d dir(std::cos(angle), std::sin(angle));
        double lo = 0.0, hi = reach;
        const double tolerance = std::max(rim_tolerance, 1e-12) * 2.0 * front.semi_aperture_mm;
        for (int i = 0; i < 64 && hi - lo > tolerance; ++i) {
            const double mid = 0.5 * (lo + hi);
            (passes(inside + mid * dir) ? lo : hi) = mid;
        }
        beam.rim_entries.push_back(inside + lo * dir);
    }
    return beam;
}

}  // namespace flarelab::optics
