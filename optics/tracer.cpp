#include "optics/tracer.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

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

// Records the first stop crossing; false when the stop clips the ray.
bool PathTracer::stopCrossing(const Step& step, RayState& r) const {
    if (step.first_stop_crossing) {
        r.out.stop_u = r.p.x() / stop_semi_aperture_mm_;
        r.out.stop_v = r.p.y() / stop_semi_aperture_mm_;
        r.out.inside_stop = aperture_.contains(r.out.stop_u, r.out.stop_v);
        if (options_.clip_stop && !r.out.inside_stop) return false;
    } else if (options_.clip_stop) {
        const double u = r.p.x() / stop_semi_aperture_mm_;
        const double v = r.p.y() / stop_semi_aperture_mm_;
        if (!aperture_.contains(u, v)) return false;
    }
    return true;
}

// One step of one ray: what trace() does for `step`, on the ray's running state. false when the
// ray ends there (missed the surface, clipped, totally reflected).
bool PathTracer::advance(const Step& step, RayState& r) const {
    const std::optional<double> t = intersectSurface(r.p, r.d, step.z_mm, step.curvature);
    if (!t) return false;
    r.p += *t * r.d;
    if (step.kind == StepKind::Image) return true;
    const double r2 = r.p.x() * r.p.x() + r.p.y() * r.p.y();
    if (step.kind == StepKind::Stop) return stopCrossing(step, r);
    r.aperture_ratio2 = std::max(r.aperture_ratio2, r2 / step.semi_aperture2);
    if (r2 > step.semi_aperture2) {
        if (options_.clip_apertures) return false;
        r.out.cut = true;
    }
    double cos_i = 1.0;
    if (!bend(step, r.p, r.d, cos_i)) return false;  // total internal reflection
    if (options_.fresnel) {
        const FresnelResult f =
            step.coated ? fresnelCoated(step.n1, step.coat_index, step.coat_thickness_nm, step.n2,
                                        cos_i, wavelength_nm_)
                        : fresnelUncoated(step.n1, step.n2, cos_i);
        r.throughput *= step.kind == StepKind::Reflect ? f.reflectance : f.transmittance;
    }
    return true;
}

std::optional<TracedRay> PathTracer::finish(RayState& r) const {
    r.out.ray.position = r.p;
    r.out.ray.direction = r.d;
    r.out.ray.wavelength_nm = wavelength_nm_;
    r.out.ray.throughput = r.throughput;
    r.out.aperture_ratio = std::sqrt(r.aperture_ratio2);
    r.out.ray.valid =
        std::isfinite(r.p.x()) && std::isfinite(r.p.y()) && std::isfinite(r.throughput);
    if (!r.out.ray.valid) return std::nullopt;
    return r.out;
}

std::optional<TracedRay> PathTracer::trace(const Ray& input) const {
    FLARELAB_DCHECK(input.wavelength_nm == wavelength_nm_);
    if (!input.valid) return std::nullopt;
    RayState r{input.position, input.direction, input.throughput, 0.0, {}};
    for (const Step& step : steps_)
        if (!advance(step, r)) return std::nullopt;
    return finish(r);
}

void PathTracer::traceBatch(std::span<const Ray> rays,
                            std::span<std::optional<TracedRay>> out) const {
    FLARELAB_CHECK_EQ(rays.size(), out.size());
    std::vector<RayState> state(rays.size());
    std::vector<uint32_t> alive;
    alive.reserve(rays.size());
    for (size_t i = 0; i < rays.size(); ++i) {
        FLARELAB_DCHECK(rays[i].wavelength_nm == wavelength_nm_);
        out[i].reset();
        if (!rays[i].valid) continue;
        state[i] = RayState{rays[i].position, rays[i].direction, rays[i].throughput, 0.0, {}};
        alive.push_back(static_cast<uint32_t>(i));
    }
    // Each step in phases over all live rays (intersect, clip, bend, Fresnel): short loops of
    // independent iterations that the processor overlaps; per ray the operations are trace()'s.
    std::vector<double> cos_i(rays.size());
    for (const Step& step : steps_) {
        size_t kept = 0;
        for (const uint32_t i : alive) {
            RayState& r = state[i];
            const std::optional<double> t = intersectSurface(r.p, r.d, step.z_mm, step.curvature);
            if (!t) continue;
            r.p += *t * r.d;
            alive[kept++] = i;
        }
        alive.resize(kept);
        if (step.kind == StepKind::Image) break;
        if (step.kind == StepKind::Stop) {
            kept = 0;
            for (const uint32_t i : alive)
                if (stopCrossing(step, state[i])) alive[kept++] = i;
            alive.resize(kept);
            continue;
        }
        kept = 0;
        for (const uint32_t i : alive) {
            RayState& r = state[i];
            const double r2 = r.p.x() * r.p.x() + r.p.y() * r.p.y();
            r.aperture_ratio2 = std::max(r.aperture_ratio2, r2 / step.semi_aperture2);
            if (r2 > step.semi_aperture2) {
                if (options_.clip_apertures) continue;
                r.out.cut = true;
            }
            double c = 1.0;
            if (!bend(step, r.p, r.d, c)) continue;  // total internal reflection
            cos_i[i] = c;
            alive[kept++] = i;
        }
        alive.resize(kept);
        if (!options_.fresnel) continue;
        if (step.coated) {
            for (const uint32_t i : alive) {
                const FresnelResult f =
                    fresnelCoated(step.n1, step.coat_index, step.coat_thickness_nm, step.n2,
                                  cos_i[i], wavelength_nm_);
                state[i].throughput *=
                    step.kind == StepKind::Reflect ? f.reflectance : f.transmittance;
            }
        } else {
            for (const uint32_t i : alive) {
                const FresnelResult f = fresnelUncoated(step.n1, step.n2, cos_i[i]);
                state[i].throughput *=
                    step.kind == StepKind::Reflect ? f.reflectance : f.transmittance;
            }
        }
    }
    for (const uint32_t i : alive) out[i] = finish(state[i]);
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
