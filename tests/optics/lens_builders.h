// Small lenses built in code for the optics tests.
#pragma once

#include <cstdlib>
#include <string>
#include <vector>

#include "optics/lens.h"
#include "optics/prescription.h"
#include "tests/test_paths.h"

namespace flarelab::optics::testing {

inline Surface refracting(double radius,
                          double thickness,
                          double ior,
                          double semi_ap,
                          double abbe = 0.0,
                          double coating_nm = 0.0) {
    Surface s;
    s.radius_mm = radius;
    s.thickness_mm = thickness;
    s.ior_d = ior;
    s.abbe = ior == 1.0 ? 0.0 : abbe;
    s.semi_aperture_mm = semi_ap;
    s.coating_wavelength_nm = coating_nm;
    return s;
}

inline Surface stop(double thickness, double semi_ap, double ior = 1.0) {
    Surface s;
    s.kind = SurfaceKind::Stop;
    s.thickness_mm = thickness;
    s.ior_d = ior;
    s.semi_aperture_mm = semi_ap;
    return s;
}

inline Prescription prescriptionOf(std::vector<Surface> surfaces) {
    Prescription p;
    p.source = "test";
    p.name = "test";
    p.surfaces = std::move(surfaces);
    for (size_t k = 0; k < p.surfaces.size(); ++k)
        if (p.surfaces[k].kind == SurfaceKind::Stop) p.stop_index = static_cast<int>(k);
    return p;
}

// Keeps the stop as given (f_number 0 and no label: the table's stop).
inline Lens lensOf(std::vector<Surface> surfaces, CameraDescription camera = {}) {
    auto lens = Lens::make(prescriptionOf(std::move(surfaces)), camera);
    if (!lens) std::abort();
    return *lens;
}

// A biconvex singlet (f ~ 100 mm) with the stop in front: the smallest real imaging lens.
inline Lens singlet(double coating_nm = 0.0) {
    return lensOf({stop(5.0, 10.0), refracting(100.0, 6.0, 1.5168, 20.0, 64.17, coating_nm),
                   refracting(-100.0, 97.0, 1.0, 20.0, 0.0, coating_nm)});
}

// A shipped lens (data/lenses/FILE) with the default camera; aborts if it does not load, which
// the lens tests themselves report.
inline Lens shippedLens(const std::string& file) {
    auto prescription = loadPrescription(flarelab::testing::lensPath(file));
    if (!prescription) std::abort();
    auto lens = Lens::make(*prescription, CameraDescription{});
    if (!lens) std::abort();
    return *lens;
}

}  // namespace flarelab::optics::testing
