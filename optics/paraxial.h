// ============================================================================
//  flarelab optics: paraxial ray-transfer matrices
// ============================================================================
//
// First-order optics with 2x2 ray-transfer (ABCD) matrices acting on (height y, slope u), as in
// §4.2.1 of the thesis and the course report: translation by d, refraction at a surface of
// curvature c from index n1 to n2, and reflection at a surface of curvature c. A ghost path is
// unfolded: after a reflection the light keeps travelling "forward" along its own direction, so
// translations stay positive and each surface's curvature is taken with the sign it has as seen
// along the light's direction (c_eff = +c going towards the sensor, -c coming back).
//
//   translation  [1 d; 0 1]
//   refraction   [1 0; (n1 - n2) c_eff / n2  n1 / n2]
//   reflection   [1 0; 2 c_eff  1]
//
// Slopes are plain (not reduced) slopes, so det(M) = n_in / n_out.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <vector>

#include "optics/lens.h"

namespace flarelab::optics {

using Matrix2 = Eigen::Matrix2d;

Matrix2 translationMatrix(double distance_mm);
Matrix2 refractionMatrix(double n1, double n2, double curvature_eff);
Matrix2 reflectionMatrix(double curvature_eff);

// First-order properties of the imaging path at one wavelength (lengths in mm).
struct ParaxialProperties {
    double efl_mm = 0.0;  // -1 / C of the lens matrix: the rear focal length, which is the
                          // effective focal length when image space is air, as in a camera
    double bfl_mm = 0.0;  // back focal distance: last surface to the rear focal point
    double ffl_mm = 0.0;  // front focal distance: first surface to the front focal point
                          // (positive when the focal point lies in front of the lens)
    double entrance_pupil_z_mm = 0.0;       // from the first vertex, positive towards the sensor
    double entrance_pupil_radius_mm = 0.0;  // paraxial, for the lens's current stop
    double exit_pupil_z_mm = 0.0;           // from the first vertex
    double stop_magnification = 0.0;  // stop height per entrance height of a ray from infinity
    double working_f_number = 0.0;    // efl / (2 * entrance pupil radius)
    Matrix2 lens_matrix;              // first vertex to last vertex
    Matrix2 system_matrix;            // first vertex to the image plane
};

// Fails (nullopt) for an afocal lens (C = 0), a stop no paraxial ray from infinity reaches, or a
// table so extreme that a property overflows.
std::optional<ParaxialProperties> paraxialProperties(const Lens& lens, double wavelength_nm);

// The unfolded transfer of a path from the first vertex (light in object space) to the image
// plane, split at the first crossing of the stop: to_stop takes (y, u) at the first vertex to the
// stop plane, from_stop the stop plane to the image plane.
struct PathMatrices {
    Matrix2 to_stop;
    Matrix2 from_stop;
    Matrix2 total;
};
PathMatrices pathMatrices(const Lens& lens, const GhostPath& path, double wavelength_nm);

// Every surface the light meets along a path, in order, with the transfer from the first vertex
// to its arrival there. Crossing k is step k of a PathTracer on the same path.
struct PathCrossing {
    int surface = 0;
    bool is_stop = false;
    double semi_aperture_mm = 0.0;
    Matrix2 to_here;
};
struct PathTransfer {
    std::vector<PathCrossing> crossings;
    Matrix2 total;  // to the image plane
};
PathTransfer pathTransfer(const Lens& lens, const GhostPath& path, double wavelength_nm);

// A ghost as first-order optics sees it. A parallel beam of slope tan(theta) is cut down by the
// path's limiting aperture: of all surfaces it meets, the one that admits the narrowest on-axis
// beam (semi-aperture / |A| of its transfer). That is usually the stop, but when the path focuses
// the beam near the stop plane the stop barely cuts it and a clear aperture takes over. The ghost
// is the image of the limiting aperture: its centre lies at centre_per_tan * tan(theta) along the
// light's roll direction, its radius is radius_mm. nullopt when no surface limits the beam (every
// transfer has A = 0), where paraxial optics has no answer.
struct ParaxialGhost {
    double centre_per_tan_mm = 0.0;
    double radius_mm = 0.0;
    int limiting_crossing = -1;   // index into pathTransfer(...).crossings
    int limiting_surface = -1;    // index into Lens::surfaces()
    double beam_radius_mm = 0.0;  // radius of the admitted beam at the first vertex
};
std::optional<ParaxialGhost> paraxialGhost(const Lens& lens,
                                           const GhostPath& path,
                                           double wavelength_nm);
// The same from a path's transfer already computed.
std::optional<ParaxialGhost> paraxialGhost(const PathTransfer& transfer);

}  // namespace flarelab::optics
