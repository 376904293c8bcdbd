// ============================================================================
//  flarelab optics: Lens, GhostPath
// ============================================================================
//
// A Lens is a prescription placed in space for tracing, with a camera's choices applied: surface
// vertices on the z axis (first vertex at z = 0, light travelling towards +z), curvatures, clear
// apertures, the stop scaled for the f-number, coatings resolved, and the image (sensor) plane.
//
// Frames and signs. Lens space is right-handed with z along the optical axis towards the sensor.
// Sensor millimetres are the x, y of lens space on the image plane: the optical axis is (0, 0),
// and a light at angle theta from the axis and roll phi (eq. 8.1-8.2 of the thesis) is imaged
// near f * tan(theta) * (cos phi, sin phi). Read out with x right and y down, that is where the
// frame shows it.
//
// A GhostPath names the two surfaces where a ghost's light reflects (first < second): the light
// goes forward to `second`, reflects, goes back to `first`, reflects, and goes forward to the
// sensor. The imaging path (no reflection) has first = second = -1.
#pragma once

#include <string>
#include <vector>

#include "common/result.h"
#include "optics/aperture.h"
#include "optics/prescription.h"

namespace flarelab::optics {

struct LensSurface {
    double z_mm = 0.0;       // vertex position on the axis
    double curvature = 0.0;  // 1 / radius_mm (1/mm); 0 for flat
    double semi_aperture_mm = 0.0;
    double ior_d = 1.0;                  // medium after the surface
    double abbe = 0.0;                   // 0: non-dispersive
    double coating_wavelength_nm = 0.0;  // 0: uncoated
    bool is_stop = false;
};

struct GhostPath {
    int first = -1;   // surface index of the second reflection (nearer the front)
    int second = -1;  // surface index of the first reflection (nearer the back)
    bool isImaging() const { return first < 0; }
    bool operator==(const GhostPath&) const = default;
    auto operator<=>(const GhostPath&) const = default;
};

class Lens {
public:
    // Applies `camera` to `prescription`: the stop semi-aperture is set so that the paraxial
    // entrance pupil at the d line gives camera.f_number at camera.focal_length_mm (each resolved
    // from the lens's labels when zero, see CameraDescription). Fails on an invalid description
    // or on a lens whose stop cannot be reached paraxially by light from infinity.
    static Result<Lens> make(const Prescription& prescription, const CameraDescription& camera);

    const std::vector<LensSurface>& surfaces() const { return surfaces_; }
    int stopIndex() const { return stop_index_; }
    double sensorZ_mm() const { return sensor_z_mm_; }
    const ApertureShape& aperture() const { return aperture_; }
    const CameraDescription& camera() const { return camera_; }  // with zeros resolved
    const std::string& name() const { return name_; }
    double labelFocalLength_mm() const { return label_focal_mm_; }  // 0 if the file has none
    double tableStopSemiAperture_mm() const { return table_stop_mm_; }
    int uncoatedUnspecifiedSurfaces() const { return uncoated_unspecified_; }
    int nonDispersiveGlasses() const { return non_dispersive_glasses_; }

    // Index of the medium after surface k (k = -1: the object-space medium, air) at a wavelength.
    double mediumIndex(int k, double wavelength_nm) const;

    // Half the sensor diagonal, the unit of the ghost-centre tolerances.
    double sensorHalfDiagonal_mm() const;

    // Whether the path is a well-formed ghost of this lens (two distinct non-stop surfaces).
    bool isValidPath(const GhostPath& path) const;

    // How many times a path crosses the aperture stop (1 for the imaging path; 1 or 3 for a ghost).
    int stopCrossings(const GhostPath& path) const;

    // A copy with a different stop semi-aperture (e.g. the table's); the camera's f-number field
    // then no longer describes it.
    Lens withStopSemiAperture(double semi_aperture_mm) const;

private:
    std::vector<LensSurface> surfaces_;
    int stop_index_ = -1;
    double sensor_z_mm_ = 0.0;
    ApertureShape aperture_;
    CameraDescription camera_;
    std::string name_;
    double label_focal_mm_ = 0.0;
    double table_stop_mm_ = 0.0;
    int uncoated_unspecified_ = 0;
    int non_dispersive_glasses_ = 0;
};

// 1-based surface numbers as people read them in the lens file ("3-7"); "imaging" for no ghost.
std::string pathLabel(const GhostPath& path);

}  // namespace flarelab::optics
