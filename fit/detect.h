// ============================================================================
//  flarelab fit: DetectOptions, LightSpot, GhostCandidate, FrameDetection, detectGhosts
// ============================================================================
//
// Automatic detection: what the thesis set by hand (chapter 11: manual initial parameters), found
// in the frame itself.
//   1. The sky: the background level and its noise per channel, robustly (the lowest mode of the
//      values and the spread below it), so that the ghosts, however many, do not bias it.
//   2. The light: the brightest blob (the light's own image, saturated in every bracket on the rig)
//      and a disc around it that the fit and the score leave out: its radius grows with the
//      light's blob until its neighbourhood falls to the noise, plus a margin.
//   3. Ghost candidates: connected components (OpenCV) of the smoothed frame above the noise floor
//      outside the light's disc, each measured (bounding box, centroid, second moments, energy,
//      peak) and turned into an initial ghost (shape from its extents, shading from its values).
//      Blobs whose energy does not rise above the noise are dropped.
// A black frame, pure noise or a saturated frame gives no candidates, not an error.
// Details (fit/detect.cpp): the background is the lowest mode rather than the median because
// broad ghosts may cover most of the frame; the threshold applies to the smoothed noise (sigma
// times the kernel's sum of squares); ghosts that overlap form one component, which the circle
// detector (DetectOptions::circles) splits into the circles it finds inside it.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <vector>

#include "common/result.h"
#include "fit/frame.h"

namespace flarelab::fit {

struct DetectOptions {
    double smoothing_px = 1.0;      // Gaussian sigma applied before thresholding, >= 0
    double threshold_sigmas = 4.0;  // a pixel is lit above background + this many noise sigmas, > 0
    int64_t min_area_px = 6;        // smaller components are noise, >= 1
    // A candidate's energy (sum over its pixels of value - background) must exceed this many
    // times the noise sigma times the square root of its area (its energy's own noise), > 0.
    double min_energy_sigmas = 10.0;
    // false: the frame holds no light of its own (a ghost path rendered alone, as `bench oracle`
    // fits them), so its brightest blob is a ghost and is not left out as the light.
    bool find_light = true;
    // A light whose peak (channel-summed, above the background) is under this is not the light
    // but a ghost (the light out of view, a small bright ghost the brightest blob); finite, >= 0.
    // The sweep fit sets it from the light it finds in its probe frames (fit/sweep_fit.h).
    double min_light_peak = 0.0;
    double light_margin_px = 3.0;  // added to the light's radius, >= 0
    double light_min_radius_px = 2.0;
    int max_candidates = 256;  // the brightest kept, >= 0

    // Overlapping circular ghosts (a second detector; fit/detect.cpp, detectCircles). Every
    // ghost's centre lies on the light line: through the image centre and the light when the
    // light is found away from the centre, else the horizontal line through the image centre.
    // Edge pixels of the smoothed signal vote, for each centre on that line, for the radius that
    // puts them on the circle (only where their gradient points at that centre), in a (centre,
    // radius) Hough accumulator. A component holding two or more circles is replaced by them.
    bool circles = true;
    int max_circles = 32;  // the best supported kept, >= 0
    // A circle's support: its votes over the length of its arc inside the frame and outside the
    // excluded pixels (edge pixels per pixel of visible arc, weighted by how radial their
    // gradient is); kept at this or more, > 0.
    double min_circle_support = 2.5;
    double min_circle_radius_px = 3.0;  // > 0
    // An edge pixel: its gradient above this many noise sigmas of the gradient, > 0, and above
    // min_circle_step times the local signal per pixel (a relative step: a smooth falloff of a
    // bright ghost is no edge), >= 0.
    double circle_edge_sigmas = 5.0;
    double min_circle_step = 0.01;
    int max_edge_pixels = 3000;  // edge pixels sampled evenly beyond this many, >= 16
    bool operator==(const DetectOptions&) const = default;
};

struct LightSpot {
    bool found = false;
    Eigen::Vector2d centre_px = Eigen::Vector2d::Zero();  // image space (pixel centres at +0.5)
    double radius_px = 0.0;                               // of the disc left out
    double peak = 0.0;  // its brightest pixel, channel-summed, above the background
};

struct GhostCandidate {
    Eigen::Vector2d centroid_px = Eigen::Vector2d::Zero();  // energy-weighted
    int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;               // bounding box, inclusive pixels
    int64_t area_px = 0;
    std::array<double, 3> energy{};  // sum of (value - background) over the component
    std::array<double, 3> peak{};    // largest value - background in it
    // Semi-axes of the blob along x and y in pixels: from the centroid to the outer edges of its
    // body, the pixels whose smoothed value reaches a quarter of the component's 90th percentile
    // (so the smoothing's fringe around a bright ghost does not count); within the bbox.
    double left_px = 0.0, right_px = 0.0, up_px = 0.0, down_px = 0.0;
    // Sensor mm and the frame's unit: centre x at the centroid, centre y mid-way between the up
    // and down extents (the model is symmetric there), circle handles, border from the 90th
    // percentile, inside from the median within half the extents; passes validateGhostShape and
    // validateShading.
    GhostState initial;
};

struct FrameDetection {
    std::array<double, 3> background{};   // per channel, the frame's unit
    std::array<double, 3> noise_sigma{};  // per channel, > 0 (a floor keeps it positive)
    LightSpot light;
    // width * height: 1 where a pixel is left out of fitting and scoring (the light's disc,
    // non-finite or saturated-looking values), 0 elsewhere.
    std::vector<uint8_t> excluded;
    std::vector<GhostCandidate> candidates;  // by total energy, brightest first
};

// InvalidArgument for options out of range. Never fails on the image's content.
Result<FrameDetection> detectGhosts(const FitFrame& frame, const DetectOptions& options = {});

}  // namespace flarelab::fit
