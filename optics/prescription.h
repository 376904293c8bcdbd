// ============================================================================
//  flarelab optics: Surface, Prescription, CameraDescription
// ============================================================================
//
// A lens prescription is the designer's table: one row per surface, front (object side) to back
// (sensor side), in the CSV format of data/lenses/README.md (format v1). Loading validates every
// field and names file, line and column of the first fault. A CameraDescription (focal length,
// f-number, sensor size, aperture blades) turns a prescription into the lens a camera uses: it
// scales the aperture stop so that the paraxial entrance pupil gives the requested f-number.
#pragma once

#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"

namespace flarelab::optics {

enum class SurfaceKind { Refracting, Stop };

struct Surface {
    SurfaceKind kind = SurfaceKind::Refracting;
    double radius_mm = 0.0;     // signed; positive: centre of curvature towards the sensor; 0: flat
    double thickness_mm = 0.0;  // to the next surface; on the last row, to the image plane
    double ior_d = 1.0;         // medium after the surface at 587.56 nm; 1 is air
    double abbe = 0.0;          // V_d of that medium; 0: no dispersion (air, or not given)
    double semi_aperture_mm = 0.0;
    double coating_wavelength_nm = 0.0;  // single-layer quarter-wave AR coating; 0: none given
    int line = 0;                        // 1-based line in the source file, for messages
    bool operator==(const Surface&) const = default;
};

struct Prescription {
    std::string source;                           // file name or other label used in messages
    std::string name;                             // from the "# name:" header, else the file stem
    std::map<std::string, std::string> metadata;  // "# key: value" header comments
    std::vector<Surface> surfaces;
    int stop_index = -1;  // index into surfaces of the aperture stop

    // Leading number of a metadata value ("100 (label ...)" gives 100), if there is one.
    std::optional<double> metadataNumber(const std::string& key) const;
};

// Parses format v1 text. `source` names the text in error messages ("file:line:col: ...").
Result<Prescription> parsePrescription(std::string_view text, const std::string& source);

// Reads and parses a file; errors name the path.
Result<Prescription> loadPrescription(const std::string& path);

// How a camera uses a lens. Zero means "take it from the prescription": the focal length from its
// "focal_length_mm" label, else the paraxial EFL; the f-number from its "f_number" label, else the
// stop as the table gives it.
struct CameraDescription {
    double focal_length_mm = 0.0;
    double f_number = 0.0;
    double sensor_width_mm = 36.0;
    double sensor_height_mm = 24.0;
    int aperture_blades = 0;  // 0: circular stop; n >= 3: regular n-gon
    double aperture_rotation_deg = 0.0;
    double default_coating_wavelength_nm = 550.0;  // for surfaces whose coating is not given
    bool coat_unspecified_surfaces = false;  // true: give them the default coating; false: bare

    // Empty when the description is usable; else what is wrong.
    std::optional<std::string> invalidReason() const;
};

}  // namespace flarelab::optics
