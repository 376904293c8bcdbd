// ============================================================================
//  flarelab optics: RowTracer, FresnelPolynomial
// ============================================================================
//
// The ray grid's tracer (ray_grid.h): one path at one wavelength, a row of parallel rays at a
// time, held as a structure of arrays so that every step of the path is a loop of independent
// lanes the compiler turns into SIMD code (AVX2 where the processor has it, chosen at run time,
// SSE2 otherwise; the same source). It does what PathTracer does with clear apertures and the
// stop recorded but not clipped, the mode the ray grid traces in, and differs from it in three
// ways, each measured (bench/optics_bench.cpp, tests/optics/row_tracer_test.cpp):
//   - precision: float lanes by default (double on request). The intersection keeps each ray's z
//     relative to the vertex of the surface it heads for, so no coordinate grows with the lens's
//     length, and the quadratic is PathTracer's cancellation-free form;
//   - double lanes do not normalize directions again after a reflection or a refraction (with
//     unit normal and unit direction both keep unit length in exact arithmetic); float lanes do,
//     after every bend: the intersection's quadratic assumes a unit direction, and float's drift
//     in the length, some 1e-7 a bend, moved a ray's sensor position by up to 1e-4 mm over a long
//     path (renormalizing cut the rays of a Canon 200 frame that had to be traced in double
//     from 3.4 M to 1.8 M, and the worst float error over every shipped lens from 0.0078 px to
//     0.0067 px);
//   - a coated surface's reflectance is a Chebyshev polynomial in the incidence cosine, fitted per
//     surface and wavelength to the exact thin-film formula (fresnel.h) on the cosines where that
//     formula is smooth; below the fitted range (near total or frustrated internal reflection)
//     the exact formula is called for the lanes that land there. The transmittance is 1 - R
//     (the layer does not absorb).
// Aiming and fitting stay on PathTracer (double): Newton's method needs its derivatives clean.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <utility>
#include <vector>

#include "optics/lens.h"

namespace flarelab::optics {

// A coated surface's reflectance R(cos_i) as a Chebyshev series on [lo, 1], and how far it is
// from the exact formula there (the largest |R_poly - R_exact| found on a dense check, and that
// over the smallest R of the range).
struct FresnelPolynomial {
    double lo = 1.0;                   // below this cosine the exact formula is used
    std::vector<double> coefficients;  // Chebyshev coefficients in x = (2 cos - 1 - lo) / (1 - lo)
    double max_abs_error = 0.0;
    double max_rel_error = 0.0;

    double operator()(double cos_i) const;
};

// Fits R for the coating (n_coat, d_coat_nm) between media n1 and n2 at `wavelength_nm` to
// within `relative_tolerance` of the smallest R on the range, wherever it is used: the degree
// grows (up to 36) and, if that is not enough, the range's lower end rises towards 1 until it is
// met. A ghost's power is a product of reflectances, so the relative error is what reaches it.
// The range starts at min_lo at the least (0: wherever the formula is smooth): a narrower range
// needs a lower degree.
FresnelPolynomial fitCoatedReflectance(double n1,
                                       double n_coat,
                                       double d_coat_nm,
                                       double n2,
                                       double wavelength_nm,
                                       double relative_tolerance = 1e-5,
                                       double min_lo = 0.0);

// One traced row, as the ray grid keeps it. status: 0 no geometry (missed a surface, totally
// reflected, not finite), 1 reached the sensor inside every clear aperture, 2 reached it but left
// some clear aperture on the way (traced on as if the lens were wider).
struct TracedRow {
    std::vector<double> x_mm, y_mm;      // on the sensor plane
    std::vector<double> throughput;      // with Fresnel terms (1 without)
    std::vector<double> stop_u, stop_v;  // first stop crossing / stop semi-aperture
    std::vector<double> aperture_ratio;  // largest r / clear semi-aperture along the path
    std::vector<uint8_t> status;

    void resize(size_t n);
};

class RowTracer {
public:
    enum class Precision { Float, Double };
    struct Options {
        Precision precision = Precision::Float;
        bool fresnel = true;
        bool allow_avx2 = true;  // false: the SSE2 build even where AVX2 runs (for comparison)
        double fresnel_tolerance = 1e-5;  // relative, see fitCoatedReflectance
    };

    RowTracer(const Lens& lens,
              const GhostPath& path,
              double wavelength_nm,
              const Options& options);

    // Traces the rays of direction `direction` (unit length) starting at (x[i], y[i], z) in lens
    // space, in front of the first surface. x and y have the same size; `out` is resized to it.
    void trace(std::span<const double> x,
               std::span<const double> y,
               double z,
               const Eigen::Vector3d& direction,
               TracedRow& out) const;

    // Traces the probe rays in float and in double and keeps float for trace() only if no ray
    // with geometry in both lands more than `tolerance_mm` apart, nor moves its stop coordinates
    // by more than that at the scale of the footprint (the stop edge's shift on the sensor).
    // Ghost paths that magnify rounding, e.g. a strongly defocused ghost of a simple lens, get
    // double. Returns the precision chosen and the largest such distance.
    // It also narrows each coated surface's fitted range to the probe's incidence cosines there
    // (narrowCoatings): a lower degree for every lane after.
    std::pair<Precision, double> choosePrecision(std::span<const double> x,
                                                 std::span<const double> y,
                                                 double z,
                                                 const Eigen::Vector3d& direction,
                                                 double tolerance_mm);
    Precision precision() const { return options_.precision; }
    void setPrecision(Precision precision) { options_.precision = precision; }

    // Refits each coated crossing's reflectance on [c - margin, 1] rounded down to 1/32, c being
    // min_cos[step] (one per step, as traced by a probe), where that is narrower than its range:
    // a lower degree for every lane. Lanes that still come below the range take the exact formula.
    static constexpr double kCoatingMargin = 0.05;
    void narrowCoatings(std::span<const double> min_cos);

    // Whether trace() runs the AVX2 build on this processor with these options.
    bool usesAvx2() const;
    // The fitted reflectance of each coated crossing, in path order (for the record and tests).
    const std::vector<FresnelPolynomial>& coatings() const { return coatings_; }

    struct Step {
        enum Kind : uint8_t { Refract, Reflect, Stop, Image } kind = Refract;
        double shift_mm = 0.0;  // this vertex's z minus the previous one's (first: minus 0)
        double curvature = 0.0;
        double semi_aperture2 = 0.0;
        double inv_semi_aperture2 = 0.0;
        double eta = 1.0;  // n1 / n2
        bool same_medium = true;
        bool first_stop_crossing = false;
        bool coated = false;
        int coating = -1;  // index into coatings_
        double n1 = 1.0, n2 = 1.0, coat_index = 1.0, coat_thickness_nm = 0.0;
    };

private:
    void traceRecording(std::span<const double> x,
                        std::span<const double> y,
                        double z,
                        const Eigen::Vector3d& direction,
                        TracedRow& out,
                        double* min_cos) const;

    std::vector<Step> steps_;
    std::vector<FresnelPolynomial> coatings_;
    double wavelength_nm_;
    double inv_stop_semi_aperture_;
    double first_vertex_z_mm_ = 0.0;
    Options options_;
};

}  // namespace flarelab::optics
