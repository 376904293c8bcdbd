#include "render/scene.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include "common/units.h"
#include "optics/aim.h"
#include "optics/paraxial.h"
#include "optics/ray_grid.h"
#include "optics/tracer.h"

namespace flarelab::render {
namespace {

constexpr double kChannel_nm[3] = {kLambdaRed_nm, kLambdaGreen_nm, kLambdaBlue_nm};

// Rays per side of the grid whose integral is the light's own power (imagingPower): the stop's
// outline crosses about 100 of its cells, each sampled finely.
constexpr int kLightGrid = 32;

using Clock = std::chrono::steady_clock;

double millisecondsSince(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

Error invalid(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "scene: " + what);
}

// Area of the bounding rectangle of a probe grid's valid rays on the sensor (mm^2), 0 if none.
double footprintArea(const optics::RayGrid& grid) {
    double lo_x = 1e300, hi_x = -1e300, lo_y = 1e300, hi_y = -1e300;
    bool any = false;
    for (const optics::GridSample& s : grid.samples) {
        if (!s.valid) continue;
        any = true;
        lo_x = std::min<double>(lo_x, s.sensor_x_mm);
        hi_x = std::max<double>(hi_x, s.sensor_x_mm);
        lo_y = std::min<double>(lo_y, s.sensor_y_mm);
        hi_y = std::max<double>(hi_y, s.sensor_y_mm);
    }
    return any ? (hi_x - lo_x) * (hi_y - lo_y) : 0.0;
}

// The light's own image: where its chief ray lands, and the power the imaging path carries.
void addLightImage(ImageRGB& image,
                   const optics::Lens& lens,
                   const Light& light,
                   const SceneOptions& options,
                   const SensorToImage& mapping,
                   const ImageRGB& pattern) {
    const auto paraxial = optics::paraxialProperties(lens, kLambdaGreen_nm);
    if (!paraxial) return;
    const Eigen::Vector3d direction =
        optics::lightDirection(degToRad(light.theta_deg), degToRad(light.phi_deg));
    const optics::EntryPlane plane = optics::defaultEntryPlane(lens);
    float power[3] = {0.0f, 0.0f, 0.0f};
    Eigen::Vector2d centre_mm = Eigen::Vector2d::Zero();
    bool placed = false;
    for (int c = 0; c < 3; ++c) {
        const auto grid = optics::traceRayGrid(lens, optics::GhostPath{}, degToRad(light.theta_deg),
                                               degToRad(light.phi_deg), kChannel_nm[c],
                                               std::max(options.probe_grid, kLightGrid));
        if (!grid || grid->n < 2) continue;
        power[c] = static_cast<float>(light.rgb[c] * imagingPower(*grid, lens.aperture()));
        if (c == 1) {
            const optics::PathTracer chief(lens, optics::GhostPath{}, kLambdaGreen_nm);
            const auto entry =
                optics::aimAtStop(optics::PathTracer(lens, optics::GhostPath{}, kLambdaGreen_nm,
                                                     optics::TraceOptions{.clip_apertures = false,
                                                                          .clip_stop = false,
                                                                          .fresnel = false}),
                                  plane, direction, Eigen::Vector2d::Zero(), grid->entry_centre_mm);
            if (entry) {
                const auto traced =
                    chief.trace(optics::rayThroughEntry(plane, *entry, direction, kLambdaGreen_nm));
                if (traced) {
                    centre_mm = traced->ray.position.head<2>();
                    placed = true;
                }
            }
        }
    }
    if (!placed) return;
    // Pattern pixels to image pixels: the pattern's angle per pixel over the image's.
    const double pupil_diameter_mm = 2.0 * paraxial->entrance_pupil_radius_mm;
    const double pattern_rad = starburstPixelAngle(options.starburst_options, pupil_diameter_mm);
    const double image_rad = 1.0 / (mapping.px_per_mm_x * std::abs(paraxial->efl_mm));
    const double scale = pattern_rad / image_rad;
    const Eigen::Vector2d centre_px = mapping.toPixels(centre_mm.x(), centre_mm.y());
    if (!(scale > 0.0) || !std::isfinite(scale) || !centre_px.allFinite()) return;
    addStarburst(image, pattern, centre_px.x(), centre_px.y(), power, scale);
}

}  // namespace

Result<ImageRGB> renderScene(const optics::Lens& lens,
                             std::span<const Light> lights,
                             const SceneOptions& options,
                             SceneStats* stats) {
    if (options.width < 1 || options.height < 1 || options.width > 32768 || options.height > 32768)
        return invalid("width and height must lie in 1..32768 pixels");
    if (options.base_grid < 2 || options.base_grid > 2048)
        return invalid("base_grid must lie in 2..2048");
    if (options.max_pending_primitives < 1)
        return invalid("max_pending_primitives must be at least 1");
    if (options.merge.steps < 0 || options.merge.steps > 7)
        return invalid("merge steps must lie in 0..7");
    if (!(options.merge.gamma >= 0.0) || !std::isfinite(options.merge.gamma))
        return invalid("merge gamma must be finite and >= 0");
    if (options.raster.supersample < 0 || options.raster.supersample > 64)
        return invalid("raster supersample must lie in 0..64");
    if (options.probe_grid < 2 || options.probe_grid > 256)
        return invalid("probe_grid must lie in 2..256");
    if (!(options.grid_sigma > 0.0) || !(options.grid_phi > 0.0) ||
        !std::isfinite(options.grid_sigma) || !std::isfinite(options.grid_phi))
        return invalid("grid_sigma and grid_phi must be positive");
    for (size_t i = 0; i < lights.size(); ++i) {
        const Light& l = lights[i];
        const bool finite = std::isfinite(l.theta_deg) && std::isfinite(l.phi_deg) &&
                            std::all_of(l.rgb.begin(), l.rgb.end(),
                                        [](float v) { return std::isfinite(v) && v >= 0.0f; });
        if (!finite || l.theta_deg < 0.0) {
            std::ostringstream msg;
            msg << "light " << i + 1
                << ": theta must be >= 0 and every value finite, with rgb >= 0";
            return invalid(msg.str());
        }
    }
    if (options.starburst) {
        if (Status ok = validateStarburstOptions(options.starburst_options); !ok) return ok.error();
    }
    auto enumeration = optics::enumerateGhosts(lens, options.ghosts);
    if (!enumeration) return enumeration.error();

    SceneStats local;
    SceneStats& st = stats ? *stats : local;
    st = SceneStats{};
    ImageRGB image(options.width, options.height);
    const SensorToImage mapping = sensorToImage(lens.camera(), options.width, options.height);
    const double sensor_area = lens.camera().sensor_width_mm * lens.camera().sensor_height_mm;
    std::optional<ImageRGB> pattern;
    if (options.starburst) {
        StarburstOptions burst = options.starburst_options;
        burst.aperture = lens.aperture();
        auto rendered = renderStarburst(burst);
        if (!rendered) return rendered.error();
        pattern = std::move(*rendered);
    }
    std::vector<Primitive> primitives;
    double draw_ms = 0.0;
    const auto flush = [&]() -> Status {
        TileStats batch;
        if (Status drawn = renderTiled(image, primitives, lens.aperture(), options.tiles, &batch);
            !drawn)
            return drawn;
        st.tiles.primitives += batch.primitives;
        st.tiles.coarse_entries += batch.coarse_entries;
        st.tiles.dense_entries += batch.dense_entries;
        st.tiles.memory_bytes = std::max(st.tiles.memory_bytes, batch.memory_bytes);
        st.tiles.build_ms += batch.build_ms;
        st.tiles.traverse_ms += batch.traverse_ms;
        draw_ms += batch.build_ms + batch.traverse_ms;
        primitives.clear();
        return Ok{};
    };
    // One grid per light, ghost and channel, with its eq. 13 size from a probe grid whose entry
    // square the full grid reuses.
    struct Task {
        const Light* light;
        const optics::GhostPath* path;
        int channel;
    };
    struct Traced {
        GhostQuads quads;
        int64_t quad_count = 0;
        int64_t rays = 0;
        Status status = Ok{};
    };
    const auto traceTask = [&](const Task& task) {
        Traced out;
        const double theta = degToRad(task.light->theta_deg), phi = degToRad(task.light->phi_deg);
        const double lambda = kChannel_nm[task.channel];
        const auto probe =
            optics::traceRayGrid(lens, *task.path, theta, phi, lambda, options.probe_grid);
        if (!probe) {
            out.status = probe.error();
            return out;
        }
        if (probe->validCount() == 0) return out;
        const int n = adaptiveGridSize(options.base_grid, footprintArea(*probe), sensor_area,
                                       options.grid_sigma, options.grid_phi);
        optics::RayGridOptions grid_options;
        grid_options.square = probe->square();
        const auto grid =
            optics::traceRayGrid(lens, *task.path, theta, phi, lambda, n, grid_options);
        if (!grid) {
            out.status = grid.error();
            return out;
        }
        out.quads = quadsFromGrid(*grid, mapping, options.merge);
        out.quad_count = static_cast<int64_t>(out.quads.quads.size());
        out.rays = static_cast<int64_t>(n) * n;
        return out;
    };
    std::vector<Task> tasks;
    for (const Light& light : lights) {
        if (light.theta_deg >= 90.0) {
            ++st.lights_behind;
            continue;
        }
        for (const optics::GhostPath& path : enumeration->ghosts)
            for (int c = 0; c < 3; ++c)
                if (light.rgb[c] > 0.0f) tasks.push_back({&light, &path, c});
    }
    const auto count = [&](const Traced& t) {
        ++st.ghosts_drawn;
        st.quads += t.quad_count;
        st.rays += t.rays;
    };
    const auto start = Clock::now();
    if (options.tiled) {
        // Tasks in blocks, each block traced in parallel and its primitives appended in task
        // order; a block is a few tasks per core, so memory stays bounded.
        const size_t block =
            8 * static_cast<size_t>(std::max(1, tbb::this_task_arena::max_concurrency()));
        std::vector<Traced> traced;
        std::vector<std::vector<Primitive>> prepared;
        for (size_t first = 0; first < tasks.size(); first += block) {
            const size_t last = std::min(tasks.size(), first + block);
            traced.assign(last - first, Traced{});
            prepared.assign(last - first, {});
            tbb::parallel_for(size_t{0}, last - first, [&](size_t i) {
                const Task& task = tasks[first + i];
                traced[i] = traceTask(task);
                const GhostQuads& quads = traced[i].quads;
                for (size_t q = 0; q < quads.quads.size(); ++q)
                    if (auto p = preparePrimitive(quads.quads[q], quads.cellArea(q), task.channel,
                                                  task.light->rgb[task.channel], options.width,
                                                  options.height, options.raster))
                        prepared[i].push_back(*p);
                traced[i].quads = GhostQuads{};  // the primitives hold what is needed now
            });
            for (size_t i = 0; i < traced.size(); ++i) {
                if (!traced[i].status) return traced[i].status.error();
                if (traced[i].quad_count == 0) continue;
                count(traced[i]);
                primitives.insert(primitives.end(), prepared[i].begin(), prepared[i].end());
                if (static_cast<int64_t>(primitives.size()) >= options.max_pending_primitives) {
                    if (Status drawn = flush(); !drawn) return drawn.error();
                }
            }
        }
        if (!primitives.empty()) {
            if (Status drawn = flush(); !drawn) return drawn.error();
        }
    } else {
        for (const Task& task : tasks) {
            const Traced t = traceTask(task);
            if (!t.status) return t.status.error();
            if (t.quads.quads.empty()) continue;
            const auto draw_start = Clock::now();
            rasterizeReference(image, t.quads, task.channel, task.light->rgb[task.channel],
                               lens.aperture(), options.raster);
            draw_ms += millisecondsSince(draw_start);
            count(t);
        }
    }
    const auto lights_start = Clock::now();
    if (pattern)
        for (const Light& light : lights)
            if (light.theta_deg < 90.0)
                addLightImage(image, lens, light, options, mapping, *pattern);
    st.light_ms = millisecondsSince(lights_start);
    st.trace_ms = millisecondsSince(start) - draw_ms - st.light_ms;
    st.draw_ms = draw_ms;
    return image;
}

}  // namespace flarelab::render
