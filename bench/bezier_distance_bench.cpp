// bezier_distance_bench: accuracy and speed of the fast distance to a ghost's Bézier border.
//
//   bezier_distance_bench [--shapes N] [--queries N] [--runs N] [--seeds N]
//
// The renderer evaluates signedDistanceFast (a fixed number of Newton steps from a few seeds per
// segment) for every pixel a ghost covers; fits trust signedDistanceExact (branch and bound to
// 1e-9 mm). This tool draws seeded random default shapes (render/ghost_shape.h, inside their
// documented bounds) and, per shape, query points in three equal groups:
//   near   - a curve point moved along the normal by up to 5 % of the shape's size either way;
//   far    - 1.5 to 4 sizes from the centre;
//   inside - a curve point pulled towards the centre (the shapes are star-shaped about it).
// For 1..8 Newton steps it prints a Markdown table of the absolute error of the fast signed
// distance against the exact one (maximum per group, median over all) and the time per
// evaluation, best of --runs passes over all queries, as a ratio to the exact method timed in
// the same run, and the time of the winding number (the sign) both share. Exit status 0 always:
// this tool measures, the reader judges.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <numbers>
#include <random>
#include <string>
#include <vector>

#include "render/ghost_shape.h"

namespace flarelab::bench {
namespace {

using render::BezierLoop;
using render::FastDistanceOptions;
using render::GhostShapeParams;
using Vec2 = Eigen::Vector2d;

enum Group { kNear = 0, kFar = 1, kInside = 2, kGroupCount = 3 };
const char* const kGroupNames[kGroupCount] = {"near", "far", "inside"};

struct Query {
    int shape = 0;
    Group group = kNear;
    Vec2 point = Vec2::Zero();
};

struct Options {
    int shapes = 200;
    int queries_per_shape = 300;
    int runs = 5;
    int seeds_per_segment = 4;
};

GhostShapeParams randomShape(std::mt19937_64& rng) {
    std::uniform_real_distribution<double> centre(-12.0, 12.0);
    std::uniform_real_distribution<double> size(0.2, 6.0);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    GhostShapeParams p;
    p.centre_x_mm = centre(rng);
    p.centre_y_mm = centre(rng);
    p.half_height_mm = size(rng);
    p.left_mm = size(rng);
    p.right_mm = size(rng);
    p.left_handle_x_mm = unit(rng) * p.left_mm;
    p.left_handle_y_mm = unit(rng) * p.half_height_mm;
    p.right_handle_x_mm = unit(rng) * p.right_mm;
    p.right_handle_y_mm = unit(rng) * p.half_height_mm;
    return p;
}

Query randomQuery(int shape_index,
                  const GhostShapeParams& p,
                  const BezierLoop& loop,
                  Group group,
                  std::mt19937_64& rng) {
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    std::uniform_int_distribution<int> segment(0, loop.segmentCount() - 1);
    const double size = std::max({p.half_height_mm, p.left_mm, p.right_mm});
    const Vec2 centre(p.centre_x_mm, p.centre_y_mm);
    const int s = segment(rng);
    const double t = unit(rng);
    const Vec2 on_curve = loop.point(s, t);
    Vec2 q = on_curve;
    if (group == kNear) {
        // Normal from the chord of a small parameter step (finite even at a zero tangent).
        const Vec2 ahead = loop.point(s, std::min(t + 1e-3, 1.0));
        const Vec2 behind = loop.point(s, std::max(t - 1e-3, 0.0));
        Vec2 normal(-(ahead - behind).y(), (ahead - behind).x());
        normal = normal.norm() > 0.0 ? Vec2(normal.normalized()) : Vec2(1.0, 0.0);
        q = on_curve + (0.1 * unit(rng) - 0.05) * size * normal;
    } else if (group == kFar) {
        const double angle = 2.0 * std::numbers::pi * unit(rng);
        q = centre + (1.5 + 2.5 * unit(rng)) * size * Vec2(std::cos(angle), std::sin(angle));
    } else {
        q = centre + 0.95 * unit(rng) * (on_curve - centre);
    }
    return Query{shape_index, group, q};
}

double nowSeconds() {
    using Clock = std::chrono::steady_clock;
    return std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
}

// Best time per evaluation over `runs` passes; `sink` keeps the work from being optimized away.
template <typename F>
double bestSecondsPerEvaluation(const std::vector<Query>& queries, int runs, F&& evaluate) {
    double best = 1e300;
    volatile double sink = 0.0;
    for (int r = 0; r < runs; ++r) {
        double sum = 0.0;
        const double start = nowSeconds();
        for (const Query& q : queries) sum += evaluate(q);
        const double elapsed = nowSeconds() - start;
        sink = sink + sum;
        best = std::min(best, elapsed / static_cast<double>(queries.size()));
    }
    return best;
}

double median(std::vector<double> values) {
    if (values.empty()) return 0.0;
    const auto mid = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
    std::nth_element(values.begin(), mid, values.end());
    return *mid;
}

int parsePositive(const char* flag, const char* value) {
    char* end = nullptr;
    const long v = value ? std::strtol(value, &end, 10) : 0;
    if (!value || *end != '\0' || v < 1 || v > 100000000) {
        std::fprintf(stderr, "bezier_distance_bench: %s needs a positive integer\n", flag);
        std::exit(2);
    }
    return static_cast<int>(v);
}

int run(int argc, char** argv) {
    Options options;
    for (int i = 1; i < argc; ++i) {
        const char* value = i + 1 < argc ? argv[i + 1] : nullptr;
        if (std::strcmp(argv[i], "--shapes") == 0) {
            options.shapes = parsePositive(argv[i], value);
        } else if (std::strcmp(argv[i], "--queries") == 0) {
            options.queries_per_shape = parsePositive(argv[i], value);
        } else if (std::strcmp(argv[i], "--runs") == 0) {
            options.runs = parsePositive(argv[i], value);
        } else if (std::strcmp(argv[i], "--seeds") == 0) {
            options.seeds_per_segment = parsePositive(argv[i], value);
        } else {
            std::fprintf(stderr,
                         "usage: bezier_distance_bench [--shapes N] [--queries N] [--runs N] "
                         "[--seeds N]\n");
            return 2;
        }
        ++i;
    }

    // Shapes and queries, seeded.
    std::mt19937_64 rng(20261129);
    std::vector<BezierLoop> loops;
    std::vector<Query> queries;
    for (int s = 0; s < options.shapes; ++s) {
        const GhostShapeParams p = randomShape(rng);
        if (!render::validateGhostShape(p)) std::abort();  // randomShape stays inside the bounds
        loops.push_back(render::toBezierLoop(p));
        for (int k = 0; k < options.queries_per_shape; ++k)
            queries.push_back(
                randomQuery(s, p, loops.back(), static_cast<Group>(k % kGroupCount), rng));
    }

    // The reference values and the reference time.
    std::vector<double> exact(queries.size());
    for (std::size_t i = 0; i < queries.size(); ++i)
        exact[i] = render::signedDistanceExact(loops[queries[i].shape], queries[i].point);
    const double exact_s = bestSecondsPerEvaluation(queries, options.runs, [&](const Query& q) {
        return render::signedDistanceExact(loops[q.shape], q.point);
    });

    // The inside/outside decision both methods share, timed alone.
    const double winding_s = bestSecondsPerEvaluation(queries, options.runs, [&](const Query& q) {
        return static_cast<double>(render::windingNumber(loops[q.shape], q.point));
    });

    std::printf("# bezier_distance_bench\n\n");
    std::printf(
        "%d random default shapes (4 segments), %zu queries (%d per shape: near, far, "
        "inside in equal parts), %d seeds per segment, best of %d runs.\n",
        options.shapes, queries.size(), options.queries_per_shape, options.seeds_per_segment,
        options.runs);
    std::printf(
        "Errors: |fast - exact| of the signed distance in mm (shape sizes 0.2 to 6 mm). "
        "Exact: %.0f ns per evaluation (branch and bound to 1e-9 mm).\n",
        exact_s * 1e9);
    std::printf(
        "Both include the winding number for the sign: %.0f ns of it alone (%.3f of the "
        "exact time).\n\n",
        winding_s * 1e9, winding_s / exact_s);
    std::printf(
        "| Newton steps | max err near | max err far | max err inside | max err all | "
        "median err all | ns / eval | time vs exact |\n");
    std::printf("|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for (int iterations = 1; iterations <= 8; ++iterations) {
        const FastDistanceOptions fast{iterations, options.seeds_per_segment};
        double worst[kGroupCount] = {0.0, 0.0, 0.0};
        std::vector<double> errors(queries.size());
        for (std::size_t i = 0; i < queries.size(); ++i) {
            const Query& q = queries[i];
            errors[i] =
                std::abs(render::signedDistanceFast(loops[q.shape], q.point, fast) - exact[i]);
            worst[q.group] = std::max(worst[q.group], errors[i]);
        }
        const double fast_s = bestSecondsPerEvaluation(queries, options.runs, [&](const Query& q) {
            return render::signedDistanceFast(loops[q.shape], q.point, fast);
        });
        std::printf("| %d | %.2e | %.2e | %.2e | %.2e | %.2e | %.0f | %.3f |\n", iterations,
                    worst[kNear], worst[kFar], worst[kInside],
                    std::max({worst[kNear], worst[kFar], worst[kInside]}), median(errors),
                    fast_s * 1e9, fast_s / exact_s);
    }
    return 0;
}

}  // namespace
}  // namespace flarelab::bench

int main(int argc, char** argv) { return flarelab::bench::run(argc, argv); }
