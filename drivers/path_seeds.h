// ============================================================================
//  flarelab drivers: pathSeeder
// ============================================================================
//
// A lens prescription's ghost paths as seeds of the sweep fit (fit/sweep_fit.h, PathSeed;
// `flarelab fit --lens FILE --paths`), so that tracks start where the optics core puts each ghost
// and keep its identity. At a head angle (the light as the simulated rig sets it: theta = |angle|,
// phi = 0, or 180 for negative angles) every two-reflection path the simulator draws
// (optics::enumerateGhosts with its defaults) is traced on a 48 x 48 ray grid at 550 nm
// (optics::traceRayGrid). The rays that pass the stop and every clear aperture give the path's
// power (their throughput) and the box they span on the sensor: the ghost as vignetting leaves
// it, so a disc cut by a clear aperture is seeded with the cut box. The seed's outline is the
// ellipse through that box (four arcs, circle handles). Paths with fewer than 4 such rays, or
// with less than `min_share` of all paths' power at that angle, are left out; the fit itself
// then drops seeds whose ghost is out of view or not above the noise.
#pragma once

#include "fit/sweep_fit.h"
#include "optics/lens.h"

namespace flarelab::drivers {

// The seeder keeps a copy of the lens; it is safe to call from several threads.
// InvalidArgument for min_share outside [0, 1); the seeder's errors: the lens's paths cannot be
// enumerated, or the angle is not finite or at 90 degrees or beyond.
Result<fit::PathSeeder> pathSeeder(const optics::Lens& lens, double min_share = 1e-3);

}  // namespace flarelab::drivers
