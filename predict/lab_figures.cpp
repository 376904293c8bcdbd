#include "predict/lab_figures.h"

#include <algorithm>
#include <cmath>
#include <numbers>

namespace flarelab::predict {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;

// F_c at theta, linear between the table's nodes (theta inside them).
double centreAt(const std::vector<double>& theta, const std::vector<double>& value, double t) {
    const auto upper = std::upper_bound(theta.begin(), theta.end(), t);
    if (upper == theta.begin()) return value.front();
    if (upper == theta.end()) return value.back();
    const size_t i = static_cast<size_t>(upper - theta.begin()) - 1;
    const double a = (t - theta[i]) / (theta[i + 1] - theta[i]);
    return (1.0 - a) * value[i] + a * value[i + 1];
}

// integral over [from, to] (deg) of F_c(theta) sin(theta) weight(theta) d theta (radians), by the
// midpoint rule on steps a tenth of the table's or finer.
template <typename Weight>
double integrate(const LabFigures& l, double from, double to, double node_step, Weight weight) {
    if (!(to > from)) return 0.0;
    const int64_t n =
        std::max<int64_t>(16, static_cast<int64_t>(std::ceil((to - from) / (node_step / 10.0))));
    const double h = (to - from) / static_cast<double>(n);
    double sum = 0.0;
    for (int64_t k = 0; k < n; ++k) {
        const double t = from + (static_cast<double>(k) + 0.5) * h;
        sum += centreAt(l.theta_deg, l.centre_flare, t) * std::sin(t * kDeg) * weight(t);
    }
    return sum * h * kDeg;
}

double pixelArea(const fit::FlareModel& model) {
    return (model.lens.sensor_width_mm / static_cast<double>(model.capture.width_px)) *
           (model.lens.sensor_height_mm / static_cast<double>(model.capture.height_px));
}

}  // namespace

double arcInsideFrame(double r_mm, double w_mm, double h_mm) {
    if (!(r_mm > 0.0)) return 2.0 * std::numbers::pi;
    const double a = 0.5 * w_mm / r_mm, b = 0.5 * h_mm / r_mm;
    // In the first quadrant the circle is inside where cos(phi) <= a and sin(phi) <= b.
    const double quadrant = std::asin(std::min(1.0, b)) - std::acos(std::min(1.0, a));
    return 4.0 * std::max(0.0, quadrant);
}

Result<LabFigures> labFiguresOfCentre(const fit::FlareModel& model,
                                      std::vector<double> theta_deg,
                                      std::vector<double> centre_flare,
                                      const LabFigureOptions& options) {
    if (!(options.black_spot_deg > 0.0 && options.black_spot_deg <= 20.0))
        return makeError(ErrorCode::InvalidArgument,
                         "lab figures: black_spot_deg must lie in (0, 20] degrees");
    if (theta_deg.size() < 2 || theta_deg.size() != centre_flare.size() || !(theta_deg[0] >= 0.0))
        return makeError(ErrorCode::InvalidArgument,
                         "lab figures: need two or more angles >= 0, one centre value each");
    for (size_t i = 0; i < theta_deg.size(); ++i) {
        if (i > 0 && !(theta_deg[i] > theta_deg[i - 1]))
            return makeError(ErrorCode::InvalidArgument, "lab figures: angles must increase");
        if (!(std::isfinite(centre_flare[i]) && centre_flare[i] >= 0.0))
            return makeError(ErrorCode::InvalidArgument,
                             "lab figures: a centre flare is negative or not finite");
    }
    LabFigures l;
    l.theta_deg = std::move(theta_deg);
    l.centre_flare = std::move(centre_flare);
    std::vector<std::string> missing;
    if (!model.capture.light_power_dn_s) missing.push_back("capture.light_power_dn_s");
    if (!model.lens.focal_length_mm) missing.push_back("lens.focal_length_mm");
    if (!model.lens.f_number) missing.push_back("lens.f_number");
    if (!missing.empty()) {
        for (size_t i = 0; i < missing.size(); ++i)
            l.missing += (i == 0 ? "" : ", ") + missing[i];
        return l;
    }
    l.scaled = true;
    const double from = l.theta_deg.front(), to = l.theta_deg.back();
    const double node_step = (to - from) / static_cast<double>(l.theta_deg.size() - 1);
    const double f = *model.lens.focal_length_mm;
    const double w = model.lens.sensor_width_mm, h = model.lens.sensor_height_mm;
    const double scale = f * f / (pixelArea(model) * *model.capture.light_power_dn_s);
    const double spot = 0.5 * options.black_spot_deg;
    l.vgi_from_deg = std::max(spot, from);
    l.vgi_to_deg = std::max(l.vgi_from_deg, to);
    l.vgi = scale * integrate(l, l.vgi_from_deg, l.vgi_to_deg, node_step,
                              [](double) { return 2.0 * std::numbers::pi; });
    l.frame_field_deg = std::atan(0.5 * std::hypot(w, h) / f) / kDeg;
    const double chart_to = std::min(l.frame_field_deg, to);
    l.image_flare = scale * integrate(l, l.vgi_from_deg, chart_to, node_step, [&](double t) {
                        return arcInsideFrame(f * std::tan(t * kDeg), w, h);
                    });
    l.image_flare_complete = to >= l.frame_field_deg && from <= spot;
    return l;
}

Result<LabFigures> labFigures(const fit::FlareModel& model,
                              const FlareFigureTable& table,
                              const LabFigureOptions& options) {
    std::vector<double> theta, centre;
    for (int64_t i = 0; i < table.thetaCount(); ++i) {
        theta.push_back(table.thetaAt(i));
        centre.push_back(table.centreFlare(i));
    }
    auto l = labFiguresOfCentre(model, std::move(theta), std::move(centre), options);
    if (!l || !l->scaled) return l;
    // PST: the frame's mean irradiance over the pupil's, P being what the pupil passes.
    const double pupil = *model.lens.focal_length_mm / *model.lens.f_number;
    const double pupil_area = std::numbers::pi * pupil * pupil / 4.0;
    for (int64_t i = 0; i < table.thetaCount(); ++i)
        l->pst.push_back(table.node(i, 0).mean / pixelArea(model) /
                         (*model.capture.light_power_dn_s / pupil_area));

    // Off axis: every node's light, at theta_i and roll phi_j, images at
    // f tan(theta_i) (cos phi_j, sin phi_j); the spot hides those within half its diameter of
    // the point's own direction, and the chart holds those whose image lies in the frame.
    const double f = *model.lens.focal_length_mm;
    const double w = model.lens.sensor_width_mm, h = model.lens.sensor_height_mm;
    const double scale = f * f / (pixelArea(model) * *model.capture.light_power_dn_s);
    const double cos_spot = std::cos(0.5 * options.black_spot_deg * kDeg);
    const int64_t n = table.thetaCount(), m = table.phiCount();
    const double dphi = 2.0 * std::numbers::pi / static_cast<double>(m);
    for (size_t k = 0; k < table.fieldPoints().size(); ++k) {
        LabFieldPoint point;
        point.height = table.fieldPoints()[k];
        const double px = point.height * 0.5 * w, py = point.height * 0.5 * h;
        const double norm = std::sqrt(px * px + py * py + f * f);
        const double dx = px / norm, dy = py / norm, dz = f / norm;
        point.field_deg = std::acos(dz) / kDeg;
        double veil = 0.0, chart = 0.0;
        for (int64_t i = 0; i < n; ++i) {
            const double t = table.thetaAt(i) * kDeg;
            const double lo = i > 0 ? table.thetaAt(i - 1) : table.thetaAt(i);
            const double hi = i + 1 < n ? table.thetaAt(i + 1) : table.thetaAt(i);
            const double weight = std::sin(t) * 0.5 * (hi - lo) * kDeg * dphi;
            for (int64_t j = 0; j < m; ++j) {
                const double phi = table.phiAt(j) * kDeg;
                const double c = std::cos(phi), s = std::sin(phi);
                const double cos_to_point =
                    std::sin(t) * c * dx + std::sin(t) * s * dy + std::cos(t) * dz;
                if (cos_to_point >= cos_spot) continue;  // behind the black spot
                const double v = table.fieldFlare(k, i, j) * weight;
                veil += v;
                const double r = f * std::tan(t);
                if (std::abs(r * c) <= 0.5 * w && std::abs(r * s) <= 0.5 * h) chart += v;
            }
        }
        const double white = std::pow(dz, 4.0);  // cos^4 of the field angle
        point.vgi = scale * veil / white;
        point.image_flare = scale * chart / white;
        l->field.push_back(point);
    }
    return l;
}

}  // namespace flarelab::predict
