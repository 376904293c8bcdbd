#include "predict/switching.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace flarelab::predict {
namespace {

// A plan's cost so far, compared in the order of the header's three aims.
struct Cost {
    int64_t over = std::numeric_limits<int64_t>::max();
    int64_t cuts = 0;
    double sum = 0.0;

    bool reachable() const { return over != std::numeric_limits<int64_t>::max(); }
    bool operator<(const Cost& o) const {
        if (over != o.over) return over < o.over;
        if (cuts != o.cuts) return cuts < o.cuts;
        return sum < o.sum;
    }
};

}  // namespace

const char* switchFigureName(SwitchFigure figure) {
    switch (figure) {
        case SwitchFigure::ContrastLoss:
            return "contrast-loss";
        case SwitchFigure::FlareMean:
            return "flare-mean";
        case SwitchFigure::FlarePeak:
            return "flare-peak";
        case SwitchFigure::GlareIndicator:
            return "glare";
    }
    return "unknown";
}

Result<SwitchingPlan> planSwitching(std::span<const std::vector<double>> figures,
                                    const SwitchingOptions& options) {
    if (figures.empty()) return makeError(ErrorCode::InvalidArgument, "switching: no camera");
    if (figures.size() > 32767)
        return makeError(ErrorCode::InvalidArgument, "switching: more than 32767 cameras");
    const int64_t steps = static_cast<int64_t>(figures.front().size());
    for (const auto& f : figures)
        if (static_cast<int64_t>(f.size()) != steps)
            return makeError(ErrorCode::InvalidArgument,
                             "switching: the cameras' timelines differ in length");
    if (steps == 0) return makeError(ErrorCode::InvalidArgument, "switching: no time step");
    if (options.min_dwell_steps < 1)
        return makeError(ErrorCode::InvalidArgument, "switching: the dwell must be >= 1 step");
    if (!std::isfinite(options.threshold))
        return makeError(ErrorCode::InvalidArgument, "switching: the threshold must be finite");
    const int64_t cameras = static_cast<int64_t>(figures.size());
    // Dwell states beyond the timeline's length can never be reached: cap them.
    const int64_t dwell = std::min(options.min_dwell_steps, steps);
    if (steps > kMaxSwitchingStates / cameras / dwell)
        return makeError(ErrorCode::InvalidArgument,
                         "switching: " + std::to_string(steps) + " steps x " +
                             std::to_string(cameras) + " cameras x " + std::to_string(dwell) +
                             " dwell steps exceed " + std::to_string(kMaxSwitchingStates) +
                             " states; use a longer step");
    const auto over = [&](int64_t c, int64_t t) {
        return !(figures[static_cast<size_t>(c)][static_cast<size_t>(t)] <= options.threshold);
    };
    const auto known = [&](int64_t c, int64_t t) {
        const double v = figures[static_cast<size_t>(c)][static_cast<size_t>(t)];
        return std::isfinite(v) ? v : 0.0;
    };
    // State (c, d): on camera c for d steps (d in 1..dwell, dwell meaning "dwell or more").
    const int64_t layer = cameras * dwell;
    const auto index = [&](int64_t c, int64_t d) { return c * dwell + (d - 1); };
    std::vector<Cost> now(static_cast<size_t>(layer)), next(static_cast<size_t>(layer));
    // back[t * layer + state]: the state at t - 1 it came from.
    std::vector<int32_t> back(static_cast<size_t>(steps * layer), -1);
    for (int64_t c = 0; c < cameras; ++c)
        now[static_cast<size_t>(index(c, 1))] = Cost{over(c, 0) ? 1 : 0, 0, known(c, 0)};
    for (int64_t t = 1; t < steps; ++t) {
        std::fill(next.begin(), next.end(), Cost{});
        // A cut is allowed from a camera held for the full dwell; the best two such cameras
        // serve every target (the best one unless it is the target itself).
        int64_t best = -1, second = -1;
        for (int64_t c = 0; c < cameras; ++c) {
            const Cost& k = now[static_cast<size_t>(index(c, dwell))];
            if (!k.reachable()) continue;
            if (best < 0 || k < now[static_cast<size_t>(index(best, dwell))]) {
                second = best;
                best = c;
            } else if (second < 0 || k < now[static_cast<size_t>(index(second, dwell))]) {
                second = c;
            }
        }
        for (int64_t c = 0; c < cameras; ++c) {
            const int64_t step_over = over(c, t) ? 1 : 0;
            const double step_sum = known(c, t);
            const auto offer = [&](int64_t to_state, int64_t from_state, const Cost& from,
                                   int64_t cut) {
                const Cost cost{from.over + step_over, from.cuts + cut, from.sum + step_sum};
                Cost& slot = next[static_cast<size_t>(to_state)];
                if (cost < slot) {
                    slot = cost;
                    back[static_cast<size_t>(t * layer + to_state)] =
                        static_cast<int32_t>(from_state);
                }
            };
            for (int64_t d = 1; d <= dwell; ++d) {
                const Cost& from = now[static_cast<size_t>(index(c, d))];
                if (!from.reachable()) continue;
                offer(index(c, std::min(d + 1, dwell)), index(c, d), from, 0);
            }
            const int64_t source = best != c ? best : second;
            if (source >= 0)
                offer(index(c, 1), index(source, dwell),
                      now[static_cast<size_t>(index(source, dwell))], 1);
        }
        std::swap(now, next);
    }
    int64_t state = -1;
    for (int64_t s = 0; s < layer; ++s)
        if (now[static_cast<size_t>(s)].reachable() &&
            (state < 0 || now[static_cast<size_t>(s)] < now[static_cast<size_t>(state)]))
            state = s;
    SwitchingPlan plan;
    const Cost total = now[static_cast<size_t>(state)];
    plan.steps_over = total.over;
    plan.cuts = total.cuts;
    plan.figure_sum = total.sum;
    std::vector<int64_t> chosen(static_cast<size_t>(steps));
    for (int64_t t = steps - 1; t >= 0; --t) {
        chosen[static_cast<size_t>(t)] = state / dwell;
        if (t > 0) state = back[static_cast<size_t>(t * layer + state)];
    }
    for (int64_t t = 0; t < steps; ++t) {
        const int camera = static_cast<int>(chosen[static_cast<size_t>(t)]);
        if (plan.segments.empty() || plan.segments.back().camera != camera)
            plan.segments.push_back(PlanSegment{camera, t, t + 1});
        else
            plan.segments.back().end_step = t + 1;
        bool any_clean = false;
        for (int64_t c = 0; c < cameras && !any_clean; ++c) any_clean = !over(c, t);
        if (!any_clean) {
            if (!plan.no_clean_camera.empty() && plan.no_clean_camera.back().end_step == t)
                plan.no_clean_camera.back().end_step = t + 1;
            else
                plan.no_clean_camera.push_back(StepInterval{t, t + 1});
        }
    }
    return plan;
}

}  // namespace flarelab::predict
