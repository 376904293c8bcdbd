// optics_bench: the exact tracer's speed, in ray-surface intersections per second on one core.
//
// Items are intersections, so lenses with more surfaces and paths with more steps compare on one
// scale. Two baselines run in the same binary, over the same kind of data, so that a report can
// quote ratios that survive a change of machine:
//
//   BM_IntersectSphereTextbook  the centre-based |o - c|^2 = R^2 quadratic with the plain root
//                               formula, over the rays of BM_IntersectSurface;
//   BM_ReadRays                 a loop that only reads that ray array: the memory floor.
//
// BM_IntersectSurfaceChained makes each intersection wait for the previous one, as the steps of a
// traced path do, and so measures latency rather than throughput.
//
// BM_TraceImagingPath/<lens> and BM_TraceGhostPath/<lens> trace a 64 x 64 grid of rays spread
// over the paraxial entrance pupil, light at theta = 5 deg, 550 nm; the ghost is the path that
// carries the most light at that angle. Clear apertures and the stop do not clip, so every ray
// that neither misses a surface nor is totally reflected does all intersectionsPerRay()
// intersections, and the item count is what was done (the `completed` counter says how many did).
// BM_TraceGhostPathGeometry/<lens> is the same ghost without Fresnel terms, which isolates their
// cost. BM_TraceGhostPathRow{Double,Float}{Sse2,}/<lens> trace the same ghost's rays through
// RowTracer, a row of 64 at a time: double or float lanes, SSE2 or (where the processor has it)
// AVX2; the ratio to BM_TraceGhostPathBatched is the row tracer's gain.
#include <benchmark/benchmark.h>

#include <Eigen/Core>
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "common/units.h"
#include "optics/aim.h"
#include "optics/ghosts.h"
#include "optics/lens.h"
#include "optics/paraxial.h"
#include "optics/prescription.h"
#include "optics/row_tracer.h"
#include "optics/tracer.h"

namespace flarelab::bench {
namespace {

using namespace flarelab::optics;

constexpr int kGridSide = 64;
constexpr double kTheta_deg = 5.0;
constexpr double kWavelength_nm = kLambdaGreen_nm;
constexpr int kSurfaceCases = kGridSide * kGridSide;

// ---------------------------------------------------------------------------------------------
// Bare intersections

struct SurfaceCase {
    Eigen::Vector3d position;
    Eigen::Vector3d direction;
    double vertex_z = 0.0;
    double curvature = 0.0;
};

// Surfaces and rays as lenses have them: radii log-uniform from 10 mm to 1 m of either sign, one
// surface in seven flat, rays starting up to 20 mm in front of the vertex at heights up to 80 %
// of the radius (or 15 mm), up to 20 degrees off axis. Some rays miss strongly curved surfaces,
// as some do in a lens; both kernels see the same ones.
const std::vector<SurfaceCase>& surfaceCases() {
    static const std::vector<SurfaceCase> cases = [] {
        std::mt19937_64 rng(7);
        std::uniform_real_distribution<double> unit(0.0, 1.0);
        std::vector<SurfaceCase> out(kSurfaceCases);
        for (SurfaceCase& c : out) {
            double max_height = 15.0;
            if (unit(rng) < 1.0 / 7.0) {
                c.curvature = 0.0;
            } else {
                const double radius = std::exp(std::log(10.0) + unit(rng) * std::log(100.0));
                c.curvature = (unit(rng) < 0.5 ? -1.0 : 1.0) / radius;
                max_height = std::min(max_height, 0.8 * radius);
            }
            c.vertex_z = 100.0 * unit(rng);
            const double h = max_height * std::sqrt(unit(rng));
            const double a = 2.0 * kPi * unit(rng);
            c.position = Eigen::Vector3d(h * std::cos(a), h * std::sin(a),
                                         c.vertex_z - 1.0 - 19.0 * unit(rng));
            c.direction = lightDirection(degToRad(20.0 * unit(rng)), 2.0 * kPi * unit(rng));
        }
        return out;
    }();
    return cases;
}

// The textbook ray-sphere test: centre c = v + R z^, solve |o + t d - c|^2 = R^2 with
// t = -b -+ sqrt(b^2 - |o - c|^2 + R^2) and keep the nearest positive root. It loses digits for
// large radii (|o - c|^2 and R^2 cancel), which is why flarelab does not use it; here it is the
// yardstick. Kept out of line like intersectSurface, so both pay one call.
[[gnu::noinline]] std::optional<double> intersectTextbook(const Eigen::Vector3d& position,
                                                          const Eigen::Vector3d& direction,
                                                          double vertex_z,
                                                          double curvature) {
    if (curvature == 0.0) {
        if (direction.z() == 0.0) return std::nullopt;
        const double t = (vertex_z - position.z()) / direction.z();
        if (!(t >= 0.0)) return std::nullopt;
        return t;
    }
    const double radius = 1.0 / curvature;
    const Eigen::Vector3d oc(position.x(), position.y(), position.z() - (vertex_z + radius));
    const double b = oc.dot(direction);
    const double disc = b * b - (oc.squaredNorm() - radius * radius);
    if (disc < 0.0) return std::nullopt;
    const double root = std::sqrt(disc);
    const double near = -b - root;
    if (near >= 0.0) return near;
    const double far = -b + root;
    if (far >= 0.0) return far;
    return std::nullopt;
}

void setIntersectionCounters(benchmark::State& state, int64_t per_iteration, double hit_fraction) {
    state.SetItemsProcessed(state.iterations() * per_iteration);
    state.counters["rays_per_s"] = benchmark::Counter(
        static_cast<double>(state.iterations() * per_iteration), benchmark::Counter::kIsRate);
    state.counters["hit"] = hit_fraction;
}

template <typename Intersect>
double hitFraction(Intersect intersect) {
    int hits = 0;
    for (const SurfaceCase& c : surfaceCases())
        if (intersect(c.position, c.direction, c.vertex_z, c.curvature)) ++hits;
    return static_cast<double>(hits) / kSurfaceCases;
}

void BM_IntersectSurface(benchmark::State& state) {
    const std::vector<SurfaceCase>& cases = surfaceCases();
    for (auto _ : state) {
        for (const SurfaceCase& c : cases) {
            std::optional<double> t =
                intersectSurface(c.position, c.direction, c.vertex_z, c.curvature);
            benchmark::DoNotOptimize(t);
        }
    }
    setIntersectionCounters(state, kSurfaceCases, hitFraction(intersectSurface));
}

// The same intersections, each made to wait for the one before (its start moves by 0 * t, which
// the compiler may not drop): latency instead of throughput. A path is such a chain, so this is
// what one step of a trace can at best cost.
void BM_IntersectSurfaceChained(benchmark::State& state) {
    const std::vector<SurfaceCase>& cases = surfaceCases();
    double carry = 0.0;
    for (auto _ : state) {
        for (const SurfaceCase& c : cases) {
            const Eigen::Vector3d position(c.position.x() + carry, c.position.y(), c.position.z());
            const std::optional<double> t =
                intersectSurface(position, c.direction, c.vertex_z, c.curvature);
            carry = t.value_or(0.0) * 0.0;
        }
    }
    benchmark::DoNotOptimize(carry);
    setIntersectionCounters(state, kSurfaceCases, hitFraction(intersectSurface));
}

void BM_IntersectSphereTextbook(benchmark::State& state) {
    const std::vector<SurfaceCase>& cases = surfaceCases();
    for (auto _ : state) {
        for (const SurfaceCase& c : cases) {
            std::optional<double> t =
                intersectTextbook(c.position, c.direction, c.vertex_z, c.curvature);
            benchmark::DoNotOptimize(t);
        }
    }
    setIntersectionCounters(state, kSurfaceCases, hitFraction(intersectTextbook));
}

// Reads every word of every case and folds the bits with XOR, which the compiler may vectorize
// freely: an adding loop would measure the latency of a chain of floating-point additions, not
// the cost of reading.
void BM_ReadRays(benchmark::State& state) {
    const std::vector<SurfaceCase>& cases = surfaceCases();
    for (auto _ : state) {
        uint64_t fold = 0;
        for (const SurfaceCase& c : cases) {
            fold ^=
                std::bit_cast<uint64_t>(c.position.x()) ^ std::bit_cast<uint64_t>(c.position.y()) ^
                std::bit_cast<uint64_t>(c.position.z()) ^ std::bit_cast<uint64_t>(c.direction.x()) ^
                std::bit_cast<uint64_t>(c.direction.y()) ^
                std::bit_cast<uint64_t>(c.direction.z()) ^ std::bit_cast<uint64_t>(c.vertex_z) ^
                std::bit_cast<uint64_t>(c.curvature);
        }
        benchmark::DoNotOptimize(fold);
    }
    setIntersectionCounters(state, kSurfaceCases, 1.0);
}

// ---------------------------------------------------------------------------------------------
// Whole paths through shipped lenses

struct LensCase {
    Lens lens;
    GhostPath ghost;
    double ghost_power = 0.0;
    std::vector<Ray> rays;
};

// Shirley & Chiu's concentric map from the square to the disk: every grid point lands inside the
// pupil, and the points stay evenly spread up to its rim.
Eigen::Vector2d concentricDisk(double u, double v) {
    const double a = 2.0 * u - 1.0, b = 2.0 * v - 1.0;
    if (a == 0.0 && b == 0.0) return Eigen::Vector2d::Zero();
    if (std::abs(a) > std::abs(b)) {
        const double phi = (kPi / 4.0) * (b / a);
        return a * Eigen::Vector2d(std::cos(phi), std::sin(phi));
    }
    const double phi = kPi / 2.0 - (kPi / 4.0) * (a / b);
    return b * Eigen::Vector2d(std::cos(phi), std::sin(phi));
}

std::unique_ptr<LensCase> makeLensCase(const std::string& file) {
    auto prescription = loadPrescription(file);
    if (!prescription) {
        std::cerr << "optics_bench: " << prescription.error().message << "\n";
        return nullptr;
    }
    auto lens = Lens::make(*prescription, CameraDescription{});
    if (!lens) {
        std::cerr << "optics_bench: " << lens.error().message << "\n";
        return nullptr;
    }
    auto result = std::make_unique<LensCase>(LensCase{*lens, {}, 0.0, {}});
    const Eigen::Vector3d direction = lightDirection(degToRad(kTheta_deg), 0.0);
    const EntryPlane plane = defaultEntryPlane(*lens);
    const auto paraxial = paraxialProperties(*lens, kWavelength_nm);
    if (!paraxial) {
        std::cerr << "optics_bench: " << file << ": no paraxial entrance pupil\n";
        return nullptr;
    }
    // Centre the grid on the real chief ray. The entry plane is the paraxial entrance pupil, so
    // the paraxial chief ray crosses it on the axis: that is the first guess, and the fallback.
    const PathTracer aim_tracer(
        *lens, GhostPath{}, kWavelength_nm,
        TraceOptions{.clip_apertures = false, .clip_stop = false, .fresnel = false});
    const Eigen::Vector2d centre =
        aimAtStop(aim_tracer, plane, direction, Eigen::Vector2d::Zero(), Eigen::Vector2d::Zero())
            .value_or(Eigen::Vector2d::Zero());
    const double radius = paraxial->entrance_pupil_radius_mm;
    for (int iy = 0; iy < kGridSide; ++iy) {
        for (int ix = 0; ix < kGridSide; ++ix) {
            const Eigen::Vector2d disk =
                concentricDisk((ix + 0.5) / kGridSide, (iy + 0.5) / kGridSide);
            result->rays.push_back(
                rayThroughEntry(plane, centre + radius * disk, direction, kWavelength_nm));
        }
    }
    const auto enumeration = enumerateGhosts(*lens);
    const LightDirectionDeg light{kTheta_deg, 0.0};
    const auto reference = imagingPower(*lens, light, 16);
    if (!enumeration || enumeration->ghosts.empty() || !reference) {
        std::cerr << "optics_bench: " << file << ": no ghosts to trace\n";
        return nullptr;
    }
    result->ghost = enumeration->ghosts[enumeration->ghosts.size() / 2];
    for (const GhostPath& path : enumeration->ghosts) {
        const auto power = ghostIntensity(*lens, path, light, *reference);
        if (power && power->relative_power > result->ghost_power) {
            result->ghost_power = power->relative_power;
            result->ghost = path;
        }
    }
    return result;
}

// Built on first use and kept, so repetitions and the iteration-count probes of one benchmark do
// not pay for the ghost search again, and a filtered run builds only the lenses it needs. nullptr
// when the lens cannot be used (the reason went to stderr).
const LensCase* lensCase(const std::string& file) {
    static std::map<std::string, std::unique_ptr<LensCase>> cache;
    auto it = cache.find(file);
    if (it == cache.end()) it = cache.emplace(file, makeLensCase(file)).first;
    return it->second.get();
}

void tracePath(benchmark::State& state,
               const LensCase& c,
               const GhostPath& path,
               const TraceOptions& options) {
    const PathTracer tracer(c.lens, path, kWavelength_nm, options);
    int completed = 0;
    for (const Ray& ray : c.rays)
        if (tracer.trace(ray)) ++completed;
    for (auto _ : state) {
        for (const Ray& ray : c.rays) {
            std::optional<TracedRay> traced = tracer.trace(ray);
            benchmark::DoNotOptimize(traced);
        }
    }
    const int64_t rays = static_cast<int64_t>(c.rays.size());
    state.SetItemsProcessed(state.iterations() * rays * tracer.intersectionsPerRay());
    state.counters["rays_per_s"] = benchmark::Counter(
        static_cast<double>(state.iterations() * rays), benchmark::Counter::kIsRate);
    state.counters["per_ray"] = tracer.intersectionsPerRay();
    state.counters["completed"] = static_cast<double>(completed) / static_cast<double>(rays);
    state.SetLabel(path.isImaging() ? "imaging" : "ghost " + pathLabel(path));
}

// The same rays through traceBatch, 256 at a time (a grid row of the default base size).
void tracePathBatched(benchmark::State& state,
                      const LensCase& c,
                      const GhostPath& path,
                      const TraceOptions& options) {
    const PathTracer tracer(c.lens, path, kWavelength_nm, options);
    constexpr size_t kBatch = 256;
    std::vector<std::optional<TracedRay>> out(kBatch);
    for (auto _ : state) {
        for (size_t first = 0; first < c.rays.size(); first += kBatch) {
            const size_t count = std::min(kBatch, c.rays.size() - first);
            tracer.traceBatch(std::span(c.rays).subspan(first, count), std::span(out).first(count));
            benchmark::DoNotOptimize(out.data());
        }
    }
    const int64_t rays = static_cast<int64_t>(c.rays.size());
    state.SetItemsProcessed(state.iterations() * rays * tracer.intersectionsPerRay());
    state.counters["rays_per_s"] = benchmark::Counter(
        static_cast<double>(state.iterations() * rays), benchmark::Counter::kIsRate);
    state.counters["per_ray"] = tracer.intersectionsPerRay();
    state.SetLabel("ghost " + pathLabel(path) + ", batches of 256");
}

constexpr TraceOptions kUnclipped{.clip_apertures = false, .clip_stop = false, .fresnel = true};
constexpr TraceOptions kUnclippedGeometry{
    .clip_apertures = false, .clip_stop = false, .fresnel = false};

void BM_TraceImagingPath(benchmark::State& state, const std::string& file) {
    const LensCase* c = lensCase(file);
    if (!c) return state.SkipWithError("lens unusable, see stderr");
    tracePath(state, *c, GhostPath{}, kUnclipped);
}

void BM_TraceGhostPath(benchmark::State& state, const std::string& file) {
    const LensCase* c = lensCase(file);
    if (!c) return state.SkipWithError("lens unusable, see stderr");
    tracePath(state, *c, c->ghost, kUnclipped);
}

void BM_TraceGhostPathGeometry(benchmark::State& state, const std::string& file) {
    const LensCase* c = lensCase(file);
    if (!c) return state.SkipWithError("lens unusable, see stderr");
    tracePath(state, *c, c->ghost, kUnclippedGeometry);
}

void BM_TraceGhostPathBatched(benchmark::State& state, const std::string& file) {
    const LensCase* c = lensCase(file);
    if (!c) return state.SkipWithError("lens unusable, see stderr");
    tracePathBatched(state, *c, c->ghost, kUnclipped);
}

// The same rays through RowTracer (row_tracer.h), a row of kGridSide at a time, as the ray grid
// traces them: the structure-of-arrays kernel in float or double, AVX2 or SSE2.
void traceRows(benchmark::State& state, const LensCase& c, const RowTracer::Options& options) {
    const RowTracer tracer(c.lens, c.ghost, kWavelength_nm, options);
    const size_t rows = c.rays.size() / kGridSide;
    std::vector<std::vector<double>> xs(rows), ys(rows);
    for (size_t r = 0; r < rows; ++r)
        for (int i = 0; i < kGridSide; ++i) {
            xs[r].push_back(c.rays[r * kGridSide + i].position.x());
            ys[r].push_back(c.rays[r * kGridSide + i].position.y());
        }
    const double z = c.rays.front().position.z();
    const Eigen::Vector3d direction = c.rays.front().direction;
    TracedRow out;
    for (auto _ : state) {
        for (size_t r = 0; r < rows; ++r) {
            tracer.trace(xs[r], ys[r], z, direction, out);
            benchmark::DoNotOptimize(out.x_mm.data());
        }
    }
    const PathTracer exact(c.lens, c.ghost, kWavelength_nm);
    const int64_t rays = static_cast<int64_t>(rows * kGridSide);
    state.SetItemsProcessed(state.iterations() * rays * exact.intersectionsPerRay());
    state.counters["rays_per_s"] = benchmark::Counter(
        static_cast<double>(state.iterations() * rays), benchmark::Counter::kIsRate);
    state.counters["avx2"] = tracer.usesAvx2() ? 1 : 0;
}

template <RowTracer::Precision kPrecision, bool kAvx2>
void BM_TraceGhostPathRow(benchmark::State& state, const std::string& file) {
    const LensCase* c = lensCase(file);
    if (!c) return state.SkipWithError("lens unusable, see stderr");
    RowTracer::Options options;
    options.precision = kPrecision;
    options.allow_avx2 = kAvx2;
    traceRows(state, *c, options);
}

std::vector<std::filesystem::path> shippedLenses() {
    std::vector<std::filesystem::path> files;
    const std::filesystem::path dir = std::filesystem::path(FLARELAB_SOURCE_DIR) / "data/lenses";
    std::error_code error;
    for (const auto& entry : std::filesystem::directory_iterator(dir, error))
        if (entry.path().extension() == ".csv") files.push_back(entry.path());
    std::sort(files.begin(), files.end());
    return files;
}

void registerBenchmarks() {
    benchmark::RegisterBenchmark("BM_ReadRays", BM_ReadRays);
    benchmark::RegisterBenchmark("BM_IntersectSphereTextbook", BM_IntersectSphereTextbook);
    benchmark::RegisterBenchmark("BM_IntersectSurface", BM_IntersectSurface);
    benchmark::RegisterBenchmark("BM_IntersectSurfaceChained", BM_IntersectSurfaceChained);
    const auto lenses = shippedLenses();
    const auto add = [&](const char* name, void (*fn)(benchmark::State&, const std::string&)) {
        for (const auto& file : lenses)
            benchmark::RegisterBenchmark((std::string(name) + "/" + file.stem().string()).c_str(),
                                         fn, file.string());
    };
    add("BM_TraceImagingPath", BM_TraceImagingPath);
    add("BM_TraceGhostPath", BM_TraceGhostPath);
    add("BM_TraceGhostPathGeometry", BM_TraceGhostPathGeometry);
    add("BM_TraceGhostPathBatched", BM_TraceGhostPathBatched);
    add("BM_TraceGhostPathRowDoubleSse2",
        BM_TraceGhostPathRow<RowTracer::Precision::Double, false>);
    add("BM_TraceGhostPathRowFloatSse2", BM_TraceGhostPathRow<RowTracer::Precision::Float, false>);
    add("BM_TraceGhostPathRowDouble", BM_TraceGhostPathRow<RowTracer::Precision::Double, true>);
    add("BM_TraceGhostPathRowFloat", BM_TraceGhostPathRow<RowTracer::Precision::Float, true>);
}

}  // namespace
}  // namespace flarelab::bench

int main(int argc, char** argv) {
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    flarelab::bench::registerBenchmarks();
    benchmark::RunSpecifiedBenchmarks();
    benchmark::Shutdown();
    return 0;
}
