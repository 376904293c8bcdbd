#include "drivers/lens_settings.h"

#include <sstream>

namespace flarelab::drivers {

hdr::SweepLens describeLens(const optics::Lens& lens) {
    const optics::CameraDescription& camera = lens.camera();
    hdr::SweepLens out;
    out.description = lens.name();
    if (camera.f_number > 0.0) out.f_number = camera.f_number;
    if (camera.focal_length_mm > 0.0) out.focal_length_mm = camera.focal_length_mm;
    out.aperture_blades = camera.aperture_blades;
    out.blade_rotation_deg = camera.aperture_rotation_deg;
    // The stop's own row: after withStopSemiAperture the f-number no longer says what it is.
    const double stop_mm = lens.surfaces()[static_cast<size_t>(lens.stopIndex())].semi_aperture_mm;
    if (stop_mm > 0.0) out.stop_semi_aperture_mm = stop_mm;
    out.coat_unspecified_surfaces = camera.coat_unspecified_surfaces;
    out.sensor_width_mm = camera.sensor_width_mm;
    out.sensor_height_mm = camera.sensor_height_mm;
    return out;
}

Result<RebuiltLens> rebuildLens(const optics::Prescription& prescription,
                                const fit::ModelLens& recorded) {
    std::vector<std::string> assumed;
    optics::CameraDescription camera;
    if (recorded.f_number)
        camera.f_number = *recorded.f_number;
    else
        assumed.push_back("f-number (assumed the lens file's label)");
    if (recorded.focal_length_mm)
        camera.focal_length_mm = *recorded.focal_length_mm;
    else
        assumed.push_back("focal length (assumed the lens file's label, else its EFL)");
    camera.sensor_width_mm = recorded.sensor_width_mm;
    camera.sensor_height_mm = recorded.sensor_height_mm;
    if (recorded.aperture_blades)
        camera.aperture_blades = *recorded.aperture_blades;
    else
        assumed.push_back("aperture blades (assumed a circular stop)");
    if (recorded.blade_rotation_deg)
        camera.aperture_rotation_deg = *recorded.blade_rotation_deg;
    else if (camera.aperture_blades != 0)
        assumed.push_back("blade rotation (assumed 0 deg)");
    if (recorded.coat_unspecified_surfaces)
        camera.coat_unspecified_surfaces = *recorded.coat_unspecified_surfaces;
    else
        assumed.push_back("coating of unspecified surfaces (assumed bare)");
    auto made = optics::Lens::make(prescription, camera);
    if (!made) {
        // Lens::make names the file in its own errors, but not in the camera description's.
        if (made.error().message.rfind(prescription.source + ":", 0) == 0) return made.error();
        return made.error().withContext(prescription.source);
    }
    if (recorded.stop_semi_aperture_mm)
        return RebuiltLens{made->withStopSemiAperture(*recorded.stop_semi_aperture_mm),
                           std::move(assumed)};
    const optics::Lens& lens = *made;
    std::ostringstream stop;
    stop << "stop semi-aperture (assumed "
         << lens.surfaces()[static_cast<size_t>(lens.stopIndex())].semi_aperture_mm << " mm, for f/"
         << lens.camera().f_number << ")";
    assumed.push_back(stop.str());
    return RebuiltLens{lens, std::move(assumed)};
}

}  // namespace flarelab::drivers
