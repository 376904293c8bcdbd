// ============================================================================
//  flarelab predict: FlareFigures, flareFigures, contrastRatio, coveredTheta, FigureTableOptions,
//                    FlareFigureTable
// ============================================================================
//
// The numbers a planner reads off a flare image (§9.1-9.2 of the thesis), and the same numbers as
// functions of the constellation, built once per model so that a timeline does not draw a frame
// per instant.
//
// Every figure is taken on the image's luminance, Y = 0.2126 R + 0.7152 G + 0.0722 B (Rec. 709),
// in the image's unit. min, max, mean and the log-average are per pixel, so they do not depend on
// the resolution the image is drawn at; `total` is the mean times the pixel count of the camera's
// own image. The log-average is exp(mean ln max(Y, 1e-6 max Y)): a floor relative to the peak (20
// stops under it, what an HDR capture holds) keeps it finite on black pixels and makes every
// figure scale with the light, so a table of a unit light serves any brightness.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <utility>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "fit/model_file.h"

namespace flarelab::predict {

inline constexpr double kLogAverageFloor = 1e-6;  // of the image's peak

struct FlareFigures {
    double min = 0.0;
    double max = 0.0;
    double mean = 0.0;
    double log_average = 0.0;
    double total = 0.0;  // mean * pixel count

    FlareFigures scaled(double k) const {
        return {min * k, max * k, mean * k, log_average * k, total * k};
    }
};

// The figures of `image` (all 0 for an empty or black image).
FlareFigures flareFigures(const ImageRGB& image);

// Eq. 9.3 of the thesis: K_real / K_ideal = (I_max + I_min) / (I_max + I_min + 2 I_flare), the
// share of the scene's contrast that survives a flare of I_flare added to every pixel. In (0, 1];
// 1 for no flare. Inputs in one unit, I_max >= I_min >= 0, I_max > 0, I_flare >= 0 (checked by
// the caller; FLARELAB_CHECK here).
double contrastRatio(double scene_min, double scene_max, double flare);

// The glare indicator of §9.2 of the thesis: the flare over the scene's log-average (the key a
// tone mapper exposes for), both in one unit. The flare's mean stands for the overlay: its own
// log-average is ruled by the black pixels of a flare that covers part of the frame, so it would
// call a bright ghost over a tenth of the frame harmless. 0 for no flare; 1: the flare adds as
// much light as the scene's key. scene_log_average > 0, flare >= 0 (FLARELAB_CHECK).
double glareIndicator(double scene_log_average, double flare_mean);

// The light angles theta (>= 0) that `model` answers for: its head angles folded onto theta (a
// negative head angle is the light on the other side, playback.h), [from, to] with from < to
// unless the model's range is degenerate.
std::pair<double, double> coveredTheta(const fit::FlareModel& model);

struct FigureTableOptions {
    double theta_step_deg = 0.0;  // 0: the model's capture step, at most 0.5 deg
    double phi_step_deg = 5.0;    // (0, 90], a divisor of 360 within 1e-9
    int64_t width = 240;          // the frame's width in the drawing; the height keeps the aspect
    // Asked before each theta is drawn, from any thread (a server's check that its client is
    // still there); true ends the build with Unsupported ("stopped") within one drawing per core.
    std::function<bool()> stop_requested;
    // Points of the frame where the flare is also kept for every node (the lab figures' black
    // patches off axis, predict/lab_figures.h): relative image heights in (0, 1], fractions of
    // the half-diagonal along the diagonal towards the frame's corner at +x, +y.
    std::vector<double> field_points = {0.5, 0.7};
};

// The options with these steps and width and the rest at their defaults.
inline FigureTableOptions tableOptions(double theta_step_deg, double phi_step_deg, int64_t width) {
    FigureTableOptions o;
    o.theta_step_deg = theta_step_deg;
    o.phi_step_deg = phi_step_deg;
    o.width = width;
    return o;
}

// Figures of a unit light (model units: DN/s of the capture, for the rig's light) at a grid of
// (theta, phi) over the model's valid angles and a whole turn of roll, interpolated bilinearly
// (periodic in phi). Roll changes the figures only through the frame's edges (ghosts leaving the
// image), so each theta is drawn once, at roll 0, on a square canvas as wide as the frame's
// diagonal, and each roll's figures are taken over the canvas pixels the frame covers when turned
// the other way: one drawing per theta instead of one per node. Nodes therefore sample the frame
// on a turned pixel grid, which differs from drawing the constellation by the pixels along the
// frame's edge (about one pixel's share of the frame); `flarelab bench predict` measures the
// table against drawing each constellation.
class FlareFigureTable {
public:
    // Draws the grid (on every core). InvalidArgument for options out of range or a model with no
    // valid angle at or above 0.
    static Result<FlareFigureTable> build(const fit::FlareModel& model,
                                          const FigureTableOptions& options = {});

    // Figures per pixel at (theta, phi); `total` is per pixel of the capture's size. nullopt
    // outside [theta_from, theta_to]: every theta the model covers, on either side of its head
    // angles (playback.h), so wherever placeLight draws a light the table answers.
    std::optional<FlareFigures> at(double theta_deg, double phi_deg) const;

    double thetaFromDeg() const { return theta_from_deg_; }
    double thetaToDeg() const { return theta_to_deg_; }
    int64_t thetaCount() const { return theta_count_; }
    int64_t phiCount() const { return phi_count_; }
    // The figures at grid node (i, j): theta_i = from + i * step (the last node is theta_to),
    // phi_j = j * phi_step.
    const FlareFigures& node(int64_t i, int64_t j) const {
        return nodes_[static_cast<size_t>(i * phi_count_ + j)];
    }
    double thetaAt(int64_t i) const;
    // The flare at the image's centre (luminance per pixel, like the figures) for a unit light
    // at theta_i: the same for every roll. predict/lab_figures.h integrates it.
    double centreFlare(int64_t i) const { return centre_[static_cast<size_t>(i)]; }
    // The flare at field point k (FigureTableOptions::field_points) for a unit light at node
    // (i, j): the frame at roll phi_j, the light at theta_i, whose own image lies at
    // f tan(theta_i) (cos phi_j, sin phi_j) on the sensor.
    const std::vector<double>& fieldPoints() const { return field_points_; }
    double fieldFlare(size_t k, int64_t i, int64_t j) const {
        return field_[k][static_cast<size_t>(i * phi_count_ + j)];
    }
    double phiAt(int64_t j) const { return static_cast<double>(j) * phi_step_deg_; }

private:
    double theta_from_deg_ = 0.0;
    double theta_to_deg_ = 0.0;
    double theta_step_deg_ = 0.0;
    double phi_step_deg_ = 0.0;
    int64_t theta_count_ = 0;
    int64_t phi_count_ = 0;
    double capture_pixels_ = 0.0;
    std::vector<FlareFigures> nodes_;
    std::vector<double> centre_;
    std::vector<double> field_points_;
    std::vector<std::vector<double>> field_;  // [point][node]
};

}  // namespace flarelab::predict
