// ============================================================================
//  flarelab predict: LabFigureOptions, LabFigures, labFigures
// ============================================================================
//
// The stray-light figures lens labs report, taken from a model so that its results compare with
// their benches (item 4 of issue 21). Each is a ratio of the flare to the light the lens images,
// so each needs the model's scale: the power of the rig light's own image
// (capture.light_power_dn_s, fit/model_file.h), the focal length, the f-number and the sensor.
// A model without them gets none of these figures, and `missing` says what it lacks.
//
// Units: F(theta, phi) is the model's flare luminance per pixel (DN/s) for the rig light at
// (theta, phi) (predict/figures.h); P the rig light's own image in DN/s; A_pix the area of one
// capture pixel (mm^2); f the focal length (mm); N the f-number; D = f / N the entrance pupil.
//
//   - Point source transmittance along theta: the irradiance the flare puts on the sensor,
//     averaged over the frame, over the irradiance the light puts on the entrance pupil,
//       PST(theta) = mean_frame F(theta, 0) / A_pix  /  (P / (pi D^2 / 4)).
//     P is what reaches the image, so PST here is relative to the lens's own transmittance on
//     axis (an ideal lens passes all of it). Roll 0: the sensor's x axis, the plane of the sweep.
//   - Veiling glare index (ISO 9358's definition: the irradiance at the centre of the image of a
//     black spot in a uniform bright field, over the irradiance the bright field's image gets),
//     on axis. A field of radiance L puts L P / f^2 per mm^2 into its image near the centre; each
//     direction's share of the veil at the centre is L F_c(theta) dOmega / A_pix, F_c the flare
//     at the centre pixel (the same for every roll). So
//       VGI = f^2 / (A_pix P) * integral over theta_spot..theta_end of F_c(theta) 2 pi sin(theta),
//     the black spot hiding theta < theta_spot (half its angular diameter); the field ends where
//     the model ends (vgi_to_deg), so the index counts only the light the model knows.
//   - Image flare (ISO 18844's black-patch method), at the centre patch of a chart that fills
//     the frame: the same integral over the directions whose image falls inside the frame (a
//     rectilinear lens: radius f tan(theta); for each theta the arc of roll inside the frame
//     replaces 2 pi), over the chart's white at the centre. image_flare_complete says whether
//     the model covers the frame's corners.
//
// What a model holds is its ghosts: scatter from surfaces, dust and the lens barrel, which a
// bench's VGI also measures, is not in it, so these are the ghost part of each figure, a lower
// bound of a bench's value.
//
// Off axis (LabFieldPoint): a spot or patch at a field point of the table, the flare there summed
// over every node's light (the table keeps it per node), over a white of cos^4 of the point's
// field angle. The points are image heights along the diagonal (0.5 and 0.7 by default), not the
// positions of ISO 18844's chart, whose text the project does not hold.
#pragma once

#include <string>
#include <vector>

#include "common/result.h"
#include "fit/model_file.h"
#include "predict/figures.h"

namespace flarelab::predict {

struct LabFigureOptions {
    // Angular diameter of the black spot (ISO 9358) and of the chart's centre patch (ISO 18844),
    // degrees, (0, 20].
    double black_spot_deg = 1.0;
};

// The veiling glare index and the image flare at a black spot or patch off axis (a field point of
// the table, FigureTableOptions::field_points), summed over the table's nodes: theta by the
// trapezoid rule, roll at the table's step. The white there is the centre's times cos^4 of the
// field angle (an ideal rectilinear lens; a real lens's vignetting is not in a model).
struct LabFieldPoint {
    double height = 0.0;    // of the half-diagonal, towards the corner at +x, +y
    double field_deg = 0.0;  // the point's field angle
    double vgi = 0.0;
    double image_flare = 0.0;
};

struct LabFigures {
    bool scaled = false;   // false: the model lacks the scale, and only centre_flare is filled
    std::string missing;   // what it lacks ("capture.light_power_dn_s", ...), when not scaled
    std::vector<double> theta_deg;     // the table's nodes
    std::vector<double> centre_flare;  // F_c at each node, DN/s per pixel for the rig light
    std::vector<double> pst;           // PST at each node (when scaled)
    double vgi = 0.0;                  // when scaled; a fraction (x 100: percent)
    double vgi_from_deg = 0.0;         // the field's directions the index sums
    double vgi_to_deg = 0.0;
    double image_flare = 0.0;          // when scaled; a fraction
    double frame_field_deg = 0.0;      // the field angle of the frame's corner
    bool image_flare_complete = false;  // the model reaches the frame's corner
    std::vector<LabFieldPoint> field;   // off axis (labFigures, when scaled)
};

// InvalidArgument for options out of range. A model without the scale is not an error (see
// LabFigures::scaled).
Result<LabFigures> labFigures(const fit::FlareModel& model,
                              const FlareFigureTable& table,
                              const LabFigureOptions& options = {});

// The VGI and the image flare of the centre flare F_c given at increasing angles theta_deg (at
// least two, >= 0), with the scale of `model`: labFigures without the table, for a centre flare
// measured elsewhere (the simulator's, in `flarelab bench predict`). pst stays empty.
// InvalidArgument for options out of range or angles that do not increase.
Result<LabFigures> labFiguresOfCentre(const fit::FlareModel& model,
                                      std::vector<double> theta_deg,
                                      std::vector<double> centre_flare,
                                      const LabFigureOptions& options = {});

// The share of a circle of radius r (mm, about the centre) that lies inside a w x h rectangle
// centred on it, as an angle in radians (2 pi: all of it; 0 for r beyond the corners).
double arcInsideFrame(double r_mm, double w_mm, double h_mm);

}  // namespace flarelab::predict
