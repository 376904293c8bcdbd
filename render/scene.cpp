#include "render/scene.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
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

// Whether any ray on the grid's border is valid: the beam may then reach past the grid's square.
bool ringHasValidRays(const optics::RayGrid& grid) {
    for (int i = 0; i < grid.n; ++i)
        if (grid.at(i, 0).valid || grid.at(i, grid.n - 1).valid || grid.at(0, i).valid ||
            grid.at(grid.n - 1, i).valid)
            return true;
    return false;
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

// The rays a side a grid over the probe's square needs so that what its quads interpolate
// linearly across one cell is off by at most `bend_px` pixels: linear interpolation over a step h
// misses by about |f''| h^2 / 8, and the probe's second difference between neighbours along a
// row or column is |f''| times its own step squared. Two things are interpolated and both count:
// the sensor position (in pixels), and the stop coordinates, whose error moves the stop's outline
// by about that error times half the footprint's extent (the coordinates run from -1 to 1 across
// an uncut beam). Every sample with a position counts, cut ones too: the outline lies among them.
// A probe with no three such neighbours in a line asks for nothing.
int gridForBend(const optics::RayGrid& probe, const SensorToImage& mapping, double bend_px) {
    const auto px = [&](const optics::GridSample& s) {
        return mapping.toPixels(s.sensor_x_mm, s.sensor_y_mm);
    };
    const auto uv = [](const optics::GridSample& s) { return Eigen::Vector2d(s.stop_u, s.stop_v); };
    Eigen::Vector2d lo(1e300, 1e300), hi(-1e300, -1e300);
    for (const optics::GridSample& s : probe.samples)
        if (s.has_position) {
            lo = lo.cwiseMin(px(s));
            hi = hi.cwiseMax(px(s));
        }
    const double half_extent = 0.5 * (hi - lo).maxCoeff();
    double second = 0.0;
    for (int iy = 0; iy < probe.n; ++iy)
        for (int ix = 0; ix < probe.n; ++ix)
            for (const auto& [dx, dy] : {std::pair{1, 0}, std::pair{0, 1}}) {
                if (ix - dx < 0 || iy - dy < 0 || ix + dx >= probe.n || iy + dy >= probe.n)
                    continue;
                const optics::GridSample& a = probe.at(ix - dx, iy - dy);
                const optics::GridSample& b = probe.at(ix, iy);
                const optics::GridSample& c = probe.at(ix + dx, iy + dy);
                if (!a.has_position || !b.has_position || !c.has_position) continue;
                second = std::max(second, (px(a) - 2.0 * px(b) + px(c)).lpNorm<Eigen::Infinity>());
                second = std::max(
                    second, half_extent * (uv(a) - 2.0 * uv(b) + uv(c)).lpNorm<Eigen::Infinity>());
            }
    const double cells = (probe.n - 1) * std::sqrt(second / (8.0 * bend_px));
    if (!std::isfinite(cells)) return std::numeric_limits<int>::max();
    return static_cast<int>(std::min(std::ceil(cells), 4096.0)) + 1;
}

}  // namespace

namespace {

// A zeroed frame whose pages all threads fault in at once: a fresh 1920x1080 image is 25 MB,
// and on the shared machines this project is measured on, faulting it in on one thread took 13
// to 50 ms of a 160 ms Heliar frame. The reserved storage is written as raw bytes, a large page
// per task, before the vector constructs (zeroes) its floats in memory already mapped.
ImageRGB parallelZeroedImage(int64_t width, int64_t height) {
    ImageRGB image;
    image.width = width;
    image.height = height;
    const size_t n = static_cast<size_t>(width * height * 3);
    reserveLargePages(image.pixels, n);
    const size_t bytes = n * sizeof(float);
    if (bytes >= kLargePageMinBytes) {
        auto* storage = reinterpret_cast<unsigned char*>(image.pixels.data());
        tbb::parallel_for(size_t{0}, (bytes + kLargePageBytes - 1) / kLargePageBytes,
                          [&](size_t page) {
                              const size_t at = page * kLargePageBytes;
                              std::memset(storage + at, 0, std::min(kLargePageBytes, bytes - at));
                          });
    }
    image.pixels.resize(n);
    return image;
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
    if (options.max_grid != 0 && (options.max_grid < 2 || options.max_grid > 2048))
        return invalid("max_grid must be 0 (no cap) or lie in 2..2048");
    if (!(options.grid_bend_px > 0.0) || !std::isfinite(options.grid_bend_px))
        return invalid("grid_bend_px must be positive and finite");
    if (options.max_pending_primitives < 1)
        return invalid("max_pending_primitives must be at least 1");
    if (options.merge.steps < 0 || options.merge.steps > 7)
        return invalid("merge steps must lie in 0..7");
    if (!(options.merge.gamma >= 0.0) || !std::isfinite(options.merge.gamma))
        return invalid("merge gamma must be finite and >= 0");
    if (!(options.merge.centre_edge_jump >= 0.0 && options.merge.centre_edge_jump <= 1.0))
        return invalid("merge centre_edge_jump must lie in 0..1");
    if (options.raster.supersample < 0 || options.raster.supersample > 64)
        return invalid("raster supersample must lie in 0..64");
    if (options.probe_grid < 2 || options.probe_grid > 256)
        return invalid("probe_grid must lie in 2..256");
    if (!(options.cull_relative_l2 >= 0.0 && options.cull_relative_l2 <= 1.0))
        return invalid("cull_relative_l2 must lie in 0..1");
    if (!(options.cull_mean_below >= 0.0) || !std::isfinite(options.cull_mean_below))
        return invalid("cull_mean_below must be finite and >= 0");
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
    if (!options.only_paths.empty()) {
        std::vector<optics::GhostPath> kept;
        for (const optics::GhostPath& path : options.only_paths) {
            if (std::find(enumeration->ghosts.begin(), enumeration->ghosts.end(), path) ==
                enumeration->ghosts.end())
                return invalid("only_paths: " + optics::pathLabel(path) +
                               " is not one of the lens's ghost paths");
            kept.push_back(path);
        }
        std::sort(kept.begin(), kept.end());
        kept.erase(std::unique(kept.begin(), kept.end()), kept.end());
        enumeration->ghosts = std::move(kept);
    }

    SceneStats local;
    SceneStats& st = stats ? *stats : local;
    st = SceneStats{};
    ImageRGB image = parallelZeroedImage(options.width, options.height);
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
    // The primitives waiting to be drawn, one array per ghost grid (moved, never copied).
    std::vector<PrimitiveArray> pending;
    size_t pending_count = 0;
    double draw_ms = 0.0;
    const auto flush = [&]() -> Status {
        TileStats batch;
        if (Status drawn =
                renderTiledChunks(image, pending, lens.aperture(), options.tiles, &batch);
            !drawn)
            return drawn;
        st.tiles.primitives += batch.primitives;
        st.tiles.coarse_entries += batch.coarse_entries;
        st.tiles.dense_entries += batch.dense_entries;
        st.tiles.memory_bytes = std::max(st.tiles.memory_bytes, batch.memory_bytes);
        st.tiles.build_ms += batch.build_ms;
        st.tiles.traverse_ms += batch.traverse_ms;
        draw_ms += batch.build_ms + batch.traverse_ms;
        pending.clear();
        pending_count = 0;
        return Ok{};
    };
    // One grid per light, ghost and channel, with its eq. 13 size from a probe grid whose entry
    // square the full grid reuses. The probes come first, all of them, so that culling can weigh
    // each ghost against all the others.
    struct Task {
        const Light* light = nullptr;
        const optics::GhostPath* path = nullptr;
        int channel = 0;
        // From the probe:
        bool lit = false;  // some valid ray, and the footprint touches the image
        int n = 0;         // the full grid's size (eq. 13)
        optics::EntrySquare square;
        int aimed_again = 0;    // 1: the shared square did not hold this channel's beam
        int windowed = 0;       // 1: the grid shrank to the image's window
        double power = 0.0;     // on the image, in image units summed over pixels
        double area_px = 0.0;   // of the footprint on the image
        double l2_share = 0.0;  // power^2 / area
    };
    struct Traced {
        GhostQuads quads;
        int64_t quad_count = 0;
        int64_t rays = 0;
        Status status = Ok{};
    };
    const double width_px = static_cast<double>(options.width);
    const double height_px = static_cast<double>(options.height);
    // SceneOptions::image_window: the full grid shrinks to the square of probe cells that can put
    // light in the image, grown by one probe cell, at the same ray spacing. A probe cell counts
    // when the pixel box of its corners that have a position, grown by the probe's largest step
    // between neighbouring rays (`spacing`), touches the image.
    const auto imageWindow = [&](Task& task, const optics::RayGrid& probe, double spacing) {
        const int np = probe.n;
        if (np < 2 || task.n < 3) return;
        int lo_x = np, hi_x = -1, lo_y = np, hi_y = -1;
        for (int iy = 0; iy + 1 < np; ++iy) {
            for (int ix = 0; ix + 1 < np; ++ix) {
                double bx0 = 1e300, bx1 = -1e300, by0 = 1e300, by1 = -1e300;
                for (const auto& [dx, dy] :
                     {std::pair{0, 0}, std::pair{1, 0}, std::pair{0, 1}, std::pair{1, 1}}) {
                    const optics::GridSample& s = probe.at(ix + dx, iy + dy);
                    if (!s.has_position) continue;
                    const Eigen::Vector2d p = mapping.toPixels(s.sensor_x_mm, s.sensor_y_mm);
                    bx0 = std::min(bx0, p.x());
                    bx1 = std::max(bx1, p.x());
                    by0 = std::min(by0, p.y());
                    by1 = std::max(by1, p.y());
                }
                if (!(bx1 + spacing >= 0.0 && bx0 - spacing <= width_px && by1 + spacing >= 0.0 &&
                      by0 - spacing <= height_px))
                    continue;  // no corner with a position, or all of them far off the image
                lo_x = std::min(lo_x, ix);
                hi_x = std::max(hi_x, ix + 1);
                lo_y = std::min(lo_y, iy);
                hi_y = std::max(hi_y, iy + 1);
            }
        }
        if (hi_x < 0) return;
        lo_x = std::max(0, lo_x - 1);
        lo_y = std::max(0, lo_y - 1);
        hi_x = std::min(np - 1, hi_x + 1);
        hi_y = std::min(np - 1, hi_y + 1);
        const int span = std::max(hi_x - lo_x, hi_y - lo_y);  // probe cells
        if (span >= np - 1) return;
        const double probe_cell = 2.0 * probe.entry_half_width_mm / (np - 1);
        const double cell = 2.0 * probe.entry_half_width_mm / (task.n - 1);
        const int cells = static_cast<int>(std::ceil(span * probe_cell / cell - 1e-9));
        if (cells + 1 >= task.n) return;
        task.square.centre_mm =
            probe.entry_centre_mm +
            Eigen::Vector2d(-probe.entry_half_width_mm + 0.5 * probe_cell * (lo_x + hi_x),
                            -probe.entry_half_width_mm + 0.5 * probe_cell * (lo_y + hi_y));
        task.square.half_width_mm = 0.5 * cells * cell;
        task.n = cells + 1;
        ++task.windowed;
    };
    // The probe of one task: green's own, traced over the square aimed at green for its light and
    // path, or the channel's over that square. Where the channel's outer ring has valid rays and
    // green's had none, dispersion has pushed the beam past the square: it is aimed on its own.
    const auto probeTask = [&](Task& task, const optics::RayGrid& green) -> Status {
        const optics::RayGrid* probe = &green;
        std::optional<optics::RayGrid> own;
        if (kChannel_nm[task.channel] != kLambdaGreen_nm) {
            const double theta = degToRad(task.light->theta_deg);
            const double phi = degToRad(task.light->phi_deg);
            optics::RayGridOptions probe_options;
            probe_options.tracer = options.grid_tracer;
            probe_options.square = green.square();
            auto traced =
                optics::traceRayGrid(lens, *task.path, theta, phi, kChannel_nm[task.channel],
                                     options.probe_grid, probe_options);
            if (traced && !ringHasValidRays(green) && ringHasValidRays(*traced)) {
                probe_options.square.reset();
                traced =
                    optics::traceRayGrid(lens, *task.path, theta, phi, kChannel_nm[task.channel],
                                         options.probe_grid, probe_options);
                ++task.aimed_again;
            }
            if (!traced) return traced.error();
            own = std::move(*traced);
            probe = &*own;
        }
        task.square = probe->square();
        if (probe->validCount() == 0) return Ok{};
        task.n = adaptiveGridSize(options.base_grid, footprintArea(*probe), sensor_area,
                                  options.grid_sigma, options.grid_phi);
        // The footprint in pixels, and the power that lands on the image. A probe cell stands
        // for cell_area of the entry plane.
        const double cell = 2.0 * probe->entry_half_width_mm / (probe->n - 1);
        double lo_x = 1e300, hi_x = -1e300, lo_y = 1e300, hi_y = -1e300, power = 0.0;
        double spacing = 0.0;  // the largest step between neighbouring valid samples (pixels)
        for (int iy = 0; iy < probe->n; ++iy) {
            for (int ix = 0; ix < probe->n; ++ix) {
                const optics::GridSample& s = probe->at(ix, iy);
                if (!s.valid) continue;
                const Eigen::Vector2d p = mapping.toPixels(s.sensor_x_mm, s.sensor_y_mm);
                lo_x = std::min(lo_x, p.x());
                hi_x = std::max(hi_x, p.x());
                lo_y = std::min(lo_y, p.y());
                hi_y = std::max(hi_y, p.y());
                if (p.x() >= 0.0 && p.x() <= width_px && p.y() >= 0.0 && p.y() <= height_px)
                    power += s.throughput * cell * cell;
                for (const auto& [dx, dy] : {std::pair{1, 0}, std::pair{0, 1}}) {
                    if (ix + dx >= probe->n || iy + dy >= probe->n) continue;
                    const optics::GridSample& t = probe->at(ix + dx, iy + dy);
                    if (!t.valid) continue;
                    spacing = std::max(spacing, (mapping.toPixels(t.sensor_x_mm, t.sensor_y_mm) - p)
                                                    .lpNorm<Eigen::Infinity>());
                }
            }
        }
        if (options.max_grid > 0 && task.n > options.max_grid)
            task.n = std::min(task.n, std::max(options.max_grid,
                                               gridForBend(*probe, mapping, options.grid_bend_px)));
        // Grown by one probe cell: the full grid's quads reach that far past the probe's rays.
        lo_x -= spacing;
        hi_x += spacing;
        lo_y -= spacing;
        hi_y += spacing;
        const double in_x = std::min(hi_x, width_px) - std::max(lo_x, 0.0);
        const double in_y = std::min(hi_y, height_px) - std::max(lo_y, 0.0);
        if (!(in_x > 0.0 && in_y > 0.0)) return Ok{};
        task.lit = true;
        task.power = power * task.light->rgb[task.channel];
        task.area_px = std::max(1.0, in_x * in_y);
        task.l2_share = task.power * task.power / task.area_px;
        if (options.image_window) imageWindow(task, *probe, spacing);
        return Ok{};
    };
    // Merged quads stay clear of this lens's stop outline (MergeOptions::clear_stop_radius).
    MergeOptions merge = options.merge;
    merge.clear_stop_radius = StopMask(lens.aperture()).inscribedRadius();
    const auto traceTask = [&](const Task& task) {
        Traced out;
        const double theta = degToRad(task.light->theta_deg), phi = degToRad(task.light->phi_deg);
        optics::RayGridOptions grid_options;
        grid_options.square = task.square;
        grid_options.tracer = options.grid_tracer;
        if (options.adaptive_grid && options.grid_tracer != optics::GridTracer::Exact) {
            auto adaptive = adaptiveQuads(lens, *task.path, theta, phi, kChannel_nm[task.channel],
                                          task.n, grid_options, mapping, merge);
            if (!adaptive) {
                out.status = adaptive.error();
                return out;
            }
            out.quads = std::move(adaptive->quads);
            out.quad_count = static_cast<int64_t>(out.quads.quads.size());
            out.rays = adaptive->rays;
            return out;
        }
        const auto grid = optics::traceRayGrid(lens, *task.path, theta, phi,
                                               kChannel_nm[task.channel], task.n, grid_options);
        if (!grid) {
            out.status = grid.error();
            return out;
        }
        out.quads = quadsFromGrid(*grid, mapping, merge);
        out.quad_count = static_cast<int64_t>(out.quads.quads.size());
        out.rays = static_cast<int64_t>(task.n) * task.n;
        return out;
    };
    std::vector<Task> probed;
    for (const Light& light : lights) {
        if (light.theta_deg >= 90.0) {
            ++st.lights_behind;
            continue;
        }
        for (const optics::GhostPath& path : enumeration->ghosts)
            for (int c = 0; c < 3; ++c)
                if (light.rgb[c] > 0.0f) {
                    Task task;
                    task.light = &light;
                    task.path = &path;
                    task.channel = c;
                    probed.push_back(task);
                }
    }
    const auto start = Clock::now();
    // The channels of one light and path share the square aimed at green (aiming is the costly
    // part of a probe: Newton steps through every surface); each channel's own probe checks it.
    std::vector<std::pair<size_t, size_t>> groups;  // [first, last) of tasks of one light and path
    for (size_t i = 0; i < probed.size(); ++i)
        if (groups.empty() || probed[i].light != probed[groups.back().first].light ||
            probed[i].path != probed[groups.back().first].path)
            groups.push_back({i, i + 1});
        else
            groups.back().second = i + 1;
    std::vector<Status> probe_status(probed.size(), Ok{});
    tbb::parallel_for(size_t{0}, groups.size(), [&](size_t g) {
        const auto [first, last] = groups[g];
        const Light& light = *probed[first].light;
        optics::RayGridOptions aim;
        aim.tracer = options.grid_tracer;
        auto green =
            optics::traceRayGrid(lens, *probed[first].path, degToRad(light.theta_deg),
                                 degToRad(light.phi_deg), kLambdaGreen_nm, options.probe_grid, aim);
        if (!green) {
            probe_status[first] = green.error();
            return;
        }
        for (size_t i = first; i < last; ++i) probe_status[i] = probeTask(probed[i], *green);
    });
    for (const Status& status : probe_status)
        if (!status) return status.error();
    for (const Task& t : probed) st.channels_aimed_again += t.aimed_again;
    for (const Task& t : probed) st.grids_windowed += t.windowed;
    // Culling: the faintest first, while their shares together stay within the budget.
    double total_share = 0.0;
    for (const Task& t : probed) total_share += t.lit ? t.l2_share : 0.0;
    std::vector<size_t> faintest;
    for (size_t i = 0; i < probed.size(); ++i)
        if (probed[i].lit) faintest.push_back(i);
    std::sort(faintest.begin(), faintest.end(),
              [&](size_t a, size_t b) { return probed[a].l2_share < probed[b].l2_share; });
    const double budget = options.cull_relative_l2 * options.cull_relative_l2 * total_share;
    double dropped = 0.0;
    std::vector<bool> culled(probed.size(), false);
    for (const size_t i : faintest) {
        if (dropped + probed[i].l2_share > budget) break;
        dropped += probed[i].l2_share;
        culled[i] = true;
    }
    std::vector<Task> tasks;
    double culled_share = 0.0;
    for (size_t i = 0; i < probed.size(); ++i) {
        const Task& t = probed[i];
        if (!t.lit) {
            st.ghosts_off_image += t.n > 0 ? 1 : 0;
            continue;
        }
        const bool faint =
            options.cull_mean_below > 0.0 && t.power / t.area_px < options.cull_mean_below;
        if (culled[i] || faint) {
            ++st.ghosts_culled;
            culled_share += t.l2_share;
            continue;
        }
        tasks.push_back(t);
    }
    st.culled_relative_l2 = total_share > 0.0 ? std::sqrt(culled_share / total_share) : 0.0;
    const auto count = [&](const Traced& t) {
        ++st.ghosts_drawn;
        st.quads += t.quad_count;
        st.rays += t.rays;
    };
    if (options.tiled) {
        // Tasks in blocks, each block traced in parallel and its primitives appended in task
        // order; a block is a few tasks per core, so memory stays bounded. Within a block the
        // largest grids start first and each thread takes the next task as it finishes one
        // (longest-first list scheduling), so a large grid does not run alone at the end.
        const int threads = std::max(1, tbb::this_task_arena::max_concurrency());
        const size_t block = 8 * static_cast<size_t>(threads);
        std::vector<Traced> traced;
        std::vector<PrimitiveArray> prepared;
        std::vector<size_t> order;
        for (size_t first = 0; first < tasks.size(); first += block) {
            const size_t last = std::min(tasks.size(), first + block);
            traced.assign(last - first, Traced{});
            prepared.assign(last - first, {});
            order.resize(last - first);
            for (size_t i = 0; i < order.size(); ++i) order[i] = i;
            std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
                return tasks[first + a].n > tasks[first + b].n;
            });
            std::atomic<size_t> next{0};
            const auto traceBlockTask = [&](size_t i) {
                const Task& task = tasks[first + i];
                traced[i] = traceTask(task);
                const GhostQuads& quads = traced[i].quads;
                prepared[i].reserve(quads.quads.size());
                for (size_t q = 0; q < quads.quads.size(); ++q)
                    if (auto p = preparePrimitive(quads.quads[q], quads.cellArea(q), task.channel,
                                                  task.light->rgb[task.channel], options.width,
                                                  options.height, options.raster))
                        prepared[i].push_back(*p);
                // Kept until drawn: no room for the quads that made no primitive (off the image,
                // outside the stop), so the pending primitives bound the memory.
                if (prepared[i].capacity() > 2 * prepared[i].size() + 1024)
                    prepared[i].shrink_to_fit();
                traced[i].quads = GhostQuads{};  // the primitives hold what is needed now
            };
            tbb::parallel_for(0, threads, [&](int) {
                for (size_t k = next++; k < order.size(); k = next++) traceBlockTask(order[k]);
            });
            for (size_t i = 0; i < traced.size(); ++i) {
                if (!traced[i].status) return traced[i].status.error();
                if (traced[i].quad_count == 0) continue;
                count(traced[i]);
                pending_count += prepared[i].size();
                pending.push_back(std::move(prepared[i]));
                if (pending_count >= static_cast<size_t>(options.max_pending_primitives)) {
                    if (Status drawn = flush(); !drawn) return drawn.error();
                }
            }
        }
        if (pending_count > 0) {
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
