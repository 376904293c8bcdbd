#include "optics/tracer.h"

#include <cmath>

#include "common/check.h"
#include "optics/fresnel.h"

namespace flarelab::optics {

Eigen::Vector3d lightDirection(double theta_rad, double phi_rad) {
    const double s = std::sin(theta_rad);
    return {s * std::cos(phi_rad), s * std::sin(phi_rad), std::cos(theta_rad)};
}

std::optional<double> intersectSurface(const Eigen::Vector3d& position,
                                       const Eigen::Vector3d& direction,
                                       double vertex_z,
                                       double curvature) {
    const Eigen::Vector3d p(position.x(), position.y(), position.z() - vertex_z);
    const Eigen::Vector3d& d = direction;
    if (curvature == 0.0) {
        if (d.z() == 0.0) return std::nullopt;
        const double t = -p.z() / d.z();
        if (!(t >= 0.0)) return std::nullopt;
        return t;
    }
    // c t^2 + 2 b t + k = 0 with b = c (p.d) - d_z and k = c |p|^2 - 2 p_z.
    const double c = curvature;
    const double b = c * p.dot(d) - d.z();
    const double k = c * p.squaredNorm() - 2.0 * p.z();
    const double disc = b * b - c * k;
    if (!(disc >= 0.0)) return std::nullopt;
    const double q = -(b + std::copysign(std::sqrt(disc), b));
    if (q == 0.0) return std::nullopt;
    // Both roots without cancellation; keep the nearest one ahead of the ray that lies on the
    // vertex's hemisphere, where the surface normal c(p - v) - z^ still points backwards
    // (c z < 1). For a ray starting nearer the vertex than the centre of curvature that is k / q;
    // from beyond the centre (a strongly curved surface far ahead) it can be q / c.
    const double roots[2] = {k / q, q / c};
    std::optional<double> best;
    for (const double t : roots) {
        if (!(t >= 0.0)) continue;
        const double hit_z = p.z() + t * d.z();
        if (!(c * hit_z < 1.0)) continue;
        if (!best || t < *best) best = t;
    }
    return best;
}

std::optional<Eigen::Vector3d> refractDirection(const Eigen::Vector3d& d,
                                                const Eigen::Vector3d& n,
                                                double n1,
                                                double n2) {
    double cos_i = -n.dot(d);
    Eigen::Vector3d normal = n;
    if (cos_i < 0.0) {
        cos_i = -cos_i;
        normal = -n;
    }
    const double eta = n1 / n2;
    const double k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    if (k < 0.0) return std::nullopt;
    const Eigen::Vector3d t = eta * d + (eta * cos_i - std::sqrt(k)) * normal;
    return t.normalized();
}

PathTracer::PathTracer(const Lens& lens,
                       const GhostPath& path,
                       double wavelength_nm,
                       const TraceOptions& options)
    : path_(path),
      wavelength_nm_(wavelength_nm),
      stop_semi_aperture_mm_(lens.surfaces()[lens.stopIndex()].semi_aperture_mm),
      aperture_(lens.aperture()),
      options_(options) {
    FLARELAB_CHECK(lens.isValidPath(path));
    FLARELAB_CHECK_GT(wavelength_nm, 0.0);
    const auto& s = lens.surfaces();
    const int n = static_cast<int>(s.size());
    bool stop_seen = false;
    const auto add = [&](int k, StepKind kind, double n1, double n2) {
        Step step;
        step.kind = s[k].is_stop ? StepKind::Stop : kind;
        step.z_mm = s[k].z_mm;
        step.curvature = s[k].curvature;
        step.semi_aperture2 = s[k].semi_aperture_mm * s[k].semi_aperture_mm;
        step.n1 = n1;
        step.n2 = n2;
        if (s[k].is_stop && !stop_seen) {
            step.first_stop_crossing = true;
            stop_seen = true;
            first_stop_crossing_ = static_cast<int>(steps_.size());
        }
        if (!s[k].is_stop && s[k].coating_wavelength_nm > 0.0) {
            const double design = s[k].coating_wavelength_nm;
            const QuarterWaveCoating coat = designQuarterWaveCoating(
                lens.mediumIndex(k - 1, design), lens.mediumIndex(k, design), design);
            step.coated = true;
            step.coat_index = coat.index;
            step.coat_thickness_nm = coat.thickness_nm;
        }
        steps_.push_back(step);
    };
    const auto index = [&](int k) { return lens.mediumIndex(k, wavelength_nm); };
    const int forward_end = path.isImaging() ? n - 1 : path.second;
    for (int k = 0; k <= forward_end; ++k)
        add(k, k == path.second ? StepKind::Reflect : StepKind::Refract, index(k - 1), index(k));
    if (!path.isImaging()) {
        for (int k = path.second - 1; k >= path.first; --k)
            add(k, k == path.first ? StepKind::Reflect : StepKind::Refract, index(k), index(k - 1));
        for (int k = path.first + 1; k < n; ++k) add(k, StepKind::Refract, index(k - 1), index(k));
    }
    Step image;
    image.kind = StepKind::Image;
    image.z_mm = lens.sensorZ_mm();
    steps_.push_back(image);
}

std::optional<TracedRay> PathTracer::trace(const Ray& input) const {
    FLARELAB_DCHECK(input.wavelength_nm == wavelength_nm_);
    if (!input.valid) return std::nullopt;
    TracedRay out;
    Eigen::Vector3d p = input.position;
    Eigen::Vector3d d = input.direction;
    double throughput = input.throughput;
    for (const Step& step : steps_) {
        const std::optional<double> t = intersectSurface(p, d, step.z_mm, step.curvature);
        if (!t) return std::nullopt;
        p += *t * d;
        if (step.kind == StepKind::Image) break;
        const double r2 = p.x() * p.x() + p.y() * p.y();
        if (step.kind == StepKind::Stop) {
            if (step.first_stop_crossing) {
                out.stop_u = p.x() / stop_semi_aperture_mm_;
                out.stop_v = p.y() / stop_semi_aperture_mm_;
                out.inside_stop = aperture_.contains(out.stop_u, out.stop_v);
                if (options_.clip_stop && !out.inside_stop) return std::nullopt;
            } else if (options_.clip_stop) {
                const double u = p.x() / stop_semi_aperture_mm_;
                const double v = p.y() / stop_semi_aperture_mm_;
                if (!aperture_.contains(u, v)) return std::nullopt;
            }
            continue;
        }
        if (r2 > step.semi_aperture2) {
            if (options_.clip_apertures) return std::nullopt;
            out.cut = true;
        }
        double cos_i = 1.0;
        if (!bend(step, p, d, cos_i)) return std::nullopt;  // total internal reflection
        if (options_.fresnel) {
            const FresnelResult f =
                step.coated ? fresnelCoated(step.n1, step.coat_index, step.coat_thickness_nm,
                                            step.n2, cos_i, wavelength_nm_)
                            : fresnelUncoated(step.n1, step.n2, cos_i);
            throughput *= step.kind == StepKind::Reflect ? f.reflectance : f.transmittance;
        }
    }
    out.ray.position = p;
    out.ray.direction = d;
    out.ray.wavelength_nm = wavelength_nm_;
    out.ray.throughput = throughput;
    out.ray.valid = std::isfinite(p.x()) && std::isfinite(p.y()) && std::isfinite(throughput);
    if (!out.ray.valid) return std::nullopt;
    return out;
}

bool PathTracer::bend(const Step& step,
                      const Eigen::Vector3d& p,
                      Eigen::Vector3d& d,
                      double& cos_i) {
    // Unit normal of c|p - v|^2 - 2 (p - v)_z = 0, turned to face the incoming light.
    Eigen::Vector3d normal(step.curvature * p.x(), step.curvature * p.y(),
                           step.curvature * (p.z() - step.z_mm) - 1.0);
    normal.normalize();
    if (normal.dot(d) > 0.0) normal = -normal;
    cos_i = std::min(1.0, -normal.dot(d));
    if (step.kind == StepKind::Reflect) {
        d = (d + 2.0 * cos_i * normal).normalized();
        return true;
    }
    if (step.n1 == step.n2) return true;
    const std::optional<Eigen::Vector3d> refracted = refractDirection(d, normal, step.n1, step.n2);
    if (!refracted) return false;
    d = *refracted;
    return true;
}

std::optional<Eigen::Vector2d> PathTracer::traceToCrossing(int crossing,
                                                           const Eigen::Vector3d& position,
                                                           const Eigen::Vector3d& direction) const {
    if (crossing < 0 || crossing >= crossingCount()) return std::nullopt;
    Eigen::Vector3d p = position;
    Eigen::Vector3d d = direction;
    for (int k = 0; k <= crossing; ++k) {
        const Step& step = steps_[k];
        const std::optional<double> t = intersectSurface(p, d, step.z_mm, step.curvature);
        if (!t) return std::nullopt;
        p += *t * d;
        if (k == crossing) return Eigen::Vector2d(p.x(), p.y());
        double cos_i = 1.0;
        if (step.kind != StepKind::Stop && !bend(step, p, d, cos_i)) return std::nullopt;
    }
    return std::nullopt;
}

}  // namespace flarelab::optics
