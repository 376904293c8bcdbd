#include "render/ghost_quads.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>

#include "common/check.h"
#include "common/cpu.h"
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

// The Wachspress sums of a convex primitive at pixel centres as polynomials of u = x - x0 and
// v = y - y0 (the form of Primitive::inside_total): with a_i = alpha_i + g_i u + h_i v edge i's
// function, corner i's weight C_i a_j a_k (j = i + 1, k = i + 2) expands into six coefficients.
// Besides the weights' total and the throughput-weighted sum, when asked, the sums weighted by
// the stop coordinates and the aperture ratio.
using Polynomial = std::array<double, 6>;
struct CentrePolynomials {
    Polynomial total{}, throughput{}, stop_u{}, stop_v{}, ratio{};
};
CentrePolynomials centrePolynomials(const Primitive& p, bool stop_and_ratio) {
    CentrePolynomials out;
    const double cx = static_cast<double>(p.x0) + 0.5, cy = static_cast<double>(p.y0) + 0.5;
    for (size_t i = 0; i < 4; ++i) {
        const size_t j = (i + 1) % 4, k = (i + 2) % 4;
        const EdgeFunction& ej = p.edge[j];
        const EdgeFunction& ek = p.edge[k];
        const double aj = ej.at(cx, cy), ak = ek.at(cx, cy);
        const double area = p.corner_area[i];
        const double terms[6] = {area * (aj * ak),
                                 area * (aj * ek.gy + ak * ej.gy),
                                 area * (ej.gy * ek.gy),
                                 area * (aj * ek.gx + ak * ej.gx),
                                 area * (ej.gy * ek.gx + ek.gy * ej.gx),
                                 area * (ej.gx * ek.gx)};
        const QuadCorner& corner = p.quad.corners[i];
        for (size_t m = 0; m < 6; ++m) {
            out.total[m] += terms[m];
            out.throughput[m] += terms[m] * corner.throughput;
            if (stop_and_ratio) {
                out.stop_u[m] += terms[m] * corner.stop_u;
                out.stop_v[m] += terms[m] * corner.stop_v;
                out.ratio[m] += terms[m] * corner.aperture_ratio;
            }
        }
    }
    return out;
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
        const double dx = e.x() - s.x(), dy = e.y() - s.y();
        // (e - s) x (p - s) = (dy sx - dx sy) + dx py - dy px is positive left of s -> e in the
        // orientation() sense, where a quad turning with sign `turn` keeps its inside when it
        // runs a -> b.
        const double sign = (forward ? 1.0 : -1.0) * static_cast<double>(turn);
        edge.c = sign * (dy * s.x() - dx * s.y());
        edge.gx = sign * -dy;
        edge.gy = sign * dx;
        edge.closed = forward;  // of the two quads sharing the edge, the one running s -> e
        edge.reach = 0.5 * (std::abs(dx) + std::abs(dy));
        edge.by_centre = (p.quad.centre_edges >> i) & 1u;
    }
    for (int i = 0; i < 4; ++i) {
        const Eigen::Vector2d u = c[i].position_px - c[(i + 3) % 4].position_px;
        const Eigen::Vector2d v = c[(i + 1) % 4].position_px - c[i].position_px;
        p.corner_area[i] = std::abs(u.x() * v.y() - u.y() * v.x());
    }
    const CentrePolynomials sums = centrePolynomials(p, /*stop_and_ratio=*/false);
    p.inside_total = sums.total;
    p.inside_sum = sums.throughput;
    p.throughput_low = std::min({c[0].throughput, c[1].throughput, c[2].throughput, c[3].throughput});
    p.throughput_high =
        std::max({c[0].throughput, c[1].throughput, c[2].throughput, c[3].throughput});
    p.convex = true;
}

}  // namespace

StopMask::StopMask(const optics::ApertureShape& shape) {
    if (shape.blades < 3) return;
    blades_ = shape.blades;
    inscribed_radius_ = std::cos(kPi / blades_);
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
        // A cut ray keeps the light it would carry: its aperture ratio cuts it between rays.
        q.corners[k].throughput = s[k]->valid          ? s[k]->throughput
                                  : s[k]->has_position ? s[k]->open_throughput
                                                       : 0.0f;
        q.corners[k].stop_u = s[k]->stop_u;
        q.corners[k].stop_v = s[k]->stop_v;
        q.corners[k].aperture_ratio = s[k]->aperture_ratio;
    }
    return q;
}

// Whether the six lines of the block of `size` cells at (x0, y0) (its four sides and two midlines,
// three grid points each) keep their direction within gamma, in the coordinates at(ix, iy) gives.
template <typename At>
bool linesStraight(const At& at, int x0, int y0, int size, double gamma) {
    const int half = size / 2;
    for (int line = 0; line < 3; ++line) {
        const int x = x0 + line * half, y = y0 + line * half;
        if (!sameDirection(at(x0, y), at(x0 + half, y), at(x0 + half, y), at(x0 + size, y),
                           gamma) ||
            !sameDirection(at(x, y0), at(x, y0 + half), at(x, y0 + half), at(x, y0 + size), gamma))
            return false;
    }
    return true;
}

// Distance from the origin to the convex hull of four points, 0 when the hull holds it.
double hullDistanceFromOrigin(const std::array<Eigen::Vector2d, 4>& p) {
    // The origin lies in the hull when it lies in one of the four triangles of three corners.
    for (int skip = 0; skip < 4; ++skip) {
        int sides[3], k = 0;
        std::array<Eigen::Vector2d, 3> t;
        for (int i = 0; i < 4; ++i)
            if (i != skip) t[static_cast<size_t>(k++)] = p[static_cast<size_t>(i)];
        for (int e = 0; e < 3; ++e)
            sides[e] = orientation(t[static_cast<size_t>(e)], t[static_cast<size_t>((e + 1) % 3)],
                                   Eigen::Vector2d::Zero());
        const bool no_negative = sides[0] >= 0 && sides[1] >= 0 && sides[2] >= 0;
        const bool no_positive = sides[0] <= 0 && sides[1] <= 0 && sides[2] <= 0;
        if (no_negative || no_positive) return 0.0;
    }
    // Outside: the nearest point lies on a hull edge, and every pair's segment lies in the hull,
    // so the nearest of the six segments is it.
    double best = std::numeric_limits<double>::infinity();
    for (int i = 0; i < 4; ++i)
        for (int j = i + 1; j < 4; ++j) {
            const Eigen::Vector2d& a = p[static_cast<size_t>(i)];
            const Eigen::Vector2d d = p[static_cast<size_t>(j)] - a;
            const double length2 = d.squaredNorm();
            const double t = length2 > 0.0 ? std::clamp(-a.dot(d) / length2, 0.0, 1.0) : 0.0;
            best = std::min(best, (a + t * d).norm());
        }
    return best;
}

// Whether no stop outline of inscribed radius `radius` nor clear aperture can cut the quad (its
// interpolated values are convex mixtures of its corners', as Primitive::stop_radius and
// vignette_clear decide it), or it is dropped whole (preparePrimitive: every corner vignetted, or
// its stop coordinates' hull misses the stop).
bool uncut(const Quad& q, double radius) {
    bool clear = true, all_cut = true;
    std::array<Eigen::Vector2d, 4> stop_uv;
    for (size_t i = 0; i < 4; ++i) {
        const QuadCorner& c = q.corners[i];
        stop_uv[i] = {c.stop_u, c.stop_v};
        clear = clear && c.aperture_ratio <= 1.0f && stop_uv[i].norm() <= radius;
        all_cut = all_cut && c.aperture_ratio > 1.0f;
    }
    return clear || all_cut || hullDistanceFromOrigin(stop_uv) > 1.0;
}

// A single cell becomes a quad when one of its corners is a valid ray and all four have a
// position.
bool cellHasQuad(const optics::RayGrid& grid, int ix, int iy) {
    const optics::GridSample* s[4] = {&grid.at(ix, iy), &grid.at(ix + 1, iy),
                                      &grid.at(ix + 1, iy + 1), &grid.at(ix, iy + 1)};
    bool any_valid = false, all_placed = true;
    for (const optics::GridSample* c : s) {
        any_valid = any_valid || c->valid;
        all_placed = all_placed && c->has_position;
    }
    return any_valid && all_placed;
}

constexpr double kCentreEdgeMinWidthPx = 1.0;

// Sets Quad::centre_edges (MergeOptions::centre_edge_jump): quads i and j share an edge when the
// block across it has the same extent along it; they lie on either side when both are strictly
// convex and turn the same way; their densities are cells over area on the sensor.
template <class Block>
void markCentreEdges(GhostQuads& out,
                     const std::vector<Block>& blocks,
                     const LargePageVector<int32_t>& owner,
                     int cells,
                     double jump) {
    const size_t n = out.quads.size();
    std::vector<int8_t> turn(n, 0);
    std::vector<double> density(n, 0.0);
    for (size_t i = 0; i < n; ++i) {
        const Quad& q = out.quads[i];
        const double area = quadArea(q);
        // A pixel must meet few quads for its centre to stand for it: each at least a pixel wide
        // (its area over its longest edge; below that a pixel holds quads no centre falls in).
        double longest = 0.0;
        for (int k = 0; k < 4; ++k)
            longest = std::max(
                longest, (q.corners[(k + 1) % 4].position_px - q.corners[k].position_px).norm());
        if (!(area >= kCentreEdgeMinWidthPx * longest) || !quadIsConvex(q)) continue;
        turn[i] = static_cast<int8_t>(orientation(
            q.corners[0].position_px, q.corners[1].position_px, q.corners[2].position_px));
        const double size = blocks[i].size;
        density[i] = size * size / area;
    }
    const auto at = [&](int x, int y) -> int32_t {
        if (x < 0 || y < 0 || x >= cells || y >= cells) return -1;
        return owner[static_cast<size_t>(y) * cells + x];
    };
    for (size_t i = 0; i < n; ++i) {
        if (turn[i] == 0) continue;
        const Block& b = blocks[i];
        // Edge k runs from corner k to k + 1: top, right, bottom, left; the cell across it, and
        // whether the block there must start at the same x (top, bottom) or y (right, left).
        const int across[4][2] = {
            {b.x0, b.y0 - 1}, {b.x0 + b.size, b.y0}, {b.x0, b.y0 + b.size}, {b.x0 - 1, b.y0}};
        uint8_t bits = 0;
        for (int k = 0; k < 4; ++k) {
            const int32_t j = at(across[k][0], across[k][1]);
            if (j < 0 || turn[static_cast<size_t>(j)] != turn[i]) continue;
            const Block& o = blocks[static_cast<size_t>(j)];
            const bool same_extent = o.size == b.size && (k % 2 == 0 ? o.x0 == b.x0 : o.y0 == b.y0);
            if (!same_extent) continue;
            const double a = density[i], c = density[static_cast<size_t>(j)];
            if (std::abs(a - c) <= jump * std::max(a, c)) bits |= static_cast<uint8_t>(1u << k);
        }
        out.quads[i].centre_edges = bits;
    }
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
            const int side = cells >> k, child_side = cells >> (k - 1), size = 1 << k;
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
                    if (!linesStraight(pixel, x0, y0, size, merge.gamma)) continue;
                    const Quad merged = quadFrom(grid, mapping, x0, y0, size);
                    if (quadIsConvex(merged) && uncut(merged, merge.clear_stop_radius))
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
    const bool centre_edges = merge.centre_edge_jump > 0.0;
    // For the interior edges: each quad's block (origin, size) and the quad covering each cell.
    struct Block {
        int x0, y0, size;
    };
    std::vector<Block> blocks;
    LargePageVector<int32_t> owner;
    if (centre_edges) owner.assign(static_cast<size_t>(cells) * cells, -1);
    const auto emit = [&](int ix, int iy, int size) {
        out.quads.push_back(quadFrom(grid, mapping, ix, iy, size));
        if (!centre_edges) return;
        const auto index = static_cast<int32_t>(blocks.size());
        blocks.push_back({ix, iy, size});
        for (int y = iy; y < iy + size; ++y)
            std::fill_n(owner.begin() + static_cast<ptrdiff_t>(y) * cells + ix, size, index);
    };
    for (int iy = 0; iy < cells; ++iy) {
        for (int ix = 0; ix < cells; ++ix) {
            const int level = steps > 0 ? levelOf(ix, iy) : -1;
            if (level >= 1) {
                // A merged block is emitted once, at its first cell.
                const int size = 1 << level;
                if (ix % size != 0 || iy % size != 0) continue;
                emit(ix, iy, size);
                out.cells.resize(out.quads.size(), 1);
                out.cells.back() = static_cast<uint16_t>(size * size);
                continue;
            }
            if (!cellHasQuad(grid, ix, iy)) continue;
            emit(ix, iy, 1);
            if (!out.cells.empty()) out.cells.push_back(1);
        }
    }
    if (!out.cells.empty()) out.cells.resize(out.quads.size(), 1);
    if (centre_edges) markCentreEdges(out, blocks, owner, cells, merge.centre_edge_jump);
    return out;
}

Result<AdaptiveQuads> adaptiveQuads(const optics::Lens& lens,
                                    const optics::GhostPath& path,
                                    double theta_rad,
                                    double phi_rad,
                                    double wavelength_nm,
                                    int n,
                                    const optics::RayGridOptions& options,
                                    const SensorToImage& mapping,
                                    const MergeOptions& merge) {
    auto filler =
        optics::GridFiller::open(lens, path, theta_rad, phi_rad, wavelength_nm, n, options);
    if (!filler) return filler.error();
    AdaptiveQuads out;
    const int steps = std::clamp(merge.steps, 0, 7);  // as quadsFromGrid
    if (steps == 0 || n < 3) {
        filler->traceAll();
        out.quads = quadsFromGrid(filler->grid(), mapping, merge);
        out.rays = filler->tracedCount();
        return out;
    }
    const optics::RayGrid& grid = filler->grid();
    const int cells = n - 1;
    out.quads.cell_area_mm2 = std::pow(2.0 * grid.entry_half_width_mm / cells, 2);
    const auto pixel = [&](int ix, int iy) {
        const optics::GridSample& s = grid.at(ix, iy);
        return mapping.toPixels(s.sensor_x_mm, s.sensor_y_mm);
    };
    const auto stop = [&](int ix, int iy) {
        const optics::GridSample& s = grid.at(ix, iy);
        return Eigen::Vector2d(s.stop_u, s.stop_v);
    };
    struct Block {
        int x0, y0, size;
    };
    // A block of `size` cells at (x0, y0), inside the grid, with its nine rays traced.
    // The block's merged quad, when its nine rays are valid, its six lines straight on the sensor
    // and in stop coordinates, and its quad and four half-size quads convex.
    const auto merged = [&](const Block& b) -> std::optional<Quad> {
        const int half = b.size / 2;
        for (int j = 0; j <= 2; ++j)
            for (int i = 0; i <= 2; ++i)
                if (!grid.at(b.x0 + i * half, b.y0 + j * half).valid) return std::nullopt;
        if (!linesStraight(pixel, b.x0, b.y0, b.size, merge.gamma) ||
            !linesStraight(stop, b.x0, b.y0, b.size, merge.gamma))
            return std::nullopt;
        Quad quad = quadFrom(grid, mapping, b.x0, b.y0, b.size);
        if (!quadIsConvex(quad) || !uncut(quad, merge.clear_stop_radius)) return std::nullopt;
        for (int j = 0; j < 2; ++j)
            for (int i = 0; i < 2; ++i)
                if (!quadIsConvex(quadFrom(grid, mapping, b.x0 + i * half, b.y0 + j * half, half)))
                    return std::nullopt;
        return quad;
    };
    // Level by level, so that each level's rays are traced together, in long batches.
    const int top = 1 << steps;
    std::vector<Block> level, next;
    for (int y0 = 0; y0 < cells; y0 += top)
        for (int x0 = 0; x0 < cells; x0 += top) level.push_back({x0, y0, top});
    std::vector<std::pair<int, int>> points;
    while (!level.empty()) {
        points.clear();
        for (const Block& b : level) {
            if (b.x0 + b.size > cells || b.y0 + b.size > cells) continue;  // split untraced
            const int half = std::max(1, b.size / 2);
            for (int j = 0; j <= b.size; j += half)
                for (int i = 0; i <= b.size; i += half) points.emplace_back(b.x0 + i, b.y0 + j);
        }
        filler->trace(points);
        next.clear();
        for (const Block& b : level) {
            const bool inside = b.x0 + b.size <= cells && b.y0 + b.size <= cells;
            if (b.size == 1) {
                if (!cellHasQuad(grid, b.x0, b.y0)) continue;
                out.quads.quads.push_back(quadFrom(grid, mapping, b.x0, b.y0, 1));
                out.quads.cells.push_back(1);
                continue;
            }
            if (auto quad = inside ? merged(b) : std::nullopt) {
                out.quads.quads.push_back(*quad);
                out.quads.cells.push_back(static_cast<uint16_t>(b.size * b.size));
                continue;
            }
            const int half = b.size / 2;
            for (int j = 0; j < 2; ++j)
                for (int i = 0; i < 2; ++i) {
                    const Block c{b.x0 + i * half, b.y0 + j * half, half};
                    if (c.x0 < cells && c.y0 < cells) next.push_back(c);
                }
        }
        level.swap(next);
    }
    out.rays = filler->tracedCount();
    return out;
}

namespace {

// Non-convex quads (folds at caustics, flat corners) are point-sampled this many times per side
// in each pixel: they are rare, and their interpolation (mean value coordinates, triangles) has
// no cheap gradient to place edges with.
constexpr int kNonConvexSamples = 4;
// Convex quads below this area (px^2) are splats even when integrated: their edge functions and
// weights lose their digits, and their light fits in one pixel anyway.
constexpr double kMinIntegratedArea = 1e-9;

}  // namespace

std::optional<Primitive> preparePrimitive(const Quad& quad,
                                          double cell_area_mm2,
                                          int channel,
                                          float irradiance,
                                          int64_t width,
                                          int64_t height,
                                          const RasterOptions& options) {
    FLARELAB_CHECK(channel >= 0 && channel < 3);
    FLARELAB_CHECK(options.supersample >= 0 && options.supersample <= 64);
    if (width < 1 || height < 1 || !(irradiance > 0.0f) || !std::isfinite(irradiance))
        return std::nullopt;
    double lo_x = quad.corners[0].position_px.x(), hi_x = lo_x;
    double lo_y = quad.corners[0].position_px.y(), hi_y = lo_y;
    bool lit = false;
    for (const QuadCorner& c : quad.corners) {
        if (!std::isfinite(c.position_px.x()) || !std::isfinite(c.position_px.y()))
            return std::nullopt;
        lo_x = std::min(lo_x, c.position_px.x());
        hi_x = std::max(hi_x, c.position_px.x());
        lo_y = std::min(lo_y, c.position_px.y());
        hi_y = std::max(hi_y, c.position_px.y());
        lit = lit || c.throughput > 0.0f;
    }
    if (!lit) return std::nullopt;
    Primitive p;
    p.quad = quad;
    p.channel = channel;
    const double area = quadArea(quad);
    const bool convex = quadIsConvex(quad);
    const int samples = options.supersample;
    const double min_area = std::max(options.min_quad_area_px, 1e-12);
    const bool splat = samples > 0 ? area < min_area / (static_cast<double>(samples) * samples)
                                   : (convex ? area < kMinIntegratedArea : area < min_area);
    if (splat) {
        // Too small to sample or integrate: it goes whole to the pixel under its centre, masked
        // there.
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
        // Every pixel the quad's box overlaps, clamped to the image in double before any
        // conversion, so quads far outside cost nothing and cannot overflow an index.
        const double x0 = std::max(0.0, std::floor(lo_x));
        const double x1 = std::min(static_cast<double>(width) - 1.0, std::ceil(hi_x) - 1.0);
        const double y0 = std::max(0.0, std::floor(lo_y));
        const double y1 = std::min(static_cast<double>(height) - 1.0, std::ceil(hi_y) - 1.0);
        if (x0 > x1 || y0 > y1) return std::nullopt;
        p.x0 = static_cast<int64_t>(x0);
        p.x1 = static_cast<int64_t>(x1);
        p.y0 = static_cast<int64_t>(y0);
        p.y1 = static_cast<int64_t>(y1);
        p.scale = irradiance * cell_area_mm2 / area;
        if (convex) {
            setUpConvex(p);
            // What the corners say about the whole quad: its interpolated values are convex
            // mixtures of theirs, and the stop and the clear apertures' limit are convex.
            bool all_clear = true, all_cut = true;
            std::array<Eigen::Vector2d, 4> stop_uv;
            for (int i = 0; i < 4; ++i) {
                const QuadCorner& c = quad.corners[static_cast<size_t>(i)];
                all_clear = all_clear && c.aperture_ratio <= 1.0f;
                all_cut = all_cut && c.aperture_ratio > 1.0f;
                stop_uv[static_cast<size_t>(i)] = {c.stop_u, c.stop_v};
                p.stop_radius = std::max(p.stop_radius, stop_uv[static_cast<size_t>(i)].norm());
            }
            if (all_cut) return std::nullopt;
            p.vignette_clear = all_clear;
            // A hull farther than 1 from the stop's centre misses the circle and every blade
            // polygon inscribed in it.
            if (hullDistanceFromOrigin(stop_uv) > 1.0) return std::nullopt;
        }
        if (samples > 0)
            p.supersample = samples;
        else if (!convex)
            p.supersample = kNonConvexSamples;
    }
    if (!std::isfinite(p.scale)) return std::nullopt;
    return p;
}
namespace {

// A convex polygon in pixel coordinates relative to the pixel's centre: the pixel square cut by
// half-planes, each cut adding at most one corner (4 quad edges, one clear-aperture edge, up to
// 64 blades).
constexpr int kMaxPolygon = 4 + 4 + 1 + 64 + 3;
struct Polygon {
    int n = 0;
    double x[kMaxPolygon];  // left uninitialized: a pixel that needs no cut never touches them
    double y[kMaxPolygon];
};

void setPixelSquare(Polygon& poly) {
    poly.n = 4;
    poly.x[0] = -0.5, poly.y[0] = -0.5;
    poly.x[1] = 0.5, poly.y[1] = -0.5;
    poly.x[2] = 0.5, poly.y[2] = 0.5;
    poly.x[3] = -0.5, poly.y[3] = 0.5;
}

// Writes to `out` the part of `in` where h + gx x + gy y >= 0 (one step of Sutherland-Hodgman).
void clip(const Polygon& in, double h, double gx, double gy, Polygon& out) {
    out.n = 0;
    for (int i = 0; i < in.n; ++i) {
        const int j = i + 1 < in.n ? i + 1 : 0;
        const double hi = h + gx * in.x[i] + gy * in.y[i];
        const double hj = h + gx * in.x[j] + gy * in.y[j];
        if (hi >= 0.0 && out.n < kMaxPolygon) {
            out.x[out.n] = in.x[i];
            out.y[out.n++] = in.y[i];
        }
        if ((hi >= 0.0) != (hj >= 0.0) && out.n < kMaxPolygon) {
            const double t = hi / (hi - hj);
            out.x[out.n] = in.x[i] + t * (in.x[j] - in.x[i]);
            out.y[out.n++] = in.y[i] + t * (in.y[j] - in.y[i]);
        }
    }
}

// The pixel square and the cuts made to it so far, in two buffers used in turn.
class PixelPart {
public:
    PixelPart() { setPixelSquare(buffer_[0]); }
    void cut(double h, double gx, double gy) {
        clip(buffer_[current_], h, gx, gy, buffer_[1 - current_]);
        current_ = 1 - current_;
    }
    const Polygon& polygon() const { return buffer_[current_]; }

private:
    Polygon buffer_[2];
    int current_ = 0;
};

struct AreaCentroid {
    double area = 0.0;
    double x = 0.0, y = 0.0;
};
AreaCentroid measure(const Polygon& poly) {
    double twice = 0.0, cx = 0.0, cy = 0.0;
    for (int i = 0; i < poly.n; ++i) {
        const int j = i + 1 < poly.n ? i + 1 : 0;
        const double xi = poly.x[i], yi = poly.y[i];
        const double xj = poly.x[j], yj = poly.y[j];
        const double cross = xi * yj - xj * yi;
        twice += cross;
        cx += (xi + xj) * cross;
        cy += (yi + yj) * cross;
    }
    if (!(std::abs(twice) > 0.0)) return {};
    return {0.5 * std::abs(twice), cx / (3.0 * twice), cy / (3.0 * twice)};
}

// The corner attributes of a convex primitive (throughput, stop u and v, aperture ratio) mixed
// with Wachspress weights at (px, py), and, when asked, their gradients in pixels: the weights
// are w_i = C_i A_{i+1} A_{i+2} with linear A, so dw_i = C_i (A_{i+2} dA_{i+1} + A_{i+1} dA_{i+2})
// and d(sum w f / sum w) = (sum dw f - f sum dw) / sum w. false where the weights vanish.
// Without the gradient only the throughput (value[0]) is set.
struct Attributes {
    std::array<double, 4> value{}, dx{}, dy{};
};
bool interpolateConvex(const Primitive& p, double px, double py, bool gradient, Attributes& out) {
    double a[4];
    for (int i = 0; i < 4; ++i)
        a[i] = std::max(0.0, p.edge[static_cast<size_t>(i)].at(px, py));  // inside up to rounding
    const auto& c = p.quad.corners;
    const auto& area = p.corner_area;
    const double w[4] = {area[0] * a[1] * a[2], area[1] * a[2] * a[3], area[2] * a[3] * a[0],
                         area[3] * a[0] * a[1]};
    const double total = w[0] + w[1] + w[2] + w[3];
    if (!(total > 0.0)) return false;
    const auto mix = [&](const double* weights, std::array<double, 4>& sums) {
        sums = {0.0, 0.0, 0.0, 0.0};
        for (int i = 0; i < 4; ++i) {
            sums[0] += weights[i] * c[static_cast<size_t>(i)].throughput;
            sums[1] += weights[i] * c[static_cast<size_t>(i)].stop_u;
            sums[2] += weights[i] * c[static_cast<size_t>(i)].stop_v;
            sums[3] += weights[i] * c[static_cast<size_t>(i)].aperture_ratio;
        }
    };
    if (!gradient) {  // only the throughput is asked for (an unmasked primitive)
        double t = 0.0;
        for (int i = 0; i < 4; ++i) t += w[i] * c[static_cast<size_t>(i)].throughput;
        out.value[0] = t / total;
        return true;
    }
    mix(w, out.value);
    for (double& v : out.value) v /= total;
    double wx[4], wy[4];
    double total_x = 0.0, total_y = 0.0;
    for (int i = 0; i < 4; ++i) {
        const int j = (i + 1) % 4, k = (i + 2) % 4;
        const EdgeFunction& ej = p.edge[static_cast<size_t>(j)];
        const EdgeFunction& ek = p.edge[static_cast<size_t>(k)];
        wx[i] = area[static_cast<size_t>(i)] * (a[k] * ej.gradX() + a[j] * ek.gradX());
        wy[i] = area[static_cast<size_t>(i)] * (a[k] * ej.gradY() + a[j] * ek.gradY());
        total_x += wx[i];
        total_y += wy[i];
    }
    std::array<double, 4> sum_x, sum_y;
    mix(wx, sum_x);
    mix(wy, sum_y);
    for (size_t f = 0; f < 4; ++f) {
        out.dx[f] = (sum_x[f] - out.value[f] * total_x) / total;
        out.dy[f] = (sum_y[f] - out.value[f] * total_y) / total;
    }
    return true;
}

// std::max(0.0, x) as a value: 0 for NaN.
[[gnu::always_inline]] inline double positive(double x) { return x > 0.0 ? x : 0.0; }
constexpr double kLargestValue = std::numeric_limits<double>::max();

// An unmasked convex primitive along pixel row y: the Wachspress sums as quadratics in
// u = x - p.x0 (Primitive::inside_total and inside_sum at v = y - p.y0).
struct RowQuadratics {
    double d0 = 0.0, d1 = 0.0, d2 = 0.0;
    double n0 = 0.0, n1 = 0.0, n2 = 0.0;
};
[[gnu::always_inline]] inline RowQuadratics rowQuadratics(const Primitive& p, int64_t y) {
    const double v = static_cast<double>(y - p.y0);
    const auto& d = p.inside_total;
    const auto& n = p.inside_sum;
    return RowQuadratics{d[0] + v * (d[1] + v * d[2]), d[3] + v * d[4], d[5],
                         n[0] + v * (n[1] + v * n[2]), n[3] + v * n[4], n[5]};
}

// The light of pixel x of the row, wholly inside the unmasked convex primitive: its throughput at
// the centre, kept within the corners' range (it is a convex mixture of them; rounding of the
// expanded quadratics near a corner must not carry it outside).
double insideValue(const Primitive& p, const RowQuadratics& q, int64_t x) {
    const double u = static_cast<double>(x - p.x0);
    const double total = q.d0 + u * (q.d1 + u * q.d2);
    const double sum = q.n0 + u * (q.n1 + u * q.n2);
    double t = sum / total;
    t = t < p.throughput_low ? p.throughput_low : t;
    t = t > p.throughput_high ? p.throughput_high : t;
    const double v = p.scale * positive(t);
    return total > 0.0 && std::abs(v) <= kLargestValue ? v : 0.0;
}

// A pixel wholly inside a masked convex primitive's quad, from the primitive's centre
// polynomials (centrePolynomials with the stop and the ratio): its light when neither the stop's
// outline nor a clear aperture's limit comes within the pixel, 0 when one of them leaves the
// whole pixel outside, as convexAreaValue's linearized cuts decide from the values and gradients
// at the centre; nullopt when one of them cuts it (convexAreaValue's whole path then decides).
std::optional<double> maskedInsideValue(const Primitive& p,
                                        const CentrePolynomials& s,
                                        int64_t x,
                                        int64_t y,
                                        const StopMask& stop) {
    const double u = static_cast<double>(x - p.x0), v = static_cast<double>(y - p.y0);
    const auto at = [&](const Polynomial& c) {
        return (c[0] + v * (c[1] + v * c[2])) + u * ((c[3] + v * c[4]) + u * c[5]);
    };
    const auto dx = [&](const Polynomial& c) { return (c[3] + v * c[4]) + 2.0 * u * c[5]; };
    const auto dy = [&](const Polynomial& c) { return (c[1] + 2.0 * v * c[2]) + u * c[4]; };
    const double total = at(s.total);
    if (!(total > 0.0)) return std::nullopt;
    const double total_x = dx(s.total), total_y = dy(s.total);
    struct Mixed {
        double f, fx, fy;
    };
    // f = sum / total and its gradient (d sum - f d total) / total.
    const auto mix = [&](const Polynomial& c) {
        const double f = at(c) / total;
        return Mixed{f, (dx(c) - f * total_x) / total, (dy(c) - f * total_y) / total};
    };
    // For h linear with this value and gradient at the centre: h >= 0 over the whole pixel
    // (Clear), h <= 0 over all of it (Outside: no light, as convexAreaValue finds), or a cut.
    enum class Side { Clear, Outside, Cut };
    const auto side = [](double h, double gx, double gy) {
        const double reach = 0.5 * (std::abs(gx) + std::abs(gy));
        if (h >= reach) return Side::Clear;
        if (!(h > -reach)) return Side::Outside;
        return Side::Cut;
    };
    bool cut = false;
    const auto keep = [&](double h, double gx, double gy) {
        const Side where = side(h, gx, gy);
        cut = cut || where == Side::Cut;
        return where != Side::Outside;
    };
    if (!p.vignette_clear) {
        const Mixed r = mix(s.ratio);
        if (!keep(1.0 - r.f, -r.fx, -r.fy)) return 0.0;
    }
    if (!(p.stop_radius <= stop.inscribedRadius())) {
        const Mixed su = mix(s.stop_u), sv = mix(s.stop_v);
        if (stop.blades() == 0) {
            const double r = std::sqrt(su.f * su.f + sv.f * sv.f);
            if (r > 1e-9 && !keep(1.0 - r, -(su.f * su.fx + sv.f * sv.fx) / r,
                                  -(su.f * su.fy + sv.f * sv.fy) / r))
                return 0.0;
        } else {
            for (int k = 0; k < stop.blades(); ++k) {
                const double nu = stop.normalU(k), nv = stop.normalV(k);
                if (!keep(1.0 - (nu * su.f + nv * sv.f), -(nu * su.fx + nv * sv.fx),
                          -(nu * su.fy + nv * sv.fy)))
                    return 0.0;
            }
        }
    }
    if (cut) return std::nullopt;
    double t = at(s.throughput) / total;
    t = t < p.throughput_low ? p.throughput_low : t;
    t = t > p.throughput_high ? p.throughput_high : t;
    const double value = p.scale * positive(t);
    return std::abs(value) <= kLargestValue ? value : 0.0;
}

// The light of a convex primitive integrated over pixel (x, y): the pixel square cut by the
// quad's edges exactly, then by the stop's outline and the clear-aperture limit linearized about
// the centroid of what is left; the throughput taken at the centroid of the final part.
// masked_sums: centrePolynomials(p, true) where the caller has them (they are made here
// otherwise), for a masked primitive.
double convexAreaValue(const Primitive& p,
                       int64_t x,
                       int64_t y,
                       const StopMask& stop,
                       const CentrePolynomials* masked_sums = nullptr) {
    const double cx = static_cast<double>(x) + 0.5, cy = static_cast<double>(y) + 0.5;
    PixelPart poly;
    bool clipped = false;
    for (const EdgeFunction& e : p.edge) {
        // The edge function is linear: over the pixel it stays within `reach` of its centre value.
        const double a = e.at(cx, cy);
        if (e.by_centre) {  // an interior edge: the pixel is wholly on its centre's side
            if (!(a > 0.0 || (a == 0.0 && e.closed))) return 0.0;
            continue;
        }
        if (!(a > -e.reach)) return 0.0;
        if (a < e.reach) {
            poly.cut(a, e.gradX(), e.gradY());
            clipped = true;
        }
    }
    const bool stop_clear = p.stop_radius <= stop.inscribedRadius();
    const bool masked = !stop_clear || !p.vignette_clear;
    if (!clipped && !masked) return insideValue(p, rowQuadratics(p, y), x);
    if (!clipped) {
        CentrePolynomials own;
        if (masked_sums == nullptr) {
            own = centrePolynomials(p, /*stop_and_ratio=*/true);
            masked_sums = &own;
        }
        if (const auto value = maskedInsideValue(p, *masked_sums, x, y, stop)) return *value;
    }
    AreaCentroid part{1.0, 0.0, 0.0};
    if (clipped) part = measure(poly.polygon());
    if (!(part.area > 0.0)) return 0.0;
    Attributes at;
    if (!interpolateConvex(p, cx + part.x, cy + part.y, masked, at)) return 0.0;
    double throughput = at.value[0];
    if (masked) {
        bool cut = false;
        // Keeps h(q) = h0 + g . (q - centroid) >= 0 over the polygon; false when nothing is left.
        const auto keep = [&](double h0, double gx, double gy) {
            const double h = h0 - gx * part.x - gy * part.y;  // at the pixel's centre
            const double reach = 0.5 * (std::abs(gx) + std::abs(gy));
            if (h >= reach) return true;
            if (!(h > -reach)) return false;
            poly.cut(h, gx, gy);
            cut = true;
            return true;
        };
        if (!p.vignette_clear && !keep(1.0 - at.value[3], -at.dx[3], -at.dy[3])) return 0.0;
        if (!stop_clear) {
            const double u = at.value[1], v = at.value[2];
            if (stop.blades() == 0) {
                const double r = std::sqrt(u * u + v * v);  // stop coordinates: near 1, no overflow
                // Near the stop's centre the radius has no gradient, and no edge is near.
                if (r > 1e-9 && !keep(1.0 - r, -(u * at.dx[1] + v * at.dx[2]) / r,
                                      -(u * at.dy[1] + v * at.dy[2]) / r))
                    return 0.0;
            } else {
                for (int k = 0; k < stop.blades(); ++k) {
                    const double nu = stop.normalU(k), nv = stop.normalV(k);
                    if (!keep(1.0 - (nu * u + nv * v), -(nu * at.dx[1] + nv * at.dx[2]),
                              -(nu * at.dy[1] + nv * at.dy[2])))
                        return 0.0;
                }
            }
        }
        if (cut) {
            const AreaCentroid rest = measure(poly.polygon());
            if (!(rest.area > 0.0)) return 0.0;
            throughput += at.dx[0] * (rest.x - part.x) + at.dy[0] * (rest.y - part.y);
            part = rest;
        }
    }
    const double value = p.scale * std::max(0.0, throughput) * part.area;
    return std::isfinite(value) ? value : 0.0;
}

// The light of a primitive that is not convex at a point, per pixel area.
double pointValueAt(const Primitive& p, double px, double py, const StopMask& stop) {
    if (p.convex) return convexValueAt(p, px, py, stop);
    const auto weights = quadBarycentrics(p.quad, Eigen::Vector2d(px, py));
    if (!weights) return 0.0;
    const QuadSample sample = interpolateQuad(p.quad, *weights);
    if (!(sample.throughput > 0.0f) || !(sample.aperture_ratio <= 1.0f) ||
        !stop.contains(sample.stop_u, sample.stop_v))
        return 0.0;
    const double value = p.scale * sample.throughput;
    return std::isfinite(value) ? value : 0.0;
}

}  // namespace

double primitiveValueAt(const Primitive& primitive, int64_t x, int64_t y, const StopMask& stop) {
    if (primitive.splat) {
        const QuadSample sample = interpolateQuad(primitive.quad, {0.25, 0.25, 0.25, 0.25});
        if (!(sample.throughput > 0.0f) || !(sample.aperture_ratio <= 1.0f) ||
            !stop.contains(sample.stop_u, sample.stop_v))
            return 0.0;
        const double value = primitive.scale * sample.throughput;
        return std::isfinite(value) ? value : 0.0;
    }
    if (primitive.supersample > 0) {
        const int n = primitive.supersample;
        const double step = 1.0 / n;
        double sum = 0.0;
        for (int j = 0; j < n; ++j) {
            const double py = static_cast<double>(y) + (j + 0.5) * step;
            for (int i = 0; i < n; ++i)
                sum += pointValueAt(primitive, static_cast<double>(x) + (i + 0.5) * step, py, stop);
        }
        return sum / (static_cast<double>(n) * n);
    }
    return convexAreaValue(primitive, x, y, stop);
}

namespace {

// Four doubles and four floats in GCC's and Clang's vector extension: the explicit lanes keep
// the arithmetic (and so the bits) of the scalar code while the compiler does not have to prove
// that if-converting the tests is safe, which it will not do under -ftrapping-math.
using Double4 = double __attribute__((vector_size(32)));
using Float4 = float __attribute__((vector_size(16)));

// The pixels x0..x1 of the rows y0..y1 wholly inside an unmasked convex primitive, each the
// Wachspress-interpolated throughput at its centre (insideValue, bit for bit), four at a time.
template <int64_t Step>
[[gnu::always_inline]] inline void insideRowsBody(const Primitive& p,
                                                  int64_t x0,
                                                  int64_t y0,
                                                  int64_t x1,
                                                  int64_t y1,
                                                  float* out,
                                                  int64_t stride) {
    const Double4 zero = {}, lane = {0.0, 1.0, 2.0, 3.0};
    const double lowest = p.throughput_low, highest = p.throughput_high;
    for (int64_t y = y0; y <= y1; ++y) {
        const RowQuadratics q = rowQuadratics(p, y);
        float* row = out + (y - y0) * stride;
        // Four pixels at a time; the last group's lanes past x1 are computed and not added.
        for (int64_t x = x0; x <= x1; x += 4) {
            // Whole numbers: exact, as in insideValue.
            const Double4 u = static_cast<double>(x - p.x0) + lane;
            const Double4 total = q.d0 + u * (q.d1 + u * q.d2);
            const Double4 sum = q.n0 + u * (q.n1 + u * q.n2);
            Double4 t = sum / total;
            t = t < lowest ? lowest : t;
            t = t > highest ? highest : t;
            const Double4 v = p.scale * (t > zero ? t : zero);
            const Double4 magnitude = v < zero ? -v : v;
            const Double4 kept = (total > zero) & (magnitude <= kLargestValue) ? v : zero;
            const Float4 value = __builtin_convertvector(kept, Float4);
            float* dst = row + (x - x0) * Step;
            const int64_t lanes = std::min<int64_t>(4, x1 - x + 1);
            if (Step == 1 && lanes == 4) {  // one channel's plane: four neighbours at once
                Float4 sum;
                __builtin_memcpy(&sum, dst, sizeof sum);
                sum += value;
                __builtin_memcpy(dst, &sum, sizeof sum);
                continue;
            }
            for (int64_t j = 0; j < lanes; ++j) dst[j * Step] += value[j];
        }
    }
}

template <int64_t Step>
void insideRowsBase(const Primitive& p,
                    int64_t x0,
                    int64_t y0,
                    int64_t x1,
                    int64_t y1,
                    float* out,
                    int64_t stride) {
    insideRowsBody<Step>(p, x0, y0, x1, y1, out, stride);
}
template <int64_t Step>
[[gnu::target("avx2")]] void insideRowsAvx2(const Primitive& p,
                                            int64_t x0,
                                            int64_t y0,
                                            int64_t x1,
                                            int64_t y1,
                                            float* out,
                                            int64_t stride) {
    insideRowsBody<Step>(p, x0, y0, x1, y1, out, stride);
}
using InsideRowsFn =
    void (*)(const Primitive&, int64_t, int64_t, int64_t, int64_t, float*, int64_t);
// The AVX2 builds of the row loops where the processor has it; both builds give the same bits
// (no contraction into fused multiply-adds). `step`: floats from one pixel to the next, 3 in an
// interleaved RGB row, 1 in one channel's plane.
InsideRowsFn insideRows(int64_t step) {
    const bool avx2 = processorHasAvx2();
    if (step == 1) return avx2 ? &insideRowsAvx2<1> : &insideRowsBase<1>;
    return avx2 ? &insideRowsAvx2<3> : &insideRowsBase<3>;
}

// convexAreaValue for the pixels x0..x1 of row y, each wholly inside a masked convex primitive
// (`sums` from centrePolynomials with the stop and the ratio; a round stop): maskedInsideValue
// four pixels at a time, with its arithmetic lane for lane, and convexAreaValue for a pixel an
// edge of the stop or a clear aperture cuts. The same values, bit for bit.
using Long4 = long long __attribute__((vector_size(32)));
template <int64_t Step>
[[gnu::always_inline]] inline void maskedInsideRowBody(const Primitive& p,
                                                       const CentrePolynomials& s,
                                                       int64_t x0,
                                                       int64_t x1,
                                                       int64_t y,
                                                       const StopMask& stop,
                                                       float* out) {
    const double v = static_cast<double>(y - p.y0);
    // A polynomial along the row: value a0 + u (a1 + u a2), d/dx a1 + 2 u a2, d/dy b0 + u b1.
    struct Row {
        double a0, a1, a2, b0, b1;
    };
    const auto along = [&](const Polynomial& c) {
        return Row{c[0] + v * (c[1] + v * c[2]), c[3] + v * c[4], c[5], c[1] + 2.0 * v * c[2],
                   c[4]};
    };
    const Row total_row = along(s.total), ratio_row = along(s.ratio), u_row = along(s.stop_u),
              v_row = along(s.stop_v), t_row = along(s.throughput);
    const bool vignetted = !p.vignette_clear;
    const bool stop_edge = !(p.stop_radius <= stop.inscribedRadius());
    const Double4 zero = {}, lane = {0.0, 1.0, 2.0, 3.0};
    const auto abs4 = [&](Double4 a) { return a < zero ? -a : a; };
    for (int64_t x = x0; x <= x1; x += 4) {
        const Double4 u = static_cast<double>(x - p.x0) + lane;
        const auto at = [&](const Row& r) { return r.a0 + u * (r.a1 + u * r.a2); };
        const Double4 total = at(total_row);
        const Double4 total_x = total_row.a1 + 2.0 * u * total_row.a2;
        const Double4 total_y = total_row.b0 + u * total_row.b1;
        // Weights that vanish send the pixel to convexAreaValue before any test (as the scalar
        // code returns nullopt first).
        const Long4 vanish = ~(total > zero);
        Long4 outside = {}, cut = {};
        // maskedInsideValue's side(): h >= reach clear, !(h > -reach) outside, else cut.
        const auto test = [&](Double4 h, Double4 gx, Double4 gy, Long4 applies) {
            const Double4 reach = 0.5 * (abs4(gx) + abs4(gy));
            const Long4 clear = h >= reach;
            const Long4 out_side = ~(h > -reach);
            outside |= applies & out_side;
            cut |= applies & ~clear & ~out_side;
        };
        struct Mixed {
            Double4 f, fx, fy;
        };
        const auto mix = [&](const Row& r) {
            const Double4 f = at(r) / total;
            return Mixed{f, ((r.a1 + 2.0 * u * r.a2) - f * total_x) / total,
                         ((r.b0 + u * r.b1) - f * total_y) / total};
        };
        if (vignetted) {
            const Mixed r = mix(ratio_row);
            test(1.0 - r.f, -r.fx, -r.fy, ~Long4{});
        }
        if (stop_edge) {
            const Mixed su = mix(u_row), sv = mix(v_row);
            const Double4 squared = su.f * su.f + sv.f * sv.f;
            Double4 r = {};
            for (int j = 0; j < 4; ++j) r[j] = std::sqrt(squared[j]);
            test(1.0 - r, -(su.f * su.fx + sv.f * sv.fx) / r, -(su.f * su.fy + sv.f * sv.fy) / r,
                 r > 1e-9);
        }
        Double4 t = at(t_row) / total;
        t = t < p.throughput_low ? p.throughput_low : t;
        t = t > p.throughput_high ? p.throughput_high : t;
        const Double4 value = p.scale * (t > zero ? t : zero);
        const Double4 kept = abs4(value) <= kLargestValue ? value : zero;
        const int64_t lanes = std::min<int64_t>(4, x1 - x + 1);
        for (int64_t j = 0; j < lanes; ++j) {
            float* dst = out + (x + j - x0) * Step;
            if (!vanish[j] && outside[j]) continue;  // += 0
            if (vanish[j] || cut[j])
                *dst += static_cast<float>(convexAreaValue(p, x + j, y, stop, &s));
            else
                *dst += static_cast<float>(kept[j]);
        }
    }
}
template <int64_t Step>
void maskedInsideRowBase(const Primitive& p,
                         const CentrePolynomials& s,
                         int64_t x0,
                         int64_t x1,
                         int64_t y,
                         const StopMask& stop,
                         float* out) {
    maskedInsideRowBody<Step>(p, s, x0, x1, y, stop, out);
}
template <int64_t Step>
[[gnu::target("avx2")]] void maskedInsideRowAvx2(const Primitive& p,
                                                 const CentrePolynomials& s,
                                                 int64_t x0,
                                                 int64_t x1,
                                                 int64_t y,
                                                 const StopMask& stop,
                                                 float* out) {
    maskedInsideRowBody<Step>(p, s, x0, x1, y, stop, out);
}
using MaskedInsideRowFn = void (*)(const Primitive&,
                                   const CentrePolynomials&,
                                   int64_t,
                                   int64_t,
                                   int64_t,
                                   const StopMask&,
                                   float*);
MaskedInsideRowFn maskedInsideRow(int64_t step) {
    const bool avx2 = processorHasAvx2();
    if (step == 1) return avx2 ? &maskedInsideRowAvx2<1> : &maskedInsideRowBase<1>;
    return avx2 ? &maskedInsideRowAvx2<3> : &maskedInsideRowBase<3>;
}

// Narrows [lo, hi] to the pixels x of a row where `holds(x)` is true, for a predicate on
// r + g (x + 0.5) that is monotone along the row (rounding is monotone, so the computed edge
// function is too): the analytic crossing first, then the exact test on its neighbours.
template <class Holds>
void narrowSpan(int64_t& lo, int64_t& hi, double r, double g, double threshold, Holds holds) {
    if (lo > hi) return;
    if (g == 0.0) {
        if (!holds(lo)) hi = lo - 1;
        return;
    }
    const double crossing = (threshold - r) / g - 0.5;
    const double clamped = std::clamp(std::isfinite(crossing) ? crossing : 0.0,
                                      static_cast<double>(lo) - 1.0, static_cast<double>(hi) + 1.0);
    int64_t k = static_cast<int64_t>(std::floor(clamped));
    if (g > 0.0) {  // false, then true: the first x that holds
        k = std::clamp(k, lo, hi + 1);
        while (k > lo && holds(k - 1)) --k;
        while (k <= hi && !holds(k)) ++k;
        lo = k;
    } else {  // true, then false: the last x that holds
        k = std::clamp(k, lo - 1, hi);
        while (k < hi && holds(k + 1)) ++k;
        while (k >= lo && !holds(k)) --k;
        hi = k;
    }
}

// A convex primitive's row, for the edges whose bit in `check` is set (the others are known to
// be at least their reach over the row): as convexAreaValue decides, a pixel is outside when an
// edge function at its centre is at or below -reach, wholly inside when every one is at least
// its reach (then the pixel's part is the whole square, its centroid the centre, and unmasked
// primitives need no more than the throughput there); an interior edge (EdgeFunction::by_centre)
// only decides by the centre's side. Along the row each edge function is monotone, so both sets
// are spans: [lo, hi] not outside, [in_lo, in_hi] wholly inside.
void addConvexRow(const Primitive& p,
                  int64_t x0,
                  int64_t x1,
                  int64_t y,
                  const StopMask& stop,
                  bool masked,
                  unsigned check,
                  const CentrePolynomials* masked_sums,
                  float* out,
                  int64_t step) {
    const double cy = static_cast<double>(y) + 0.5;
    int64_t lo = x0, hi = x1, in_lo = x0, in_hi = x1;
    for (size_t i = 0; i < 4; ++i) {
        if (!(check & (1u << i))) continue;
        const EdgeFunction& e = p.edge[i];
        const double r = e.c + e.gy * cy, g = e.gx, reach = e.reach;
        const auto at = [&](int64_t x) { return r + g * (static_cast<double>(x) + 0.5); };
        if (e.by_centre) {  // the pixels whose centre is on the inside are wholly in
            const bool closed = e.closed;
            const auto owns = [&](int64_t x) {
                const double a = at(x);
                return a > 0.0 || (a == 0.0 && closed);
            };
            narrowSpan(lo, hi, r, g, 0.0, owns);
            narrowSpan(in_lo, in_hi, r, g, 0.0, owns);
            continue;
        }
        narrowSpan(lo, hi, r, g, -reach, [&](int64_t x) { return at(x) > -reach; });
        narrowSpan(in_lo, in_hi, r, g, reach, [&](int64_t x) { return at(x) >= reach; });
    }
    if (lo > hi) return;
    in_lo = std::max(in_lo, lo);
    in_hi = std::min(in_hi, hi);
    if (in_lo > in_hi) in_lo = hi + 1, in_hi = hi;  // no inside pixel: all are cut
    for (int64_t x = lo; x < in_lo; ++x)
        out[(x - x0) * step] += static_cast<float>(convexAreaValue(p, x, y, stop, masked_sums));
    if (in_lo <= in_hi) {
        float* in = out + (in_lo - x0) * step;
        if (!masked)
            insideRows(step)(p, in_lo, y, in_hi, y, in, 0);
        else if (stop.blades() == 0)
            maskedInsideRow(step)(p, *masked_sums, in_lo, in_hi, y, stop, in);
        else
            for (int64_t x = in_lo; x <= in_hi; ++x)
                out[(x - x0) * step] +=
                    static_cast<float>(convexAreaValue(p, x, y, stop, masked_sums));
    }
    for (int64_t x = in_hi + 1; x <= hi; ++x)
        out[(x - x0) * step] += static_cast<float>(convexAreaValue(p, x, y, stop, masked_sums));
}

bool drawnConvex(const Primitive& p) { return p.convex && !p.splat && p.supersample == 0; }
bool isMasked(const Primitive& p, const StopMask& stop) {
    return !(p.stop_radius <= stop.inscribedRadius()) || !p.vignette_clear;
}

}  // namespace

void addPrimitiveRow(const Primitive& p,
                     int64_t x0,
                     int64_t x1,
                     int64_t y,
                     const StopMask& stop,
                     float* out,
                     int64_t pixel_step) {
    FLARELAB_CHECK(pixel_step == 1 || pixel_step == 3);
    if (!drawnConvex(p)) {
        for (int64_t x = x0; x <= x1; ++x)
            out[(x - x0) * pixel_step] += static_cast<float>(primitiveValueAt(p, x, y, stop));
        return;
    }
    const bool masked = isMasked(p, stop);
    CentrePolynomials sums;
    if (masked) sums = centrePolynomials(p, /*stop_and_ratio=*/true);
    addConvexRow(p, x0, x1, y, stop, masked, 0xfu, masked ? &sums : nullptr, out, pixel_step);
}

void addPrimitiveBlock(const Primitive& p,
                       int64_t x0,
                       int64_t y0,
                       int64_t x1,
                       int64_t y1,
                       const StopMask& stop,
                       float* out,
                       int64_t stride,
                       int64_t pixel_step) {
    FLARELAB_CHECK(pixel_step == 1 || pixel_step == 3);
    if (!drawnConvex(p)) {
        for (int64_t y = y0; y <= y1; ++y)
            addPrimitiveRow(p, x0, x1, y, stop, out + (y - y0) * stride, pixel_step);
        return;
    }
    // The edge functions are linear, so over the block's pixel centres each is least at one of
    // the four corner centres; with a margin for rounding (far above the few ulps of the
    // products), an edge at least its reach there is at least its reach at every pixel, as
    // addPrimitiveRow would find it, and its tests can be left out. With no edge left, and no
    // stop edge or clear aperture to cut, every pixel is wholly inside.
    const double xs[2] = {static_cast<double>(x0) + 0.5, static_cast<double>(x1) + 0.5};
    const double ys[2] = {static_cast<double>(y0) + 0.5, static_cast<double>(y1) + 0.5};
    unsigned check = 0;
    for (size_t i = 0; i < 4; ++i) {
        const EdgeFunction& e = p.edge[i];
        bool clear = true;
        for (const double cy : ys)
            for (const double cx : xs) {
                const double size = std::abs(e.c) + std::abs(e.gy * cy) + std::abs(e.gx * cx);
                // An interior edge needs only the centres strictly inside.
                const double a = e.at(cx, cy), margin = 1e-12 * size;
                clear = clear && (e.by_centre ? a > margin : a >= e.reach + margin);
            }
        if (!clear) check |= 1u << i;
    }
    const bool masked = isMasked(p, stop);
    if (check == 0 && !masked) {
        insideRows(pixel_step)(p, x0, y0, x1, y1, out, stride);
        return;
    }
    CentrePolynomials sums;
    if (masked) sums = centrePolynomials(p, /*stop_and_ratio=*/true);
    for (int64_t y = y0; y <= y1; ++y)
        addConvexRow(p, x0, x1, y, stop, masked, check, masked ? &sums : nullptr,
                     out + (y - y0) * stride, pixel_step);
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

double imagingPower(const optics::RayGrid& grid, const optics::ApertureShape& aperture) {
    if (grid.n < 2) return 0.0;
    const StopMask stop(aperture);
    constexpr int kSamples = 16;
    const auto light = [](const optics::GridSample& s) {
        return static_cast<double>(s.valid ? s.throughput : s.open_throughput);
    };
    double cells = 0.0;  // the sum, in cells
    for (int iy = 0; iy + 1 < grid.n; ++iy) {
        for (int ix = 0; ix + 1 < grid.n; ++ix) {
            // Bilinear order: (0, 0), (1, 0), (0, 1), (1, 1).
            const optics::GridSample* s[4] = {&grid.at(ix, iy), &grid.at(ix + 1, iy),
                                              &grid.at(ix, iy + 1), &grid.at(ix + 1, iy + 1)};
            bool placed = true;
            int inside = 0, clear = 0;
            std::array<Eigen::Vector2d, 4> uv;
            for (int k = 0; k < 4; ++k) {
                placed = placed && s[k]->has_position;
                inside += stop.contains(s[k]->stop_u, s[k]->stop_v);
                clear += s[k]->aperture_ratio <= 1.0f;
                uv[static_cast<size_t>(k)] = {s[k]->stop_u, s[k]->stop_v};
            }
            if (!placed) {
                for (const optics::GridSample* c : s)
                    if (c->valid && stop.contains(c->stop_u, c->stop_v)) cells += 0.25 * light(*c);
                continue;
            }
            if (inside == 4 && clear == 4) {
                cells += 0.25 * (light(*s[0]) + light(*s[1]) + light(*s[2]) + light(*s[3]));
                continue;
            }
            if (clear == 0 || (inside == 0 && hullDistanceFromOrigin(uv) > 1.0)) continue;
            double sum = 0.0;
            for (int j = 0; j < kSamples; ++j) {
                const double b = (j + 0.5) / kSamples;
                for (int i = 0; i < kSamples; ++i) {
                    const double a = (i + 0.5) / kSamples;
                    const double w[4] = {(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b};
                    double t = 0.0, u = 0.0, v = 0.0, ratio = 0.0;
                    for (int k = 0; k < 4; ++k) {
                        t += w[k] * light(*s[k]);
                        u += w[k] * s[k]->stop_u;
                        v += w[k] * s[k]->stop_v;
                        ratio += w[k] * s[k]->aperture_ratio;
                    }
                    if (ratio <= 1.0 && stop.contains(u, v)) sum += t;
                }
            }
            cells += sum / (kSamples * kSamples);
        }
    }
    const double cell = 2.0 * grid.entry_half_width_mm / (grid.n - 1);
    return cells * cell * cell;
}

}  // namespace flarelab::render
