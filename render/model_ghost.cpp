#include "render/model_ghost.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace flarelab::render {

std::optional<GhostPrimitive> prepareGhostPrimitive(const BezierLoop& loop_mm,
                                                    const GhostShading& shading,
                                                    const SensorToImage& mapping,
                                                    int64_t width,
                                                    int64_t height,
                                                    const FastDistanceOptions& distance) {
    if (loop_mm.segmentCount() < 1 || width < 1 || height < 1) return std::nullopt;
    if (!validateShading(shading)) return std::nullopt;
    if (!(mapping.px_per_mm_x > 0.0) || !(mapping.px_per_mm_y > 0.0) ||
        !std::isfinite(mapping.centre_x_px) || !std::isfinite(mapping.centre_y_px))
        return std::nullopt;
    if (distance.iterations < 0 || distance.seeds_per_segment < 1) return std::nullopt;
    bool lit = false;
    for (int c = 0; c < 3; ++c)
        lit = lit || shading.border_rgb[c] > 0.0 || shading.inner_rgb[c] > 0.0;
    if (!lit) return std::nullopt;

    double lo_x = std::numeric_limits<double>::infinity(), hi_x = -lo_x;
    double lo_y = lo_x, hi_y = -lo_x;
    for (const auto& p : loop_mm.control_points_mm) {
        if (!std::isfinite(p.x()) || !std::isfinite(p.y())) return std::nullopt;
        lo_x = std::min(lo_x, p.x());
        hi_x = std::max(hi_x, p.x());
        lo_y = std::min(lo_y, p.y());
        hi_y = std::max(hi_y, p.y());
    }
    // Beyond the outer falloff the ghost is zero; the curve lies in its control points' box. A
    // pixel's mean reaches half its diagonal further.
    const double grow = shading.outer_falloff_mm +
                        0.5 * std::hypot(1.0 / mapping.px_per_mm_x, 1.0 / mapping.px_per_mm_y);
    const Eigen::Vector2d a = mapping.toPixels(lo_x - grow, lo_y - grow);
    const Eigen::Vector2d b = mapping.toPixels(hi_x + grow, hi_y + grow);
    if (!std::isfinite(a.x()) || !std::isfinite(a.y()) || !std::isfinite(b.x()) ||
        !std::isfinite(b.y()))
        return std::nullopt;
    // Pixel x is sampled at x + 0.5: the range holds the centres inside [a, b].
    const double fx0 = std::ceil(a.x() - 0.5), fx1 = std::floor(b.x() - 0.5);
    const double fy0 = std::ceil(a.y() - 0.5), fy1 = std::floor(b.y() - 0.5);
    const double w = static_cast<double>(width), h = static_cast<double>(height);
    if (fx1 < 0.0 || fy1 < 0.0 || fx0 > w - 1.0 || fy0 > h - 1.0 || fx0 > fx1 || fy0 > fy1)
        return std::nullopt;
    GhostPrimitive g;
    g.loop_mm = loop_mm;
    g.shading = shading;
    g.mapping = mapping;
    g.distance = distance;
    g.x0 = static_cast<int64_t>(std::max(0.0, fx0));
    g.x1 = static_cast<int64_t>(std::min(w - 1.0, fx1));
    g.y0 = static_cast<int64_t>(std::max(0.0, fy0));
    g.y1 = static_cast<int64_t>(std::min(h - 1.0, fy1));
    return g;
}

void addGhostRow(const GhostPrimitive& g, int64_t y, int64_t x0, int64_t x1, float* rgb) {
    const double qy =
        (static_cast<double>(y) + 0.5 - g.mapping.centre_y_px) / g.mapping.px_per_mm_y;
    const Eigen::Vector2d half(0.5 / g.mapping.px_per_mm_x, 0.5 / g.mapping.px_per_mm_y);
    for (int64_t x = x0; x <= x1; ++x, rgb += 3) {
        const double qx =
            (static_cast<double>(x) + 0.5 - g.mapping.centre_x_px) / g.mapping.px_per_mm_x;
        const std::array<double, 3> v =
            shadeGhostBlock(g.loop_mm, g.shading, {qx, qy}, half, g.distance);
        for (int c = 0; c < 3; ++c)
            if (std::isfinite(v[c])) rgb[c] += static_cast<float>(v[c]);
    }
}

}  // namespace flarelab::render
