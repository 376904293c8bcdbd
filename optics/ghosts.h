// ============================================================================
//  flarelab optics: ghost enumeration and per-ghost analysis
// ============================================================================
//
// Ghosts are light paths with an even number of reflections; flarelab models the two-reflection
// paths, which carry nearly all ghost energy (a third and fourth reflection multiply it by two
// more reflectances of ~1e-2 or less). Any two distinct non-stop surfaces i < j give one path.
// Following Hullin et al. 2011 and Bodonyi & Kunkli 2023 §3.2, paths whose reflections lie on
// opposite sides of the stop cross it three times and are skipped by default; an intensity
// threshold relative to the imaging path can cull further.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "common/result.h"
#include "optics/lens.h"

namespace flarelab::optics {

// Where a light is, as seen from the camera: theta from the optical axis, phi its roll.
struct LightDirectionDeg {
    double theta_deg = 0.0;
    double phi_deg = 0.0;
};

// Power that reaches the sensor through one path, relative to the power the imaging path carries
// from the same light through the same stop (so 1e-3 means a ghost a thousandth of the light).
// Estimated on a ray grid per red, green and blue wavelength, counting only rays that pass every
// aperture and the stop and land on the sensor. `grid` rays per side.
struct GhostIntensity {
    double relative_power = 0.0;  // mean of the three wavelengths
    double relative_power_rgb[3] = {0.0, 0.0, 0.0};
    double on_sensor_fraction = 0.0;  // of the ghost's rays through the stop, share on the sensor
};
Result<GhostIntensity> ghostIntensity(const Lens& lens,
                                      const GhostPath& path,
                                      const LightDirectionDeg& light,
                                      int grid = 24);

// The imaging path's power per wavelength, the reference of ghostIntensity; compute it once when
// measuring many ghosts under the same light.
struct ImagingPower {
    double rgb[3] = {0.0, 0.0, 0.0};
    int grid = 0;
};
Result<ImagingPower> imagingPower(const Lens& lens, const LightDirectionDeg& light, int grid = 24);
Result<GhostIntensity> ghostIntensity(const Lens& lens,
                                      const GhostPath& path,
                                      const LightDirectionDeg& light,
                                      const ImagingPower& reference);

struct EnumerationOptions {
    bool skip_double_stop_crossing = true;  // the papers' default
    // false reproduces the ghost counts of Bodonyi & Kunkli 2023 (11, 64, 139, 304): their
    // enumeration never reflects at the last surface behind the stop. Those ghosts are real and
    // among the bright ones, so flarelab keeps them by default.
    bool include_last_surface = true;
    double min_relative_power = 0.0;  // 0: no intensity culling
    LightDirectionDeg cull_light;     // where the culling measures intensity
    int cull_grid = 24;
};

struct CulledGhost {
    GhostPath path;
    std::string reason;
    double relative_power = 0.0;
};

struct GhostEnumeration {
    std::vector<GhostPath> ghosts;  // kept, ordered by (first, second)
    std::vector<CulledGhost> culled;
    int all_pairs = 0;             // C(number of non-stop surfaces, 2)
    int double_stop_skipped = 0;   // paths skipped for crossing the stop three times
    int last_surface_skipped = 0;  // paths skipped for reflecting at the last surface
};
Result<GhostEnumeration> enumerateGhosts(const Lens& lens, const EnumerationOptions& options = {});

// A ghost as real rays draw it at one light direction and wavelength: the image of the stop's
// centre (centre) and rim (radius, extent) through the path, found by aiming real rays at those
// stop points. Clear apertures are ignored here: this is where the ghost is, not how much of it
// survives vignetting.
struct ExactGhost {
    Eigen::Vector2d centre_mm = Eigen::Vector2d::Zero();
    double radius_mm = 0.0;  // mean distance of the rim's image from the centre
    Eigen::Vector4d extent_mm = Eigen::Vector4d::Zero();  // min x, min y, max x, max y
    int rim_points = 0;                                   // rim rays that could be aimed
};
// rim_points = 0 finds only the centre (radius and extent stay zero).
std::optional<ExactGhost> exactGhost(const Lens& lens,
                                     const GhostPath& path,
                                     const LightDirectionDeg& light,
                                     double wavelength_nm,
                                     int rim_points = 32);

}  // namespace flarelab::optics
