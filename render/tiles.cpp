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

// The tiled renderer on primitives held anywhere (one array, or a frame's arrays one per ghost
// grid, which need not be copied into one).
Status renderTiledAt(ImageRGB& image,
                     std::span<const Primitive* const> primitives,
                     std::span<const GhostPrimitive> ghosts,
                     const optics::ApertureShape& aperture,
                     const TileOptions& options,
                     TileStats* stats);

std::vector<const Primitive*> addressesOf(std::span<const Primitive> primitives) {
    std::vector<const Primitive*> out(primitives.size());
    for (size_t i = 0; i < primitives.size(); ++i) out[i] = &primitives[i];
    return out;
}

}  // namespace

Status renderTiled(ImageRGB& image,
                   std::span<const Primitive> primitives,
                   const optics::ApertureShape& aperture,
                   const TileOptions& options,
                   TileStats* stats) {
    return renderTiledAt(image, addressesOf(primitives), {}, aperture, options, stats);
}

Status renderTiled(ImageRGB& image,
                   std::span<const Primitive> primitives,
                   std::span<const GhostPrimitive> ghosts,
                   const optics::ApertureShape& aperture,
                   const TileOptions& options,
                   TileStats* stats) {
    return renderTiledAt(image, addressesOf(primitives), ghosts, aperture, options, stats);
}

Status renderTiledChunks(ImageRGB& image,
                         std::span<const PrimitiveArray> chunks,
                         const optics::ApertureShape& aperture,
                         const TileOptions& options,
                         TileStats* stats) {
    std::vector<const Primitive*> addresses;
    size_t total = 0;
    for (const auto& chunk : chunks) total += chunk.size();
    addresses.reserve(total);
    for (const auto& chunk : chunks)
        for (const Primitive& p : chunk) addresses.push_back(&p);
    return renderTiledAt(image, addresses, {}, aperture, options, stats);
}

namespace {

Status renderTiledAt(ImageRGB& image,
                     std::span<const Primitive* const> primitives,
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
        const Primitive& p = *primitives[i];
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
            const Primitive& p = *primitives[index];
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
    // Fast model ghosts' smooth parts, summed per dense tile as the values at the tile's 3 x 3
    // nodes (model_ghost.h; biquadratic in between): written only by the thread that owns the
    // tile's coarse tile, like the lists.
    using Nodes = std::array<float, 27>;  // [j][i][channel]
    std::vector<Nodes> smooth_nodes;
    // The branch (model_ghost.h) of a fast ghost's edge tile, where its classification found one:
    // the tile's pixels then need no search.
    std::vector<std::vector<std::pair<uint32_t, GhostBranch>>> dense_branches;
    std::vector<uint8_t> has_smooth;
    std::atomic<int64_t> smooth_tiles{0}, edge_tiles{0};
    const auto tilePixels = [&](int64_t ax, int64_t ay, int64_t bx, int64_t by) {
        return Range{ax * dense, ay * dense, std::min((bx + 1) * dense, image.width) - 1,
                     std::min((by + 1) * dense, image.height) - 1};
    };
    // Adds a smooth block to the nodes of the dense tiles ax..bx, ay..by: a biquadratic restricted
    // to a tile is the biquadratic through its values at the tile's nodes.
    const auto addSmooth = [&](const GhostBlockCover& cover, int64_t ax, int64_t ay, int64_t bx,
                               int64_t by) {
        const auto& nx = cover.node_x;
        const auto& ny = cover.node_y;
        // The block's weights at each tile column's and row's three nodes, once per block;
        // then per tile the nodes interpolated in y, then in x.
        using Weights = std::array<std::array<double, 3>, 3>;  // [tile node][block node]
        thread_local std::vector<Weights> column_weights;
        column_weights.resize(static_cast<size_t>(bx - ax + 1));
        for (int64_t tx = ax; tx <= bx; ++tx) {
            const Range t = tilePixels(tx, ay, tx, ay);
            const int64_t xs[3] = {t.x0, midPixel(t.x0, t.x1), t.x1};
            for (size_t i = 0; i < 3; ++i)
                column_weights[static_cast<size_t>(tx - ax)][i] =
                    quadraticWeights(nx[0], nx[1], nx[2], static_cast<double>(xs[i]));
        }
        for (int64_t ty = ay; ty <= by; ++ty) {
            const Range row = tilePixels(ax, ty, ax, ty);
            const int64_t ys[3] = {row.y0, midPixel(row.y0, row.y1), row.y1};
            // Down the block's node columns p at the tile row's nodes j: [j][p][channel].
            double in_y[3][3][3];
            for (size_t j = 0; j < 3; ++j) {
                const auto wy = quadraticWeights(ny[0], ny[1], ny[2], static_cast<double>(ys[j]));
                for (size_t p = 0; p < 3; ++p)
                    for (size_t k = 0; k < 3; ++k)
                        in_y[j][p][k] = wy[0] * cover.nodes[0][p][k] +
                                        wy[1] * cover.nodes[1][p][k] + wy[2] * cover.nodes[2][p][k];
            }
            for (int64_t tx = ax; tx <= bx; ++tx) {
                const size_t index = static_cast<size_t>(ty * dense_x + tx);
                Nodes& nodes = smooth_nodes[index];
                const Weights& wx = column_weights[static_cast<size_t>(tx - ax)];
                for (size_t j = 0; j < 3; ++j)
                    for (size_t i = 0; i < 3; ++i)
                        for (size_t k = 0; k < 3; ++k)
                            nodes[(j * 3 + i) * 3 + k] += static_cast<float>(
                                wx[i][0] * in_y[j][0][k] + wx[i][1] * in_y[j][1][k] +
                                wx[i][2] * in_y[j][2][k]);
                has_smooth[index] = 1;
            }
        }
    };
    // A fast ghost over the dense tiles ax..bx, ay..by: blocks the ghost misses are dropped,
    // smooth ones go to the node sums, the rest are halved down to single tiles, which go to
    // the lists and are drawn per pixel.
    const auto classify = [&](const auto& self, const GhostPrimitive& g, uint32_t index, int64_t ax,
                              int64_t ay, int64_t bx, int64_t by, int64_t& smooth_count,
                              int64_t& edge_count, GhostSampleMemo* memo,
                              const GhostBranch* branch) -> void {
        const Range block = tilePixels(ax, ay, bx, by);
        const bool finest = ax == bx && ay == by;
        const GhostBlockCover cover =
            coverGhostBlock(g, block.x0, block.y0, block.x1, block.y1, finest, memo, branch);
        if (cover.kind == GhostBlockKind::Outside) return;
        if (cover.kind == GhostBlockKind::Smooth) {
            addSmooth(cover, ax, ay, bx, by);
            smooth_count += (bx - ax + 1) * (by - ay + 1);
            return;
        }
        if (finest) {
            const size_t tile = static_cast<size_t>(ay * dense_x + ax);
            dense_lists[tile].push_back(index);
            if (cover.branch) dense_branches[tile].push_back({index, *cover.branch});
            ++edge_count;
            return;
        }
        // The halves inherit the block's branch, if it lies on one.
        const GhostBranch* inner = cover.branch ? &*cover.branch : nullptr;
        if (bx - ax >= by - ay) {
            const int64_t mid = ax + (bx - ax) / 2;
            self(self, g, index, ax, ay, mid, by, smooth_count, edge_count, memo, inner);
            self(self, g, index, mid + 1, ay, bx, by, smooth_count, edge_count, memo, inner);
        } else {
            const int64_t mid = ay + (by - ay) / 2;
            self(self, g, index, ax, ay, bx, mid, smooth_count, edge_count, memo, inner);
            self(self, g, index, ax, mid + 1, bx, by, smooth_count, edge_count, memo, inner);
        }
    };
    const bool any_fast = std::any_of(ghosts.begin(), ghosts.end(),
                                      [](const GhostPrimitive& g) { return g.outline != nullptr; });
    if (any_fast) {
        smooth_nodes.assign(dense_lists.size(), Nodes{});
        dense_branches.resize(dense_lists.size());
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
            // The blocks' nodes and check points fall on a lattice of a quarter dense tile:
            // each is evaluated once per ghost and coarse tile. Not for regions whose lattice
            // would take more than a few megabytes a thread (huge coarse tiles, or none).
            thread_local GhostSampleMemo memo;
            const GhostPrimitive& g = ghosts[index - quad_count];
            const int64_t cells_x = (bx - ax + 1) * 4, cells_y = (by - ay + 1) * 4;
            const bool lattice = dense % 4 == 0 && (cells_x + 1) * (cells_y + 1) <= (1 << 17);
            if (lattice) memo.reset(&g, ax * dense, ay * dense, cells_x, cells_y, dense / 4);
            classify(classify, g, index, ax, ay, bx, by, smooth_count, edge_count,
                     lattice ? &memo : nullptr, nullptr);
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
    st.memory_bytes +=
        static_cast<int64_t>(primitives.size() * (sizeof(Primitive) + sizeof(void*)) +
                             ghosts.size() * sizeof(GhostPrimitive));
    st.ghost_tiles_smooth = smooth_tiles.load();
    st.ghost_tiles_edge = edge_tiles.load();
    st.memory_bytes +=
        static_cast<int64_t>(smooth_nodes.size() * sizeof(Nodes) + has_smooth.size());
    st.build_ms = millisecondsSince(build_start);

    const auto traverse_start = Clock::now();
    const StopMask stop(aperture);
    // The biquadratic's weights along a whole tile's row or column, pixel by pixel: the same for
    // every whole tile (they depend on the pixel's offset in the tile alone, all in whole numbers
    // until the last division), so computed once; tiles cut by the image's edge compute their own.
    using TileWeights = std::vector<std::array<double, 3>>;
    const auto tileWeights = [](int64_t t0, int64_t t1) {
        TileWeights w(static_cast<size_t>(t1 - t0 + 1));
        const double mid = static_cast<double>(midPixel(t0, t1));
        for (int64_t x = t0; x <= t1; ++x)
            w[static_cast<size_t>(x - t0)] = quadraticWeights(
                static_cast<double>(t0), mid, static_cast<double>(t1), static_cast<double>(x));
        return w;
    };
    const TileWeights whole_tile = tileWeights(0, dense - 1);
    tbb::parallel_for(int64_t{0}, dense_x * dense_y, [&](int64_t t) {
        const std::vector<uint32_t>& list = dense_lists[static_cast<size_t>(t)];
        const bool smooth = !has_smooth.empty() && has_smooth[static_cast<size_t>(t)];
        if (list.empty() && !smooth) return;
        const int64_t tx = (t % dense_x) * dense, ty = (t / dense_x) * dense;
        const int64_t tx1 = std::min(image.width, tx + dense) - 1;
        const int64_t ty1 = std::min(image.height, ty + dense) - 1;
        // The tile's pixels are summed here, each in the order of the list, and written once.
        if (!smooth && list.back() < quad_count) {
            // Only quads (the list is in index order, model ghosts last): each channel summed in
            // a plane of its own, where a row's neighbours are adjacent, with the same additions
            // in the same order as in an interleaved accumulator.
            thread_local std::vector<float> planes;
            const int64_t plane = static_cast<int64_t>(dense) * dense;
            planes.assign(static_cast<size_t>(3 * plane), 0.0f);
            for (const uint32_t index : list) {
                const Primitive& p = *primitives[index];
                const int64_t x0 = std::max(tx, p.x0), x1 = std::min(tx1, p.x1);
                const int64_t y0 = std::max(ty, p.y0), y1 = std::min(ty1, p.y1);
                addPrimitiveBlock(p, x0, y0, x1, y1, stop,
                                  planes.data() + p.channel * plane + (y0 - ty) * dense + (x0 - tx),
                                  dense, 1);
            }
            for (int64_t y = ty; y <= ty1; ++y) {
                float* pixel = image.at(tx, y);
                const float* r = planes.data() + (y - ty) * dense;
                const float* g = r + plane;
                const float* b = g + plane;
                for (int64_t x = 0; x <= tx1 - tx; ++x) {
                    pixel[3 * x] += r[x];
                    pixel[3 * x + 1] += g[x];
                    pixel[3 * x + 2] += b[x];
                }
            }
            return;
        }
        thread_local std::vector<float> accumulator;
        accumulator.assign(static_cast<size_t>(dense) * dense * 3, 0.0f);
        if (smooth) {  // the fast ghosts' smooth parts first, biquadratic between the nodes
            const Nodes& nodes = smooth_nodes[static_cast<size_t>(t)];
            const TileWeights cut_x = tx1 - tx + 1 < dense ? tileWeights(tx, tx1) : TileWeights{};
            const TileWeights cut_y = ty1 - ty + 1 < dense ? tileWeights(ty, ty1) : TileWeights{};
            const TileWeights& weights_x = cut_x.empty() ? whole_tile : cut_x;
            const TileWeights& weights_y = cut_y.empty() ? whole_tile : cut_y;
            std::array<std::array<float, 3>, 256> wx;
            for (int64_t x = tx; x <= tx1; ++x) {
                const auto& w = weights_x[static_cast<size_t>(x - tx)];
                for (size_t i = 0; i < 3; ++i)
                    wx[static_cast<size_t>(x - tx)][i] = static_cast<float>(w[i]);
            }
            for (int64_t y = ty; y <= ty1; ++y) {
                const auto& wy = weights_y[static_cast<size_t>(y - ty)];
                float column[3][3];  // [node i][channel]
                for (size_t i = 0; i < 3; ++i)
                    for (size_t k = 0; k < 3; ++k)
                        column[i][k] = static_cast<float>(wy[0] * nodes[(0 + i) * 3 + k] +
                                                          wy[1] * nodes[(3 + i) * 3 + k] +
                                                          wy[2] * nodes[(6 + i) * 3 + k]);
                float* row = accumulator.data() + (y - ty) * dense * 3;
                for (int64_t x = tx; x <= tx1; ++x) {
                    const auto& w = wx[static_cast<size_t>(x - tx)];
                    for (size_t k = 0; k < 3; ++k)
                        row[(x - tx) * 3 + static_cast<int64_t>(k)] =
                            w[0] * column[0][k] + w[1] * column[1][k] + w[2] * column[2][k];
                }
            }
        }
        for (const uint32_t index : list) {
            if (index >= quad_count) {
                const GhostPrimitive& g = ghosts[index - quad_count];
                const int64_t x0 = std::max(tx, g.x0), x1 = std::min(tx1, g.x1);
                const int64_t y0 = std::max(ty, g.y0), y1 = std::min(ty1, g.y1);
                if (x0 > x1 || y0 > y1) continue;
                const GhostBranch* branch = nullptr;
                if (g.outline)  // fast ghosts only; dense_branches is empty without one
                    for (const auto& [which, b] : dense_branches[static_cast<size_t>(t)])
                        if (which == index) branch = &b;
                addGhostBlock(g, x0, y0, x1, y1,
                              accumulator.data() + ((y0 - ty) * dense + (x0 - tx)) * 3, dense * 3,
                              branch);
                continue;
            }
            const Primitive& p = *primitives[index];
            const int64_t x0 = std::max(tx, p.x0), x1 = std::min(tx1, p.x1);
            const int64_t y0 = std::max(ty, p.y0), y1 = std::min(ty1, p.y1);
            addPrimitiveBlock(p, x0, y0, x1, y1, stop,
                              accumulator.data() + ((y0 - ty) * dense + (x0 - tx)) * 3 + p.channel,
                              dense * 3);
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

}  // namespace

}  // namespace flarelab::render
