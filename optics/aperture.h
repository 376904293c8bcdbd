// ============================================================================
//  flarelab optics: ApertureShape
// ============================================================================
//
// The opening of the aperture stop: a circle, or a regular polygon of n straight blades whose
// corners lie on the stop's circle. Coordinates are normalized by the stop's semi-aperture, so
// (u, v) = (x, y) / r_stop; the renderer looks a ray's stop coordinates up in the same shape.
#pragma once

#include <cmath>

#include "common/units.h"

namespace flarelab::optics {

struct ApertureShape {
    int blades = 0;             // 0: circle; n >= 3: regular n-gon inscribed in the unit circle
    double rotation_rad = 0.0;  // of the first corner, from +u towards +v

    // Signed distance-like value: < 1 inside, 1 on the edge, > 1 outside. For the circle it is
    // the radius; for the polygon, the largest edge-normal projection over the apothem.
    double edgeRatio(double u, double v) const {
        if (blades < 3) return std::sqrt(u * u + v * v);
        const double apothem = std::cos(kPi / blades);
        const double step = 2.0 * kPi / blades;
        // The edge normal closest in angle to (u, v) gives the largest projection.
        const double angle = std::atan2(v, u) - rotation_rad - 0.5 * step;
        const double k = std::round(angle / step);
        const double normal = rotation_rad + 0.5 * step + k * step;
        return (u * std::cos(normal) + v * std::sin(normal)) / apothem;
    }
    bool contains(double u, double v) const { return edgeRatio(u, v) <= 1.0; }
    bool operator==(const ApertureShape&) const = default;
};

}  // namespace flarelab::optics
