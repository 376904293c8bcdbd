#include "render/ghost_quads.h"

#include <algorithm>
#include <cmath>

#include "common/check.h"
#include "common/units.h"

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

// The set-up of a strictly convex quad (see Primitive).
void setUpConvex(Primitive& p) {
    const auto& c = p.quad.corners;
    // +1 when the corners turn clockwise on screen (y down); all four turns agree for a convex
    // quad.
    const int turn = orientation(c[0].position_px, c[1].position_px, c[2].position_px);
    for (int i = 0; i < 4; ++i) {
        const Eigen::Vector2d& a = c[i].position_px;
        const Eigen::Vector2d& b = c[(i + 1) % 4].position_px;
        const bool forward = a.x() < b.x() || (a.x() == b.x() && a.y() < b.y());
        const Eigen::Vector2d& s = forward ? a : b;
        const Eigen::Vector2d& e = forward ? b : a;
        EdgeFunction& edge = p.edge[i];
        edge.ax = s.x();
        edge.ay = s.y();
        edge.dx = e.x() - s.x();
        edge.dy = e.y() - s.y();
        // (e - s) x (p - s) is positive left of s -> e in the orientation() sense, where a quad
        // turning with sign `turn` keeps its inside when it runs a -> b.
        edge.sign = (forward ? 1.0 : -1.0) * static_cast<double>(turn);
        edge.closed = forward;  // of the two quads sharing the edge, the one running s -> e
    }
    for (int i = 0; i < 4; ++i) {
        const Eigen::Vector2d u = c[i].position_px - c[(i + 3) % 4].position_px;
        const Eigen::Vector2d v = c[(i + 1) % 4].position_px - c[i].position_px;
        p.corner_area[i] = std::abs(u.x() * v.y() - u.y() * v.x());
    }
    p.convex = true;
}

}  // namespace

StopMask::StopMask(const optics::ApertureShape& shape) {
    if (shape.blades < 3) return;
    blades_ = shape.blades;
    const double step = 2.0 * kPi / blades_;
    const double apothem = std::cos(kPi / blades_);
    for (int k = 0; k < blades_; ++k) {
        const double angle = shape.rotation_rad + 0.5 * step + k * step;
        normal_u_.push_back(std::cos(angle) / apothem);
        normal_v_.push_back(std::sin(angle) / apothem);
    }
}

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

namespace {

// Whether edges a (from a0 to a1) and b (from b0 to b1) point the same way within gamma.
bool sameDirection(const Eigen::Vector2d& a0,
                   const Eigen::Vector2d& a1,
                   const Eigen::Vector2d& b0,
                   const Eigen::Vector2d& b1,
                   double gamma) {
    const Eigen::Vector2d a = a1 - a0, b = b1 - b0;
    const double dot = a.dot(b);
    const double cross = a.x() * b.y() - a.y() * b.x();
    const double lengths = a.norm() * b.norm();
    return dot > 0.0 && std::isfinite(lengths) && std::abs(cross) <= gamma * lengths;
}

Quad quadFrom(const optics::RayGrid& grid, const SensorToImage& mapping, int ix, int iy, int size) {
    const optics::GridSample* s[4] = {&grid.at(ix, iy), &grid.at(ix + size, iy),
                                      &grid.at(ix + size, iy + size), &grid.at(ix, iy + size)};
    Quad q;
    for (int k = 0; k < 4; ++k) {
        q.corners[k].position_px = mapping.toPixels(s[k]->sensor_x_mm, s[k]->sensor_y_mm);
        q.corners[k].throughput = s[k]->valid ? s[k]->throughput : 0.0f;
        q.corners[k].stop_u = s[k]->stop_u;
        q.corners[k].stop_v = s[k]->stop_v;
    }
    return q;
}

}  // namespace

GhostQuads quadsFromGrid(const optics::RayGrid& grid,
                         const SensorToImage& mapping,
                         const MergeOptions& merge) {
    GhostQuads out;
    if (grid.n < 2) return out;
    const double cell = 2.0 * grid.entry_half_width_mm / (grid.n - 1);
    out.cell_area_mm2 = cell * cell;
    const int cells = grid.n - 1;
    const int steps = std::clamp(merge.steps, 0, 7);  // 4^7 cells still fit in uint16_t
    const auto pixel = [&](int ix, int iy) {
        const optics::GridSample& s = grid.at(ix, iy);
        return mapping.toPixels(s.sensor_x_mm, s.sensor_y_mm);
    };
    // whole[k][J * side_k + I]: block (I, J) of 2^k x 2^k cells is one merged quad.
    std::vector<std::vector<uint8_t>> whole;
    if (steps > 0) {
        whole.emplace_back(static_cast<size_t>(cells) * cells, 0);
        for (int iy = 0; iy < cells; ++iy)
            for (int ix = 0; ix < cells; ++ix) {
                const bool lit = grid.at(ix, iy).valid && grid.at(ix + 1, iy).valid &&
                                 grid.at(ix + 1, iy + 1).valid && grid.at(ix, iy + 1).valid;
                whole[0][static_cast<size_t>(iy) * cells + ix] =
                    lit && quadIsConvex(quadFrom(grid, mapping, ix, iy, 1));
            }
        for (int k = 1; k <= steps; ++k) {
            const int side = cells >> k, child_side = cells >> (k - 1), size = 1 << k,
                      half = size / 2;
            if (side < 1) break;
            whole.emplace_back(static_cast<size_t>(side) * side, 0);
            for (int by = 0; by < side; ++by)
                for (int bx = 0; bx < side; ++bx) {
                    const auto child = [&](int dx, int dy) {
                        return whole[k - 1][static_cast<size_t>(2 * by + dy) * child_side + 2 * bx +
                                            dx] != 0;
                    };
                    if (!(child(0, 0) && child(1, 0) && child(0, 1) && child(1, 1))) continue;
                    const int x0 = bx * size, y0 = by * size;
                    // Three grid points along each of the six lines of the block.
                    bool straight = true;
                    for (int line = 0; line < 3 && straight; ++line) {
                        const int x = x0 + line * half, y = y0 + line * half;
                        straight =
                            sameDirection(pixel(x0, y), pixel(x0 + half, y), pixel(x0 + half, y),
                                          pixel(x0 + size, y), merge.gamma) &&
                            sameDirection(pixel(x, y0), pixel(x, y0 + half), pixel(x, y0 + half),
                                          pixel(x, y0 + size), merge.gamma);
                    }
                    if (straight && quadIsConvex(quadFrom(grid, mapping, x0, y0, size)))
                        whole[k][static_cast<size_t>(by) * side + bx] = 1;
                }
        }
    }
    const int levels = static_cast<int>(whole.size());
    // The highest merged level that covers cell (ix, iy), or -1.
    const auto levelOf = [&](int ix, int iy) {
        for (int k = levels - 1; k >= 1; --k) {
            const int side = cells >> k;
            const int bx = ix >> k, by = iy >> k;
            if (bx < side && by < side && whole[k][static_cast<size_t>(by) * side + bx]) return k;
        }
        return levels > 0 && whole[0][static_cast<size_t>(iy) * cells + ix] ? 0 : -1;
    };
    out.quads.reserve(static_cast<size_t>(cells) * static_cast<size_t>(cells));
    for (int iy = 0; iy < cells; ++iy) {
        for (int ix = 0; ix < cells; ++ix) {
            const int level = steps > 0 ? levelOf(ix, iy) : -1;
            if (level >= 1) {
                // A merged block is emitted once, at its first cell.
                const int size = 1 << level;
                if (ix % size != 0 || iy % size != 0) continue;
                out.quads.push_back(quadFrom(grid, mapping, ix, iy, size));
                out.cells.resize(out.quads.size(), 1);
                out.cells.back() = static_cast<uint16_t>(size * size);
                continue;
            }
            const optics::GridSample* s[4] = {&grid.at(ix, iy), &grid.at(ix + 1, iy),
                                              &grid.at(ix + 1, iy + 1), &grid.at(ix, iy + 1)};
            bool any_valid = false, all_placed = true;
            for (const optics::GridSample* c : s) {
                any_valid = any_valid || c->valid;
                all_placed = all_placed && c->has_position;
            }
            if (!any_valid || !all_placed) continue;
            out.quads.push_back(quadFrom(grid, mapping, ix, iy, 1));
            if (!out.cells.empty()) out.cells.push_back(1);
        }
    }
    if (!out.cells.empty()) out.cells.resize(out.quads.size(), 1);
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
        if (quadIsConvex(quad)) setUpConvex(p);
    }
    if (!std::isfinite(p.scale)) return std::nullopt;
    return p;
}

double primitiveValueAt(const Primitive& primitive, int64_t x, int64_t y, const StopMask& stop) {
    const double px = static_cast<double>(x) + 0.5, py = static_cast<double>(y) + 0.5;
    if (primitive.convex) return convexValueAt(primitive, px, py, stop);
    QuadSample sample;
    if (primitive.splat) {
        sample = interpolateQuad(primitive.quad, {0.25, 0.25, 0.25, 0.25});
    } else {
        const auto weights = quadBarycentrics(primitive.quad, Eigen::Vector2d(px, py));
        if (!weights) return 0.0;
        sample = interpolateQuad(primitive.quad, *weights);
    }
    if (!(sample.throughput > 0.0f) || !stop.contains(sample.stop_u, sample.stop_v)) return 0.0;
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
    const StopMask stop(aperture);
    for (size_t i = 0; i < ghost.quads.size(); ++i) {
        const auto primitive = preparePrimitive(ghost.quads[i], ghost.cellArea(i), channel,
                                                irradiance, image.width, image.height, options);
        if (!primitive) continue;
        for (int64_t y = primitive->y0; y <= primitive->y1; ++y)
            for (int64_t x = primitive->x0; x <= primitive->x1; ++x)
                image.at(x, y)[channel] +=
                    static_cast<float>(primitiveValueAt(*primitive, x, y, stop));
    }
}

}  // namespace flarelab::render
