// ============================================================================
//  flarelab render: TileOptions, TileStats, renderTiled
// ============================================================================
//
// The tiled renderer of Bodonyi & Kunkli 2023 (§4.3-4.5, Algorithm 2): instead of drawing ghost
// after ghost into the frame buffer, collect every primitive of every ghost and light into screen
// tiles first, then visit each pixel once and sum what the primitives of its tile put there.
//
// Tiles come in two levels. Primitives are first sorted into coarse tiles (default 128 px) by
// their pixel range; each coarse tile then distributes its own primitives to the dense tiles
// (default 8 px) it contains. A dense tile lies in exactly one coarse tile, so coarse tiles refine
// in parallel without locks, and a primitive is tested only against the dense tiles of the coarse
// tiles it touches. Dense tiles hold indices into the one primitive array. The traversal gives
// each dense tile to one thread (oneTBB), so no pixel is ever written by two threads.
//
// Every pixel sums its primitives in the order of the input array, in a per-tile accumulator that
// is written to the image once, with the arithmetic of rasterizeReference (primitiveValueAt): the
// two renderers agree bit for bit on an empty image.
//
// Two primitive kinds share the tiles: the quads of traced ray grids (ghost_quads.h), one colour
// channel each, and model ghosts (model_ghost.h), shaded Bézier loops that add all three
// channels. A pixel sums the quads of its tile first, then the model ghosts, each in input order.
//
// Fast model ghosts (model_ghost.h) are sorted into dense tiles by coverGhostBlock while the tiles
// are built: from the blocks of the coarse tile down to single dense tiles, a block the ghost
// misses is dropped, a block where it is constant or biquadratic is added to its tiles' node values
// (3 x 3 per tile, summed over ghosts, drawn first, before the quads), and only dense tiles an edge
// crosses go to the lists and are drawn per pixel. A block's nodes and check points lie on a
// lattice of a quarter dense tile; one GhostSampleMemo per ghost and coarse tile evaluates each
// point once for all the blocks that share it. The per-pixel ghosts and the node values are summed
// in a fixed order too, so the image still does not depend on the number of threads, but it is not
// the order of the input array.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "optics/aperture.h"
#include "render/ghost_quads.h"
#include "render/model_ghost.h"

namespace flarelab::render {

struct TileOptions {
    int coarse_tile_px = 128;  // a multiple of dense_tile_px, at most 4096
    int dense_tile_px = 8;     // 1..256
    bool coarse_level = true;  // false: primitives go straight to dense tiles (the paper's Table 4)
};

struct TileStats {
    int64_t primitives = 0;
    int64_t coarse_entries = 0;      // primitive references in coarse tiles
    int64_t dense_entries = 0;       // primitive references in dense tiles
    int64_t memory_bytes = 0;        // of the tile lists and the primitive array
    int64_t ghost_tiles_smooth = 0;  // dense tiles x fast model ghosts interpolated
    int64_t ghost_tiles_edge = 0;    // dense tiles x fast model ghosts drawn per pixel
    double build_ms = 0.0;           // tile building (and fast model ghosts' classification)
    double traverse_ms = 0.0;        // per-pixel accumulation
};

// Adds the primitives (prepared for this image's size) to `image`. InvalidArgument for tile sizes
// out of range or a primitive whose pixel range leaves the image.
Status renderTiled(ImageRGB& image,
                   std::span<const Primitive> primitives,
                   const optics::ApertureShape& aperture,
                   const TileOptions& options = {},
                   TileStats* stats = nullptr);

// The same with the primitives in several arrays, drawn as if they were one array in their order
// (a frame's grids, each prepared on its own, are not copied together).
Status renderTiledChunks(ImageRGB& image,
                         std::span<const PrimitiveArray> chunks,
                         const optics::ApertureShape& aperture,
                         const TileOptions& options = {},
                         TileStats* stats = nullptr);

// The same with model ghosts (prepared for this image's size) after the quads. InvalidArgument
// also for a ghost whose pixel range leaves the image.
Status renderTiled(ImageRGB& image,
                   std::span<const Primitive> primitives,
                   std::span<const GhostPrimitive> ghosts,
                   const optics::ApertureShape& aperture,
                   const TileOptions& options = {},
                   TileStats* stats = nullptr);

}  // namespace flarelab::render
