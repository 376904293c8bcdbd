#include "render/ghost_quads.h"

#include <algorithm>
#include <cmath>

#include "common/check.h"

namespace flarelab::render {
namespace {

// Twice the signed area of the quad's polygon (shoelace), in px^2; its magnitude is the area for
// simple quads and the net area for folded ones.
double quadArea(const Quad& q) {
    double twice = 0.0;
    for (int k = 0; k < 4; ++k) {
        const Eigen::Vector2d& a = q.corners[k].position_px;
        const Eigen::Vector2d& b = q.corners[(k + 1) % 4].position_px;
        twice += a.x() * b.y() - a.y() * b.x();
    }
    return 0.5 * std::abs(twice);
}

}  // namespace

SensorToImage sensorToImage(const optics::CameraDescription& camera,
                            int64_t width,
                            int64_t height) {
    FLARELAB_CHECK_GT(camera.sensor_width_mm, 0.0);
    FLARELAB_CHECK_GT(camera.sensor_height_mm, 0.0);
    SensorToImage m;
    m.px_per_mm_x = static_cast<double>(width) / camera.sensor_width_mm;
    m.px_per_mm_y = static_cast<double>(height) / camera.sensor_height_mm;
    m.centre_x_px = 0.5 * static_cast<double>(width);
    m.centre_y_px = 0.5 * static_cast<double>(height);
    return m;
}

int adaptiveGridSize(
    int base_size, double ghost_area_mm2, double sensor_area_mm2, double sigma, double phi) {
    FLARELAB_CHECK_GE(base_size, 2);
    double factor = 1.0;
    if (sensor_area_mm2 > 0.0 && ghost_area_mm2 >= 0.0 && std::isfinite(ghost_area_mm2)) {
        const double ratio = ghost_area_mm2 / sensor_area_mm2 * sigma;
        factor = std::min(std::max(std::pow(ratio, phi), 0.05), 1.0);
    }
    if (!std::isfinite(factor)) factor = 1.0;
    return std::max(2, static_cast<int>(std::lround(base_size * factor)));
}

GhostQuads quadsFromGrid(const optics::RayGrid& grid, const SensorToImage& mapping) {
    GhostQuads out;
    if (grid.n < 2) return out;
    const double cell = 2.0 * grid.entry_half_width_mm / (grid.n - 1);
    out.cell_area_mm2 = cell * cell;
    out.quads.reserve(static_cast<size_t>(grid.n - 1) * static_cast<size_t>(grid.n - 1));
    for (int iy = 0; iy + 1 < grid.n; ++iy) {
        for (int ix = 0; ix + 1 < grid.n; ++ix) {
            const optics::GridSample* s[4] = {&grid.at(ix, iy), &grid.at(ix + 1, iy),
                                              &grid.at(ix + 1, iy + 1), &grid.at(ix, iy + 1)};
            bool any_valid = false, all_placed = true;
            for (const optics::GridSample* c : s) {
                any_valid = any_valid || c->valid;
                all_placed = all_placed && c->has_position;
            }
            if (!any_valid || !all_placed) continue;
            Quad q;
            for (int k = 0; k < 4; ++k) {
                q.corners[k].position_px = mapping.toPixels(s[k]->sensor_x_mm, s[k]->sensor_y_mm);
                q.corners[k].throughput = s[k]->valid ? s[k]->throughput : 0.0f;
                q.corners[k].stop_u = s[k]->stop_u;
                q.corners[k].stop_v = s[k]->stop_v;
            }
            out.quads.push_back(q);
        }
    }
    return out;
}

std::optional<Primitive> preparePrimitive(const Quad& quad,
                                          double cell_area_mm2,
                                          int channel,
                                          float irradiance,
                                          int64_t width,
                                          int64_t height,
                                          const RasterOptions& options) {
    FLARELAB_CHECK(channel >= 0 && channel < 3);
    if (width < 1 || height < 1 || !(irradiance > 0.0f) || !std::isfinite(irradiance))
        return std::nullopt;
    double lo_x = quad.corners[0].position_px.x(), hi_x = lo_x;
    double lo_y = quad.corners[0].position_px.y(), hi_y = lo_y;
    for (const QuadCorner& c : quad.corners) {
        if (!std::isfinite(c.position_px.x()) || !std::isfinite(c.position_px.y()))
            return std::nullopt;
        lo_x = std::min(lo_x, c.position_px.x());
        hi_x = std::max(hi_x, c.position_px.x());
        lo_y = std::min(lo_y, c.position_px.y());
        hi_y = std::max(hi_y, c.position_px.y());
    }
    Primitive p;
    p.quad = quad;
    p.channel = channel;
    const double min_area = std::max(options.min_quad_area_px, 1e-12);
    const double area = quadArea(quad);
    if (area < min_area) {
        // Smaller than a pixel: it may hold no pixel centre at all, and point sampling would
        // lose its light. It goes whole to the pixel under its centre, masked there.
        const Eigen::Vector2d centre =
            0.25 * (quad.corners[0].position_px + quad.corners[1].position_px +
                    quad.corners[2].position_px + quad.corners[3].position_px);
        if (!(centre.x() >= 0.0 && centre.x() < static_cast<double>(width) && centre.y() >= 0.0 &&
              centre.y() < static_cast<double>(height)))
            return std::nullopt;
        p.splat = true;
        p.x0 = p.x1 = static_cast<int64_t>(centre.x());
        p.y0 = p.y1 = static_cast<int64_t>(centre.y());
        p.scale = irradiance * cell_area_mm2;
    } else {
        // Pixel centres x + 0.5 inside [lo, hi], clamped to the image in double before any
        // conversion, so quads far outside cost nothing and cannot overflow an index.
        const double x0 = std::max(0.0, std::ceil(lo_x - 0.5));
        const double x1 = std::min(static_cast<double>(width) - 1.0, std::floor(hi_x - 0.5));
        const double y0 = std::max(0.0, std::ceil(lo_y - 0.5));
        const double y1 = std::min(static_cast<double>(height) - 1.0, std::floor(hi_y - 0.5));
        if (x0 > x1 || y0 > y1) return std::nullopt;
        p.x0 = static_cast<int64_t>(x0);
        p.x1 = static_cast<int64_t>(x1);
        p.y0 = static_cast<int64_t>(y0);
        p.y1 = static_cast<int64_t>(y1);
        p.scale = irradiance * cell_area_mm2 / area;
    }
    if (!std::isfinite(p.scale)) return std::nullopt;
    return p;
}

double primitiveValueAt(const Primitive& primitive,
                        int64_t x,
                        int64_t y,
                        const optics::ApertureShape& aperture) {
    QuadSample sample;
    if (primitive.splat) {
        sample = interpolateQuad(primitive.quad, {0.25, 0.25, 0.25, 0.25});
    } else {
        const Eigen::Vector2d p(static_cast<double>(x) + 0.5, static_cast<double>(y) + 0.5);
        const auto weights = quadBarycentrics(primitive.quad, p);
        if (!weights) return 0.0;
        sample = interpolateQuad(primitive.quad, *weights);
    }
    if (!(sample.throughput > 0.0f) || !aperture.contains(sample.stop_u, sample.stop_v)) return 0.0;
    const double value = primitive.scale * sample.throughput;
    return std::isfinite(value) ? value : 0.0;
}

void rasterizeReference(ImageRGB& image,
                        const GhostQuads& ghost,
                        int channel,
                        float irradiance,
                        const optics::ApertureShape& aperture,
                        const RasterOptions& options) {
    FLARELAB_CHECK(channel >= 0 && channel < 3);
    for (const Quad& q : ghost.quads) {
        const auto primitive = preparePrimitive(q, ghost.cell_area_mm2, channel, irradiance,
                                                image.width, image.height, options);
        if (!primitive) continue;
        for (int64_t y = primitive->y0; y <= primitive->y1; ++y)
            for (int64_t x = primitive->x0; x <= primitive->x1; ++x)
                image.at(x, y)[channel] +=
                    static_cast<float>(primitiveValueAt(*primitive, x, y, aperture));
    }
}

}  // namespace flarelab::render
