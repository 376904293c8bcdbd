#include "optics/lens.h"

#include <cmath>
#include <sstream>

#include "common/units.h"
#include "optics/glass.h"
#include "optics/paraxial.h"

namespace flarelab::optics {
namespace {

constexpr double kMaxFocalLength_mm = 1e6;
constexpr double kMaxFNumber = 1e4;

}  // namespace

Result<Lens> Lens::make(const Prescription& prescription, const CameraDescription& camera) {
    if (const auto reason = camera.invalidReason())
        return makeError(ErrorCode::InvalidArgument, "camera description: " + *reason);
    if (prescription.surfaces.empty() || prescription.stop_index < 0 ||
        prescription.stop_index >= static_cast<int>(prescription.surfaces.size()))
        return makeError(ErrorCode::InvalidArgument,
                         prescription.source + ": prescription has no surfaces or no stop");
    Lens lens;
    lens.name_ = prescription.name;
    lens.stop_index_ = prescription.stop_index;
    lens.camera_ = camera;
    lens.aperture_ = ApertureShape{camera.aperture_blades, degToRad(camera.aperture_rotation_deg)};
    double z = 0.0;
    for (const Surface& row : prescription.surfaces) {
        LensSurface s;
        s.z_mm = z;
        s.curvature = row.radius_mm == 0.0 ? 0.0 : 1.0 / row.radius_mm;
        s.semi_aperture_mm = row.semi_aperture_mm;
        s.ior_d = row.ior_d;
        s.abbe = row.abbe;
        s.is_stop = row.kind == SurfaceKind::Stop;
        if (!s.is_stop) {
            if (row.coating_wavelength_nm > 0.0) {
                s.coating_wavelength_nm = row.coating_wavelength_nm;
            } else if (camera.coat_unspecified_surfaces) {
                s.coating_wavelength_nm = camera.default_coating_wavelength_nm;
            } else {
                ++lens.uncoated_unspecified_;
            }
            if (row.ior_d != 1.0 && row.abbe <= 0.0) ++lens.non_dispersive_glasses_;
        }
        lens.surfaces_.push_back(s);
        z += row.thickness_mm;
    }
    lens.sensor_z_mm_ = z;
    lens.table_stop_mm_ = lens.surfaces_[lens.stop_index_].semi_aperture_mm;
    lens.label_focal_mm_ = prescription.metadataNumber("focal_length_mm").value_or(0.0);
    if (!(lens.label_focal_mm_ > 0.0)) lens.label_focal_mm_ = 0.0;

    const auto paraxial = paraxialProperties(lens, kLambdaD_nm);
    if (!paraxial)
        return makeError(ErrorCode::InvalidArgument,
                         prescription.source +
                             ": afocal lens, or a stop that no paraxial ray from infinity "
                             "reaches; cannot place the entrance pupil");
    // Resolve the camera's zeros from the lens. Labels are header prose: one out of the range a
    // camera description accepts is an error naming it, never a silent substitute.
    const auto label_error = [&](const std::string& key, double value) {
        std::ostringstream msg;
        msg << prescription.source << ": header label " << key << ": " << value << " is outside "
            << (key == "f_number" ? "0.5..10000" : "0.01..1e6 mm")
            << "; give the camera's value explicitly (--"
            << (key == "f_number" ? "f-number" : "focal-mm") << ")";
        return makeError(ErrorCode::InvalidArgument, msg.str());
    };
    if (lens.camera_.focal_length_mm == 0.0) {
        if (lens.label_focal_mm_ > 0.0 &&
            !(lens.label_focal_mm_ >= 0.01 && lens.label_focal_mm_ <= kMaxFocalLength_mm))
            return label_error("focal_length_mm", lens.label_focal_mm_);
        lens.camera_.focal_length_mm =
            lens.label_focal_mm_ > 0.0 ? lens.label_focal_mm_ : std::abs(paraxial->efl_mm);
    }
    if (lens.camera_.f_number == 0.0) {
        const double label_f = prescription.metadataNumber("f_number").value_or(0.0);
        if (label_f > 0.0 && !(label_f >= 0.5 && label_f <= kMaxFNumber))
            return label_error("f_number", label_f);
        lens.camera_.f_number = label_f;
    }
    if (lens.camera_.f_number > 0.0) {
        // Entrance pupil radius F / (2N), carried to the stop by the paraxial stop magnification.
        const double pupil_radius = lens.camera_.focal_length_mm / (2.0 * lens.camera_.f_number);
        const double stop_mm = pupil_radius * std::abs(paraxial->stop_magnification);
        if (!(stop_mm >= 1e-6 && stop_mm <= 1e6)) {
            std::ostringstream msg;
            msg << prescription.source << ": f/" << lens.camera_.f_number << " at "
                << lens.camera_.focal_length_mm << " mm needs a stop semi-aperture of " << stop_mm
                << " mm, outside 1e-6..1e6 mm";
            return makeError(ErrorCode::InvalidArgument, msg.str());
        }
        lens.surfaces_[lens.stop_index_].semi_aperture_mm = stop_mm;
    } else {
        lens.camera_.f_number =
            lens.camera_.focal_length_mm / (2.0 * paraxial->entrance_pupil_radius_mm);
    }
    return lens;
}

double Lens::mediumIndex(int k, double wavelength_nm) const {
    if (k < 0) return 1.0;
    const LensSurface& s = surfaces_[k];
    return refractiveIndex(s.ior_d, s.abbe, wavelength_nm);
}

double Lens::sensorHalfDiagonal_mm() const {
    return 0.5 * std::hypot(camera_.sensor_width_mm, camera_.sensor_height_mm);
}

bool Lens::isValidPath(const GhostPath& path) const {
    if (path.isImaging()) return path.second < 0;
    const int n = static_cast<int>(surfaces_.size());
    return path.first >= 0 && path.first < path.second && path.second < n &&
           !surfaces_[path.first].is_stop && !surfaces_[path.second].is_stop;
}

int Lens::stopCrossings(const GhostPath& path) const {
    if (path.isImaging()) return 1;
    return (path.first < stop_index_ && stop_index_ < path.second) ? 3 : 1;
}

Lens Lens::withStopSemiAperture(double semi_aperture_mm) const {
    Lens copy = *this;
    copy.surfaces_[stop_index_].semi_aperture_mm = semi_aperture_mm;
    return copy;
}

std::string pathLabel(const GhostPath& path) {
    if (path.isImaging()) return "imaging";
    std::ostringstream out;
    out << path.first + 1 << "-" << path.second + 1;
    return out.str();
}

}  // namespace flarelab::optics
