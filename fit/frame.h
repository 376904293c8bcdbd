// ============================================================================
//  flarelab fit: FitFrame, GhostState, frameFromImage, loadFitFrame
// ============================================================================
//
// One HDR frame of a sweep as the fitter sees it: the linear image (the sweep's unit, DN per
// second at unity gain for merged frames), the light's angle, and the map from sensor millimetres
// to its pixels (DESIGN.md: model parameters live in sensor millimetres). A frame whose three
// channels are equal in every pixel (a monochrome camera, or a merged mosaic copied to R, G, B)
// is fitted in one channel and its ghosts get equal colours.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <string>

#include "common/image.h"
#include "common/result.h"
#include "hdr/sweep.h"
#include "render/ghost_quads.h"
#include "render/ghost_shape.h"

namespace flarelab::fit {

struct FitFrame {
    ImageRGB image;          // linear, finite, >= 0 (loadFitFrame checks)
    double angle_deg = 0.0;  // the head angle the frame was captured at
    render::SensorToImage mapping;
    int channels = 3;  // 1 when R = G = B everywhere: fitted in channel 0 only
    // Per pixel (row-major), the channels that are only lower bounds (hdr/merge.h lowerBounds:
    // saturated in every bracket); empty when the frame does not say. The fit leaves such pixels
    // out, as it does the light's disc.
    std::vector<uint8_t> lower_bound;
};

// The sensor size of a sweep in mm: the one the manifest records (lens.sensor_width_mm and
// sensor_height_mm, format version 3: what the simulated camera used), else `sensor_mm` (width,
// height; both > 0), else the camera's pixel pitch times the frame size, else InvalidArgument
// saying that the sweep does not record it and how to give it. A `sensor_mm` that contradicts
// the recorded size is refused (InvalidArgument naming both): the frames show the recorded one.
Result<std::array<double, 2>> sweepSensorSize(const hdr::Sweep& sweep,
                                              const std::array<double, 2>* sensor_mm = nullptr);

// A frame from an image: the mapping puts the optical axis at the image centre and spreads the
// sensor over the image (render::SensorToImage). InvalidArgument for an empty image, a
// non-finite or negative value (named by pixel and channel), or a sensor size <= 0.
Result<FitFrame> frameFromImage(ImageRGB image,
                                double angle_deg,
                                double sensor_width_mm,
                                double sensor_height_mm);

// Frame `index` of `sweep` (hdr::loadFrame), with frameFromImage's checks; errors name the file.
Result<FitFrame> loadFitFrame(const hdr::Sweep& sweep,
                              size_t index,
                              double sensor_width_mm,
                              double sensor_height_mm);

// One ghost in one frame: its shape (sensor mm) and its shading (the frame's unit).
struct GhostState {
    render::GhostShapeParams shape;
    render::GhostShading shading;
    bool operator==(const GhostState&) const = default;
};

// A ghost's size: its largest extent from the centre (half height, left, right), in mm.
inline double ghostSize(const GhostState& state) {
    return std::max({state.shape.half_height_mm, state.shape.left_mm, state.shape.right_mm});
}

}  // namespace flarelab::fit
