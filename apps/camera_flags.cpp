#include "apps/camera_flags.h"

#include <cstdio>

#include "optics/prescription.h"

namespace flarelab::apps {

using namespace flarelab::optics;

void addCameraFlags(CLI::App* cmd, CameraFlags& flags) {
    cmd->add_option("--focal-mm", flags.focal_mm,
                    "focal length the f-number refers to (default: the file's label, else EFL)");
    cmd->add_option("--f-number", flags.f_number,
                    "working f-number; scales the stop (default: the file's f_number label)");
    cmd->add_flag("--table-stop", flags.table_stop,
                  "keep the stop semi-aperture as the table gives it");
    cmd->add_option("--sensor-mm", flags.sensor, "sensor size WxH in mm")->capture_default_str();
    cmd->add_option("--blades", flags.blades, "aperture blades (0: circle)");
    cmd->add_option("--blade-rotation-deg", flags.blade_rotation_deg, "rotation of the blades");
    cmd->add_flag("--coat-unspecified", flags.coat_unspecified,
                  "give surfaces without a coating in the file the default 550 nm coating");
}

bool parseSensorMm(const std::string& text, double& width_mm, double& height_mm) {
    char x = 0, extra = 0;
    return std::sscanf(text.c_str(), "%lf%c%lf%c", &width_mm, &x, &height_mm, &extra) == 3 &&
           (x == 'x' || x == 'X');
}

std::optional<Lens> loadLens(const std::string& path, const CameraFlags& flags, std::ostream& err) {
    auto prescription = loadPrescription(path);
    if (!prescription) {
        err << "flarelab: " << prescription.error().message << "\n";
        return std::nullopt;
    }
    return makeLens(*prescription, flags, err);
}

std::optional<Lens> makeLens(const Prescription& prescription,
                             const CameraFlags& flags,
                             std::ostream& err) {
    CameraDescription camera;
    camera.focal_length_mm = flags.focal_mm;
    camera.f_number = flags.f_number;
    camera.aperture_blades = flags.blades;
    camera.aperture_rotation_deg = flags.blade_rotation_deg;
    camera.coat_unspecified_surfaces = flags.coat_unspecified;
    double w = 0.0, h = 0.0;
    if (!parseSensorMm(flags.sensor, w, h)) {
        err << "flarelab: --sensor-mm '" << flags.sensor << "' is not WIDTHxHEIGHT in mm\n";
        return std::nullopt;
    }
    camera.sensor_width_mm = w;
    camera.sensor_height_mm = h;
    auto lens = Lens::make(prescription, camera);
    if (!lens) {
        err << "flarelab: " << lens.error().message << "\n";
        return std::nullopt;
    }
    if (flags.table_stop) return lens->withStopSemiAperture(lens->tableStopSemiAperture_mm());
    return *lens;
}

}  // namespace flarelab::apps
