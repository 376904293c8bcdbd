// ============================================================================
//  flarelab drivers: pathSeeder
// ============================================================================
//
// A lens prescription's ghost paths as seeds of the sweep fit (fit/sweep_fit.h, PathSeed;
// `flarelab fit --lens FILE --paths`), so that tracks start where the optics core puts each ghost
// and keep its identity. At a head angle (the light as the simulated rig sets it: theta = |angle|,
// phi = 0, or 180 for negative angles) every two-reflection path the simulator draws
// (optics::enumerateGhosts with its defaults) is a seed when its stop image can be aimed
// (optics::exactGhost at 550 nm): the image's extent as a four-arc outline (circle handles),
// before vignetting, so a ghost cut by a clear aperture is fitted from its whole disc. Paths
// that carry less than `min_share` of the power of all paths at that angle
// (optics::ghostIntensity on a 12-ray grid) are left out; the fit itself then drops seeds whose
// ghost is out of view or not above the noise.
#pragma once

#include "fit/sweep_fit.h"
#include "optics/lens.h"

namespace flarelab::drivers {

// The seeder keeps a copy of the lens; it is safe to call from several threads.
// InvalidArgument for min_share outside [0, 1); the seeder's errors: the lens's paths cannot be
// enumerated, or the angle is not finite or at 90 degrees or beyond.
Result<fit::PathSeeder> pathSeeder(const optics::Lens& lens, double min_share = 1e-3);

}  // namespace flarelab::drivers
