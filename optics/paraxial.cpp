#include "optics/paraxial.h"

#include <Eigen/LU>
#include <cmath>
#include <limits>

#include "common/check.h"

namespace flarelab::optics {
namespace {

// Calls `visit(matrix)` for each elementary matrix of the path in order, and `at_surface(k)`
// when the light arrives at surface k (after the translation to it, before its own matrix).
template <typename Visit, typename AtSurface>
void walkPath(const Lens& lens,
              const GhostPath& path,
              double wavelength_nm,
              Visit&& visit,
              AtSurface&& at_surface) {
    const auto& s = lens.surfaces();
    const int n = static_cast<int>(s.size());
    // Forward leg to `second` (or to the end for the imaging path).
    const int forward_end = path.isImaging() ? n - 1 : path.second;
    for (int k = 0; k <= forward_end; ++k) {
        if (k > 0) visit(translationMatrix(s[k].z_mm - s[k - 1].z_mm));
        at_surface(k);
        if (k == path.second) {
            visit(reflectionMatrix(s[k].curvature));
        } else if (!s[k].is_stop) {
            visit(refractionMatrix(lens.mediumIndex(k - 1, wavelength_nm),
                                   lens.mediumIndex(k, wavelength_nm), s[k].curvature));
        }
    }
    if (!path.isImaging()) {
        // Back from `second` to `first`: curvature seen reversed, media swapped.
        for (int k = path.second - 1; k >= path.first; --k) {
            visit(translationMatrix(s[k + 1].z_mm - s[k].z_mm));
            at_surface(k);
            if (k == path.first) {
                visit(reflectionMatrix(-s[k].curvature));
            } else if (!s[k].is_stop) {
                visit(refractionMatrix(lens.mediumIndex(k, wavelength_nm),
                                       lens.mediumIndex(k - 1, wavelength_nm), -s[k].curvature));
            }
        }
        // Forward again from `first` to the last surface.
        for (int k = path.first + 1; k < n; ++k) {
            visit(translationMatrix(s[k].z_mm - s[k - 1].z_mm));
            at_surface(k);
            if (!s[k].is_stop)
                visit(refractionMatrix(lens.mediumIndex(k - 1, wavelength_nm),
                                       lens.mediumIndex(k, wavelength_nm), s[k].curvature));
        }
    }
    visit(translationMatrix(lens.sensorZ_mm() - s[n - 1].z_mm));
}

}  // namespace

Matrix2 translationMatrix(double distance_mm) {
    Matrix2 m;
    m << 1.0, distance_mm, 0.0, 1.0;
    return m;
}

Matrix2 refractionMatrix(double n1, double n2, double curvature_eff) {
    Matrix2 m;
    m << 1.0, 0.0, (n1 - n2) * curvature_eff / n2, n1 / n2;
    return m;
}

Matrix2 reflectionMatrix(double curvature_eff) {
    Matrix2 m;
    m << 1.0, 0.0, 2.0 * curvature_eff, 1.0;
    return m;
}

PathMatrices pathMatrices(const Lens& lens, const GhostPath& path, double wavelength_nm) {
    PathMatrices result;
    Matrix2 current = Matrix2::Identity();
    bool split = false;
    walkPath(
        lens, path, wavelength_nm, [&](const Matrix2& m) { current = m * current; },
        [&](int k) {
            if (split || !lens.surfaces()[k].is_stop) return;
            result.to_stop = current;
            current = Matrix2::Identity();
            split = true;
        });
    FLARELAB_CHECK(split);  // every path of a valid lens crosses the stop
    result.from_stop = current;
    result.total = result.from_stop * result.to_stop;
    return result;
}

std::optional<ParaxialProperties> paraxialProperties(const Lens& lens, double wavelength_nm) {
    const auto& s = lens.surfaces();
    ParaxialProperties p;
    const PathMatrices imaging = pathMatrices(lens, GhostPath{}, wavelength_nm);
    p.system_matrix = imaging.total;
    p.lens_matrix = translationMatrix(-(lens.sensorZ_mm() - s.back().z_mm)) * imaging.total;
    const double a = p.lens_matrix(0, 0), c = p.lens_matrix(1, 0), d = p.lens_matrix(1, 1);
    if (!(std::abs(c) > 1e-15)) return std::nullopt;  // afocal
    p.efl_mm = -1.0 / c;
    p.bfl_mm = -a / c;
    p.ffl_mm = -d / c;  // positive: front focus lies in front of the first vertex
    // Entrance pupil: the stop seen from object space. A ray (y0, u0) at the first vertex reaches
    // the stop at A y0 + B u0; the chief ray (stop height 0) crosses the axis at z = B / A.
    const double sa = imaging.to_stop(0, 0), sb = imaging.to_stop(0, 1);
    if (!(std::abs(sa) > 1e-12)) return std::nullopt;
    p.stop_magnification = sa;
    p.entrance_pupil_z_mm = sb / sa;
    p.entrance_pupil_radius_mm = s[lens.stopIndex()].semi_aperture_mm / std::abs(sa);
    p.working_f_number = std::abs(p.efl_mm) / (2.0 * p.entrance_pupil_radius_mm);
    // Exit pupil: the stop seen from image space. A ray leaving the stop axis with slope u has
    // height B2 u and slope D2 u after the last surface; it crosses the axis at -B2 / D2 from it.
    const Matrix2 stop_to_last =
        translationMatrix(-(lens.sensorZ_mm() - s.back().z_mm)) * imaging.from_stop;
    const double b2 = stop_to_last(0, 1), d2 = stop_to_last(1, 1);
    p.exit_pupil_z_mm = std::abs(d2) > 1e-15 ? s.back().z_mm - b2 / d2 : s.back().z_mm;
    // Extreme but legal tables can overflow the matrix products; no infinity leaves here.
    for (const double v : {p.efl_mm, p.bfl_mm, p.ffl_mm, p.entrance_pupil_z_mm,
                           p.entrance_pupil_radius_mm, p.exit_pupil_z_mm, p.working_f_number})
        if (!std::isfinite(v)) return std::nullopt;
    return p;
}

PathTransfer pathTransfer(const Lens& lens, const GhostPath& path, double wavelength_nm) {
    PathTransfer result;
    Matrix2 current = Matrix2::Identity();
    walkPath(
        lens, path, wavelength_nm, [&](const Matrix2& m) { current = m * current; },
        [&](int k) {
            const LensSurface& s = lens.surfaces()[k];
            result.crossings.push_back(PathCrossing{k, s.is_stop, s.semi_aperture_mm, current});
        });
    result.total = current;
    return result;
}

std::optional<ParaxialGhost> paraxialGhost(const Lens& lens,
                                           const GhostPath& path,
                                           double wavelength_nm) {
    return paraxialGhost(pathTransfer(lens, path, wavelength_nm));
}

std::optional<ParaxialGhost> paraxialGhost(const PathTransfer& transfer) {
    ParaxialGhost ghost;
    double narrowest = std::numeric_limits<double>::infinity();
    for (size_t i = 0; i < transfer.crossings.size(); ++i) {
        const PathCrossing& c = transfer.crossings[i];
        const double a = std::abs(c.to_here(0, 0));
        if (!(a > 1e-12)) continue;  // the beam is focused here: this surface does not cut it
        const double beam = c.semi_aperture_mm / a;
        if (beam < narrowest) {
            narrowest = beam;
            ghost.limiting_crossing = static_cast<int>(i);
            ghost.limiting_surface = c.surface;
        }
    }
    if (ghost.limiting_crossing < 0) return std::nullopt;
    const PathCrossing& lim = transfer.crossings[ghost.limiting_crossing];
    const Matrix2& m1 = lim.to_here;
    const Matrix2 m2 = transfer.total * m1.inverse();
    const double a1 = m1(0, 0), b1 = m1(0, 1), c1 = m1(1, 0), d1 = m1(1, 1);
    const double a2 = m2(0, 0), b2 = m2(0, 1);
    // Parametrize the beam by its height y_l at the limiting aperture: y0 = (y_l - B1 u0) / A1,
    // and the sensor height is y_l (A2 + B2 C1 / A1) + u0 B2 (D1 - C1 B1 / A1).
    ghost.centre_per_tan_mm = b2 * (d1 - c1 * b1 / a1);
    ghost.radius_mm = lim.semi_aperture_mm * std::abs(a2 + b2 * c1 / a1);
    ghost.beam_radius_mm = narrowest;
    return ghost;
}

}  // namespace flarelab::optics
