#include "fit/frame_fit.h"

#include <ceres/ceres.h>
#include <ceres/jet.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <optional>
#include <string>

#include "fit/model_eval.h"
#include "fit/shading_refit.h"

namespace flarelab::fit {
namespace {

using Clock = std::chrono::steady_clock;
constexpr int kMaxParams = 19;  // 9 shape + 2 x 3 intensities + 4 falloffs and exponents
using Jet = ceres::Jet<double, kMaxParams>;
using Jet5 = ceres::Jet<double, 5>;  // d and the four falloff values

double millisecondsSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// ---------------------------------------------------------------------------
// A ghost's parameter vector: shape with handle fractions, scaled intensities, falloffs
// ---------------------------------------------------------------------------

struct Layout {
    int channels = 1;
    int size() const { return 9 + 2 * channels + 4; }
    int border(int c) const { return 9 + 2 * c; }
    int inner(int c) const { return 10 + 2 * c; }
    int innerFalloff() const { return 9 + 2 * channels; }
    int outerFalloff() const { return innerFalloff() + 1; }
    int innerExponent() const { return innerFalloff() + 2; }
    int outerExponent() const { return innerFalloff() + 3; }
};

struct Bounds {
    std::vector<double> lower, upper, scale;  // scale: a typical size of each parameter
};

// The vector of `state` (intensities over `intensity_scale`) and its bounds for a frame whose
// pixels are `px_mm` wide and whose sensor diagonal is `diagonal_mm`.
std::vector<double> packState(const GhostState& state,
                              const Layout& layout,
                              double intensity_scale) {
    std::vector<double> v(static_cast<size_t>(layout.size()));
    const GhostParameters p = ghostParameters(state);
    for (int i = 0; i < 9; ++i) v[static_cast<size_t>(i)] = p[static_cast<size_t>(i)];
    for (int c = 0; c < layout.channels; ++c) {
        v[static_cast<size_t>(layout.border(c))] = state.shading.border_rgb[c] / intensity_scale;
        v[static_cast<size_t>(layout.inner(c))] = state.shading.inner_rgb[c] / intensity_scale;
    }
    v[static_cast<size_t>(layout.innerFalloff())] = state.shading.inner_falloff_mm;
    v[static_cast<size_t>(layout.outerFalloff())] = state.shading.outer_falloff_mm;
    v[static_cast<size_t>(layout.innerExponent())] = state.shading.inner_exponent;
    v[static_cast<size_t>(layout.outerExponent())] = state.shading.outer_exponent;
    return v;
}

GhostState unpackState(const double* v, const Layout& layout, double intensity_scale) {
    GhostState s;
    s.shape.centre_x_mm = v[0];
    s.shape.centre_y_mm = v[1];
    s.shape.half_height_mm = v[2];
    s.shape.left_mm = v[3];
    s.shape.right_mm = v[4];
    s.shape.left_handle_x_mm = v[5] * v[3];
    s.shape.left_handle_y_mm = v[6] * v[2];
    s.shape.right_handle_x_mm = v[7] * v[4];
    s.shape.right_handle_y_mm = v[8] * v[2];
    for (int c = 0; c < 3; ++c) {
        const int k = std::min(c, layout.channels - 1);  // one fitted channel: all three equal
        s.shading.border_rgb[c] = std::max(0.0, v[layout.border(k)] * intensity_scale);
        s.shading.inner_rgb[c] = std::max(0.0, v[layout.inner(k)] * intensity_scale);
    }
    s.shading.inner_falloff_mm = v[layout.innerFalloff()];
    s.shading.outer_falloff_mm = v[layout.outerFalloff()];
    s.shading.inner_exponent = v[layout.innerExponent()];
    s.shading.outer_exponent = v[layout.outerExponent()];
    return s;
}

// Box bounds for a ghost starting at `start`: besides validity, its centre and extents may move
// by at most `reach_mm` (the trust region that keeps it inside its crop).
Bounds makeBounds(const Layout& layout,
                  double px_mm,
                  double diagonal_mm,
                  double size_mm,
                  const GhostState& start,
                  double reach_mm) {
    Bounds b;
    const size_t n = static_cast<size_t>(layout.size());
    b.lower.assign(n, 0.0);
    b.upper.assign(n, 1.0);
    b.scale.assign(n, 1.0);
    const double far = 10.0 * diagonal_mm;
    const double centre[2] = {start.shape.centre_x_mm, start.shape.centre_y_mm};
    for (int i : {0, 1}) {
        b.lower[static_cast<size_t>(i)] = std::max(-far, centre[i] - reach_mm);
        b.upper[static_cast<size_t>(i)] = std::min(far, centre[i] + reach_mm);
        b.scale[static_cast<size_t>(i)] = size_mm;
    }
    const double extent[3] = {start.shape.half_height_mm, start.shape.left_mm,
                              start.shape.right_mm};
    for (int i : {2, 3, 4}) {
        b.lower[static_cast<size_t>(i)] = std::max(0.5 * px_mm, extent[i - 2] - reach_mm);
        b.upper[static_cast<size_t>(i)] = std::max(
            b.lower[static_cast<size_t>(i)], std::min(4.0 * diagonal_mm, extent[i - 2] + reach_mm));
        b.scale[static_cast<size_t>(i)] = size_mm;
    }
    for (int c = 0; c < layout.channels; ++c) {
        b.upper[static_cast<size_t>(layout.border(c))] = 1e4;
        b.upper[static_cast<size_t>(layout.inner(c))] = 1e4;
    }
    // The falloffs are bounded by the ghost's size: an outer falloff wider than the ghost, or an
    // inner one wider than twice its size, no longer draws an edge but a haze, which trades off
    // against the intensities and, since the crop grows with the outer falloff, reaches over the
    // frame and takes the other ghosts' light (seen on the Heliar: outer falloffs of 6 radii).
    const double falloff_cap[2] = {2.0 * size_mm, size_mm};  // inner, outer
    for (int k : {0, 1}) {
        const auto i = static_cast<size_t>(k == 0 ? layout.innerFalloff() : layout.outerFalloff());
        b.lower[i] = 0.25 * px_mm;
        b.upper[i] = std::max(2.0 * px_mm, std::min(2.0 * diagonal_mm, falloff_cap[k]));
        b.scale[i] = size_mm;
    }
    for (int i : {layout.innerExponent(), layout.outerExponent()}) {
        b.lower[static_cast<size_t>(i)] = 0.25;
        b.upper[static_cast<size_t>(i)] = 4.0;
    }
    return b;
}

void clampInto(std::vector<double>& v, const Bounds& b) {
    for (size_t i = 0; i < v.size(); ++i) v[i] = std::clamp(v[i], b.lower[i], b.upper[i]);
}

// A start with its extents (half height, left, right) less its outer falloff, clamped into the
// bounds: a detection's blob reaches out over the ghost's outer falloff.
std::vector<double> shrunkByOuterFalloff(std::vector<double> v,
                                         const Layout& layout,
                                         const Bounds& b) {
    const double fo = v[static_cast<size_t>(layout.outerFalloff())];
    for (int i : {2, 3, 4}) v[static_cast<size_t>(i)] -= fo;
    clampInto(v, b);
    return v;
}

// The box of a loop's control points, which holds the loop.
struct ControlBox {
    Eigen::Vector2d lo, hi;
};
ControlBox controlBox(const render::BezierLoop& loop) {
    ControlBox box{loop.control_points_mm.front(), loop.control_points_mm.front()};
    for (const auto& p : loop.control_points_mm) {
        box.lo = box.lo.cwiseMin(p);
        box.hi = box.hi.cwiseMax(p);
    }
    return box;
}

// Whether a block centred on q gets none of a ghost's light: farther from its control box than
// its outer falloff plus the block's reach (half width plus half height), so that its weights
// are exactly zero, as the distance would find. The bound keeps a margin far above rounding.
bool beyondReach(const ControlBox& box,
                 const Eigen::Vector2d& q,
                 double outer_falloff_mm,
                 double reach_mm) {
    return (box.lo - q).cwiseMax(q - box.hi).cwiseMax(0.0).norm() >
           (outer_falloff_mm + reach_mm) * (1.0 + 1e-9);
}

// Whether every fitted channel's border is under a tenth of its inner intensity.
bool darkRim(const std::vector<double>& v, const Layout& layout) {
    for (int c = 0; c < layout.channels; ++c) {
        const double inner = v[static_cast<size_t>(layout.inner(c))];
        if (!(inner > 0.0) || v[static_cast<size_t>(layout.border(c))] >= 0.1 * inner) return false;
    }
    return true;
}

// The dark-rim state's alternative (see fitFrame): extents reduced by the depth at which the
// inner rise is half done, border = inner, inner falloff kept, a falloff of two pixels outside;
// clamped into the bounds. False when that changes nothing (a rise within half a pixel).
bool shrinkToRise(std::vector<double>& v, const Layout& layout, const Bounds& b, double px_mm) {
    const double fi = v[static_cast<size_t>(layout.innerFalloff())];
    const double ei = v[static_cast<size_t>(layout.innerExponent())];
    const double depth = fi * std::pow(0.5, 1.0 / std::max(ei, 0.25));
    if (!(depth > 0.5 * px_mm)) return false;
    for (int i : {2, 3, 4}) v[static_cast<size_t>(i)] -= depth;
    for (int c = 0; c < layout.channels; ++c)
        v[static_cast<size_t>(layout.border(c))] = v[static_cast<size_t>(layout.inner(c))];
    v[static_cast<size_t>(layout.outerFalloff())] = 2.0 * px_mm;
    v[static_cast<size_t>(layout.outerExponent())] = 1.0;
    clampInto(v, b);
    return true;
}

// ---------------------------------------------------------------------------
// One ghost's crop and cost
// ---------------------------------------------------------------------------

// The Laplacian of Gaussian, zero-sum, on a (2 radius + 1)^2 grid.
std::vector<double> logKernel(double sigma, int& radius) {
    radius = std::max(1, static_cast<int>(std::ceil(3.0 * sigma)));
    const int n = 2 * radius + 1;
    std::vector<double> k(static_cast<size_t>(n * n));
    double sum = 0.0;
    for (int y = -radius; y <= radius; ++y)
        for (int x = -radius; x <= radius; ++x) {
            const double r2 = (x * x + y * y) / (sigma * sigma);
            const double v = (r2 - 2.0) * std::exp(-0.5 * r2) / (sigma * sigma);
            k[static_cast<size_t>((y + radius) * n + x + radius)] = v;
            sum += v;
        }
    for (double& v : k) v -= sum / (n * n);
    return k;
}

class GhostProblem {
public:
    GhostProblem(const Layout& layout, const CostOptions& options, double intensity_scale)
        : layout_(layout), options_(options), intensity_scale_(intensity_scale) {}

    // Samples the crop of `range` (inclusive pixels) from the frame, the others' model included.
    void build(const FitFrame& frame,
               const FrameDetection& detection,
               int64_t x0,
               int64_t y0,
               int64_t x1,
               int64_t y1,
               std::span<const GhostState> others,
               const std::array<double, 3>& transform_scale) {
        closest_shape_valid_ = false;  // new samples: no closest point is known
        closest_.clear();
        anchors_.clear();
        last_[0].valid = last_[1].valid = false;
        const int64_t w = x1 - x0 + 1, h = y1 - y0 + 1;
        const int64_t side = std::max(w, h);
        stride_ = std::max<int64_t>(1, (side + options_.max_samples - 1) / options_.max_samples);
        nx_ = static_cast<int>((w + stride_ - 1) / stride_);
        ny_ = static_cast<int>((h + stride_ - 1) / stride_);
        const size_t n = static_cast<size_t>(nx_) * static_cast<size_t>(ny_);
        valid_.assign(n, 0);
        qx_.resize(static_cast<size_t>(nx_));
        qy_.resize(static_cast<size_t>(ny_));
        hx_.resize(static_cast<size_t>(nx_));
        hy_.resize(static_cast<size_t>(ny_));
        const auto& m = frame.mapping;
        for (int i = 0; i < nx_; ++i) {
            const int64_t a = x0 + i * stride_, b = std::min(x1, a + stride_ - 1);
            qx_[static_cast<size_t>(i)] =
                (0.5 * static_cast<double>(a + b + 1) - m.centre_x_px) / m.px_per_mm_x;
            hx_[static_cast<size_t>(i)] = 0.5 * static_cast<double>(b - a + 1) / m.px_per_mm_x;
        }
        for (int j = 0; j < ny_; ++j) {
            const int64_t a = y0 + j * stride_, b = std::min(y1, a + stride_ - 1);
            qy_[static_cast<size_t>(j)] =
                (0.5 * static_cast<double>(a + b + 1) - m.centre_y_px) / m.px_per_mm_y;
            hy_[static_cast<size_t>(j)] = 0.5 * static_cast<double>(b - a + 1) / m.px_per_mm_y;
        }
        for (int c = 0; c < layout_.channels; ++c) {
            data_[c].assign(n, 0.0);
            bound_[c].assign(n, 0);
            others_[c].assign(n, 0.0);
            scale_[c] = transform_scale[c];
        }
        const int64_t width = frame.image.width;
        const bool has_bounds =
            frame.lower_bound.size() == static_cast<size_t>(width * frame.image.height);
        // Each sample's block mean, rows of samples on every core (each sample is summed alone,
        // in the same order, whichever thread sums it).
        tbb::parallel_for(0, ny_, [&](int j) {
            for (int i = 0; i < nx_; ++i) {
                const int64_t ax = x0 + i * stride_, bx = std::min(x1, ax + stride_ - 1);
                const int64_t ay = y0 + j * stride_, by = std::min(y1, ay + stride_ - 1);
                bool ok = true;
                double sum[3] = {0.0, 0.0, 0.0};
                uint8_t bounds = 0;  // channels holding a lower bound (FitFrame::lower_bound)
                for (int64_t y = ay; y <= by && ok; ++y)
                    for (int64_t x = ax; x <= bx; ++x) {
                        const size_t pixel = static_cast<size_t>(y * width + x);
                        if (detection.excluded[pixel]) {
                            ok = false;
                            break;
                        }
                        if (has_bounds) bounds |= frame.lower_bound[pixel];
                        const float* p = frame.image.at(x, y);
                        for (int c = 0; c < layout_.channels; ++c) sum[c] += p[c];
                    }
                if (!ok) continue;
                const double count = static_cast<double>((bx - ax + 1) * (by - ay + 1));
                const size_t s = static_cast<size_t>(j * nx_ + i);
                valid_[s] = 1;
                for (int c = 0; c < layout_.channels; ++c) {
                    data_[c][s] = sum[c] / count - detection.background[c];
                    // A mean over a lower bound is one too.
                    bound_[c][s] = (bounds >> c) & 1u;
                }
            }
        });
        // The other ghosts at the sample centres (only those whose range meets the crop).
        for (const GhostState& g : others) {
            const render::BezierLoop loop = render::toBezierLoop(g.shape);
            const ControlBox box = controlBox(loop);
            const double grow = g.shading.outer_falloff_mm;
            if (box.hi.x() + grow < qx_.front() || box.lo.x() - grow > qx_.back() ||
                box.hi.y() + grow < qy_.front() || box.lo.y() - grow > qy_.back())
                continue;
            tbb::parallel_for(0, ny_, [&](int j) {
                for (int i = 0; i < nx_; ++i) {
                    const size_t s = static_cast<size_t>(j * nx_ + i);
                    if (!valid_[s]) continue;
                    if (beyondReach(box, {qx_[static_cast<size_t>(i)], qy_[static_cast<size_t>(j)]},
                                    grow,
                                    hx_[static_cast<size_t>(i)] + hy_[static_cast<size_t>(j)]))
                        continue;
                    const auto v = render::shadeGhostBlock(
                        loop, g.shading, {qx_[static_cast<size_t>(i)], qy_[static_cast<size_t>(j)]},
                        {hx_[static_cast<size_t>(i)], hy_[static_cast<size_t>(j)]},
                        options_.distance);
                    for (int c = 0; c < layout_.channels; ++c) others_[c][s] += v[c];
                }
            });
        }
        samples_ = 0;
        for (uint8_t v : valid_) samples_ += v;
        kernel_ = options_.edge_weight > 0.0 ? logKernel(options_.edge_sigma, radius_)
                                             : std::vector<double>{};
        // Each valid sample's valid neighbours under the kernel and their weights, in the
        // kernel's order (every edge output is summed in that order), found once per crop.
        tap_begin_.assign(static_cast<size_t>(nx_) * static_cast<size_t>(ny_) + 1, 0);
        tap_from_.clear();
        tap_weight_.clear();
        const int kn = 2 * radius_ + 1;
        for (int j = 0; j < ny_; ++j)
            for (int i = 0; i < nx_; ++i) {
                const size_t s = static_cast<size_t>(j * nx_ + i);
                if (!kernel_.empty() && valid_[s]) {
                    for (int dy = -radius_; dy <= radius_; ++dy) {
                        const int y = j + dy;
                        if (y < 0 || y >= ny_) continue;
                        for (int dx = -radius_; dx <= radius_; ++dx) {
                            const int x = i + dx;
                            if (x < 0 || x >= nx_) continue;
                            const size_t t = static_cast<size_t>(y * nx_ + x);
                            if (!valid_[t]) continue;
                            tap_from_.push_back(t);
                            tap_weight_.push_back(
                                options_.edge_weight *
                                kernel_[static_cast<size_t>((dy + radius_) * kn + dx + radius_)]);
                        }
                    }
                }
                tap_begin_[s + 1] = tap_from_.size();
            }
    }

    int64_t samples() const { return samples_; }
    int residualCount() const {
        return static_cast<int>(samples_) * layout_.channels * (kernel_.empty() ? 1 : 2) +
               (prior_ ? 9 : 0);
    }

    // A prior on the shape (the tracker's prediction): rows (v - prior) / tolerance for the nine
    // shape values, tolerance `fraction` of `size_mm` for centre and extents, 0.2 for the handle
    // fractions. It holds what the frame does not show (a ghost's edge outside the frame).
    void setPrior(const GhostState& prior, double size_mm, double fraction) {
        const GhostParameters p = ghostParameters(prior);
        prior_values_.assign(p.begin(), p.begin() + 9);
        prior_tolerance_.assign(9, 0.2);
        for (int i = 0; i < 5; ++i) prior_tolerance_[static_cast<size_t>(i)] = fraction * size_mm;
        prior_ = true;
        last_[0].valid = last_[1].valid = false;
    }

    // The residuals (robust-transformed). The last evaluation is kept and copied when the same
    // point is asked for again (a copy must be what a new evaluation would give).
    bool evaluate(const double* params, double* residuals) const {
        const int np = layout_.size();
        const size_t rows = static_cast<size_t>(residualCount());
        LastEvaluation& last = last_[0];
        if (last.valid && std::equal(params, params + np, last.params.begin())) {
            std::copy_n(last.residuals.begin(), rows, residuals);
            return last.ok;
        }
        last.ok = evaluateOnce(params, residuals, nullptr);
        last.valid = true;
        last.params.assign(params, params + np);
        last.residuals.assign(residuals, residuals + rows);
        return last.ok;
    }

    // The rows r + J x compressed to np + 1 (GhostCostFunction): `residuals` np + 1 values and,
    // when `jacobian` is not null, their row-major (np + 1) x np Jacobian. Without the Jacobian
    // only the cost is wanted: the residuals' norm, last. Ceres asks for a point's Jacobian
    // again after a step it accepts; the last one is kept (as evaluate keeps its last).
    bool evaluateCompressed(const double* params, double* residuals, double* jacobian) const {
        const int np = layout_.size();
        const auto m = static_cast<Eigen::Index>(residualCount());
        std::fill_n(residuals, np + 1, 0.0);
        if (!jacobian) {
            rows_.resize(m);
            if (!evaluate(params, rows_.data())) return false;
            residuals[np] = rows_.norm();
            return std::isfinite(residuals[np]);
        }
        LastEvaluation& last = last_[1];
        const size_t out_rows = static_cast<size_t>(np + 1);
        if (!(last.valid && std::equal(params, params + np, last.params.begin()))) {
            rows_.resize(m);
            rows_jacobian_.resize(m, np);
            last.ok = evaluateOnce(params, rows_.data(), &rows_jacobian_);
            last.valid = true;
            last.params.assign(params, params + np);
            last.residuals.assign(out_rows, 0.0);
            last.jacobian.assign(out_rows * static_cast<size_t>(np), 0.0);
            if (last.ok) {
                const detail::CompressedRows packed =
                    detail::compressRowsInPlace(rows_jacobian_, rows_);
                for (Eigen::Index i = 0; i < packed.head.size(); ++i) {
                    last.residuals[static_cast<size_t>(i)] = packed.head[i];
                    for (int k = 0; k < np; ++k)
                        last.jacobian[static_cast<size_t>(i * np + k)] = packed.factor(i, k);
                }
                last.residuals[static_cast<size_t>(np)] = packed.rest;
                last.ok = std::isfinite(packed.rest);
            }
        }
        std::copy_n(last.residuals.begin(), out_rows, residuals);
        std::copy_n(last.jacobian.begin(), out_rows * static_cast<size_t>(np), jacobian);
        return last.ok;
    }

    // Evaluations made (those answered from the last one not counted).
    int64_t evaluations() const { return evaluations_; }

private:
    // Channel c's residual at sample s for the light `total` the model puts there (this ghost's
    // and the others').
    double residualAt(int c, size_t s, double total) const {
        return censored(c, s, std::asinh(total / scale_[c]) - std::asinh(data_[c][s] / scale_[c]));
    }

    // Row `row` (sample s, channel c) for this ghost's light m there: its residual and, when
    // asked, its gradient (zero where the bound is met: the residual stays 0 nearby) and the
    // gradient's nonzero span.
    void writeRow(size_t row, int c, size_t s, const Jet& m, bool jacobian) const {
        const double total = m.a + others_[c][s];
        residual_[row] = residualAt(c, s, total);
        if (!jacobian) return;
        const double dt = residual_[row] == 0.0 && bound_[c][s]
                              ? 0.0
                              : 1.0 / std::sqrt(scale_[c] * scale_[c] + total * total);
        const int np = layout_.size();
        int first = np, last = 0;
        for (int k = 0; k < np; ++k) {
            const double g = dt * m.v[k];
            gradient_[row * np + static_cast<size_t>(k)] = g;
            if (g != 0.0) {
                first = std::min(first, k);
                last = k + 1;
            }
        }
        span_[row] = {static_cast<uint8_t>(std::min(first, last)), static_cast<uint8_t>(last)};
    }

    // The full rows, and their Jacobian (residualCount() x np) when `jacobian` is not null.
    bool evaluateOnce(const double* params, double* residuals, Eigen::MatrixXd* jacobian) const {
        ++evaluations_;
        const int np = layout_.size();
        const size_t n = static_cast<size_t>(nx_) * static_cast<size_t>(ny_);
        // Control points and their derivatives with respect to the nine shape parameters.
        std::array<Jet, 9> shape;
        for (int i = 0; i < 9; ++i) shape[static_cast<size_t>(i)] = Jet(params[i], i);
        std::array<Jet, 9> handles_mm = shape;
        handles_mm[5] = shape[5] * shape[3];
        handles_mm[6] = shape[6] * shape[2];
        handles_mm[7] = shape[7] * shape[4];
        handles_mm[8] = shape[8] * shape[2];
        const auto points = render::ghostShapeControlPoints<Jet>(handles_mm.data());
        render::BezierLoop loop;
        loop.control_points_mm.resize(12);
        for (int k = 0; k < 12; ++k)
            loop.control_points_mm[static_cast<size_t>(k)] = {points[static_cast<size_t>(k)].x().a,
                                                              points[static_cast<size_t>(k)].y().a};
        // Per sample and channel: the plain residual r and its gradient (when asked).
        residual_.assign(n * static_cast<size_t>(layout_.channels), 0.0);
        if (jacobian) {
            // Rows of valid samples are all written; no other row is read.
            gradient_.resize(residual_.size() * static_cast<size_t>(np));
            // Each row's nonzero span [first, last): empty outside the ghost's reach, one
            // intensity deep inside it. The edge term's convolution walks only that span.
            span_.resize(residual_.size());
        }
        Jet border[3], inner[3];
        const Jet fi(params[layout_.innerFalloff()], layout_.innerFalloff());
        const Jet fo(params[layout_.outerFalloff()], layout_.outerFalloff());
        const Jet ei(params[layout_.innerExponent()], layout_.innerExponent());
        const Jet eo(params[layout_.outerExponent()], layout_.outerExponent());
        for (int c = 0; c < layout_.channels; ++c) {
            border[c] = Jet(params[layout_.border(c)], layout_.border(c)) * intensity_scale_;
            inner[c] = Jet(params[layout_.inner(c)], layout_.inner(c)) * intensity_scale_;
        }
        // A block beyond the ghost's reach (most of a crop, whose margin is wide) gets no light
        // from it, so its distance is not sought.
        const ControlBox box = controlBox(loop);
        // The closest points depend on the nine shape values only. Ceres evaluates a step's
        // residuals, and on accepting it the Jacobian at the same values; the points of the
        // last shape are kept per sample and reused when the shape is the same bit for bit.
        bool same_shape = closest_shape_valid_;
        for (int i = 0; i < 9 && same_shape; ++i)
            same_shape = closest_shape_[static_cast<size_t>(i)] == params[i];
        if (!same_shape) {
            // Every sample keeps the shape its distance was last sought for (its anchor): a
            // cubic's points are weighted means of its control points, so no point of the
            // loop moved farther than the control points did (anchor_shift_), and neither did
            // any distance to it.
            if (closest_.size() != n) closest_.assign(n, SampleClosest{});
            for (SampleClosest& c : closest_) c.known = false;
            anchor_shift_.resize(anchors_.size());
            for (size_t a = 0; a < anchors_.size(); ++a) {
                double shift = 0.0;
                for (size_t k = 0; k < 12; ++k)
                    shift = std::max(shift, (loop.control_points_mm[k] - anchors_[a][k]).norm());
                anchor_shift_[a] = shift;
            }
            anchors_.emplace_back();
            std::copy_n(loop.control_points_mm.begin(), 12, anchors_.back().begin());
            anchor_shift_.push_back(0.0);
            for (int i = 0; i < 9; ++i) closest_shape_[static_cast<size_t>(i)] = params[i];
            closest_shape_valid_ = true;
        }
        const int anchor_now = static_cast<int>(anchors_.size()) - 1;
        tbb::parallel_for(0, ny_, [&](int j) {
            for (int i = 0; i < nx_; ++i) {
                const size_t s = static_cast<size_t>(j * nx_ + i);
                if (!valid_[s]) continue;
                const Eigen::Vector2d q(qx_[static_cast<size_t>(i)], qy_[static_cast<size_t>(j)]);
                const double reach = hx_[static_cast<size_t>(i)] + hy_[static_cast<size_t>(j)];
                // A sample whose block lay, at its anchor, farther outside the outer falloff or
                // deeper inside the inner one than the loop has moved since gets the weights
                // the transfer's flat ends give (0 outside; all inner light inside), as
                // boxTransferWeights would: its spread is at most the half sizes' sum.
                SampleClosest& sc = closest_[s];
                bool inside_flat = false;
                if (!sc.known && sc.anchor >= 0) {
                    const double moved = anchor_shift_[static_cast<size_t>(sc.anchor)];
                    const double away = std::abs(sc.anchor_distance) - moved - reach;
                    if (sc.anchor_distance > 0.0 && away >= fo.a) {
                        // as beyond reach, below
                    } else if (sc.anchor_distance < 0.0 && away >= fi.a) {
                        inside_flat = true;
                    } else {
                        sc.anchor = -1;
                    }
                }
                const bool outside_flat = !sc.known && sc.anchor >= 0 && !inside_flat;
                if (outside_flat || beyondReach(box, q, fo.a, reach)) {
                    for (int c = 0; c < layout_.channels; ++c) {
                        const size_t row = s * layout_.channels + c;
                        residual_[row] = residualAt(c, s, 0.0 + others_[c][s]);
                        if (!jacobian) continue;
                        std::fill_n(&gradient_[row * np], np, 0.0);
                        span_[row] = {0, 0};
                    }
                    continue;
                }
                if (inside_flat) {
                    for (int c = 0; c < layout_.channels; ++c)
                        writeRow(s * layout_.channels + c, c, s, inner[c], jacobian != nullptr);
                    continue;
                }
                if (!sc.known) {
                    sc.point = render::closestPointFast(loop, q, options_.distance);
                    sc.sign = render::windingNumber(loop, q) != 0 ? -1.0 : 1.0;
                    sc.known = true;
                    sc.anchor = anchor_now;
                    // The fast distance is a point's on the loop, so it can only overstate
                    // the distance, and does by far where Newton leaves its segment (a straight
                    // side with handles of no length). Where it puts the block on a flat end of
                    // the transfer now, a bound below it is proven (fartherThan) and kept;
                    // elsewhere the anchor holds none.
                    const double flat_from = (sc.sign < 0.0 ? fi.a : fo.a) + reach;
                    sc.anchor_distance = 0.0;
                    if (sc.point.distance_mm >= flat_from) {
                        // Most of the way to the fast distance: room for the loop to move
                        // before the bound no longer holds (0.5 and 0.95 were no faster on
                        // the Heliar).
                        const double bound = flat_from + 0.8 * (sc.point.distance_mm - flat_from);
                        if (render::fartherThan(loop, q, bound))
                            sc.anchor_distance = sc.sign * bound;
                    }
                }
                const render::ClosestPoint& cp = sc.point;
                const double sign = sc.sign;
                const double d = sign * cp.distance_mm;
                const Eigen::Vector2d half(hx_[static_cast<size_t>(i)],
                                           hy_[static_cast<size_t>(j)]);
                const Eigen::Vector2d spread = render::blockSpread(q, cp, half);
                if (!jacobian) {
                    const auto w = render::boxTransferWeights<double>(d, spread.x(), spread.y(),
                                                                      fi.a, fo.a, ei.a, eo.a);
                    for (int c = 0; c < layout_.channels; ++c) {
                        const double m = border[c].a * w.border + inner[c].a * w.inner;
                        residual_[s * layout_.channels + c] = residualAt(c, s, m + others_[c][s]);
                    }
                    continue;
                }
                // d(dist)/d(P_k) = -u B_k(t) at the closest point (envelope theorem).
                Jet dj(d);
                if (cp.distance_mm > 1e-12) {
                    const Eigen::Vector2d u = (q - cp.point_mm) / cp.distance_mm;
                    const double t = cp.t, mt = 1.0 - t;
                    const double basis[4] = {mt * mt * mt, 3.0 * mt * mt * t, 3.0 * mt * t * t,
                                             t * t * t};
                    for (int b = 0; b < 4; ++b) {
                        const auto& p = points[static_cast<size_t>((3 * cp.segment + b) % 12)];
                        dj.v -= sign * basis[b] * (u.x() * p.x().v + u.y() * p.y().v);
                    }
                }
                // The weights depend on the parameters through d and the four falloff values
                // only: differentiated in those five, then chained, instead of carrying all
                // of the ghost's derivatives through every power.
                const Jet5 d5(d, 0), fi5(fi.a, 1), fo5(fo.a, 2), ei5(ei.a, 3), eo5(eo.a, 4);
                const auto w5 = render::boxTransferWeights<Jet5>(d5, spread.x(), spread.y(), fi5,
                                                                 fo5, ei5, eo5);
                const auto chain = [&](const Jet5& x) {
                    Jet out(x.a);
                    out.v = x.v[0] * dj.v;
                    out.v[layout_.innerFalloff()] += x.v[1];
                    out.v[layout_.outerFalloff()] += x.v[2];
                    out.v[layout_.innerExponent()] += x.v[3];
                    out.v[layout_.outerExponent()] += x.v[4];
                    return out;
                };
                const render::TransferWeights<Jet> w{chain(w5.border), chain(w5.inner)};
                for (int c = 0; c < layout_.channels; ++c)
                    writeRow(s * layout_.channels + c, c, s,
                             border[c] * w.border + inner[c] * w.inner, true);
            }
        });
        // Output: the data term, then the edge term, each robust-transformed.
        const double c2 = options_.robust_scale * options_.robust_scale;
        int out = 0;
        const auto emit = [&](double r, const double* grad) {
            const double s2 = r * r;
            const double rho = c2 * std::log1p(s2 / c2);
            const double rt = std::copysign(std::sqrt(rho), r);
            if (!std::isfinite(rt)) return false;
            residuals[out] = rt;
            if (jacobian) {
                // d rt / d theta = rho'(r^2) r / rt * dr / dtheta; the factor is 1 at r = 0.
                const double factor = rt != 0.0 ? (1.0 / (1.0 + s2 / c2)) * r / rt : 1.0;
                for (int k = 0; k < np; ++k) (*jacobian)(out, k) = grad ? factor * grad[k] : 0.0;
            }
            ++out;
            return true;
        };
        for (size_t s = 0; s < n; ++s) {
            if (!valid_[s]) continue;
            for (int c = 0; c < layout_.channels; ++c) {
                const size_t row = s * layout_.channels + c;
                if (!emit(residual_[row], jacobian ? &gradient_[row * np] : nullptr)) return false;
            }
        }
        if (!kernel_.empty()) {
            edge_.assign(residual_.size(), 0.0);
            if (jacobian) edge_gradient_.resize(gradient_.size());  // valid rows all written
            const int channels = layout_.channels;
            tbb::parallel_for(0, ny_, [&](int j) {
                std::array<double, kMaxParams> acc;
                for (int i = 0; i < nx_; ++i) {
                    const size_t s = static_cast<size_t>(j * nx_ + i);
                    if (!valid_[s]) continue;
                    const size_t* from_sample = &tap_from_[tap_begin_[s]];
                    const double* weight = &tap_weight_[tap_begin_[s]];
                    const int taps = static_cast<int>(tap_begin_[s + 1] - tap_begin_[s]);
                    for (int c = 0; c < channels; ++c) {
                        const size_t row = s * channels + c;
                        double e = 0.0;
                        for (int q = 0; q < taps; ++q)
                            e += weight[static_cast<size_t>(q)] *
                                 residual_[from_sample[static_cast<size_t>(q)] * channels + c];
                        edge_[row] = e;
                        if (!jacobian) continue;
                        std::fill_n(acc.begin(), np, 0.0);
                        for (int q = 0; q < taps; ++q) {
                            const size_t from = from_sample[static_cast<size_t>(q)] * channels + c;
                            const double k = weight[static_cast<size_t>(q)];
                            const double* h = &gradient_[from * np];
                            for (int p = span_[from][0]; p < span_[from][1]; ++p)
                                acc[static_cast<size_t>(p)] += k * h[p];
                        }
                        std::copy_n(acc.begin(), np, &edge_gradient_[row * np]);
                    }
                }
            });
            for (size_t s = 0; s < n; ++s) {
                if (!valid_[s]) continue;
                for (int c = 0; c < layout_.channels; ++c) {
                    const size_t row = s * layout_.channels + c;
                    if (!emit(edge_[row], jacobian ? &edge_gradient_[row * np] : nullptr))
                        return false;
                }
            }
        }
        if (prior_) {
            for (int i = 0; i < 9; ++i) {
                residuals[out] = (params[i] - prior_values_[static_cast<size_t>(i)]) /
                                 prior_tolerance_[static_cast<size_t>(i)];
                if (jacobian) {
                    for (int k = 0; k < np; ++k) (*jacobian)(out, k) = 0.0;
                    (*jacobian)(out, i) = 1.0 / prior_tolerance_[static_cast<size_t>(i)];
                }
                ++out;
            }
        }
        return out == residualCount();
    }

public:
    // Half the sum of squared transformed residuals (Ceres' cost), or +inf when not finite.
    double cost(const double* params) const {
        std::vector<double> r(static_cast<size_t>(residualCount()));
        if (!evaluate(params, r.data())) return std::numeric_limits<double>::infinity();
        double sum = 0.0;
        for (double v : r) sum += v * v;
        return 0.5 * sum;
    }

private:
    Layout layout_;
    CostOptions options_;
    double intensity_scale_ = 1.0;
    int64_t stride_ = 1;
    int nx_ = 0, ny_ = 0;
    int64_t samples_ = 0;
    std::vector<double> qx_, qy_;  // sample centres, mm
    std::vector<double> hx_, hy_;  // half sizes of their blocks, mm
    std::vector<uint8_t> valid_;
    double censored(int c, size_t s, double r) const { return bound_[c][s] && r > 0.0 ? 0.0 : r; }
    std::vector<double> data_[3], others_[3];
    // Per channel and sample: the data is only a lower bound (clipped in every bracket), so a
    // model at or above it is no error; below it, the usual residual.
    std::vector<uint8_t> bound_[3];
    double scale_[3] = {1.0, 1.0, 1.0};
    std::vector<double> kernel_;
    // The edge term's taps per sample: tap_from_ and tap_weight_ [tap_begin_[s], tap_begin_[s+1]).
    std::vector<size_t> tap_begin_, tap_from_;
    std::vector<double> tap_weight_;
    int radius_ = 0;
    bool prior_ = false;
    std::vector<double> prior_values_, prior_tolerance_;
    mutable std::vector<double> residual_, gradient_, edge_, edge_gradient_;
    mutable Eigen::VectorXd rows_;  // evaluateCompressed's full rows and their Jacobian
    mutable Eigen::MatrixXd rows_jacobian_;
    mutable std::vector<std::array<uint8_t, 2>> span_;
    mutable int64_t evaluations_ = 0;
    struct LastEvaluation {
        bool valid = false, ok = false;
        std::vector<double> params, residuals, jacobian;
    };
    // evaluate's last (full rows) and evaluateCompressed's last with the Jacobian (compressed
    // rows); invalidated by build and setPrior.
    mutable std::array<LastEvaluation, 2> last_;
    // Per sample: the closest point and inside sign of the loop of closest_shape_ (evaluate).
    struct SampleClosest {
        render::ClosestPoint point;
        double sign = 1.0;
        bool known = false;            // sought for closest_shape_
        int anchor = -1;               // the shape (anchors_) it was last sought for; -1 none
        double anchor_distance = 0.0;  // a proven bound below its distance then, signed; 0 none
    };
    mutable std::vector<SampleClosest> closest_;
    // The loops' control points distances were sought for, and how far the current loop's lie
    // from each (the most any of the 12 moved).
    mutable std::vector<std::array<Eigen::Vector2d, 12>> anchors_;
    mutable std::vector<double> anchor_shift_;
    mutable std::array<double, 9> closest_shape_{};
    mutable bool closest_shape_valid_ = false;
};

// Ceres' view of a ghost problem: its rows r + J x (one per sample, channel and term) handed over
// compressed to k + 1 rows for k parameters (detail::compressRows: a Householder QR of the rows,
// R x + Q1'r and one constant row for the rest of Q'r), whose cost, gradient and every
// Levenberg-Marquardt step are those of the full rows. Ceres' dense QR then factors k + 1 rows,
// augmented by its damping, for each step it tries, instead of thousands; the rows are factored
// once per Jacobian. Without a Jacobian only the cost is wanted: its norm goes in the last row.
class GhostCostFunction final : public ceres::CostFunction {
public:
    GhostCostFunction(const GhostProblem& problem, int parameters) : problem_(problem) {
        set_num_residuals(parameters + 1);
        mutable_parameter_block_sizes()->push_back(parameters);
    }
    bool Evaluate(double const* const* parameters,
                  double* residuals,
                  double** jacobians) const override {
        return problem_.evaluateCompressed(parameters[0], residuals,
                                           jacobians ? jacobians[0] : nullptr);
    }

private:
    const GhostProblem& problem_;
};

// The thesis's optimizer (§7.2): central differences, a step and a learning rate per parameter,
// the rate decaying per epoch, each parameter updated at once (online).
void gradientDescent(const GhostProblem& problem,
                     std::vector<double>& v,
                     const Bounds& bounds,
                     const FrameFitOptions& options,
                     GhostFitReport& report) {
    double current = problem.cost(v.data());
    const double initial = std::max(current, 1e-300);
    double rate = options.learning_rate;
    for (int epoch = 0; epoch < options.max_iterations; ++epoch) {
        const double before = current;
        const std::vector<double> kept = v;
        for (size_t k = 0; k < v.size(); ++k) {
            const double h = options.difference_step * bounds.scale[k];
            const double keep = v[k];
            v[k] = std::min(keep + h, bounds.upper[k]);
            const double up = problem.cost(v.data());
            const double hi = v[k];
            v[k] = std::max(keep - h, bounds.lower[k]);
            const double down = problem.cost(v.data());
            const double lo = v[k];
            v[k] = keep;
            if (!std::isfinite(up) || !std::isfinite(down) || hi == lo) continue;
            const double gradient = (up - down) / (hi - lo);
            const double step = rate * bounds.scale[k] * bounds.scale[k] * gradient / initial;
            v[k] = std::clamp(keep - step, bounds.lower[k], bounds.upper[k]);
        }
        current = problem.cost(v.data());
        report.iterations = epoch + 1;
        rate *= options.learning_decay;
        if (current > before) {
            // An epoch that raised the cost is undone and the rate halved (the thesis tuned its
            // rates by hand; this keeps the baseline from diverging on frames it was not tuned
            // for).
            v = kept;
            current = before;
            rate *= 0.5;
            continue;
        }
        if (options.target_cost > 0.0 && current <= options.target_cost) break;
        if (std::abs(before - current) <= options.function_tolerance * before) break;
    }
    report.final_cost = current;
}

}  // namespace

const char* optimizerName(Optimizer optimizer) {
    return optimizer == Optimizer::Ceres ? "ceres" : "gradient-descent";
}

Status checkFrameFitOptions(const FrameFitOptions& o) {
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "frame fit: " + what);
    };
    if (o.max_iterations < 1) return bad("max_iterations must be >= 1");
    if (o.line_search_steps < 0 || o.line_search_steps > 100)
        return bad("line_search_steps must lie in 0..100");
    if (!(o.trust_region_radius >= 1e-6 && o.trust_region_radius <= 1e16))
        return bad("trust_region_radius must lie in [1e-6, 1e16]");
    if (o.passes < 1) return bad("passes must be >= 1");
    if (!(o.function_tolerance >= 0.0)) return bad("function_tolerance must be >= 0");
    if (o.cost.max_samples < 4 || o.cost.max_samples > 4096)
        return bad("cost.max_samples must lie in 4..4096");
    if (!(o.cost.margin > 0.0) || o.cost.margin > 100.0)
        return bad("cost.margin must lie in (0, 100]");
    if (!(o.cost.transform_fraction >= 0.0) || o.cost.transform_fraction > 1e6)
        return bad("cost.transform_fraction must be >= 0");
    if (!(o.cost.transform_sigmas > 0.0) || !std::isfinite(o.cost.transform_sigmas))
        return bad("cost.transform_sigmas must be > 0");
    if (!(o.cost.edge_weight >= 0.0) || !std::isfinite(o.cost.edge_weight))
        return bad("cost.edge_weight must be >= 0");
    if (!(o.cost.edge_sigma > 0.0) || o.cost.edge_sigma > 32.0)
        return bad("cost.edge_sigma must lie in (0, 32]");
    if (!(o.cost.robust_scale > 0.0) || !std::isfinite(o.cost.robust_scale))
        return bad("cost.robust_scale must be > 0");
    if (o.cost.distance.iterations < 0 || o.cost.distance.iterations > 64)
        return bad("cost.distance.iterations must lie in 0..64");
    if (o.cost.distance.seeds_per_segment < 1 || o.cost.distance.seeds_per_segment > 64)
        return bad("cost.distance.seeds_per_segment must lie in 1..64");
    if (!(o.learning_rate > 0.0) || !std::isfinite(o.learning_rate))
        return bad("learning_rate must be > 0");
    if (!(o.learning_decay > 0.0) || o.learning_decay > 1.0)
        return bad("learning_decay must lie in (0, 1]");
    if (!(o.difference_step > 0.0) || !std::isfinite(o.difference_step))
        return bad("difference_step must be > 0");
    if (!std::isfinite(o.target_cost)) return bad("target_cost must be finite");
    if (!(o.prior_tolerance >= 0.0) || !std::isfinite(o.prior_tolerance))
        return bad("prior_tolerance must be >= 0");
    return Ok{};
}

std::array<double, 3> transformScales(const FitFrame& frame,
                                      const FrameDetection& detection,
                                      const CostOptions& cost) {
    std::array<double, 3> transform_scale{};
    const int channels = frame.channels == 1 ? 1 : 3;
    const int64_t total = frame.image.width * frame.image.height;
    const int64_t step = std::max<int64_t>(1, total / 50000);
    for (int c = 0; c < channels; ++c) {
        std::vector<double> values;
        values.reserve(static_cast<size_t>(total / step + 1));
        for (int64_t i = 0; i < total; i += step)
            if (!detection.excluded[static_cast<size_t>(i)])
                values.push_back(frame.image.pixels[static_cast<size_t>(3 * i + c)] -
                                 detection.background[static_cast<size_t>(c)]);
        double bright = 0.0;
        if (!values.empty()) {
            const size_t k = static_cast<size_t>(0.99 * static_cast<double>(values.size() - 1));
            std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k),
                             values.end());
            bright = std::max(0.0, values[k]);
        }
        transform_scale[static_cast<size_t>(c)] =
            std::max(cost.transform_sigmas * detection.noise_sigma[static_cast<size_t>(c)],
                     cost.transform_fraction * bright);
    }
    return transform_scale;
}

Result<FrameFitReport> fitFrame(const FitFrame& frame,
                                const FrameDetection& detection,
                                std::vector<GhostState>& ghosts,
                                const FrameFitOptions& options,
                                std::span<const GhostState> priors,
                                std::span<const GhostState> fixed,
                                std::span<const std::vector<GhostState>> restarts) {
    if (Status ok = checkFrameFitOptions(options); !ok) return ok.error();
    const int64_t width = frame.image.width, height = frame.image.height;
    if (width < 1 || height < 1)
        return makeError(ErrorCode::InvalidArgument, "frame fit: the frame is empty");
    if (detection.excluded.size() != static_cast<size_t>(width * height))
        return makeError(ErrorCode::InvalidArgument,
                         "frame fit: the detection's excluded mask does not match the frame size");
    for (int c = 0; c < 3; ++c)
        if (!(detection.noise_sigma[c] > 0.0) || !std::isfinite(detection.background[c]))
            return makeError(ErrorCode::InvalidArgument,
                             "frame fit: the detection's noise sigma must be > 0 and its "
                             "background finite");
    for (size_t g = 0; g < ghosts.size(); ++g) {
        if (Status ok = render::validateGhostShape(ghosts[g].shape); !ok)
            return makeError(ErrorCode::InvalidArgument,
                             "frame fit: ghost " + std::to_string(g) + ": " + ok.error().message);
        if (Status ok = render::validateShading(ghosts[g].shading); !ok)
            return makeError(ErrorCode::InvalidArgument,
                             "frame fit: ghost " + std::to_string(g) + ": " + ok.error().message);
    }
    if (restarts.size() > ghosts.size())
        return makeError(ErrorCode::InvalidArgument,
                         "frame fit: restarts for " + std::to_string(restarts.size()) +
                             " ghosts, but only " + std::to_string(ghosts.size()) +
                             " ghosts to fit");
    for (size_t g = 0; g < restarts.size(); ++g)
        for (size_t k = 0; k < restarts[g].size(); ++k) {
            Status ok = render::validateGhostShape(restarts[g][k].shape);
            if (ok) ok = render::validateShading(restarts[g][k].shading);
            if (!ok)
                return makeError(ErrorCode::InvalidArgument,
                                 "frame fit: ghost " + std::to_string(g) + ", restart " +
                                     std::to_string(k) + ": " + ok.error().message);
        }
    const auto start = Clock::now();
    FrameFitReport report;
    report.ghosts.assign(ghosts.size(), GhostFitReport{});
    const Layout layout{frame.channels == 1 ? 1 : 3};
    const double px_mm = std::max(1.0 / frame.mapping.px_per_mm_x, 1.0 / frame.mapping.px_per_mm_y);
    const double diagonal_mm = std::hypot(static_cast<double>(width) / frame.mapping.px_per_mm_x,
                                          static_cast<double>(height) / frame.mapping.px_per_mm_y);

    const std::array<double, 3> transform_scale = transformScales(frame, detection, options.cost);

    // Gauss-Seidel: each ghost is fitted against the others' latest states, brightest first.
    // (Fitted at once from the same state, overlapping ghosts would each fill the same residual
    // and overshoot together.) The cores share each ghost's cost evaluation instead.
    std::vector<size_t> order(ghosts.size());
    for (size_t g = 0; g < order.size(); ++g) order[g] = g;
    const auto peak = [&](size_t g) { return render::shadingPeak(ghosts[g].shading); };
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return peak(a) > peak(b); });
    // Ghosts whose fit from a restart was kept: their prior (the prediction the restart
    // replaced) no longer holds them.
    std::vector<char> restarted(ghosts.size(), 0);
    for (int pass = 0; pass < options.passes; ++pass) {
        const auto fit_one = [&](size_t g) {
            GhostFitReport& gr = report.ghosts[g];
            const GhostState state = ghosts[g];
            const double size_mm = ghostSize(state);
            // The crop: the pixels of the ghost's box grown by its outer falloff and the cost's
            // margin, over every state given (their boxes' union), within the frame.
            struct Crop {
                int64_t x0, y0, x1, y1;
                bool empty() const { return x0 > x1 || y0 > y1; }
            };
            const auto cropOf = [&](std::span<const GhostState> states) {
                Crop c{width, height, -1, -1};
                for (const GhostState& st : states) {
                    const auto& s = st.shape;
                    const double grow =
                        st.shading.outer_falloff_mm + options.cost.margin * ghostSize(st);
                    const auto& m = frame.mapping;
                    const Eigen::Vector2d a = m.toPixels(s.centre_x_mm - s.left_mm - grow,
                                                         s.centre_y_mm - s.half_height_mm - grow);
                    const Eigen::Vector2d b = m.toPixels(s.centre_x_mm + s.right_mm + grow,
                                                         s.centre_y_mm + s.half_height_mm + grow);
                    c.x0 = std::min(c.x0, static_cast<int64_t>(std::floor(a.x())));
                    c.y0 = std::min(c.y0, static_cast<int64_t>(std::floor(a.y())));
                    c.x1 = std::max(c.x1, static_cast<int64_t>(std::floor(b.x())));
                    c.y1 = std::max(c.y1, static_cast<int64_t>(std::floor(b.y())));
                }
                return Crop{std::max<int64_t>(0, c.x0), std::max<int64_t>(0, c.y0),
                            std::min<int64_t>(width - 1, c.x1),
                            std::min<int64_t>(height - 1, c.y1)};
            };
            const Crop crop = cropOf(std::span<const GhostState>(&state, 1));
            const int64_t x0 = crop.x0, y0 = crop.y0, x1 = crop.x1, y1 = crop.y1;
            if (crop.empty()) {
                gr.samples = 0;
                return;
            }
            std::vector<GhostState> others;
            others.reserve(ghosts.size() + fixed.size());
            others.insert(others.end(), fixed.begin(), fixed.end());
            for (size_t k = 0; k < ghosts.size(); ++k)
                if (k != g) others.push_back(ghosts[k]);
            double intensity_scale = 0.0;
            for (int c = 0; c < 3; ++c)
                intensity_scale = std::max({intensity_scale, state.shading.border_rgb[c],
                                            state.shading.inner_rgb[c], detection.noise_sigma[c]});
            GhostProblem problem(layout, options.cost, intensity_scale);
            problem.build(frame, detection, x0, y0, x1, y1, others, transform_scale);
            if (g < priors.size() && options.prior_tolerance > 0.0 && !restarted[g])
                problem.setPrior(priors[g], size_mm, options.prior_tolerance);
            gr.samples = problem.samples();
            if (problem.samples() < layout.size()) return;  // not enough data: keep the state
            const Bounds bounds = makeBounds(layout, px_mm, diagonal_mm, size_mm, state,
                                             0.5 * options.cost.margin * size_mm);
            std::vector<double> v = packState(state, layout, intensity_scale);
            clampInto(v, bounds);
            Bounds kept_bounds = bounds;  // the bounds the kept fit was solved within
            const double initial = problem.cost(v.data());
            if (pass == 0) gr.initial_cost = initial;
            if (!std::isfinite(initial)) {
                gr.ok = false;
                return;
            }
            if (options.optimizer == Optimizer::Ceres) {
                ceres::Solver::Options so;
                so.linear_solver_type = ceres::DENSE_QR;
                // With bounds, Ceres follows each trust-region step with a projected Armijo line
                // search (up to line_search_steps) whose cubic interpolation evaluates the
                // Jacobian at every trial point (GhostProblem::evaluate keeps the last one for the
                // accepted point). Quadratic interpolation, which needs only the costs, was
                // tried: 10-30 % faster, but the held-out error grew on three lenses of four
                // (docs/fit-scoring.md).
                so.max_num_iterations = options.max_iterations;
                so.max_num_line_search_step_size_iterations = options.line_search_steps;
                so.initial_trust_region_radius = options.trust_region_radius;
                so.function_tolerance = options.function_tolerance;
                so.num_threads = 1;
                so.logging_type = ceres::SILENT;
                so.minimizer_progress_to_stdout = false;
                // Levenberg-Marquardt from x within `within` on `on`; the final cost, or nullopt.
                const auto solveOn = [&](const GhostProblem& on, const Bounds& within,
                                         std::vector<double>& x) -> std::optional<double> {
                    ceres::Problem cp;
                    cp.AddResidualBlock(new GhostCostFunction(on, layout.size()), nullptr,
                                        x.data());
                    for (int k = 0; k < layout.size(); ++k) {
                        cp.SetParameterLowerBound(x.data(), k,
                                                  within.lower[static_cast<size_t>(k)]);
                        cp.SetParameterUpperBound(x.data(), k,
                                                  within.upper[static_cast<size_t>(k)]);
                    }
                    ceres::Solver::Summary summary;
                    ceres::Solve(so, &cp, &summary);
                    gr.iterations += static_cast<int>(summary.iterations.size());
                    if (summary.termination_type == ceres::FAILURE || !summary.IsSolutionUsable())
                        return std::nullopt;
                    return on.cost(x.data());
                };
                const auto solve = [&](std::vector<double>& x) {
                    return solveOn(problem, bounds, x);
                };
                // Another start, kept when it ends lower.
                const auto tryFrom = [&](std::vector<double> x) {
                    if (const auto cost = solve(x); cost && *cost < gr.final_cost) {
                        v = std::move(x);
                        gr.final_cost = *cost;
                    }
                };
                const std::vector<double> from = v;
                const auto cost = solve(v);
                if (!cost) {
                    gr.ok = false;
                    return;
                }
                gr.final_cost = *cost;
                // A ghost with no prior starts from its detection, whose blob reaches out over
                // the ghost's outer falloff: from there the fit can settle with the shape too
                // large and the border dimmed. The same start with the extents less the outer
                // falloff is tried too (on synthetic discs it takes the recovered image's error
                // from 0.07-0.29 to 0.02).
                if (pass == 0 && g >= priors.size())
                    tryFrom(shrunkByOuterFalloff(from, layout, bounds));
                // A dark rim: a shape started too large can settle with its border at zero and
                // its inner light rising steeply some way inside, which draws the ghost's edge
                // where the rise is, but cannot draw a rim brighter than the inside and holds
                // the border at its bound, where the shape no longer feels the edge. Try once
                // more from the edge the rise draws (extents less the depth where the rise is
                // half done, border as bright as the inside, a sharp falloff outside) and keep
                // the better.
                std::vector<double> retry = v;
                if (darkRim(retry, layout) && shrinkToRise(retry, layout, bounds, px_mm))
                    tryFrom(std::move(retry));
                // Other starts for a tracked ghost whose prediction is uncertain (the tracker
                // extrapolated across missing frames): each is solved on a crop that also holds
                // the start's box, without the prior (which is that prediction), and the fit
                // that explains that crop best is kept; if a restart's is, the prior is dropped
                // for the frame's later passes.
                if (pass == 0 && g < restarts.size() && !restarts[g].empty()) {
                    std::vector<GhostState> boxes = {
                        state, unpackState(v.data(), layout, intensity_scale)};
                    boxes.insert(boxes.end(), restarts[g].begin(), restarts[g].end());
                    const Crop wide = cropOf(boxes);
                    GhostProblem wider(layout, options.cost, intensity_scale);
                    wider.build(frame, detection, wide.x0, wide.y0, wide.x1, wide.y1, others,
                                transform_scale);
                    if (wider.samples() >= layout.size()) {
                        double best = wider.cost(v.data());
                        for (const GhostState& restart : restarts[g]) {
                            const double restart_mm = ghostSize(restart);
                            const Bounds around =
                                makeBounds(layout, px_mm, diagonal_mm, restart_mm, restart,
                                           0.5 * options.cost.margin * restart_mm);
                            std::vector<double> given = packState(restart, layout, intensity_scale);
                            clampInto(given, around);
                            // As given and, like a new ghost's start, less its outer falloff.
                            for (std::vector<double> x :
                                 {given, shrunkByOuterFalloff(given, layout, around)}) {
                                if (const auto c = solveOn(wider, around, x); c && *c < best) {
                                    best = *c;
                                    v = std::move(x);
                                    kept_bounds = around;
                                    gr.final_cost = best;  // on the wider crop
                                    restarted[g] = 1;
                                }
                            }
                        }
                        gr.evaluations += wider.evaluations();
                    }
                }
            } else {
                GhostFitReport local;
                gradientDescent(problem, v, bounds, options, local);
                gr.iterations += local.iterations;
                gr.final_cost = local.final_cost;
            }
            gr.evaluations += problem.evaluations();
            clampInto(v, kept_bounds);
            GhostState fitted = unpackState(v.data(), layout, intensity_scale);
            if (render::validateGhostShape(fitted.shape) && render::validateShading(fitted.shading))
                ghosts[g] = fitted;
            else
                gr.ok = false;
        };
        for (const size_t g : order) fit_one(g);
    }
    for (const auto& gr : report.ghosts) {
        report.initial_cost += gr.initial_cost;
        report.final_cost += gr.final_cost;
        report.evaluations += gr.evaluations;
    }
    report.time_ms = millisecondsSince(start);
    return report;
}

ImageRGB drawFrameModel(const FitFrame& frame,
                        const FrameDetection& detection,
                        const std::vector<GhostState>& ghosts,
                        const render::FastDistanceOptions& distance) {
    ModelRenderOptions options;
    options.distance = distance;
    ImageRGB image =
        renderGhostStates(ghosts, frame.mapping, frame.image.width, frame.image.height, options);
    for (size_t i = 0; i < image.pixels.size(); i += 3)
        for (int c = 0; c < 3; ++c)
            image.pixels[i + static_cast<size_t>(c)] += static_cast<float>(
                detection.background[static_cast<size_t>(frame.channels == 1 ? 0 : c)]);
    return image;
}

}  // namespace flarelab::fit
