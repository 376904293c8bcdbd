#include "render/tiles.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <vector>

namespace flarelab::render {
namespace {

using Clock = std::chrono::steady_clock;

double millisecondsSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

int64_t ceilDiv(int64_t a, int64_t b) { return (a + b - 1) / b; }

}  // namespace

Status renderTiled(ImageRGB& image,
                   std::span<const Primitive> primitives,
                   const optics::ApertureShape& aperture,
                   const TileOptions& options,
                   TileStats* stats) {
    return renderTiled(image, primitives, {}, aperture, options, stats);
}

Status renderTiled(ImageRGB& image,
                   std::span<const Primitive> primitives,
                   std::span<const GhostPrimitive> ghosts,
                   const optics::ApertureShape& aperture,
                   const TileOptions& options,
                   TileStats* stats) {
    const int dense = options.dense_tile_px, coarse = options.coarse_tile_px;
    if (dense < 1 || dense > 256)
        return makeError(ErrorCode::InvalidArgument, "tiles: dense_tile_px must lie in 1..256");
    if (coarse < dense || coarse > 4096 || coarse % dense != 0)
        return makeError(ErrorCode::InvalidArgument,
                         "tiles: coarse_tile_px must be a multiple of dense_tile_px, at most 4096");
    for (size_t i = 0; i < primitives.size(); ++i) {
        const Primitive& p = primitives[i];
        if (p.x0 < 0 || p.y0 < 0 || p.x1 >= image.width || p.y1 >= image.height || p.x0 > p.x1 ||
            p.y0 > p.y1 || p.channel < 0 || p.channel > 2)
            return makeError(ErrorCode::InvalidArgument,
                             "tiles: primitive " + std::to_string(i) +
                                 " has a pixel range or channel outside the image");
    }
    for (size_t i = 0; i < ghosts.size(); ++i) {
        const GhostPrimitive& g = ghosts[i];
        if (g.x0 < 0 || g.y0 < 0 || g.x1 >= image.width || g.y1 >= image.height || g.x0 > g.x1 ||
            g.y0 > g.y1)
            return makeError(
                ErrorCode::InvalidArgument,
                "tiles: model ghost " + std::to_string(i) + " has a pixel range outside the image");
    }
    // One index space: 0..n-1 are the quads, n.. the model ghosts.
    const size_t quad_count = primitives.size();
    const size_t total = quad_count + ghosts.size();
    if (total > UINT32_MAX)
        return makeError(ErrorCode::InvalidArgument, "tiles: more than 2^32 - 1 primitives");
    struct Range {
        int64_t x0, y0, x1, y1;
    };
    const auto range = [&](uint32_t index) {
        if (index < quad_count) {
            const Primitive& p = primitives[index];
            return Range{p.x0, p.y0, p.x1, p.y1};
        }
        const GhostPrimitive& g = ghosts[index - quad_count];
        return Range{g.x0, g.y0, g.x1, g.y1};
    };
    TileStats local;
    TileStats& st = stats ? *stats : local;
    st = TileStats{};
    st.primitives = static_cast<int64_t>(total);
    if (image.empty() || total == 0) return Ok{};

    const auto build_start = Clock::now();
    const int64_t dense_x = ceilDiv(image.width, dense), dense_y = ceilDiv(image.height, dense);
    std::vector<std::vector<uint32_t>> dense_lists(static_cast<size_t>(dense_x * dense_y));
    // Fast model ghosts' smooth parts, summed per dense tile as the values at the tile's four
    // corner pixels (bilinear in between): written only by the thread that owns the tile's
    // coarse tile, like the lists.
    std::vector<std::array<float, 12>> smooth_corners;
    std::vector<uint8_t> has_smooth;
    std::atomic<int64_t> smooth_tiles{0}, edge_tiles{0};
    const auto tilePixels = [&](int64_t ax, int64_t ay, int64_t bx, int64_t by) {
        return Range{ax * dense, ay * dense, std::min((bx + 1) * dense, image.width) - 1,
                     std::min((by + 1) * dense, image.height) - 1};
    };
    // Adds a bilinear block (corners at its corner pixels) to the dense tiles ax..bx, ay..by.
    const auto addSmooth = [&](const GhostBlockCover& cover, const Range& block, int64_t ax,
                               int64_t ay, int64_t bx, int64_t by) {
        const auto at = [&](int64_t x, int64_t y, size_t k) {
            const float fx = block.x1 > block.x0 ? static_cast<float>(x - block.x0) /
                                                       static_cast<float>(block.x1 - block.x0)
                                                 : 0.0f;
            const float fy = block.y1 > block.y0 ? static_cast<float>(y - block.y0) /
                                                       static_cast<float>(block.y1 - block.y0)
                                                 : 0.0f;
            const auto& c = cover.corners;
            const float top = c[0][k] + (c[1][k] - c[0][k]) * fx;
            const float bottom = c[2][k] + (c[3][k] - c[2][k]) * fx;
            return top + (bottom - top) * fy;
        };
        for (int64_t ty = ay; ty <= by; ++ty)
            for (int64_t tx = ax; tx <= bx; ++tx) {
                const Range t = tilePixels(tx, ty, tx, ty);
                const size_t i = static_cast<size_t>(ty * dense_x + tx);
                auto& corners = smooth_corners[i];
                const int64_t xs[4] = {t.x0, t.x1, t.x0, t.x1}, ys[4] = {t.y0, t.y0, t.y1, t.y1};
                for (size_t q = 0; q < 4; ++q)
                    for (size_t k = 0; k < 3; ++k) corners[q * 3 + k] += at(xs[q], ys[q], k);
                has_smooth[i] = 1;
            }
    };
    // A fast ghost over the dense tiles ax..bx, ay..by: blocks the ghost misses are dropped,
    // smooth ones go to the corner sums, the rest are halved down to single tiles, which go to
    // the lists and are drawn per pixel.
    const auto classify = [&](const auto& self, const GhostPrimitive& g, uint32_t index,
                              int64_t ax, int64_t ay, int64_t bx, int64_t by,
                              int64_t& smooth_count, int64_t& edge_count) -> void {
        const Range block = tilePixels(ax, ay, bx, by);
        const bool finest = ax == bx && ay == by;
        const GhostBlockCover cover =
            coverGhostBlock(g, block.x0, block.y0, block.x1, block.y1, finest);
        if (cover.kind == GhostBlockKind::Outside) return;
        if (cover.kind == GhostBlockKind::Smooth) {
            addSmooth(cover, block, ax, ay, bx, by);
            smooth_count += (bx - ax + 1) * (by - ay + 1);
            return;
        }
        if (finest) {
            dense_lists[static_cast<size_t>(ay * dense_x + ax)].push_back(index);
            ++edge_count;
            return;
        }
        if (bx - ax >= by - ay) {
            const int64_t mid = ax + (bx - ax) / 2;
            self(self, g, index, ax, ay, mid, by, smooth_count, edge_count);
            self(self, g, index, mid + 1, ay, bx, by, smooth_count, edge_count);
        } else {
            const int64_t mid = ay + (by - ay) / 2;
            self(self, g, index, ax, ay, bx, mid, smooth_count, edge_count);
            self(self, g, index, ax, mid + 1, bx, by, smooth_count, edge_count);
        }
    };
    const bool any_fast = std::any_of(ghosts.begin(), ghosts.end(),
                                      [](const GhostPrimitive& g) { return g.outline != nullptr; });
    if (any_fast) {
        smooth_corners.assign(dense_lists.size(), std::array<float, 12>{});
        has_smooth.assign(dense_lists.size(), 0);
    }
    const auto add_to_dense = [&](uint32_t index, int64_t tx0, int64_t ty0, int64_t tx1,
                                  int64_t ty1) {
        const Range p = range(index);
        const int64_t ax = std::max(tx0, p.x0 / dense), bx = std::min(tx1, p.x1 / dense);
        const int64_t ay = std::max(ty0, p.y0 / dense), by = std::min(ty1, p.y1 / dense);
        if (ax > bx || ay > by) return;
        if (index >= quad_count && ghosts[index - quad_count].outline) {
            int64_t smooth_count = 0, edge_count = 0;
            classify(classify, ghosts[index - quad_count], index, ax, ay, bx, by, smooth_count,
                     edge_count);
            smooth_tiles += smooth_count;
            edge_tiles += edge_count;
            return;
        }
        for (int64_t ty = ay; ty <= by; ++ty)
            for (int64_t tx = ax; tx <= bx; ++tx)
                dense_lists[static_cast<size_t>(ty * dense_x + tx)].push_back(index);
    };
    if (options.coarse_level) {
        const int64_t coarse_x = ceilDiv(image.width, coarse);
        const int64_t coarse_y = ceilDiv(image.height, coarse);
        std::vector<std::vector<uint32_t>> coarse_lists(static_cast<size_t>(coarse_x * coarse_y));
        for (uint32_t i = 0; i < total; ++i) {
            const Range p = range(i);
            for (int64_t ty = p.y0 / coarse; ty <= p.y1 / coarse; ++ty)
                for (int64_t tx = p.x0 / coarse; tx <= p.x1 / coarse; ++tx)
                    coarse_lists[static_cast<size_t>(ty * coarse_x + tx)].push_back(i);
        }
        const int64_t per = coarse / dense;  // dense tiles per coarse tile side
        tbb::parallel_for(int64_t{0}, coarse_x * coarse_y, [&](int64_t c) {
            const int64_t cx = c % coarse_x, cy = c / coarse_x;
            const int64_t tx0 = cx * per, ty0 = cy * per;
            const int64_t tx1 = std::min(dense_x - 1, tx0 + per - 1);
            const int64_t ty1 = std::min(dense_y - 1, ty0 + per - 1);
            for (const uint32_t index : coarse_lists[static_cast<size_t>(c)])
                add_to_dense(index, tx0, ty0, tx1, ty1);
        });
        for (const auto& list : coarse_lists) {
            st.coarse_entries += static_cast<int64_t>(list.size());
            st.memory_bytes +=
                static_cast<int64_t>(list.capacity() * sizeof(uint32_t) + sizeof(list));
        }
    } else {
        for (uint32_t i = 0; i < total; ++i) add_to_dense(i, 0, 0, dense_x - 1, dense_y - 1);
    }
    for (const auto& list : dense_lists) {
        st.dense_entries += static_cast<int64_t>(list.size());
        st.memory_bytes += static_cast<int64_t>(list.capacity() * sizeof(uint32_t) + sizeof(list));
    }
    st.memory_bytes += static_cast<int64_t>(primitives.size() * sizeof(Primitive) +
                                            ghosts.size() * sizeof(GhostPrimitive));
    st.ghost_tiles_smooth = smooth_tiles.load();
    st.ghost_tiles_edge = edge_tiles.load();
    st.memory_bytes += static_cast<int64_t>(smooth_corners.size() * sizeof(std::array<float, 12>) +
                                            has_smooth.size());
    st.build_ms = millisecondsSince(build_start);

    const auto traverse_start = Clock::now();
    const StopMask stop(aperture);
    tbb::parallel_for(int64_t{0}, dense_x * dense_y, [&](int64_t t) {
        const std::vector<uint32_t>& list = dense_lists[static_cast<size_t>(t)];
        const bool smooth = !has_smooth.empty() && has_smooth[static_cast<size_t>(t)];
        if (list.empty() && !smooth) return;
        const int64_t tx = (t % dense_x) * dense, ty = (t / dense_x) * dense;
        const int64_t tx1 = std::min(image.width, tx + dense) - 1;
        const int64_t ty1 = std::min(image.height, ty + dense) - 1;
        // The tile's pixels are summed here, each in the order of the list, and written once.
        thread_local std::vector<float> accumulator;
        accumulator.assign(static_cast<size_t>(dense) * dense * 3, 0.0f);
        if (smooth) {  // the fast ghosts' smooth parts first, bilinear between the corners
            const auto& c = smooth_corners[static_cast<size_t>(t)];
            for (int64_t y = ty; y <= ty1; ++y) {
                const float fy =
                    ty1 > ty ? static_cast<float>(y - ty) / static_cast<float>(ty1 - ty) : 0.0f;
                float* row = accumulator.data() + (y - ty) * dense * 3;
                for (size_t k = 0; k < 3; ++k) {
                    const float left = c[k] + (c[6 + k] - c[k]) * fy;
                    const float right = c[3 + k] + (c[9 + k] - c[3 + k]) * fy;
                    const float step =
                        tx1 > tx ? (right - left) / static_cast<float>(tx1 - tx) : 0.0f;
                    for (int64_t x = tx; x <= tx1; ++x)
                        row[(x - tx) * 3 + static_cast<int64_t>(k)] =
                            left + step * static_cast<float>(x - tx);
                }
            }
        }
        for (const uint32_t index : list) {
            if (index >= quad_count) {
                const GhostPrimitive& g = ghosts[index - quad_count];
                const int64_t x0 = std::max(tx, g.x0), x1 = std::min(tx1, g.x1);
                const int64_t y0 = std::max(ty, g.y0), y1 = std::min(ty1, g.y1);
                if (x0 > x1 || y0 > y1) continue;
                addGhostBlock(g, x0, y0, x1, y1,
                              accumulator.data() + ((y0 - ty) * dense + (x0 - tx)) * 3, dense * 3);
                continue;
            }
            const Primitive& p = primitives[index];
            const int64_t x0 = std::max(tx, p.x0), x1 = std::min(tx1, p.x1);
            const int64_t y0 = std::max(ty, p.y0), y1 = std::min(ty1, p.y1);
            for (int64_t y = y0; y <= y1; ++y) {
                float* row = accumulator.data() + ((y - ty) * dense - tx) * 3 + p.channel;
                if (p.convex) {
                    const double py = static_cast<double>(y) + 0.5;
                    for (int64_t x = x0; x <= x1; ++x)
                        row[x * 3] += static_cast<float>(
                            convexValueAt(p, static_cast<double>(x) + 0.5, py, stop));
                } else {
                    for (int64_t x = x0; x <= x1; ++x)
                        row[x * 3] += static_cast<float>(primitiveValueAt(p, x, y, stop));
                }
            }
        }
        for (int64_t y = ty; y <= ty1; ++y) {
            float* pixel = image.at(tx, y);
            const float* sum = accumulator.data() + (y - ty) * dense * 3;
            for (int64_t k = 0; k < (tx1 - tx + 1) * 3; ++k) pixel[k] += sum[k];
        }
    });
    st.traverse_ms = millisecondsSince(traverse_start);
    return Ok{};
}

}  // namespace flarelab::render
