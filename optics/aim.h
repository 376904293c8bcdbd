// ============================================================================
//  flarelab optics: aiming real rays at points of the stop
// ============================================================================
//
// A parallel beam from a light at (theta, phi) fills the front of the lens, but only the part
// that passes the stop forms the image or a ghost. These helpers find, by Newton's method on the
// exact tracer, where on an entry plane a ray of the beam must start so that it crosses the stop
// at a given point, following a given path. They are the real-ray counterparts of the paraxial
// entrance pupil and let the ray grids cover just the light that matters, even at angles where
// pupil aberration moves the beam far from its paraxial place.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <vector>

#include "optics/lens.h"
#include "optics/tracer.h"

namespace flarelab::optics {

// A plane z = entry_z_mm on which rays start, and the z from which they are launched (in front of
// every surface; rays are moved back along their direction to it).
struct EntryPlane {
    double entry_z_mm = 0.0;
    double launch_z_mm = 0.0;
};

// The paraxial entrance-pupil plane of the lens as entry plane (the first vertex if the pupil
// cannot be found), launching 1 mm in front of the frontmost point of any surface.
EntryPlane defaultEntryPlane(const Lens& lens);

// The ray of direction `direction` that passes through (entry.x, entry.y, entry_z).
Ray rayThroughEntry(const EntryPlane& plane,
                    const Eigen::Vector2d& entry_mm,
                    const Eigen::Vector3d& direction,
                    double wavelength_nm);

// Entry point whose ray meets crossing `crossing` of the tracer's path (see pathTransfer) at
// x, y = `target_mm`, to 1e-9 of the problem's scale. Aiming ignores clear apertures: it answers
// where the ray would go. nullopt when Newton's method does not converge (e.g. the ray is totally
// reflected on the way, or no ray of this direction reaches that point).
std::optional<Eigen::Vector2d> aimAtCrossing(const PathTracer& tracer,
                                             int crossing,
                                             const EntryPlane& plane,
                                             const Eigen::Vector3d& direction,
                                             const Eigen::Vector2d& target_mm,
                                             const Eigen::Vector2d& initial_entry_mm);

// The same, aimed at the first crossing of the stop.
std::optional<Eigen::Vector2d> aimAtStop(const PathTracer& tracer,
                                         const EntryPlane& plane,
                                         const Eigen::Vector3d& direction,
                                         const Eigen::Vector2d& target_stop_mm,
                                         const Eigen::Vector2d& initial_entry_mm);

// The paraxial guess for aiming: the entry point whose ray reaches `target_mm` at a surface, from
// the path's transfer `to_here` to that surface. nullopt when its A = 0.
std::optional<Eigen::Vector2d> paraxialEntry(const Eigen::Matrix2d& to_here,
                                             const EntryPlane& plane,
                                             const Eigen::Vector3d& direction,
                                             const Eigen::Vector2d& target_mm);

// The beam of one path under one light, found with real rays.
//
// Its centre is the ray through the centre of the path's limiting aperture (see ParaxialGhost),
// the real counterpart of the paraxial chief ray. Its rim is the edge of the set of entry points
// whose rays pass every clear aperture and the stop shape and reach the image plane, found by
// bisection from the centre along `rim_points` directions of the entry plane. The rim therefore
// holds whatever really cuts the beam: the stop, a clear aperture where the path's aberrations
// squeeze the beam through the stop, or vignetting far off axis.
struct AimedBeam {
    int crossing = -1;  // the paraxial limiting aperture's crossing on the path
    Eigen::Vector2d paraxial_centre_entry = Eigen::Vector2d::Zero();
    double paraxial_beam_radius_mm = 0.0;
    std::optional<Eigen::Vector2d> centre_entry;  // nullopt when the centre ray cannot be aimed
    std::vector<Eigen::Vector2d> rim_entries;     // empty when no ray of the beam gets through
};
// The rim is located to `rim_tolerance` of the front lens's diameter (bisection steps cost one
// trace each). nullopt when first-order optics finds no limiting aperture on the path.
std::optional<AimedBeam> aimBeam(const Lens& lens,
                                 const GhostPath& path,
                                 double wavelength_nm,
                                 const EntryPlane& plane,
                                 const Eigen::Vector3d& direction,
                                 int rim_points,
                                 double rim_tolerance = 1e-9);

}  // namespace flarelab::optics
