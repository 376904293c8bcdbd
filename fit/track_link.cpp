#include "fit/track_link.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>

#include "fit/model_eval.h"
#include "fit/sweep_fit.h"

namespace flarelab::fit {
namespace {

Status invalid(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "track link: " + what);
}

// What a link compares: centre (mm), ln size, ln energy.
struct Features {
    double x = 0.0, y = 0.0, ln_size = 0.0, ln_energy = 0.0;
};

Features features(const GhostState& g) {
    constexpr double kTiny = 1e-300;  // a ghost with no light: ln far below any lit one's
    return {g.shape.centre_x_mm, g.shape.centre_y_mm, std::log(std::max(ghostSize(g), kTiny)),
            std::log(std::max(roughGhostEnergy(g), kTiny))};
}

// The features of `samples` extrapolated to `angle_deg` by a least-squares line in the angle
// (constant for one sample, or where the angles do not spread).
Features extrapolate(std::span<const TrackSample> samples, double angle_deg) {
    const double n = static_cast<double>(samples.size());
    double mean_a = 0.0;
    for (const TrackSample& s : samples) mean_a += s.angle_deg / n;
    std::array<double, 4> mean{}, slope{};
    double saa = 0.0;
    for (const TrackSample& s : samples) saa += (s.angle_deg - mean_a) * (s.angle_deg - mean_a);
    for (const TrackSample& s : samples) {
        const Features f = features(s.state);
        const std::array<double, 4> v = {f.x, f.y, f.ln_size, f.ln_energy};
        for (size_t k = 0; k < 4; ++k) {
            mean[k] += v[k] / n;
            slope[k] += (s.angle_deg - mean_a) * v[k];
        }
    }
    const double da = angle_deg - mean_a;
    std::array<double, 4> out{};
    for (size_t k = 0; k < 4; ++k) out[k] = mean[k] + (saa > 1e-12 ? slope[k] / saa * da : 0.0);
    return {out[0], out[1], out[2], out[3]};
}

double compare(const Features& predicted, const Features& seen, const TrackLinkOptions& o) {
    const double size = std::exp(std::max(predicted.ln_size, seen.ln_size));
    const double position =
        std::hypot(predicted.x - seen.x, predicted.y - seen.y) / (o.position_radii * size);
    const double sizes = std::abs(predicted.ln_size - seen.ln_size) / std::log(o.size_ratio);
    const double energy = std::abs(predicted.ln_energy - seen.ln_energy) / std::log(o.energy_ratio);
    return std::max({position, sizes, energy});
}

// The frame of the sweep nearest to an angle.
int64_t frameIndex(std::span<const double> angles, double angle_deg) {
    const auto it = std::lower_bound(angles.begin(), angles.end(), angle_deg);
    int64_t i = it - angles.begin();
    if (i > 0 && (it == angles.end() || std::abs(angles[static_cast<size_t>(i - 1)] - angle_deg) <
                                            std::abs(*it - angle_deg)))
        --i;
    return i;
}

// Minimum-cost assignment of rows to columns of a square matrix (the Hungarian method with
// potentials, O(n^3)): column of each row.
std::vector<size_t> assign(const std::vector<std::vector<double>>& cost) {
    const size_t n = cost.size();
    const double inf = std::numeric_limits<double>::infinity();
    std::vector<double> u(n + 1, 0.0), v(n + 1, 0.0);
    std::vector<size_t> p(n + 1, 0), way(n + 1, 0);  // p[j]: the row given column j (1-based)
    for (size_t i = 1; i <= n; ++i) {
        p[0] = i;
        size_t j0 = 0;
        std::vector<double> least(n + 1, inf);
        std::vector<char> used(n + 1, 0);
        do {
            used[j0] = 1;
            const size_t i0 = p[j0];
            double delta = inf;
            size_t j1 = 0;
            for (size_t j = 1; j <= n; ++j) {
                if (used[j]) continue;
                const double c = cost[i0 - 1][j - 1] - u[i0] - v[j];
                if (c < least[j]) {
                    least[j] = c;
                    way[j] = j0;
                }
                if (least[j] < delta) {
                    delta = least[j];
                    j1 = j;
                }
            }
            for (size_t j = 0; j <= n; ++j) {
                if (used[j]) {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    least[j] -= delta;
                }
            }
            j0 = j1;
        } while (p[j0] != 0);
        do {
            const size_t j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
        } while (j0 != 0);
    }
    std::vector<size_t> column(n, 0);
    for (size_t j = 1; j <= n; ++j)
        if (p[j] != 0) column[p[j] - 1] = j - 1;
    return column;
}

}  // namespace

Status checkTrackLinkOptions(const TrackLinkOptions& o) {
    if (o.max_gap_frames < 0) return invalid("max_gap_frames must be >= 0");
    if (o.max_overlap_frames < 0) return invalid("max_overlap_frames must be >= 0");
    if (o.history < 1) return invalid("history must be >= 1");
    if (!(o.position_radii > 0.0) || !std::isfinite(o.position_radii))
        return invalid("position_radii must be finite and > 0");
    if (!(o.size_ratio > 1.0) || !std::isfinite(o.size_ratio))
        return invalid("size_ratio must be finite and > 1");
    if (!(o.energy_ratio > 1.0) || !std::isfinite(o.energy_ratio))
        return invalid("energy_ratio must be finite and > 1");
    if (!(o.gate > 0.0) || !std::isfinite(o.gate)) return invalid("gate must be finite and > 0");
    return Ok{};
}

std::optional<double> trackLinkCost(const GhostTrack& from,
                                    const GhostTrack& to,
                                    std::span<const double> angles,
                                    const TrackLinkOptions& o) {
    if (from.samples.empty() || to.samples.empty() || angles.empty()) return std::nullopt;
    const TrackSample& a_first = from.samples.front();
    const TrackSample& a_last = from.samples.back();
    const TrackSample& b_first = to.samples.front();
    const TrackSample& b_last = to.samples.back();
    if (!(b_first.angle_deg > a_first.angle_deg) || !(b_last.angle_deg > a_last.angle_deg))
        return std::nullopt;
    const int64_t gap =
        frameIndex(angles, b_first.angle_deg) - frameIndex(angles, a_last.angle_deg) - 1;
    if (gap > o.max_gap_frames || -gap > o.max_overlap_frames) return std::nullopt;
    // A's samples before B begins, the last `history` of them; B's after A ends, the first.
    const auto a_end =
        std::lower_bound(from.samples.begin(), from.samples.end(), b_first.angle_deg,
                         [](const TrackSample& s, double angle) { return s.angle_deg < angle; });
    const auto b_begin =
        std::upper_bound(to.samples.begin(), to.samples.end(), a_last.angle_deg,
                         [](double angle, const TrackSample& s) { return angle < s.angle_deg; });
    const size_t a_count = static_cast<size_t>(a_end - from.samples.begin());
    const size_t b_count = static_cast<size_t>(to.samples.end() - b_begin);
    if (a_count == 0 || b_count == 0) return std::nullopt;
    const size_t h = static_cast<size_t>(o.history);
    const std::span<const TrackSample> a_side(
        from.samples.data() + (a_count - std::min(a_count, h)), std::min(a_count, h));
    const std::span<const TrackSample> b_side(&*b_begin, std::min(b_count, h));
    const double forward =
        compare(extrapolate(a_side, b_side.front().angle_deg), features(b_side.front().state), o);
    const double backward =
        compare(extrapolate(b_side, a_side.back().angle_deg), features(a_side.back().state), o);
    const double cost = std::max(forward, backward);
    if (!std::isfinite(cost)) return std::nullopt;
    return cost;
}

void mergeTrackSamples(std::vector<TrackSample>& into, std::vector<TrackSample>& from) {
    for (TrackSample& sample : from) {
        auto same = std::find_if(into.begin(), into.end(), [&](const TrackSample& k) {
            return k.angle_deg == sample.angle_deg;
        });
        if (same == into.end())
            into.push_back(std::move(sample));
        else if (sample.cost < same->cost)
            *same = std::move(sample);
    }
    from.clear();
}

std::vector<GhostTrack> linkTracks(std::vector<GhostTrack> tracks,
                                   std::span<const double> angles,
                                   const TrackLinkOptions& o,
                                   TrackLinkStats* stats) {
    TrackLinkStats local;
    TrackLinkStats& st = stats ? *stats : local;
    st = TrackLinkStats{};
    if (!o.enabled) return tracks;
    std::vector<size_t> part;  // the fragments that take part, by index into tracks
    for (size_t t = 0; t < tracks.size(); ++t)
        if (tracks[t].path < 0 && !tracks[t].samples.empty()) part.push_back(t);
    const size_t n = part.size();
    st.fragments = static_cast<int64_t>(n);
    if (n < 2) return tracks;
    // Rows: the fragments' ends, then one "no successor" per fragment; columns: the fragments'
    // starts, then one "no predecessor" each. Half the gate on each side of a fragment left
    // unlinked, so a link is made only where it costs less than the gate.
    constexpr double kNever = 1e12;
    const size_t m = 2 * n;
    std::vector<std::vector<double>> cost(m, std::vector<double>(m, kNever));
    for (size_t i = 0; i < n; ++i) {
        for (size_t j = 0; j < n; ++j) {
            if (i == j) continue;
            const auto c = trackLinkCost(tracks[part[i]], tracks[part[j]], angles, o);
            if (!c) continue;
            ++st.candidates;
            if (*c < o.gate) cost[i][j] = *c;
        }
        cost[i][n + i] = 0.5 * o.gate;
        cost[n + i][i] = 0.5 * o.gate;
        for (size_t j = 0; j < n; ++j) cost[n + i][n + j] = 0.0;
    }
    const std::vector<size_t> column = assign(cost);
    std::vector<int64_t> next(n, -1);
    std::vector<char> has_prev(n, 0);
    for (size_t i = 0; i < n; ++i) {
        const size_t j = column[i];
        if (j < n && cost[i][j] < kNever) {
            next[i] = static_cast<int64_t>(j);
            has_prev[j] = 1;
            ++st.links;
        }
    }
    // Links run forward in angle only (a fragment's successor starts and ends later), so every
    // chain starts at a fragment with no predecessor and none loops.
    std::vector<GhostTrack> out;
    std::vector<char> joined(tracks.size(), 0);
    for (size_t i = 0; i < n; ++i) {
        if (has_prev[i]) continue;
        GhostTrack track = std::move(tracks[part[i]]);
        joined[part[i]] = 1;
        for (int64_t k = next[i]; k >= 0; k = next[static_cast<size_t>(k)]) {
            GhostTrack& piece = tracks[part[static_cast<size_t>(k)]];
            joined[part[static_cast<size_t>(k)]] = 1;
            mergeTrackSamples(track.samples, piece.samples);
        }
        std::sort(
            track.samples.begin(), track.samples.end(),
            [](const TrackSample& a, const TrackSample& b) { return a.angle_deg < b.angle_deg; });
        out.push_back(std::move(track));
    }
    for (size_t t = 0; t < tracks.size(); ++t)
        if (!joined[t]) out.push_back(std::move(tracks[t]));
    std::sort(out.begin(), out.end(),
              [](const GhostTrack& a, const GhostTrack& b) { return a.id < b.id; });
    return out;
}

}  // namespace flarelab::fit
