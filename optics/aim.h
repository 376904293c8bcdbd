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

#include <optional>

#include <Eigen/Core>

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

// Entry point whose ray crosses the stop plane (first crossing along the tracer's path) at
// `target_stop_mm`, to 1e-9 mm. Aiming ignores clear apertures: it answers where the ray would
// go. nullopt when Newton's method does not converge (e.g. the ray is totally reflected on the
// way, or no ray of this direction reaches that stop point).
std::optional<Eigen::Vector2d> aimAtStop(const PathTracer& tracer,
                                         const EntryPlane& plane,
                                         const Eigen::Vector3d& direction,
                                         const Eigen::Vector2d& target_stop_mm,
                                         const Eigen::Vector2d& initial_entry_mm);

// The paraxial guess for aimAtStop: from the path's to-stop matrix. nullopt when A = 0.
std::optional<Eigen::Vector2d> paraxialEntry(const Lens& lens,
                                             const GhostPath& path,
                                             double wavelength_nm,
                                             const EntryPlane& plane,
                                             const Eigen::Vector3d& direction,
                                             const Eigen::Vector2d& target_stop_mm);

}  // namespace flarelab::optics
