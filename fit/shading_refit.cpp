#include "fit/shading_refit.h"

#include <ceres/ceres.h>
#include <ceres/jet.h>
#include <tbb/parallel_for.h>

#include <Eigen/QR>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "common/check.h"
#include "fit/gauss_seidel.h"
#include "fit/model_eval.h"
#include "fit/polyfit.h"
#include "fit/sweep_fit.h"

namespace flarelab::fit {
namespace {

using Clock = std::chrono::steady_clock;

// The ten shading values of a ghost, as indices of its parameters (model_eval.h): ln border
// r, g, b; ln inner r, g, b; inner and outer falloff; inner and outer exponent.
constexpr int kShadingCount = 10;
constexpr int kFirstShading = 9;
// The weight of a series' excursion out of its bounds, per bounds' width and observation.
constexpr double kBoundPenalty = 1.0;
// The weight of a jump between a series' adjacent pieces at their shared end, per bounds' width
// and square root of the ghost's observations: stiff, since no frame lies at the joint (it is
// half-way between two frames) and a piece's end is otherwise free to swing.
constexpr double kJointPenalty = 10.0;
using ShadingJet = ceres::Jet<double, kShadingCount>;

Error invalid(const std::string& message) {
    return makeError(ErrorCode::InvalidArgument, "shading refit: " + message);
}

// One parameter's series: where each piece's coefficients sit in the ghost's vector.
struct SeriesLayout {
    const ModelParameter* parameter = nullptr;
    std::vector<int> offsets;  // per piece
};

// Where a value comes from at an angle: the piece, its coefficient offset, x in [-1, 1].
struct SeriesPoint {
    int offset = 0;
    int count = 0;
    double x = 0.0;
};

SeriesPoint seriesPoint(const SeriesLayout& layout, double angle_deg) {
    const auto& pieces = layout.parameter->pieces;
    size_t k = 0;  // the piece holding the angle: the later one at a shared end (modelGhostsAt)
    for (size_t i = 0; i < pieces.size(); ++i)
        if (angle_deg >= pieces[i].angle_from_deg) k = i;
    const ModelPiece& piece = pieces[k];
    const double span = piece.angle_to_deg - piece.angle_from_deg;
    SeriesPoint p;
    p.offset = layout.offsets[k];
    p.count = static_cast<int>(piece.coefficients.size());
    p.x = span > 0.0 ? std::clamp(2.0 * (angle_deg - piece.angle_from_deg) / span - 1.0, -1.0, 1.0)
                     : 0.0;
    return p;
}

// The width of parameter p's bounds (the model's own, else the parameter's), at least 1e-3; 1
// when either end is open. The scale of the penalty rows.
double boundsWidth(const ModelParameter& parameter, int p) {
    const GhostParameterInfo& info = ghostParameterInfo(p);
    const std::optional<double> lo =
        parameter.lower_bound ? parameter.lower_bound : info.lower_bound;
    const std::optional<double> hi =
        parameter.upper_bound ? parameter.upper_bound : info.upper_bound;
    return lo && hi ? std::max(*hi - *lo, 1e-3) : 1.0;
}

// Opens shape value p's bounds symmetrically to at least half the ghost's size (centre and
// extents) or their whole range (handle fractions), inside the parameter's own bounds.
void openShapeBounds(ModelParameter& parameter, int p, double size_mm) {
    if (!parameter.lower_bound || !parameter.upper_bound) return;
    const double width = *parameter.upper_bound - *parameter.lower_bound;
    const double want = p < 5 ? 0.5 * size_mm : 1.0;
    if (!(width < want)) return;
    const double pad = 0.5 * (want - width);
    const GhostParameterInfo& info = ghostParameterInfo(p);
    *parameter.lower_bound -= pad;
    *parameter.upper_bound += pad;
    if (info.lower_bound)
        *parameter.lower_bound = std::max(*parameter.lower_bound, *info.lower_bound);
    if (info.upper_bound)
        *parameter.upper_bound = std::min(*parameter.upper_bound, *info.upper_bound);
}

// T_0(x) .. T_{n-1}(x).
void chebyshevBasis(double x, int n, double* out) {
    if (n > 0) out[0] = 1.0;
    if (n > 1) out[1] = x;
    for (int k = 2; k < n; ++k) out[k] = 2.0 * x * out[k - 1] - out[k - 2];
}

// One frame's view of one ghost: its crop's samples, where they lie relative to the ghost and to
// every other ghost reaching into the crop, and the data.
struct Observation {
    double angle_deg = 0.0;
    std::array<double, 3> scale{};            // of the transform, per fitted channel
    std::vector<render::BlockDistance> self;  // to this ghost, per sample
    std::vector<std::array<double, 3>> data;  // frame minus background, per sample
    // Per sample, the channels (bits 1, 2, 4) whose data is only a lower bound (FitFrame::
    // lower_bound): a model at or above it is no error.
    std::vector<uint8_t> bound;
    // Per sample, the weight of its residual: 1 for a whole block, the square root of its share
    // of the block for the parts of a block split around excluded pixels.
    std::vector<double> weight;
    std::vector<std::pair<size_t, std::vector<render::BlockDistance>>>
        others;  // ghost index, samples
    // The samples' block centres and half sizes (mm), for the shape refit's own distances.
    std::vector<Eigen::Vector2d> points, halves;
    // The share of the ghost's outline (as compressed) that lies in the frame: what the frame
    // can say about its shape.
    double outline_in_frame = 1.0;
};

// The share of `loop`'s outline, sampled evenly in each segment's parameter, inside the
// rectangle [x0, x1] x [y0, y1] (mm).
double outlineShareInside(
    const render::BezierLoop& loop, double x0, double x1, double y0, double y1) {
    constexpr int kPerSegment = 16;
    int inside = 0, all = 0;
    for (int i = 0; i < loop.segmentCount(); ++i)
        for (int k = 0; k < kPerSegment; ++k, ++all) {
            const Eigen::Vector2d q = loop.point(i, (static_cast<double>(k) + 0.5) / kPerSegment);
            inside += q.x() >= x0 && q.x() <= x1 && q.y() >= y0 && q.y() <= y1 ? 1 : 0;
        }
    return all > 0 ? static_cast<double>(inside) / static_cast<double>(all) : 0.0;
}

// The model's ghosts with the series of their parameters first..18 exposed as coefficient
// vectors: the shading values (first = kFirstShading), or every value (first = 0).
class SeriesModel {
public:
    SeriesModel(FlareModel& model, int channels, int first = kFirstShading)
        : channels_(channels), first_(first) {
        for (ModelGhost& ghost : model.ghosts) {
            Ghost g;
            g.ghost = &ghost;
            g.usable = ghost.parameters.size() == kGhostParameterCount;
            for (const auto& p : ghost.parameters) g.usable = g.usable && !p.pieces.empty();
            if (g.usable) {
                for (int i = first_; i < kGhostParameterCount; ++i) {
                    // One-channel frames: channels 1 and 2 follow channel 0.
                    const int source = sourceIndex(i);
                    SeriesLayout layout;
                    layout.parameter = &ghost.parameters[static_cast<size_t>(i)];
                    if (source == i) {
                        for (const auto& piece : layout.parameter->pieces) {
                            layout.offsets.push_back(static_cast<int>(g.coefficients.size()));
                            g.coefficients.insert(g.coefficients.end(), piece.coefficients.begin(),
                                                  piece.coefficients.end());
                        }
                    }
                    g.series[static_cast<size_t>(i)] = std::move(layout);
                }
                for (int i = first_; i < kGhostParameterCount; ++i)
                    if (sourceIndex(i) != i)
                        g.series[static_cast<size_t>(i)].offsets =
                            g.series[static_cast<size_t>(sourceIndex(i))].offsets;
            }
            ghosts_.push_back(std::move(g));
        }
    }

    // The parameter whose series parameter p reads (1-channel: ln intensities of channel 0).
    int sourceIndex(int p) const {
        if (channels_ != 1) return p;
        if (p == 10 || p == 11) return 9;
        if (p == 13 || p == 14) return 12;
        return p;
    }
    int first() const { return first_; }

    size_t size() const { return ghosts_.size(); }

    // Where two adjacent pieces of a fitted series meet: the left piece's coefficients (read at
    // x = 1) and the right one's (at x = -1), and the width of the series' bounds.
    struct Joint {
        int left_offset = 0, left_count = 0, right_offset = 0, right_count = 0;
        double span = 1.0;
    };
    std::vector<Joint> joints(size_t g) const {
        std::vector<Joint> out;
        const Ghost& ghost = ghosts_[g];
        for (int i = first_; i < kGhostParameterCount; ++i) {
            if (sourceIndex(i) != i) continue;
            const SeriesLayout& layout = ghost.series[static_cast<size_t>(i)];
            const auto& pieces = layout.parameter->pieces;
            const double span = boundsWidth(*layout.parameter, i);
            for (size_t k = 0; k + 1 < pieces.size(); ++k) {
                Joint j;
                j.left_offset = layout.offsets[k];
                j.left_count = static_cast<int>(pieces[k].coefficients.size());
                j.right_offset = layout.offsets[k + 1];
                j.right_count = static_cast<int>(pieces[k + 1].coefficients.size());
                j.span = span;
                out.push_back(j);
            }
        }
        return out;
    }
    bool usable(size_t g) const { return ghosts_[g].usable; }
    std::vector<double>& coefficients(size_t g) { return ghosts_[g].coefficients; }
    size_t coefficientCount(size_t g) const { return ghosts_[g].coefficients.size(); }
    const ModelGhost& ghost(size_t g) const { return *ghosts_[g].ghost; }

    // Whether the ghost is defined at the angle (modelGhostsAt's rule).
    bool covers(size_t g, double angle_deg) const {
        const auto& pieces = ghosts_[g].ghost->parameters.front().pieces;
        return angle_deg >= pieces.front().angle_from_deg &&
               angle_deg <= pieces.back().angle_to_deg;
    }

    // Parameters first..18 at an angle from coefficient vector `c` (the ghost's own when null),
    // clamped into the parameters' bounds, with where each comes from (its series' piece and x),
    // the value before clamping and the width of its bounds; indexed by parameter.
    struct Values {
        std::array<double, kGhostParameterCount> value{};
        std::array<SeriesPoint, kGhostParameterCount> point{};
        std::array<bool, kGhostParameterCount> clamped{};
        std::array<double, kGhostParameterCount> raw{};
        std::array<double, kGhostParameterCount> span{};
    };
    Values values(size_t g, double angle_deg, const double* c = nullptr) const {
        const Ghost& ghost = ghosts_[g];
        if (!c) c = ghost.coefficients.data();
        Values v;
        double basis[64];
        for (int i = first_; i < kGhostParameterCount; ++i) {
            const SeriesLayout& layout = ghost.series[static_cast<size_t>(i)];
            const SeriesPoint p =
                seriesPoint(ghost.series[static_cast<size_t>(sourceIndex(i))], angle_deg);
            const int n = std::min(p.count, 64);
            chebyshevBasis(p.x, n, basis);
            double value = 0.0;
            for (int k = 0; k < n; ++k) value += c[p.offset + k] * basis[k];
            // The bounds of the parameter itself (channels 1, 2 of a one-channel frame share
            // channel 0's series but keep their own bounds, as the model stores them).
            double clamped = value;
            const ModelParameter& parameter = *layout.parameter;
            const GhostParameterInfo& info = ghostParameterInfo(i);
            if (parameter.lower_bound) clamped = std::max(clamped, *parameter.lower_bound);
            if (parameter.upper_bound) clamped = std::min(clamped, *parameter.upper_bound);
            if (info.lower_bound) clamped = std::max(clamped, *info.lower_bound);
            if (info.upper_bound) clamped = std::min(clamped, *info.upper_bound);
            v.value[static_cast<size_t>(i)] = clamped;
            v.point[static_cast<size_t>(i)] = p;
            // A value whose bounds (nearly) meet is held by them whatever its series does: in the
            // shape refit no gradient either, or the solver steps along it and the step changes
            // nothing (the shading refit keeps the gradient: see refitShading).
            const bool pinned =
                first_ == 0 && parameter.lower_bound && parameter.upper_bound &&
                *parameter.upper_bound - *parameter.lower_bound <= 1e-6 * (1.0 + std::abs(clamped));
            v.clamped[static_cast<size_t>(i)] = clamped != value || pinned;
            v.raw[static_cast<size_t>(i)] = value;
            v.span[static_cast<size_t>(i)] = boundsWidth(parameter, i);
        }
        return v;
    }

    // The ghost's mean intensity over a sample's block in channel ch for given values.
    static double intensity(const Values& v, const render::BlockDistance& b, int ch) {
        const double border = intensityOf(v.value[static_cast<size_t>(9 + ch)]);
        const double inner = intensityOf(v.value[static_cast<size_t>(12 + ch)]);
        const auto w =
            render::boxTransferWeights<double>(b.distance_mm, b.spread_x_mm, b.spread_y_mm,
                                               v.value[15], v.value[16], v.value[17], v.value[18]);
        return border * w.border + inner * w.inner;
    }
    // The state of every value (first == 0 only).
    static Result<GhostState> state(const Values& v) { return ghostStateFromParameters(v.value); }
    static double intensityOf(double ln) {
        return ln <= kMinLnIntensity ? 0.0 : std::exp(std::min(ln, 80.0));
    }

    // Writes the coefficients back into the model's pieces; a value that follows another's
    // series (one-channel frames) takes that series' pieces and keeps its own bounds.
    void store(size_t g) {
        Ghost& ghost = ghosts_[g];
        for (int i = first_; i < kGhostParameterCount; ++i) {
            if (sourceIndex(i) != i) continue;
            const SeriesLayout& layout = ghost.series[static_cast<size_t>(i)];
            auto& parameter = ghost.ghost->parameters[static_cast<size_t>(i)];
            for (size_t k = 0; k < parameter.pieces.size(); ++k) {
                auto& coefficients = parameter.pieces[k].coefficients;
                for (size_t j = 0; j < coefficients.size(); ++j)
                    coefficients[j] =
                        ghost.coefficients[static_cast<size_t>(layout.offsets[k]) + j];
            }
        }
        for (int i = first_; i < kGhostParameterCount; ++i) {
            if (sourceIndex(i) == i) continue;
            ghost.ghost->parameters[static_cast<size_t>(i)].pieces =
                ghost.ghost->parameters[static_cast<size_t>(sourceIndex(i))].pieces;
        }
    }

private:
    struct Ghost {
        ModelGhost* ghost = nullptr;
        bool usable = false;
        std::vector<double> coefficients;
        std::array<SeriesLayout, kGhostParameterCount> series;  // first..18 set
    };
    int channels_ = 3;
    int first_ = kFirstShading;
    std::vector<Ghost> ghosts_;
};

// Ceres' view of one ghost: its observations' residuals as functions of its coefficients. With
// a model of shading series (first() == kFirstShading) the samples' distances are the
// observations' own (the shape held); with one of every series (first() == 0) they are sought
// from the shape the coefficients give, with their gradient.
class GhostSeriesCost final : public ceres::CostFunction {
public:
    GhostSeriesCost(const SeriesModel& model,
                    size_t ghost,
                    const std::vector<Observation>& observations,
                    int channels,
                    double robust_scale,
                    const render::FastDistanceOptions& distance)
        : model_(model),
          ghost_(ghost),
          observations_(observations),
          channels_(channels),
          c2_(robust_scale * robust_scale),
          distance_(distance),
          shape_(model.first() == 0) {
        // The other ghosts' light at every sample, from their current series.
        others_.resize(observations.size());
        offsets_.resize(observations.size());
        closest_.resize(observations.size());
        int rows = 0;
        for (size_t o = 0; o < observations.size(); ++o) {
            const Observation& obs = observations[o];
            auto& sum = others_[o];
            sum.assign(obs.self.size(), {0.0, 0.0, 0.0});
            for (const auto& [h, samples] : obs.others) {
                const auto v = model.values(h, obs.angle_deg);
                if (!shape_) {
                    for (size_t s = 0; s < samples.size(); ++s)
                        for (int c = 0; c < channels; ++c)
                            sum[s][static_cast<size_t>(c)] +=
                                SeriesModel::intensity(v, samples[s], c);
                    continue;
                }
                // Its shape too is a series: drawn where it is now.
                const auto state = SeriesModel::state(v);
                if (!state) continue;  // not finite: ghostStateFromParameters names it
                const render::BezierLoop loop = render::toBezierLoop(state->shape);
                tbb::parallel_for(size_t{0}, obs.points.size(), [&](size_t s) {
                    const auto light = render::shadeGhostBlock(loop, state->shading, obs.points[s],
                                                               obs.halves[s], distance_);
                    for (int c = 0; c < channels; ++c)
                        sum[s][static_cast<size_t>(c)] += light[static_cast<size_t>(c)];
                });
            }
            // The frame's sample rows are handed to Ceres compressed (Evaluate): values_ rows
            // and one more, whatever the number of samples.
            offsets_[o] = rows;
            rows += kGhostParameterCount - model.first() + 1;
        }
        // Then one row per observation and value: how far the series has left its bounds. The
        // clamp gives the image rows no gradient there, so without these a series that strays
        // out of bounds at a frame could never be drawn back.
        values_ = kGhostParameterCount - model.first();
        penalty_offset_ = rows;
        rows += static_cast<int>(observations.size()) * values_;
        // And one per joint of adjacent pieces: the jump between them.
        joints_ = model.joints(ghost);
        joint_offset_ = rows;
        joint_weight_ = kJointPenalty * std::sqrt(static_cast<double>(observations.size()));
        rows += static_cast<int>(joints_.size());
        set_num_residuals(rows);
        mutable_parameter_block_sizes()->push_back(static_cast<int>(model.coefficientCount(ghost)));
    }

    bool Evaluate(double const* const* parameters,
                  double* residuals,
                  double** jacobians) const override {
        const double* c = parameters[0];
        const int np = parameter_block_sizes()[0];
        double* jacobian = jacobians ? jacobians[0] : nullptr;
        std::atomic<bool> finite{true};
        // T_k(1) = 1 and T_k(-1) = (-1)^k.
        for (size_t q = 0; q < joints_.size(); ++q) {
            const auto& j = joints_[q];
            const double weight = joint_weight_ / j.span;
            double jump = 0.0;
            for (int k = 0; k < j.left_count; ++k) jump += c[j.left_offset + k];
            for (int k = 0; k < j.right_count; ++k)
                jump -= (k % 2 == 0 ? 1.0 : -1.0) * c[j.right_offset + k];
            const int row = joint_offset_ + static_cast<int>(q);
            residuals[row] = weight * jump;
            if (!jacobian) continue;
            double* out = jacobian + static_cast<size_t>(row) * np;
            std::fill(out, out + np, 0.0);
            for (int k = 0; k < j.left_count; ++k) out[j.left_offset + k] = weight;
            for (int k = 0; k < j.right_count; ++k)
                out[j.right_offset + k] = -(k % 2 == 0 ? 1.0 : -1.0) * weight;
        }
        tbb::parallel_for(size_t{0}, observations_.size(), [&](size_t o) {
            const Observation& obs = observations_[o];
            const auto v = model_.values(ghost_, obs.angle_deg, c);
            const int sample_rows = static_cast<int>(obs.self.size()) * channels_;
            // d value / d coefficient: the Chebyshev basis at each value's point.
            double basis[kGhostParameterCount][64];
            for (int p = model_.first(); p < kGhostParameterCount; ++p)
                chebyshevBasis(v.point[static_cast<size_t>(p)].x,
                               std::min(v.point[static_cast<size_t>(p)].count, 64), basis[p]);
            for (int p = model_.first(); p < kGhostParameterCount; ++p) {
                const size_t i = static_cast<size_t>(p);
                const int row =
                    penalty_offset_ + static_cast<int>(o) * values_ + (p - model_.first());
                const double weight = kBoundPenalty / v.span[i];
                residuals[row] = weight * (v.raw[i] - v.value[i]);
                if (!jacobian) continue;
                double* out = jacobian + static_cast<size_t>(row) * np;
                std::fill(out, out + np, 0.0);
                if (!v.clamped[i]) continue;
                for (int k = 0; k < std::min(v.point[i].count, 64); ++k)
                    out[v.point[i].offset + k] += weight * basis[p][k];
            }
            // The frame's sample rows, before compression: residuals and d residual / d value.
            Eigen::VectorXd local_r = Eigen::VectorXd::Zero(sample_rows);
            Eigen::MatrixXd local_j;
            if (jacobian) local_j.setZero(sample_rows, values_);
            // One sample's model m in channel ch (and d m / d value per parameter, when the
            // Jacobian is asked): the robust residual and its row.
            const auto emit = [&](size_t s, int ch, double m, const double* dm) {
                const int row = static_cast<int>(s) * channels_ + ch;
                const double scale = obs.scale[static_cast<size_t>(ch)];
                const double total = m + others_[o][s][static_cast<size_t>(ch)];
                double r = std::asinh(total / scale) -
                           std::asinh(obs.data[s][static_cast<size_t>(ch)] / scale);
                double dr = 1.0 / std::sqrt(scale * scale + total * total);
                if (((obs.bound[s] >> ch) & 1u) != 0 && r > 0.0) r = dr = 0.0;
                const double s2 = r * r;
                const double rho = c2_ * std::log1p(s2 / c2_);
                const double rt = std::copysign(std::sqrt(rho), r);
                if (!std::isfinite(rt)) {
                    finite = false;
                    return;
                }
                const double w = obs.weight[s];
                local_r[row] = w * rt;
                if (!jacobian) return;
                const double factor = w * (rt != 0.0 ? (1.0 / (1.0 + s2 / c2_)) * r / rt : 1.0);
                for (int p = model_.first(); p < kGhostParameterCount; ++p)
                    if (!v.clamped[static_cast<size_t>(p)])
                        local_j(row, p - model_.first()) = factor * dr * dm[p];
            };
            if (shape_)
                shapeSamples(o, v, jacobian != nullptr, emit);
            else
                shadingSamples(obs, v, jacobian != nullptr, emit);
            if (!finite) return;
            // The frame's rows J = D B (D: d residual / d value, B: the values' Chebyshev
            // bases) reach Ceres compressed (detail::compressRows): the dense solve sees
            // values_ + 1 rows per frame instead of one per sample and channel.
            double* const rows_out = residuals + offsets_[o];
            std::fill(rows_out, rows_out + values_ + 1, 0.0);
            if (!jacobian) {
                rows_out[values_] = local_r.norm();
                return;
            }
            const detail::CompressedRows packed = detail::compressRows(local_j, local_r);
            const int kept = static_cast<int>(packed.head.size());
            for (int i = 0; i < kept; ++i) rows_out[i] = packed.head[i];
            rows_out[values_] = packed.rest;
            for (int i = 0; i <= values_; ++i) {
                double* out = jacobian + static_cast<size_t>(offsets_[o] + i) * np;
                std::fill(out, out + np, 0.0);
                if (i >= kept) continue;
                for (int p = model_.first() + i; p < kGhostParameterCount; ++p) {
                    const size_t pi = static_cast<size_t>(p);
                    const double g = packed.factor(i, p - model_.first());
                    if (g == 0.0 || v.clamped[pi]) continue;
                    for (int k = 0; k < std::min(v.point[pi].count, 64); ++k)
                        out[v.point[pi].offset + k] += g * basis[p][k];
                }
            }
        });
        return finite;
    }

private:
    // The shading refit's samples: distances fixed, the ten shading values as Jets (ln
    // intensities through exp).
    template <typename Emit>
    void shadingSamples(const Observation& obs,
                        const SeriesModel::Values& v,
                        bool jacobian,
                        const Emit& emit) const {
        const auto at = [&](int i) { return static_cast<size_t>(kFirstShading + i); };
        ShadingJet value[kShadingCount];
        for (int i = 0; i < kShadingCount; ++i) value[i] = ShadingJet(v.value[at(i)], i);
        ShadingJet border[3], inner[3];
        for (int ch = 0; ch < 3; ++ch) {
            border[ch] = v.value[at(ch)] <= kMinLnIntensity ? ShadingJet(0.0) : exp(value[ch]);
            inner[ch] =
                v.value[at(3 + ch)] <= kMinLnIntensity ? ShadingJet(0.0) : exp(value[3 + ch]);
        }
        double dm[kGhostParameterCount] = {};
        for (size_t s = 0; s < obs.self.size(); ++s) {
            const render::BlockDistance& b = obs.self[s];
            render::TransferWeights<ShadingJet> w{};
            if (jacobian)
                w = render::boxTransferWeights<ShadingJet>(ShadingJet(b.distance_mm), b.spread_x_mm,
                                                           b.spread_y_mm, value[6], value[7],
                                                           value[8], value[9]);
            for (int ch = 0; ch < channels_; ++ch) {
                if (!jacobian) {
                    emit(s, ch, SeriesModel::intensity(v, b, ch), nullptr);
                    continue;
                }
                const ShadingJet m = border[ch] * w.border + inner[ch] * w.inner;
                for (int i = 0; i < kShadingCount; ++i) dm[kFirstShading + i] = m.v[i];
                emit(s, ch, m.a, dm);
            }
        }
    }

    // The shape refit's samples: each sample's distance to the loop the shape values draw, and
    // its gradient with respect to them at the closest point (d dist / d P_k = -u B_k(t), u the
    // unit vector from the curve to the sample), chained through the control points.
    template <typename Emit>
    void shapeSamples(size_t o,
                      const SeriesModel::Values& v,
                      bool jacobian,
                      const Emit& emit) const {
        const Observation& obs = observations_[o];
        using ShapeJet = ceres::Jet<double, 9>;
        std::array<ShapeJet, 9> shape;
        for (int i = 0; i < 9; ++i)
            shape[static_cast<size_t>(i)] = ShapeJet(v.value[static_cast<size_t>(i)], i);
        std::array<ShapeJet, 9> handles_mm = shape;  // handles from their fractions
        handles_mm[5] = shape[5] * shape[3];
        handles_mm[6] = shape[6] * shape[2];
        handles_mm[7] = shape[7] * shape[4];
        handles_mm[8] = shape[8] * shape[2];
        const auto points = render::ghostShapeControlPoints<ShapeJet>(handles_mm.data());
        render::BezierLoop loop;
        loop.control_points_mm.resize(points.size());
        for (size_t k = 0; k < points.size(); ++k)
            loop.control_points_mm[k] = {points[k].x().a, points[k].y().a};
        // Ceres asks for the residuals of a step, then for the Jacobian at the accepted one:
        // the closest points of the last shape are kept.
        Closest& cache = closest_[o];
        const std::array<double, 9> key{v.value[0], v.value[1], v.value[2], v.value[3], v.value[4],
                                        v.value[5], v.value[6], v.value[7], v.value[8]};
        if (!cache.valid || cache.shape != key) {
            cache.points.resize(obs.points.size());
            cache.sign.resize(obs.points.size());
            tbb::parallel_for(size_t{0}, obs.points.size(), [&](size_t s) {
                cache.points[s] = render::closestPointFast(loop, obs.points[s], distance_);
                cache.sign[s] = render::windingNumber(loop, obs.points[s]) != 0 ? -1.0 : 1.0;
            });
            cache.shape = key;
            cache.valid = true;
        }
        double border[3], inner[3];
        for (int ch = 0; ch < 3; ++ch) {
            border[ch] = SeriesModel::intensityOf(v.value[static_cast<size_t>(9 + ch)]);
            inner[ch] = SeriesModel::intensityOf(v.value[static_cast<size_t>(12 + ch)]);
        }
        using Jet5 = ceres::Jet<double, 5>;  // d and the four falloff values
        const Jet5 fi(v.value[15], 1), fo(v.value[16], 2), ei(v.value[17], 3), eo(v.value[18], 4);
        double dm[kGhostParameterCount] = {};
        for (size_t s = 0; s < obs.points.size(); ++s) {
            const render::ClosestPoint& cp = cache.points[s];
            const double sign = cache.sign[s];
            const double d = sign * cp.distance_mm;
            const Eigen::Vector2d spread = render::blockSpread(obs.points[s], cp, obs.halves[s]);
            const auto w = render::boxTransferWeights<Jet5>(Jet5(d, 0), spread.x(), spread.y(), fi,
                                                            fo, ei, eo);
            std::array<double, 9> dd{};
            if (jacobian && cp.distance_mm > 1e-12) {
                const Eigen::Vector2d u = (obs.points[s] - cp.point_mm) / cp.distance_mm;
                const double t = cp.t, mt = 1.0 - t;
                const double bernstein[4] = {mt * mt * mt, 3.0 * mt * mt * t, 3.0 * mt * t * t,
                                             t * t * t};
                for (int b = 0; b < 4; ++b) {
                    const auto& p = points[static_cast<size_t>((3 * cp.segment + b) % 12)];
                    for (int k = 0; k < 9; ++k)
                        dd[static_cast<size_t>(k)] -=
                            sign * bernstein[b] * (u.x() * p.x().v[k] + u.y() * p.y().v[k]);
                }
            }
            for (int ch = 0; ch < channels_; ++ch) {
                const double m = border[ch] * w.border.a + inner[ch] * w.inner.a;
                if (!jacobian) {
                    emit(s, ch, m, nullptr);
                    continue;
                }
                const double slope = border[ch] * w.border.v[0] + inner[ch] * w.inner.v[0];
                for (int k = 0; k < 9; ++k) dm[k] = slope * dd[static_cast<size_t>(k)];
                std::fill(dm + 9, dm + 15, 0.0);
                dm[9 + ch] = border[ch] * w.border.a;  // d exp(ln b) / d ln b = b
                dm[12 + ch] = inner[ch] * w.inner.a;
                for (int k = 1; k < 5; ++k)
                    dm[14 + k] = border[ch] * w.border.v[k] + inner[ch] * w.inner.v[k];
                emit(s, ch, m, dm);
            }
        }
    }

    struct Closest {
        bool valid = false;
        std::array<double, 9> shape{};
        std::vector<render::ClosestPoint> points;
        std::vector<double> sign;
    };
    const SeriesModel& model_;
    size_t ghost_;
    const std::vector<Observation>& observations_;
    int channels_;
    double c2_;
    render::FastDistanceOptions distance_;
    bool shape_ = false;
    std::vector<std::vector<std::array<double, 3>>> others_;
    std::vector<int> offsets_;
    int values_ = kShadingCount;
    int penalty_offset_ = 0;
    std::vector<SeriesModel::Joint> joints_;
    int joint_offset_ = 0;
    double joint_weight_ = 0.0;
    mutable std::vector<Closest> closest_;  // per observation (shape refit)
};

// A ghost's loop and its pixel box grown by `grow_mm`, clipped to the frame; false if empty.
struct Crop {
    int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;
};
Crop cropOf(const GhostState& state, double grow_mm, const FitFrame& frame) {
    const auto& s = state.shape;
    const auto& m = frame.mapping;
    const Eigen::Vector2d a =
        m.toPixels(s.centre_x_mm - s.left_mm - grow_mm, s.centre_y_mm - s.half_height_mm - grow_mm);
    const Eigen::Vector2d b = m.toPixels(s.centre_x_mm + s.right_mm + grow_mm,
                                         s.centre_y_mm + s.half_height_mm + grow_mm);
    Crop c;
    const double w = static_cast<double>(frame.image.width - 1);
    const double h = static_cast<double>(frame.image.height - 1);
    c.x0 = static_cast<int64_t>(std::clamp(std::floor(a.x()), 0.0, w + 1.0));
    c.y0 = static_cast<int64_t>(std::clamp(std::floor(a.y()), 0.0, h + 1.0));
    c.x1 = static_cast<int64_t>(std::clamp(std::floor(b.x()), -1.0, w));
    c.y1 = static_cast<int64_t>(std::clamp(std::floor(b.y()), -1.0, h));
    return c;
}

}  // namespace

namespace detail {

CompressedRows compressRows(const Eigen::MatrixXd& d, Eigen::VectorXd r) {
    Eigen::MatrixXd work = d;
    return compressRowsInPlace(work, r);
}

CompressedRows compressRowsInPlace(Eigen::Ref<Eigen::MatrixXd> d, Eigen::Ref<Eigen::VectorXd> r) {
    FLARELAB_CHECK(d.rows() == r.size());
    const Eigen::Index kept = std::min(d.rows(), d.cols());
    const Eigen::HouseholderQR<Eigen::Ref<Eigen::MatrixXd>> qr(d);
    r.applyOnTheLeft(qr.householderQ().adjoint());
    CompressedRows out;
    out.factor = qr.matrixQR().topRows(kept).triangularView<Eigen::Upper>();
    out.head = r.head(kept);
    out.rest = r.tail(r.size() - kept).norm();
    return out;
}

}  // namespace detail

Status checkShadingRefitOptions(const ShadingRefitOptions& options) {
    if (options.frames_per_ghost < 0 || options.frames_per_ghost == 1 ||
        options.frames_per_ghost > 10000)
        return invalid("frames_per_ghost must be 0 (off) or 2..10000");
    if (options.max_samples < 4 || options.max_samples > 4096)
        return invalid("max_samples must lie in 4..4096");
    if (options.max_iterations < 1 || options.max_iterations > 10000)
        return invalid("max_iterations must lie in 1..10000");
    if (options.passes < 1 || options.passes > 100) return invalid("passes must lie in 1..100");
    if (options.min_degree < 0 || options.min_degree > 12)
        return invalid("min_degree must lie in 0..12");
    if (options.shape_passes < 0 || options.shape_passes > 100)
        return invalid("shape_passes must lie in 0..100");
    if (options.shape_frames_per_ghost < 2 || options.shape_frames_per_ghost > 10000)
        return invalid("shape_frames_per_ghost must lie in 2..10000");
    if (!(options.shape_min_outline_in_frame >= 0.0 && options.shape_min_outline_in_frame <= 1.0))
        return invalid("shape_min_outline_in_frame must lie in 0..1");
    return Ok{};
}

std::vector<SampleBlock> sampleBlocks(int64_t x0,
                                      int64_t x1,
                                      int64_t y0,
                                      int64_t y1,
                                      int64_t stride,
                                      const std::vector<uint8_t>& excluded,
                                      int64_t width) {
    FLARELAB_CHECK(stride >= 1);
    std::vector<SampleBlock> out;
    const auto split = [&](auto&& self, SampleBlock b, double block_area) -> void {
        int64_t hit = 0;
        for (int64_t y = b.y0; y <= b.y1; ++y)
            for (int64_t x = b.x0; x <= b.x1; ++x)
                hit += excluded[static_cast<size_t>(y * width + x)] != 0;
        const int64_t area = (b.x1 - b.x0 + 1) * (b.y1 - b.y0 + 1);
        if (hit == area) return;
        if (hit == 0) {
            b.weight = static_cast<double>(area) == block_area
                           ? 1.0
                           : std::sqrt(static_cast<double>(area) / block_area);
            out.push_back(b);
            return;
        }
        SampleBlock first = b, second = b;  // a block of one pixel is never mixed
        if (b.x1 - b.x0 >= b.y1 - b.y0) {
            first.x1 = b.x0 + (b.x1 - b.x0) / 2;
            second.x0 = first.x1 + 1;
        } else {
            first.y1 = b.y0 + (b.y1 - b.y0) / 2;
            second.y0 = first.y1 + 1;
        }
        self(self, first, block_area);
        self(self, second, block_area);
    };
    for (int64_t ay = y0; ay <= y1; ay += stride)
        for (int64_t ax = x0; ax <= x1; ax += stride) {
            SampleBlock b;
            b.x0 = ax;
            b.x1 = std::min(x1, ax + stride - 1);
            b.y0 = ay;
            b.y1 = std::min(y1, ay + stride - 1);
            split(split, b, static_cast<double>((b.x1 - b.x0 + 1) * (b.y1 - b.y0 + 1)));
        }
    return out;
}

Result<ShadingRefitReport> refitShading(FlareModel& model,
                                        const FrameSource& frames,
                                        const std::array<double, 3>& sky,
                                        const DetectOptions& detect,
                                        const CostOptions& cost,
                                        const ShadingRefitOptions& options) {
    if (auto status = checkShadingRefitOptions(options); !status) return status.error();
    ShadingRefitReport report;
    if (options.frames_per_ghost == 0 || model.ghosts.empty() || frames.angles_deg.empty())
        return report;
    if (!frames.load) return invalid("the frame source has no loader");
    const auto start = Clock::now();
    FlareModel refitted = model;
    // Shading series raised to min_degree (zero coefficients: the same function), capped by the
    // frames a piece spans.
    for (ModelGhost& ghost : refitted.ghosts) {
        if (ghost.parameters.size() != kGhostParameterCount) continue;
        for (int i = kFirstShading; i < kGhostParameterCount; ++i)
            for (ModelPiece& piece : ghost.parameters[static_cast<size_t>(i)].pieces) {
                const int64_t frames_in = std::count_if(
                    frames.angles_deg.begin(), frames.angles_deg.end(),
                    [&](double a) { return a >= piece.angle_from_deg && a <= piece.angle_to_deg; });
                const size_t want = static_cast<size_t>(
                    std::clamp<int64_t>(std::min<int64_t>(options.min_degree, frames_in - 1), 0,
                                        63) +
                    1);
                if (piece.coefficients.size() < want) piece.coefficients.resize(want, 0.0);
            }
    }

    // Which frames each ghost is fitted to: up to frames_per_ghost of those inside its range,
    // evenly spread, both ends included.
    const size_t n = frames.angles_deg.size();
    std::map<size_t, std::vector<size_t>> wanted;  // frame -> ghosts
    {
        SeriesModel probe(refitted, 3);
        for (size_t g = 0; g < probe.size(); ++g) {
            if (!probe.usable(g)) continue;
            std::vector<size_t> inside;
            for (size_t j = 0; j < n; ++j)
                if (probe.covers(g, frames.angles_deg[j])) inside.push_back(j);
            if (inside.size() < 2) continue;
            const size_t take =
                std::min(inside.size(), static_cast<size_t>(options.frames_per_ghost));
            size_t last = n;
            for (size_t k = 0; k < take; ++k) {
                const size_t index = inside[static_cast<size_t>(
                    std::llround(static_cast<double>(k) * static_cast<double>(inside.size() - 1) /
                                 static_cast<double>(take - 1)))];
                if (index == last) continue;
                wanted[index].push_back(g);
                last = index;
            }
        }
    }
    if (wanted.empty()) return report;

    // The observations, one frame in memory at a time.
    std::vector<std::vector<Observation>> observations(refitted.ghosts.size());
    int channels = 0;
    DetectOptions cheap = detect;
    cheap.circles = false;
    for (const auto& [j, ghosts] : wanted) {
        auto frame = frames.load(j);
        if (!frame) return frame.error().withContext("shading refit: frame " + std::to_string(j));
        const int frame_channels = frame->channels == 1 ? 1 : 3;
        if (channels == 0) channels = frame_channels;
        if (channels != frame_channels)
            return invalid("frame " + std::to_string(j) + " has " + std::to_string(frame_channels) +
                           " channel(s), the first had " + std::to_string(channels));
        ++report.frames_loaded;
        auto detection =
            frames.detect ? frames.detect(j, *frame, cheap) : detectGhosts(*frame, cheap);
        if (!detection) return detection.error();
        for (int c = 0; c < 3; ++c)
            if (std::isfinite(sky[static_cast<size_t>(c)]))
                detection->background[static_cast<size_t>(c)] = sky[static_cast<size_t>(c)];
        const auto scale = transformScales(*frame, *detection, cost);
        const double angle = frames.angles_deg[j];
        auto at = modelGhostsAt(refitted, angle, refitted.capture.roll_deg);
        if (!at) return at.error();
        std::map<int64_t, size_t> index_of;
        for (size_t g = 0; g < refitted.ghosts.size(); ++g) index_of[refitted.ghosts[g].id] = g;
        std::vector<std::pair<size_t, GhostState>> present;
        for (const auto& a : *at) present.push_back({index_of.at(a.id), a.state});
        const auto& m = frame->mapping;
        const int64_t width = frame->image.width;
        const bool has_bounds =
            frame->lower_bound.size() == static_cast<size_t>(width * frame->image.height);
        for (const size_t g : ghosts) {
            const auto self = std::find_if(present.begin(), present.end(),
                                           [&](const auto& p) { return p.first == g; });
            if (self == present.end()) continue;
            const GhostState& state = self->second;
            const Crop crop = cropOf(
                state, state.shading.outer_falloff_mm + cost.margin * ghostSize(state), *frame);
            if (crop.x0 > crop.x1 || crop.y0 > crop.y1) continue;
            const int64_t side = std::max(crop.x1 - crop.x0 + 1, crop.y1 - crop.y0 + 1);
            const int64_t stride =
                std::max<int64_t>(1, (side + options.max_samples - 1) / options.max_samples);
            Observation obs;
            obs.angle_deg = angle;
            obs.scale = scale;
            std::vector<Eigen::Vector2d> points, halves;  // block centres and half sizes, mm
            // Block means (as the frame fit samples): one pixel per block would be unbiased at
            // sharp edges but noisier, and measured worse on the Heliar sweep (held-out median
            // 0.143 against 0.132). Blocks holding the light's disc are split around it
            // (sampleBlocks), so that every pixel the score counts is fitted.
            for (const SampleBlock& block : sampleBlocks(crop.x0, crop.x1, crop.y0, crop.y1, stride,
                                                         detection->excluded, width)) {
                std::array<double, 3> sum{};
                uint8_t bounds = 0;
                for (int64_t y = block.y0; y <= block.y1; ++y)
                    for (int64_t x = block.x0; x <= block.x1; ++x) {
                        if (has_bounds)
                            bounds |= frame->lower_bound[static_cast<size_t>(y * width + x)];
                        const float* p = frame->image.at(x, y);
                        for (int c = 0; c < channels; ++c) sum[static_cast<size_t>(c)] += p[c];
                    }
                const double count =
                    static_cast<double>((block.x1 - block.x0 + 1) * (block.y1 - block.y0 + 1));
                std::array<double, 3> data{};
                for (int c = 0; c < channels; ++c)
                    data[static_cast<size_t>(c)] = sum[static_cast<size_t>(c)] / count -
                                                   detection->background[static_cast<size_t>(c)];
                obs.data.push_back(data);
                obs.bound.push_back(bounds);
                obs.weight.push_back(block.weight);
                points.push_back(
                    {(0.5 * static_cast<double>(block.x0 + block.x1 + 1) - m.centre_x_px) /
                         m.px_per_mm_x,
                     (0.5 * static_cast<double>(block.y0 + block.y1 + 1) - m.centre_y_px) /
                         m.px_per_mm_y});
                halves.push_back(
                    {0.5 * static_cast<double>(block.x1 - block.x0 + 1) / m.px_per_mm_x,
                     0.5 * static_cast<double>(block.y1 - block.y0 + 1) / m.px_per_mm_y});
            }
            if (points.empty()) continue;
            const auto distances = [&](const GhostState& s) {
                const render::BezierLoop loop = render::toBezierLoop(s.shape);
                std::vector<render::BlockDistance> d(points.size());
                tbb::parallel_for(size_t{0}, points.size(), [&](size_t i) {
                    d[i] = render::blockDistance(loop, points[i], halves[i], cost.distance);
                });
                return d;
            };
            obs.self = distances(state);
            obs.outline_in_frame = outlineShareInside(
                render::toBezierLoop(state.shape), -m.centre_x_px / m.px_per_mm_x,
                (static_cast<double>(width) - m.centre_x_px) / m.px_per_mm_x,
                -m.centre_y_px / m.px_per_mm_y,
                (static_cast<double>(frame->image.height) - m.centre_y_px) / m.px_per_mm_y);
            // Other ghosts whose light reaches into the crop.
            for (const auto& [h, other] : present) {
                if (h == g) continue;
                const Crop reach = cropOf(other, other.shading.outer_falloff_mm, *frame);
                if (reach.x0 > crop.x1 || reach.x1 < crop.x0 || reach.y0 > crop.y1 ||
                    reach.y1 < crop.y0)
                    continue;
                obs.others.push_back({h, distances(other)});
            }
            obs.points = std::move(points);
            obs.halves = std::move(halves);
            observations[g].push_back(std::move(obs));
        }
    }
    if (channels == 0) return report;

    SeriesModel series(refitted, channels);
    // Brightest first (the largest intensity over the ghost's observations).
    std::vector<size_t> order;
    std::vector<double> peak(series.size(), 0.0);
    for (size_t g = 0; g < series.size(); ++g) {
        if (!series.usable(g) || observations[g].size() < 2) continue;
        order.push_back(g);
        for (const Observation& obs : observations[g]) {
            const auto v = series.values(g, obs.angle_deg);
            for (int i = 9; i < 15; ++i)
                peak[g] =
                    std::max(peak[g], SeriesModel::intensityOf(v.value[static_cast<size_t>(i)]));
        }
    }
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return peak[a] > peak[b]; });
    report.ghosts = static_cast<int>(order.size());
    // One ghost's series refitted to its observations; its cost before and after and the
    // evaluations it took. A failed or worse solve leaves the coefficients as they were. It
    // writes only ghost g's coefficients and reads those of the ghosts its observations show.
    struct Solved {
        double before = 0.0, after = 0.0;
        int64_t evaluations = 0;
    };
    const auto solve = [&](SeriesModel& model, size_t g,
                           const std::vector<Observation>& seen) -> Solved {
        std::vector<double>& c = model.coefficients(g);
        auto* function =
            new GhostSeriesCost(model, g, seen, channels, cost.robust_scale, cost.distance);
        std::vector<double> start_values = c;
        ceres::Problem problem;
        problem.AddResidualBlock(function, nullptr, c.data());
        ceres::Solver::Options so;
        so.linear_solver_type = ceres::DENSE_QR;
        so.max_num_iterations = options.max_iterations;
        so.function_tolerance = 1e-6;
        so.num_threads = 1;
        so.logging_type = ceres::SILENT;
        ceres::Solver::Summary summary;
        ceres::Solve(so, &problem, &summary);
        const bool usable =
            summary.IsSolutionUsable() && summary.final_cost <= summary.initial_cost &&
            std::all_of(c.begin(), c.end(), [](double x) { return std::isfinite(x); });
        if (!usable) c = start_values;
        model.store(g);
        return Solved{summary.initial_cost, usable ? summary.final_cost : summary.initial_cost,
                      summary.num_residual_evaluations};
    };
    // `passes` Gauss-Seidel passes over `ghosts` in their order, each ghost on its `seen`
    // observations, run on every core where ghosts share no observation (runGaussSeidel: the
    // result is the plain loop's, bit for bit); the summed costs before the first pass and
    // after the last, in the loop's order.
    const auto sweep = [&](SeriesModel& model, const std::vector<size_t>& ghosts,
                           const std::vector<std::vector<Observation>>& seen, int passes) {
        std::vector<std::vector<size_t>> neighbours(model.size());
        for (const size_t g : ghosts)
            for (const Observation& obs : seen[g])
                for (const auto& other : obs.others) neighbours[g].push_back(other.first);
        std::vector<size_t> items;
        for (int pass = 0; pass < passes; ++pass)
            items.insert(items.end(), ghosts.begin(), ghosts.end());
        std::vector<Solved> solved(items.size());
        runGaussSeidel(items, neighbours,
                       [&](size_t k) { solved[k] = solve(model, items[k], seen[items[k]]); });
        std::pair<double, double> cost{0.0, 0.0};
        for (size_t k = 0; k < items.size(); ++k) {
            report.evaluations += solved[k].evaluations;
            if (k < ghosts.size()) cost.first += solved[k].before;
            if (k + ghosts.size() >= items.size()) cost.second += solved[k].after;
        }
        return cost;
    };
    // The shading passes. Their values whose bounds meet keep a gradient (SeriesModel::values):
    // it is wrong there, and stalls the solver where such a value pulls hardest, but on one
    // double Gauss sweep it was what held a veil larger than the frame, which had soaked up the
    // light of a ghost the tracker lost, from growing 13 times brighter with no other ghost near
    // it to share that light (the fitted angle's relative L2 3.3, with the exact gradient 428).
    {
        std::vector<size_t> refitted_ghosts;
        for (const size_t g : order)
            if (!series.coefficients(g).empty()) refitted_ghosts.push_back(g);
        std::tie(report.initial_cost, report.final_cost) =
            sweep(series, refitted_ghosts, observations, options.passes);
    }
    if (options.shape_passes > 0) {
        const auto shape_start = Clock::now();
        // Only ghosts whose outline the frames show: one with less than
        // shape_min_outline_in_frame of its outline in its frames (a veil larger than the frame,
        // a ghost all but gone past the frame's edge) has a shape the pixels do not fix, and
        // refitting it lets it spread to take whatever light the others leave (on a double Gauss
        // sweep, a veil that took a lost ghost's light grew 13 times brighter). Such a ghost keeps
        // its compressed shape (bounds too) and refitted shading, and is drawn as the others'
        // context.
        std::vector<size_t> shaped;
        for (const size_t g : order) {
            std::vector<double> share;
            for (const Observation& obs : observations[g]) share.push_back(obs.outline_in_frame);
            if (share.empty()) continue;
            std::nth_element(share.begin(), share.begin() + share.size() / 2, share.end());
            if (share[share.size() / 2] >= options.shape_min_outline_in_frame) shaped.push_back(g);
        }
        // The compression bounded each shape value by the range its frames spanned (widened by
        // a quarter), which would hold a shape that every frame put off the ghost where it was:
        // those bounds are opened (openShapeBounds). The shading's are kept.
        for (const size_t g : shaped) {
            auto& parameters = refitted.ghosts[g].parameters;
            double size = 0.0;
            for (int p = 2; p <= 4; ++p)
                if (const auto& hi = parameters[static_cast<size_t>(p)].upper_bound)
                    size = std::max(size, *hi);
            for (int p = 0; p < 9; ++p)
                openShapeBounds(parameters[static_cast<size_t>(p)], p, size);
        }
        // Every series now, the shading as just refitted; each ghost on up to
        // shape_frames_per_ghost of its observations, evenly spread.
        SeriesModel full(refitted, channels, 0);
        std::vector<std::vector<Observation>> seen(observations.size());
        for (const size_t g : shaped) {
            const auto& all = observations[g];
            const size_t take =
                std::min(all.size(), static_cast<size_t>(options.shape_frames_per_ghost));
            size_t last = all.size();
            for (size_t k = 0; k < take; ++k) {
                const size_t index = static_cast<size_t>(
                    std::llround(static_cast<double>(k) * static_cast<double>(all.size() - 1) /
                                 static_cast<double>(take - 1)));
                if (index == last) continue;
                seen[g].push_back(all[index]);
                last = index;
            }
        }
        std::tie(report.shape_initial_cost, report.shape_final_cost) =
            sweep(full, shaped, seen, options.shape_passes);
        report.shape_ghosts = static_cast<int>(shaped.size());
        report.shape_unobserved = static_cast<int>(order.size() - shaped.size());
        report.shape_ms =
            std::chrono::duration<double, std::milli>(Clock::now() - shape_start).count();
    }
    if (auto status = validateModel(refitted); !status)
        return status.error().withContext("shading refit");
    model = std::move(refitted);
    report.time_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
    return report;
}

}  // namespace flarelab::fit
