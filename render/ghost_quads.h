// ============================================================================
//  flarelab render: SensorToImage, adaptiveGridSize, GhostQuads, rasterizeReference
// ============================================================================
//
// From traced ray grids to pixels, the plain way: each 2 x 2 block of neighbouring rays of a grid
// becomes a quad (Bodonyi & Kunkli 2023 §4.1), and the reference rasterizer draws the quads of
// one ghost after another into the frame buffer, as Hullin et al. 2011 do ("the previous method"
// of the paper). It is the baseline the tiled renderer is measured against, and on dense grids the
// reference image for its PSNR.
//
// Radiometry. A grid ray stands for the light crossing one cell of the entry plane, of area
// cell_area_mm2 (perpendicular to the axis). Landing in a quad of area A on the sensor, that light
// spreads over A: a pixel inside receives throughput * cell_area / A (per unit of the light's
// irradiance, per pixel area). Summed over the image, a quad therefore delivers exactly its
// throughput times its cell area, the power that entered through its cell: the drawing conserves
// energy whatever the grid size. A quad smaller than a pixel may cover no pixel centre, so it is
// not sampled but added whole to the pixel under its centre; that keeps the energy when grids get
// denser than the image.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "optics/aperture.h"
#include "optics/prescription.h"
#include "optics/ray_grid.h"
#include "render/image.h"
#include "render/quad.h"

namespace flarelab::render {

// Sensor millimetres to image pixels (DESIGN.md): the optical axis at the image centre, the
// sensor's width and height spread over the image's width and height.
struct SensorToImage {
    double px_per_mm_x = 1.0;
    double px_per_mm_y = 1.0;
    double centre_x_px = 0.0;
    double centre_y_px = 0.0;

    Eigen::Vector2d toPixels(double x_mm, double y_mm) const {
        return {centre_x_px + x_mm * px_per_mm_x, centre_y_px + y_mm * px_per_mm_y};
    }
};
SensorToImage sensorToImage(const optics::CameraDescription& camera, int64_t width, int64_t height);

// The grid size for a ghost, eq. 13 of Bodonyi & Kunkli 2023: the base size times
// min(max((G / S * sigma)^phi, 0.05), 1), where G and S are the areas of the ghost's and the
// sensor's bounding rectangles; at least 2 (one quad). sigma = 1, phi = 1/2 in the paper.
int adaptiveGridSize(int base_size,
                     double ghost_area_mm2,
                     double sensor_area_mm2,
                     double sigma = 1.0,
                     double phi = 0.5);

// The quads of one traced grid, in pixels. A quad is kept when at least one of its corners is a
// valid ray and all four have a position (a corner cut by a clear aperture carries throughput 0,
// so the light fades out across the cut); quads with a corner that has no geometry at all (a ray
// that missed a surface or was totally reflected) are dropped.
struct GhostQuads {
    std::vector<Quad> quads;
    double cell_area_mm2 = 0.0;  // entry-plane area one ray stands for
};
GhostQuads quadsFromGrid(const optics::RayGrid& grid, const SensorToImage& mapping);

struct RasterOptions {
    double min_quad_area_px = 1.0;  // quads below this area (px^2) are added whole at their centre
};

// A quad ready to draw into one channel of a width x height image: the range of pixels it can
// touch and its light per unit of interpolated throughput. Both renderers draw the same
// primitives with primitiveValueAt, so they agree pixel for pixel.
struct Primitive {
    Quad quad;
    int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;  // inclusive pixel range (a splat: one pixel)
    double scale = 0.0;  // irradiance x cell area / quad area; for a splat irradiance x cell area
    int channel = 0;
    bool splat = false;  // below min_quad_area_px: drawn whole at the pixel under its centre
};

// nullopt when the quad cannot put light in the image (outside it, non-finite, no irradiance).
std::optional<Primitive> preparePrimitive(const Quad& quad,
                                          double cell_area_mm2,
                                          int channel,
                                          float irradiance,
                                          int64_t width,
                                          int64_t height,
                                          const RasterOptions& options = {});

// What the primitive adds at pixel (x, y) of its range: 0 outside the quad or the stop shape.
double primitiveValueAt(const Primitive& primitive,
                        int64_t x,
                        int64_t y,
                        const optics::ApertureShape& aperture);

// Adds one ghost's quads to `channel` (0 red, 1 green, 2 blue) of `image`, scaled by the light's
// irradiance in that channel, the stop shape applied to the interpolated stop coordinates. Pixels
// are sampled at their centres. Quads partly or wholly outside the image are clipped; nothing
// non-finite is ever written.
void rasterizeReference(ImageRGB& image,
                        const GhostQuads& ghost,
                        int channel,
                        float irradiance,
                        const optics::ApertureShape& aperture,
                        const RasterOptions& options = {});

}  // namespace flarelab::render
