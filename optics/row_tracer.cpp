#include "optics/row_tracer.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <mutex>
#include <optional>
#include <type_traits>

#include "common/check.h"
#include "common/cpu.h"
#include "common/units.h"
#include "optics/fresnel.h"
#include "optics/tracer.h"

namespace flarelab::optics {

// ---- Fresnel polynomial --------------------------------------------------------------------

namespace {

// A Chebyshev series at x in [-1, 1] (Clenshaw); c is not empty.
double chebyshevAt(const std::vector<double>& c, double x) {
    double b1 = 0.0, b2 = 0.0;
    for (size_t k = c.size() - 1; k >= 1; --k) {
        const double b0 = 2.0 * x * b1 - b2 + c[k];
        b2 = b1;
        b1 = b0;
    }
    return x * b1 - b2 + c[0];
}

}  // namespace

double FresnelPolynomial::operator()(double cos_i) const {
    FLARELAB_CHECK(!coefficients.empty());
    return chebyshevAt(coefficients, (2.0 * cos_i - 1.0 - lo) / (1.0 - lo));
}

namespace {

// Chebyshev interpolation of f on [lo, 1] at degree d (nodes of the first kind):
// c_k = (2 - [k = 0]) / m sum_j f(x_j) T_k(x_j), with T_k(x_j) from the three-term recurrence
// (m cosines instead of m^2; |T_k| <= 1, so its rounding grows only as k).
std::vector<double> chebyshevFit(const auto& f, double lo, int degree) {
    const int m = degree + 1;
    std::vector<double> c(static_cast<size_t>(m), 0.0);
    for (int j = 0; j < m; ++j) {
        const double x = std::cos(kPi * (j + 0.5) / m);
        const double value = f(0.5 * (1.0 + lo) + 0.5 * (1.0 - lo) * x);
        double previous = 1.0, t = x;
        c[0] += value;
        if (m > 1) c[1] += value * x;
        for (int k = 2; k < m; ++k) {
            const double next = 2.0 * x * t - previous;
            previous = t;
            t = next;
            c[static_cast<size_t>(k)] += value * t;
        }
    }
    for (int k = 0; k < m; ++k) c[static_cast<size_t>(k)] *= (k == 0 ? 1.0 : 2.0) / m;
    return c;
}

}  // namespace

FresnelPolynomial fitCoatedReflectance(double n1,
                                       double n_coat,
                                       double d_coat_nm,
                                       double n2,
                                       double wavelength_nm,
                                       double relative_tolerance,
                                       double min_lo) {
    const auto exact = [&](double c) {
        return fresnelCoated(n1, n_coat, d_coat_nm, n2, c, wavelength_nm).reflectance;
    };
    // The formula has kinks where the wave stops propagating in the layer or in the far medium
    // (sin = n/n1); above the larger of those cosines it is smooth.
    double kink = 0.0;
    for (const double n : {n_coat, n2})
        if (n1 > n) kink = std::max(kink, std::sqrt(std::max(0.0, 1.0 - (n / n1) * (n / n1))));
    constexpr int kCheck = 1024;
    std::vector<double> exact_values(kCheck + 1), check_x(kCheck + 1);
    for (int i = 0; i <= kCheck; ++i) check_x[i] = 2.0 * i / kCheck - 1.0;
    for (double lo = std::max(kink, std::clamp(min_lo, 0.0, 0.99)); lo < 0.999;
         lo += 0.1 * (1.0 - lo)) {
        // A ghost's power is a product of reflectances: the error that matters is relative to
        // the smallest R on the range (an AR coating between two glasses reflects 1e-5).
        double smallest = 1.0;
        for (int i = 0; i <= kCheck; ++i) {
            exact_values[i] = exact(lo + (1.0 - lo) * i / kCheck);
            smallest = std::min(smallest, exact_values[i]);
        }
        const double tolerance = std::max(1e-13, relative_tolerance * smallest);
        // The polynomial of `degree` when it meets the tolerance on the dense check.
        const auto fit = [&](int degree) -> std::optional<FresnelPolynomial> {
            FresnelPolynomial p;
            p.lo = lo;
            p.coefficients = chebyshevFit(exact, lo, degree);
            double worst = 0.0;
            // The check points' x = (2 cos - 1 - lo) / (1 - lo) are 2 i / kCheck - 1.
            for (int i = 0; i <= kCheck && worst <= tolerance; ++i)
                worst = std::max(worst, std::abs(chebyshevAt(p.coefficients, check_x[i]) -
                                                 exact_values[i]));
            if (worst > tolerance) return std::nullopt;
            p.max_abs_error = worst;
            p.max_rel_error = worst / std::max(smallest, 1e-300);
            return p;
        };
        // Every lane pays for each degree at every coated surface: the first passing degree in
        // steps of 6, then the lowest below it that passes too (bisection; the error falls
        // with the degree, and whatever is returned has passed the check).
        for (int degree = 6; degree <= 36; degree += 6) {
            std::optional<FresnelPolynomial> best = fit(degree);
            if (!best) continue;
            int fails = degree - 6, passes = degree;  // fails: a degree known (or taken) to fail
            while (passes - fails > 1) {
                const int mid = (fails + passes) / 2;
                if (auto p = fit(mid)) {
                    best = std::move(p);
                    passes = mid;
                } else {
                    fails = mid;
                }
            }
            return *best;
        }
    }
    // Not even near normal incidence: no polynomial, the exact formula everywhere.
    FresnelPolynomial none;
    none.lo = 2.0;
    none.coefficients = {0.0};
    return none;
}

namespace {

// Fits are shared: every path of a lens crosses the same coated surfaces, in one direction or
// the other, at the same three wavelengths.
struct FitKey {
    double n1, n_coat, d_coat_nm, n2, wavelength_nm, tolerance, min_lo;
    auto operator<=>(const FitKey&) const = default;
};

FresnelPolynomial cachedFit(const FitKey& key) {
    static std::mutex mutex;
    static std::map<FitKey, FresnelPolynomial> fits;
    {
        const std::lock_guard<std::mutex> lock(mutex);
        const auto it = fits.find(key);
        if (it != fits.end()) return it->second;
    }
    FresnelPolynomial fit = fitCoatedReflectance(key.n1, key.n_coat, key.d_coat_nm, key.n2,
                                                 key.wavelength_nm, key.tolerance, key.min_lo);
    const std::lock_guard<std::mutex> lock(mutex);
    if (fits.size() > 4096) fits.clear();  // a long-running process tracing many lenses
    return fits.emplace(key, std::move(fit)).first->second;
}

}  // namespace

void TracedRow::resize(size_t n) {
    for (auto* v : {&x_mm, &y_mm, &throughput, &stop_u, &stop_v, &aperture_ratio}) v->resize(n);
    status.resize(n);
}

// ---- the lane kernel -----------------------------------------------------------------------

namespace {

// The running state of a row, one array per quantity (structure of arrays).
template <typename T>
struct Lanes {
    std::vector<T> px, py, pz, dx, dy, dz, throughput, alive, cut, ratio2, stop_u, stop_v, cos_i;
    std::vector<double> factor;  // the coated reflectance is summed in double
    explicit Lanes(size_t n)
        : px(n),
          py(n),
          pz(n),
          dx(n),
          dy(n),
          dz(n),
          throughput(n, T(1)),
          alive(n, T(1)),
          cut(n, T(0)),
          ratio2(n, T(0)),
          stop_u(n, T(0)),
          stop_v(n, T(0)),
          cos_i(n, T(0)),
          factor(n) {}
};

struct KernelInput {
    const RowTracer::Step* steps;
    size_t step_count;
    const FresnelPolynomial* coatings;
    bool fresnel;
    double inv_stop_semi_aperture;
    double wavelength_nm;
    double* min_cos = nullptr;  // when set: per step, the smallest incidence cosine of a live lane
};

// Every step as loops over the lanes with no branch that depends on a lane: dead lanes compute on
// and are masked by `alive`, so each loop vectorizes.
template <typename T>
[[gnu::always_inline]] inline void traceLanes(const KernelInput& in, size_t n, Lanes<T>& w) {
    T* __restrict px = w.px.data();
    T* __restrict py = w.py.data();
    T* __restrict pz = w.pz.data();
    T* __restrict dx = w.dx.data();
    T* __restrict dy = w.dy.data();
    T* __restrict dz = w.dz.data();
    T* __restrict thr = w.throughput.data();
    T* __restrict alive = w.alive.data();
    T* __restrict cut = w.cut.data();
    T* __restrict ratio2 = w.ratio2.data();
    T* __restrict cosi = w.cos_i.data();
    double* __restrict factor = w.factor.data();
    for (size_t k = 0; k < in.step_count; ++k) {
        const RowTracer::Step& s = in.steps[k];
        const T shift = static_cast<T>(s.shift_mm);
        const T c = static_cast<T>(s.curvature);
        // Intersect and move; z is kept relative to this step's vertex.
        if (s.curvature == 0.0) {
#pragma GCC ivdep
            for (size_t i = 0; i < n; ++i) {
                const T z = pz[i] - shift;
                const T t = -z / dz[i];
                const bool ok = (dz[i] != T(0)) & (t >= T(0));
                const T tt = ok ? t : T(0);
                alive[i] = ok ? alive[i] : T(0);
                px[i] += tt * dx[i];
                py[i] += tt * dy[i];
                pz[i] = z + tt * dz[i];
            }
        } else {
            const T inv_c = T(1) / c;
#pragma GCC ivdep
            for (size_t i = 0; i < n; ++i) {
                const T z = pz[i] - shift;
                const T b = c * (px[i] * dx[i] + py[i] * dy[i] + z * dz[i]) - dz[i];
                const T kq = c * (px[i] * px[i] + py[i] * py[i] + z * z) - T(2) * z;
                const T disc = b * b - c * kq;
                const T root = std::sqrt(disc >= T(0) ? disc : T(0));
                const T q = -(b + (b >= T(0) ? root : -root));
                const T t1 = kq / q;
                const T t2 = q * inv_c;
                const bool ok1 = (t1 >= T(0)) & (c * (z + t1 * dz[i]) < T(1));
                const bool ok2 = (t2 >= T(0)) & (c * (z + t2 * dz[i]) < T(1));
                const T t = ok1 ? (ok2 ? std::min(t1, t2) : t1) : t2;
                const bool ok = (disc >= T(0)) & (q != T(0)) & (ok1 | ok2);
                const T tt = ok ? t : T(0);
                alive[i] = ok ? alive[i] : T(0);
                px[i] += tt * dx[i];
                py[i] += tt * dy[i];
                pz[i] = z + tt * dz[i];
            }
        }
        if (s.kind == RowTracer::Step::Image) break;
        if (s.kind == RowTracer::Step::Stop) {
            if (s.first_stop_crossing) {
                const T inv = static_cast<T>(in.inv_stop_semi_aperture);
#pragma GCC ivdep
                for (size_t i = 0; i < n; ++i) {
                    w.stop_u[i] = px[i] * inv;
                    w.stop_v[i] = py[i] * inv;
                }
            }
            continue;
        }
        // Clear aperture (recorded, not clipped), then the bend.
        const T semi2 = static_cast<T>(s.semi_aperture2);
        const T inv_semi2 = static_cast<T>(s.inv_semi_aperture2);
        const T eta = static_cast<T>(s.eta);
        const T eta2 = eta * eta;
        const bool reflect = s.kind == RowTracer::Step::Reflect;
        const bool refract = !reflect && !s.same_medium;
#pragma GCC ivdep
        for (size_t i = 0; i < n; ++i) {
            const T r2 = px[i] * px[i] + py[i] * py[i];
            ratio2[i] = std::max(ratio2[i], r2 * inv_semi2);
            cut[i] = r2 > semi2 ? T(1) : cut[i];
            T nx = c * px[i], ny = c * py[i], nz = c * pz[i] - T(1);
            const T inv_len = T(1) / std::sqrt(nx * nx + ny * ny + nz * nz);
            const T nd = (nx * dx[i] + ny * dy[i] + nz * dz[i]) * inv_len;
            const T sign = nd > T(0) ? -inv_len : inv_len;  // face the incoming light
            nx *= sign;
            ny *= sign;
            nz *= sign;
            const T ci = std::min(T(1), nd > T(0) ? nd : -nd);
            cosi[i] = ci;
            if (reflect) {
                const T f = T(2) * ci;
                dx[i] += f * nx;
                dy[i] += f * ny;
                dz[i] += f * nz;
            } else if (refract) {
                const T kk = T(1) - eta2 * (T(1) - ci * ci);
                const bool ok = kk >= T(0);
                const T f = eta * ci - std::sqrt(ok ? kk : T(0));
                alive[i] = ok ? alive[i] : T(0);
                dx[i] = eta * dx[i] + f * nx;
                dy[i] = eta * dy[i] + f * ny;
                dz[i] = eta * dz[i] + f * nz;
            }
        }
        if (in.min_cos) {
            T least = T(1);
            for (size_t i = 0; i < n; ++i)
                least = alive[i] != T(0) ? std::min(least, cosi[i]) : least;
            in.min_cos[k] = std::min(in.min_cos[k], static_cast<double>(least));
        }
        if constexpr (std::is_same_v<T, float>) {
            if (reflect || refract) {
#pragma GCC ivdep
                for (size_t i = 0; i < n; ++i) {
                    const T inv = T(1) / std::sqrt(dx[i] * dx[i] + dy[i] * dy[i] + dz[i] * dz[i]);
                    dx[i] *= inv;
                    dy[i] *= inv;
                    dz[i] *= inv;
                }
            }
        }
        if (!in.fresnel) continue;
        if (!s.coated) {
            // fresnelUncoated, lane-wise; T = 1 - R (no absorption).
            const T n1 = static_cast<T>(s.n1), n2 = static_cast<T>(s.n2);
#pragma GCC ivdep
            for (size_t i = 0; i < n; ++i) {
                const T ci = cosi[i];
                const T st = eta * std::sqrt(std::max(T(0), T(1) - ci * ci));
                const bool total = (st >= T(1)) | (ci == T(0));
                const T ct = std::sqrt(std::max(T(0), T(1) - st * st));
                const T rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct);
                const T rp = (n1 * ct - n2 * ci) / (n1 * ct + n2 * ci);
                const T r = total ? T(1) : T(0.5) * (rs * rs + rp * rp);
                thr[i] *= reflect ? r : T(1) - r;
            }
            continue;
        }
        // The coated reflectance: the Chebyshev sum in double whatever T is. A ghost's power is
        // a product of reflectances as small as 1e-5, which float's sum would lose.
        const FresnelPolynomial& poly = in.coatings[s.coating];
        const size_t degree = poly.coefficients.size() - 1;
        const T lo = static_cast<T>(poly.lo);
        const double scale = 2.0 / (1.0 - poly.lo);
        const double offset = (1.0 + poly.lo) / (1.0 - poly.lo);
        // Clenshaw's recurrence, eight lanes at a time with the whole recurrence in registers
        // (a pass over all lanes per coefficient stored and loaded them at every step).
        const double* coefficient = poly.coefficients.data();
        const double a0 = coefficient[0];
        const auto clenshaw = [&]<size_t kLanes>(size_t i0) {
            double x[kLanes], p1[kLanes], p2[kLanes];
            for (size_t k = 0; k < kLanes; ++k) {
                x[k] = static_cast<double>(cosi[i0 + k]) * scale - offset;
                p1[k] = 0.0;
                p2[k] = 0.0;
            }
            for (size_t j = degree; j >= 1; --j) {
                const double a = coefficient[j];
                for (size_t k = 0; k < kLanes; ++k) {
                    const double b0 = 2.0 * x[k] * p1[k] - p2[k] + a;
                    p2[k] = p1[k];
                    p1[k] = b0;
                }
            }
            for (size_t k = 0; k < kLanes; ++k) {
                const double r = x[k] * p1[k] - p2[k] + a0;
                factor[i0 + k] = reflect ? r : 1.0 - r;
            }
        };
        size_t i0 = 0;
        for (; i0 + 8 <= n; i0 += 8) clenshaw.template operator()<8>(i0);
        for (; i0 < n; ++i0) clenshaw.template operator()<1>(i0);
#pragma GCC ivdep
        for (size_t i = 0; i < n; ++i) thr[i] *= cosi[i] >= lo ? static_cast<T>(factor[i]) : T(1);
        // Lanes below the fitted range (near internal reflection, rare): the exact formula, one
        // by one.
        for (size_t i = 0; i < n; ++i) {
            if (cosi[i] >= lo || alive[i] == T(0)) continue;
            const FresnelResult f = fresnelCoated(s.n1, s.coat_index, s.coat_thickness_nm, s.n2,
                                                  static_cast<double>(cosi[i]), in.wavelength_nm);
            thr[i] *= static_cast<T>(reflect ? f.reflectance : f.transmittance);
        }
    }
}

template <typename T>
using Kernel = void (*)(const KernelInput&, size_t, Lanes<T>&);

template <typename T>
void traceLanesSse2(const KernelInput& in, size_t n, Lanes<T>& w) {
    traceLanes<T>(in, n, w);
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define FLARELAB_ROW_TRACER_AVX2 1
template <typename T>
[[gnu::target("avx2")]] void traceLanesAvx2(const KernelInput& in, size_t n, Lanes<T>& w) {
    traceLanes<T>(in, n, w);
}
#endif

bool rowTracerHasAvx2() {
#ifdef FLARELAB_ROW_TRACER_AVX2
    return flarelab::processorHasAvx2();
#else
    return false;
#endif
}

template <typename T>
Kernel<T> kernelFor(bool avx2) {
#ifdef FLARELAB_ROW_TRACER_AVX2
    if (avx2) return &traceLanesAvx2<T>;
#else
    (void)avx2;
#endif
    return &traceLanesSse2<T>;
}

template <typename T>
void runRow(const KernelInput& in,
            bool avx2,
            std::span<const double> x,
            std::span<const double> y,
            double z_rel,
            const Eigen::Vector3d& direction,
            TracedRow& out) {
    const size_t n = x.size();
    Lanes<T> w(n);
    for (size_t i = 0; i < n; ++i) {
        w.px[i] = static_cast<T>(x[i]);
        w.py[i] = static_cast<T>(y[i]);
        w.pz[i] = static_cast<T>(z_rel);
        w.dx[i] = static_cast<T>(direction.x());
        w.dy[i] = static_cast<T>(direction.y());
        w.dz[i] = static_cast<T>(direction.z());
    }
    kernelFor<T>(avx2)(in, n, w);
    out.resize(n);
    for (size_t i = 0; i < n; ++i) {
        out.x_mm[i] = static_cast<double>(w.px[i]);
        out.y_mm[i] = static_cast<double>(w.py[i]);
        out.throughput[i] = static_cast<double>(w.throughput[i]);
        out.stop_u[i] = static_cast<double>(w.stop_u[i]);
        out.stop_v[i] = static_cast<double>(w.stop_v[i]);
        out.aperture_ratio[i] = std::sqrt(static_cast<double>(w.ratio2[i]));
        const bool finite = std::isfinite(out.x_mm[i]) && std::isfinite(out.y_mm[i]) &&
                            std::isfinite(out.throughput[i]) && std::isfinite(out.stop_u[i]) &&
                            std::isfinite(out.stop_v[i]);
        out.status[i] = w.alive[i] == T(0) || !finite ? 0 : (w.cut[i] != T(0) ? 2 : 1);
    }
}

}  // namespace

RowTracer::RowTracer(const Lens& lens,
                     const GhostPath& path,
                     double wavelength_nm,
                     const Options& options)
    : wavelength_nm_(wavelength_nm), options_(options) {
    // PathTracer checks the path and lays out its crossings; this tracer takes them over.
    const PathTracer exact(lens, path, wavelength_nm);
    inv_stop_semi_aperture_ = 1.0 / exact.stop_semi_aperture_mm_;
    double previous_z = 0.0;
    for (size_t k = 0; k < exact.steps_.size(); ++k) {
        const PathTracer::Step& e = exact.steps_[k];
        Step s;
        switch (e.kind) {
            case PathTracer::StepKind::Refract:
                s.kind = Step::Refract;
                break;
            case PathTracer::StepKind::Reflect:
                s.kind = Step::Reflect;
                break;
            case PathTracer::StepKind::Stop:
                s.kind = Step::Stop;
                break;
            case PathTracer::StepKind::Image:
                s.kind = Step::Image;
                break;
        }
        if (k == 0) first_vertex_z_mm_ = e.z_mm;
        s.shift_mm = k == 0 ? 0.0 : e.z_mm - previous_z;
        previous_z = e.z_mm;
        s.curvature = e.curvature;
        s.semi_aperture2 = e.semi_aperture2;
        s.inv_semi_aperture2 = e.semi_aperture2 > 0.0 ? 1.0 / e.semi_aperture2 : 0.0;
        s.n1 = e.n1;
        s.n2 = e.n2;
        s.eta = e.n1 / e.n2;
        s.same_medium = e.n1 == e.n2;
        s.first_stop_crossing = e.first_stop_crossing;
        s.coated = e.coated;
        s.coat_index = e.coat_index;
        s.coat_thickness_nm = e.coat_thickness_nm;
        if (e.coated && s.kind != Step::Stop && s.kind != Step::Image) {
            s.coating = static_cast<int>(coatings_.size());
            coatings_.push_back(cachedFit({e.n1, e.coat_index, e.coat_thickness_nm, e.n2,
                                           wavelength_nm, options.fresnel_tolerance, 0.0}));
        } else {
            s.coated = false;
        }
        steps_.push_back(s);
    }
}

std::pair<RowTracer::Precision, double> RowTracer::choosePrecision(std::span<const double> x,
                                                                   std::span<const double> y,
                                                                   double z,
                                                                   const Eigen::Vector3d& direction,
                                                                   double tolerance_mm) {
    TracedRow narrow, wide;
    options_.precision = Precision::Float;
    trace(x, y, z, direction, narrow);
    options_.precision = Precision::Double;
    std::vector<double> min_cos(steps_.size(), 1.0);
    traceRecording(x, y, z, direction, wide, min_cos.data());
    narrowCoatings(min_cos);
    // Positions count as they are; stop coordinates by what they move the ghost's stop edge on
    // the sensor: their error times the half-size of the footprint.
    double worst_position = 0.0, worst_stop = 0.0;
    double lo_x = 0.0, hi_x = 0.0, lo_y = 0.0, hi_y = 0.0;
    bool any = false;
    for (size_t i = 0; i < x.size(); ++i) {
        if (narrow.status[i] == 0 || wide.status[i] == 0) continue;
        worst_position = std::max(worst_position, std::hypot(narrow.x_mm[i] - wide.x_mm[i],
                                                             narrow.y_mm[i] - wide.y_mm[i]));
        worst_stop = std::max(worst_stop, std::hypot(narrow.stop_u[i] - wide.stop_u[i],
                                                     narrow.stop_v[i] - wide.stop_v[i]));
        lo_x = any ? std::min(lo_x, wide.x_mm[i]) : wide.x_mm[i];
        hi_x = any ? std::max(hi_x, wide.x_mm[i]) : wide.x_mm[i];
        lo_y = any ? std::min(lo_y, wide.y_mm[i]) : wide.y_mm[i];
        hi_y = any ? std::max(hi_y, wide.y_mm[i]) : wide.y_mm[i];
        any = true;
    }
    const double half_size = 0.5 * std::max(hi_x - lo_x, hi_y - lo_y);
    const double worst = std::max(worst_position, worst_stop * half_size);
    options_.precision = worst <= tolerance_mm ? Precision::Float : Precision::Double;
    return {options_.precision, worst};
}

void RowTracer::narrowCoatings(std::span<const double> min_cos) {
    FLARELAB_CHECK_EQ(min_cos.size(), steps_.size());
    for (size_t k = 0; k < steps_.size(); ++k) {
        const Step& s = steps_[k];
        if (!s.coated || s.coating < 0) continue;
        FresnelPolynomial& poly = coatings_[static_cast<size_t>(s.coating)];
        // The probe's smallest cosine less the margin, down to a multiple of 1/32 so that fits
        // are shared between grids; nothing to gain below the range fitted already.
        const double lo = std::floor((min_cos[k] - kCoatingMargin) * 32.0) / 32.0;
        if (!(lo > poly.lo + 1.0 / 32.0)) continue;
        poly = cachedFit({s.n1, s.coat_index, s.coat_thickness_nm, s.n2, wavelength_nm_,
                          options_.fresnel_tolerance, lo});
    }
}

bool RowTracer::usesAvx2() const { return options_.allow_avx2 && rowTracerHasAvx2(); }

void RowTracer::trace(std::span<const double> x,
                      std::span<const double> y,
                      double z,
                      const Eigen::Vector3d& direction,
                      TracedRow& out) const {
    traceRecording(x, y, z, direction, out, nullptr);
}

void RowTracer::traceRecording(std::span<const double> x,
                               std::span<const double> y,
                               double z,
                               const Eigen::Vector3d& direction,
                               TracedRow& out,
                               double* min_cos) const {
    FLARELAB_CHECK_EQ(x.size(), y.size());
    const KernelInput in{steps_.data(),    steps_.size(),           coatings_.data(),
                         options_.fresnel, inv_stop_semi_aperture_, wavelength_nm_,
                         min_cos};
    const double z_rel = z - first_vertex_z_mm_;
    if (options_.precision == Precision::Float)
        runRow<float>(in, usesAvx2(), x, y, z_rel, direction, out);
    else
        runRow<double>(in, usesAvx2(), x, y, z_rel, direction, out);
}

}  // namespace flarelab::optics
