// ============================================================================
//  flarelab render: GhostPrimitive, prepareGhostPrimitive, addGhostRow
// ============================================================================
//
// The second primitive kind of the tile engine (tiles.h): a model ghost, a closed loop of cubic
// Béziers in sensor millimetres shaded by the transfer function of its signed distance
// (ghost_shape.h). A pixel gets the ghost's mean over its area (shadeGhostBlock), as a sensor's
// pixel integrates the light: an edge sharper than a pixel is drawn anti-aliased, as the
// simulator and a camera record it. Its pixel range is the loop's control-point box (which holds
// the curve) grown by the outer falloff, past which the ghost is zero, and by half a pixel,
// clipped to the image; the tile engine
// visits only the dense tiles that range touches, and each pixel of it once, adding all three
// channels. No pixel outside the range is touched, so a ghost costs what it covers.
#pragma once

#include <array>
#include <cstdint>
#include <optional>

#include "render/ghost_quads.h"
#include "render/ghost_shape.h"

namespace flarelab::render {

struct GhostPrimitive {
    BezierLoop loop_mm;
    GhostShading shading;
    SensorToImage mapping;  // sensor mm to pixels of the image it is drawn into
    FastDistanceOptions distance;
    int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;  // inclusive pixel range
};

// nullopt when the ghost cannot put light in a width x height image: its range misses the image,
// it is black in every channel, or anything about it is not finite or out of bounds (an empty
// loop, a shading validateShading refuses).
std::optional<GhostPrimitive> prepareGhostPrimitive(const BezierLoop& loop_mm,
                                                    const GhostShading& shading,
                                                    const SensorToImage& mapping,
                                                    int64_t width,
                                                    int64_t height,
                                                    const FastDistanceOptions& distance = {});

// Adds the ghost's mean over the pixels (x, y) for x in [x0, x1] to rgb, three floats
// per pixel starting with pixel x0. The caller keeps x0..x1 and y inside the ghost's range.
void addGhostRow(const GhostPrimitive& ghost, int64_t y, int64_t x0, int64_t x1, float* rgb);

}  // namespace flarelab::render
