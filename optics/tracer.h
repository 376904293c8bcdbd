// ============================================================================
//  flarelab optics: Ray, PathTracer (the exact sequential tracer)
// ============================================================================
//
// Traces real rays through a lens along one path (the imaging path or a two-reflection ghost):
// exact sphere and plane intersections, Snell refraction in vector form, mirror reflection,
// Fresnel throughput with the surfaces' coatings, clipping at every clear aperture and at the
// stop's shape, and the place where the ray crossed the stop.
//
// Accuracy: a sphere is written as c|p - v|^2 - 2 (p - v)_z = 0 around its vertex v, and the
// intersection takes the roots of the quadratic in the cancellation-free forms C / q and q / a
// (Numerical Recipes §5.6) and keeps the nearest one on the vertex's hemisphere; C / q turns into
// the plane intersection as c -> 0. The normal c(p - v) - z^ needs no centre of curvature. Radii
// from 1 mm to 1e7 mm therefore lose no digits, and flat surfaces are the same code with c = 0.
//
// Physics is not an error: a ray that misses a surface, lands outside a clear aperture, is
// blocked by the stop or totally reflected where it should refract is std::nullopt.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <span>
#include <vector>

#include "optics/lens.h"

namespace flarelab::optics {

struct Ray {
    Eigen::Vector3d position = Eigen::Vector3d::Zero();    // mm, lens space
    Eigen::Vector3d direction = Eigen::Vector3d::UnitZ();  // unit length
    double wavelength_nm = 550.0;
    double throughput = 1.0;  // fraction of the ray's power still carried at this wavelength
    bool valid = true;
};

struct TraceOptions {
    bool clip_apertures = true;  // drop rays outside a refracting surface's clear semi-aperture
    bool clip_stop = true;       // drop rays outside the stop's shape (false: only record them)
    bool fresnel = true;         // false: throughput stays 1 (geometry only)
};

struct TracedRay {
    Ray ray;              // on the image plane, with the path's throughput
    double stop_u = 0.0;  // first stop crossing, normalized by the stop semi-aperture
    double stop_v = 0.0;
    bool inside_stop = true;  // whether (stop_u, stop_v) lies in the aperture shape
    // With clip_apertures off: whether the ray passed outside some clear aperture (it would have
    // been dropped with clipping on). Always false with clipping on.
    bool cut = false;
    // The largest ratio of the ray's distance from the axis to a surface's clear semi-aperture,
    // over the refracting and reflecting surfaces it met (not the stop, not the image plane):
    // above 1 exactly when the ray is cut. The renderer interpolates it across a quad, as it
    // does the stop coordinates, to place a vignetting edge inside a grid cell.
    double aperture_ratio = 0.0;
};

class PathTracer {
public:
    // The tracer for one lens, one path and one wavelength (dispersion makes paths differ by
    // wavelength). `lens` must outlive nothing: the tracer copies what it needs.
    PathTracer(const Lens& lens,
               const GhostPath& path,
               double wavelength_nm,
               const TraceOptions& options = {});

    // Traces `ray` (its wavelength must be the tracer's) from anywhere in front of the first
    // surface to the image plane.
    std::optional<TracedRay> trace(const Ray& ray) const;

    // Traces many rays, each exactly as trace() would (the same operations in the same order,
    // so the same bits), but step by step over all of them: one ray's steps form a chain of
    // dependent square roots and divisions, while different rays at the same step are
    // independent, so the processor overlaps them. out[i] is trace(rays[i]); the spans must
    // have the same size.
    void traceBatch(std::span<const Ray> rays, std::span<std::optional<TracedRay>> out) const;

    // Traces only up to crossing `crossing` of the path (the k-th surface the light meets, as
    // numbered by pathTransfer), without any clipping or Fresnel terms, and returns the x, y
    // where the ray meets that surface (mm). For aiming rays at points of an aperture.
    std::optional<Eigen::Vector2d> traceToCrossing(int crossing,
                                                   const Eigen::Vector3d& position,
                                                   const Eigen::Vector3d& direction) const;
    std::optional<Eigen::Vector2d> traceToStop(const Eigen::Vector3d& position,
                                               const Eigen::Vector3d& direction) const {
        return traceToCrossing(first_stop_crossing_, position, direction);
    }
    int firstStopCrossing() const { return first_stop_crossing_; }
    int crossingCount() const { return static_cast<int>(steps_.size()) - 1; }

    // Ray-surface intersections one ray needs on this path (image plane included).
    int intersectionsPerRay() const { return static_cast<int>(steps_.size()); }
    double wavelength_nm() const { return wavelength_nm_; }
    const GhostPath& path() const { return path_; }

private:
    friend class RowTracer;  // row_tracer.h traces the same steps, a row of rays at a time
    enum class StepKind { Refract, Reflect, Stop, Image };
    struct Step {
        StepKind kind = StepKind::Refract;
        double z_mm = 0.0;
        double curvature = 0.0;  // as in lens space (not flipped for backward travel)
        double semi_aperture2 = 0.0;
        double n1 = 1.0;  // medium the light comes from
        double n2 = 1.0;  // medium on the other side
        bool coated = false;
        double coat_index = 1.0;
        double coat_thickness_nm = 0.0;
        bool first_stop_crossing = false;
    };
    struct RayState {
        Eigen::Vector3d p = Eigen::Vector3d::Zero();
        Eigen::Vector3d d = Eigen::Vector3d::UnitZ();
        double throughput = 1.0;
        double aperture_ratio2 = 0.0;  // squared; TracedRay::aperture_ratio at the end
        TracedRay out;
    };
    bool advance(const Step& step, RayState& r) const;
    bool stopCrossing(const Step& step, RayState& r) const;
    std::optional<TracedRay> finish(RayState& r) const;
    // Bends direction d at the surface of `step` hit at p; false on total internal reflection.
    // Writes the incidence cosine for the Fresnel terms.
    static bool bend(const Step& step, const Eigen::Vector3d& p, Eigen::Vector3d& d, double& cos_i);

    std::vector<Step> steps_;  // one per crossing, then the image plane
    int first_stop_crossing_ = -1;
    GhostPath path_;
    double wavelength_nm_;
    double stop_semi_aperture_mm_;
    ApertureShape aperture_;
    TraceOptions options_;
};

// The direction of light from a source at angle theta (radians, from the optical axis) and roll
// phi, travelling into the lens. theta = 0 gives +z whatever phi is.
Eigen::Vector3d lightDirection(double theta_rad, double phi_rad);

// Intersection of a ray with the surface of curvature c whose vertex is at z = vertex_z on the
// axis. Returns the distance along the (unit) direction to the vertex-side cap, or nullopt when
// the ray misses it or would have to travel backwards. Exposed for tests and benchmarks.
std::optional<double> intersectSurface(const Eigen::Vector3d& position,
                                       const Eigen::Vector3d& direction,
                                       double vertex_z,
                                       double curvature);

// Refracts unit direction d at a surface with unit normal n (either orientation) from index n1
// into n2; nullopt on total internal reflection.
std::optional<Eigen::Vector3d> refractDirection(const Eigen::Vector3d& d,
                                                const Eigen::Vector3d& n,
                                                double n1,
                                                double n2);

}  // namespace flarelab::optics
