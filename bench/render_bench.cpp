#include "bench/render_bench.h"

#include <tbb/global_control.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iomanip>
#include <limits>
#include <ostream>
#include <sstream>

#include "optics/lens.h"
#include "optics/prescription.h"
#include "render/metrics.h"
#include "render/scene.h"

namespace flarelab::bench {
namespace {

using Clock = std::chrono::steady_clock;
using render::MergeOptions;

const char* const kPaperLenses[] = {"heliar-tronnier.csv", "itoh-wide-zoom.csv",
                                    "nikon-tele-zoom.csv", "canon-tele-zoom-135.csv",
                                    "canon-tele-zoom-200.csv"};

struct NamedMerge {
    const char* name;
    MergeOptions merge;
};
const NamedMerge kMerges[] = {
    {"none", render::kNoMerge}, {"light", render::kLightMerge}, {"heavy", render::kHeavyMerge}};

// k white lights spread over angle and roll, the first the paper-like single light.
std::vector<render::Light> lightsFor(int count) {
    std::vector<render::Light> lights;
    for (int k = 0; k < count; ++k)
        lights.push_back(
            {5.0 + 7.0 * (k % 4) + 1.5 * (k / 4), 30.0 + 137.5 * k, {1.0f, 1.0f, 1.0f}});
    return lights;
}

struct Run {
    ImageRGB image;
    render::SceneStats stats;
    double total_ms = std::numeric_limits<double>::infinity();
};

// The best of `repeat` renderings (the image of the last; they are all the same).
Result<Run> timed(const optics::Lens& lens,
                  const std::vector<render::Light>& lights,
                  const render::SceneOptions& options,
                  int repeat) {
    Run best;
    for (int r = 0; r < std::max(1, repeat); ++r) {
        render::SceneStats stats;
        const auto start = Clock::now();
        auto image = render::renderScene(lens, lights, options, &stats);
        const double ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
        if (!image) return image.error();
        if (ms < best.total_ms) {
            best.total_ms = ms;
            best.stats = stats;
        }
        best.image = std::move(*image);
    }
    return best;
}

double psnrOr(const ImageRGB& test, const ImageRGB& reference) {
    const auto value = render::psnr(test, reference);
    return value ? *value : std::nan("");
}

// JSON has no infinity: identical images are written as null and printed as "inf".
nlohmann::json finiteOrNull(double v) { return std::isfinite(v) ? nlohmann::json(v) : nullptr; }

std::string fixed(double v, int digits = 1) {
    if (std::isinf(v)) return "inf";
    if (std::isnan(v)) return "n/a";
    std::ostringstream s;
    s << std::fixed << std::setprecision(digits) << v;
    return s.str();
}

double mebibytes(int64_t bytes) { return static_cast<double>(bytes) / (1024.0 * 1024.0); }

render::SceneOptions baseOptions(const RenderBenchOptions& o) {
    render::SceneOptions s;
    s.width = o.width;
    s.height = o.height;
    s.base_grid = o.base_grid;
    s.max_grid = o.max_grid;
    s.starburst = false;
    return s;
}

// The image every figure is measured against: every ghost (no culling), traced ray by ray in
// double, on the full eq. 13 grids (no cap).
render::SceneOptions truthOptions(render::SceneOptions s) {
    s.cull_relative_l2 = 0.0;
    s.max_grid = 0;
    s.grid_tracer = optics::GridTracer::Exact;
    s.image_window = false;
    return s;
}

// The lens, culling and interior-edge tables' truth: at the truth's own base grid.
render::SceneOptions truthAt(const RenderBenchOptions& o) {
    render::SceneOptions s = truthOptions(baseOptions(o));
    s.base_grid = o.truth_grid > 0 ? o.truth_grid : o.base_grid;
    return s;
}

}  // namespace

Result<nlohmann::json> runRenderBench(const RenderBenchOptions& input,
                                      std::ostream& out,
                                      std::ostream& log) {
    RenderBenchOptions o = input;
    if (o.quick) {
        o.width = std::min<int64_t>(o.width, 640);
        o.height = std::min<int64_t>(o.height, 360);
        o.base_grid = std::min(o.base_grid, 64);
        if (o.truth_grid > 0) o.truth_grid = std::min(o.truth_grid, 64);
        o.repeat = 1;
        o.trade = false;
        o.scaling = false;
        if (o.lens_files.empty())
            o.lens_files = {o.lens_dir + "/heliar-tronnier.csv",
                            o.lens_dir + "/itoh-wide-zoom.csv"};
    }
    if (o.lens_files.empty())
        for (const char* name : kPaperLenses) o.lens_files.push_back(o.lens_dir + "/" + name);
    if (o.light_counts.empty())
        return makeError(ErrorCode::InvalidArgument, "bench: no light count");
    for (const int n : o.light_counts)
        if (n < 1 || n > 64)
            return makeError(ErrorCode::InvalidArgument, "bench: --lights must lie in 1..64");
    if (o.repeat < 1 || o.repeat > 100)
        return makeError(ErrorCode::InvalidArgument, "bench: --repeat must lie in 1..100");
    if (o.truth_samples < 0 || o.truth_samples > 64)
        return makeError(ErrorCode::InvalidArgument, "bench: --truth-samples must lie in 0..64");
    if (o.max_grid != 0 && (o.max_grid < 2 || o.max_grid > 2048))
        return makeError(ErrorCode::InvalidArgument,
                         "bench: --max-grid must be 0 (no cap) or lie in 2..2048");
    if (o.truth_grid != 0 && (o.truth_grid < 2 || o.truth_grid > 2048))
        return makeError(ErrorCode::InvalidArgument,
                         "bench: --truth-grid must be 0 (--grid's) or lie in 2..2048");

    std::vector<optics::Lens> lenses;
    for (const std::string& file : o.lens_files) {
        auto prescription = optics::loadPrescription(file);
        if (!prescription) return prescription.error();
        auto lens = optics::Lens::make(*prescription, optics::CameraDescription{});
        if (!lens) return lens.error();
        lenses.push_back(std::move(*lens));
    }

    nlohmann::json doc;
    doc["settings"] = {{"width", o.width},
                       {"height", o.height},
                       {"base_grid", o.base_grid},
                       {"max_grid", o.max_grid},
                       {"truth_grid", o.truth_grid},
                       {"repeat", o.repeat},
                       {"threads", tbb::global_control::active_value(
                                       tbb::global_control::max_allowed_parallelism)},
                       {"quick", o.quick},
                       {"starburst", false},
                       {"tiles", "8 px dense, 128 px coarse"}};
    doc["lenses"] = nlohmann::json::array();
    doc["merge"] = nlohmann::json::array();
    doc["tiles"] = nlohmann::json::array();

    // Tables 2 and 3: the tiled pipeline (light merge) against the reference.
    if (o.lenses)
        out << "## Tiled renderer against the reference rasterizer (" << o.width << "x" << o.height
            << ", base grid " << o.base_grid << ", smooth grids at most " << o.max_grid
            << " a side, truth's base " << (o.truth_grid > 0 ? o.truth_grid : o.base_grid)
            << ", best of " << o.repeat << ")\n\n"
            << "Tiled: light merge, tracing and drawing on every core. Reference: no merge, one "
               "ghost "
               "after another on one thread. PSNR of the tiled image against the reference.\n\n"
            << "| lens | lights | tiled trace ms | tile build ms | traversal ms | tiled total ms | "
               "tiled 1-thread ms | reference trace ms | reference draw ms | reference total ms | "
               "speed-up | draw speed-up | PSNR dB |\n"
            << "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    std::ostringstream merge_md, tiles_md;
    merge_md
        << "| lens | lights | merge | primitives | primitive MiB | dense entries | index MiB | "
           "total ms | PSNR dB |\n|---|---|---|---|---|---|---|---|---|\n";
    tiles_md << "| lens | dense 8, no coarse ms | dense 8, coarse 128 ms | dense 16, no coarse ms "
                "| dense 16, coarse 128 ms |\n|---|---|---|---|---|\n";
    for (size_t li = 0; li < lenses.size() && o.lenses; ++li) {
        const optics::Lens& lens = lenses[li];
        const std::string name = std::filesystem::path(o.lens_files[li]).stem().string();
        for (const int count : o.light_counts) {
            const auto lights = lightsFor(count);
            log << "bench render: " << name << ", " << count << " light(s): reference\n";
            render::SceneOptions ref_options = truthAt(o);
            ref_options.tiled = false;
            auto reference = timed(lens, lights, ref_options, o.repeat);
            if (!reference) return reference.error();
            // Tables 5-7: every merge level, tiled.
            nlohmann::json main_row;
            for (const NamedMerge& m : kMerges) {
                log << "bench render: " << name << ", " << count << " light(s): tiled, merge "
                    << m.name << "\n";
                render::SceneOptions options = baseOptions(o);
                options.merge = m.merge;
                auto tiled = timed(lens, lights, options, o.repeat);
                if (!tiled) return tiled.error();
                const double p = psnrOr(tiled->image, reference->image);
                const auto& t = tiled->stats.tiles;
                const int64_t primitive_bytes = t.primitives * sizeof(render::Primitive);
                // The tile lists hold 4-byte indices (the paper's Table 6 counts them so).
                const int64_t index_bytes =
                    (t.dense_entries + t.coarse_entries) * static_cast<int64_t>(sizeof(uint32_t));
                doc["merge"].push_back({{"name", name},
                                        {"lights", count},
                                        {"merge", m.name},
                                        {"primitives", t.primitives},
                                        {"primitive_bytes", primitive_bytes},
                                        {"dense_entries", t.dense_entries},
                                        {"coarse_entries", t.coarse_entries},
                                        {"index_bytes", index_bytes},
                                        {"total_ms", tiled->total_ms},
                                        {"psnr_db", finiteOrNull(p)}});
                merge_md << "| " << name << " | " << count << " | " << m.name << " | "
                         << t.primitives << " | " << fixed(mebibytes(primitive_bytes), 2) << " | "
                         << t.dense_entries << " | " << fixed(mebibytes(index_bytes), 2) << " | "
                         << fixed(tiled->total_ms) << " | " << fixed(p) << " |\n";
                if (std::string(m.name) != "light") continue;
                double one_thread_ms = std::nan("");
                if (!o.quick && count == o.light_counts.front()) {
                    log << "bench render: " << name << ", " << count
                        << " light(s): tiled on one thread\n";
                    tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
                    auto single = timed(lens, lights, options, o.repeat);
                    if (!single) return single.error();
                    one_thread_ms = single->total_ms;
                }
                const auto& rs = reference->stats;
                const double speedup = reference->total_ms / tiled->total_ms;
                const double draw_speedup = rs.draw_ms / (t.build_ms + t.traverse_ms);
                main_row = {{"name", name},
                            {"lens", lens.name()},
                            {"lights", count},
                            {"tiled_ms", tiled->total_ms},
                            {"tiled_trace_ms", tiled->stats.trace_ms},
                            {"tile_build_ms", t.build_ms},
                            {"traversal_ms", t.traverse_ms},
                            {"tiled_one_thread_ms", finiteOrNull(one_thread_ms)},
                            {"reference_ms", reference->total_ms},
                            {"reference_trace_ms", rs.trace_ms},
                            {"reference_draw_ms", rs.draw_ms},
                            {"speedup", speedup},
                            {"draw_speedup", draw_speedup},
                            {"psnr_db", finiteOrNull(p)},
                            {"ghost_grids", tiled->stats.ghosts_drawn},
                            {"rays", tiled->stats.rays}};
                if (o.truth_samples > 0) {
                    log << "bench render: " << name << ", " << count
                        << " light(s): " << o.truth_samples << " x " << o.truth_samples
                        << " samples per pixel\n";
                    render::SceneOptions truth_options = options;
                    truth_options.raster.supersample = o.truth_samples;
                    auto truth = timed(lens, lights, truth_options, 1);
                    if (!truth) return truth.error();
                    main_row["truth_psnr_db"] = finiteOrNull(psnrOr(tiled->image, truth->image));
                    main_row["truth_ms"] = truth->total_ms;
                    log << "bench render: " << name << ": "
                        << fixed(psnrOr(tiled->image, truth->image)) << " dB against "
                        << o.truth_samples << " x " << o.truth_samples << " samples\n";
                }
                out << "| " << name << " | " << count << " | " << fixed(tiled->stats.trace_ms)
                    << " | " << fixed(t.build_ms) << " | " << fixed(t.traverse_ms) << " | "
                    << fixed(tiled->total_ms) << " | " << fixed(one_thread_ms) << " | "
                    << fixed(rs.trace_ms) << " | " << fixed(rs.draw_ms) << " | "
                    << fixed(reference->total_ms) << " | " << fixed(speedup, 2) << " | "
                    << fixed(draw_speedup, 2) << " | " << fixed(p) << " |\n";
                out.flush();
            }
            doc["lenses"].push_back(main_row);
            // Table 4: tile sizes, with and without the coarse level (one light, light merge).
            if (count != o.light_counts.front() || o.quick) continue;
            nlohmann::json row = {{"name", name}};
            tiles_md << "| " << name;
            for (const int dense : {8, 16})
                for (const bool coarse : {false, true}) {
                    render::SceneOptions options = baseOptions(o);
                    options.merge = render::kLightMerge;
                    options.tiles.dense_tile_px = dense;
                    options.tiles.coarse_level = coarse;
                    auto run = timed(lens, lights, options, o.repeat);
                    if (!run) return run.error();
                    const double ms = run->stats.tiles.build_ms + run->stats.tiles.traverse_ms;
                    row["dense" + std::to_string(dense) + (coarse ? "_coarse" : "_flat") + "_ms"] =
                        ms;
                    tiles_md << " | " << fixed(ms);
                }
            tiles_md << " |\n";
            doc["tiles"].push_back(row);
        }
    }
    if (o.lenses)
        out << "\n## Primitives, memory and quality by merge level (Tables 5-7)\n\n"
            << "PSNR against the reference rasterizer without merge. Primitive memory: all "
               "primitives at "
            << sizeof(render::Primitive)
            << " bytes each (the renderer holds at most SceneOptions::max_pending_primitives at "
               "once); index memory: the coarse and dense tile lists at 4 bytes an entry.\n\n"
            << merge_md.str();
    if (o.lenses && !o.quick)
        out << "\n## Tile sizes with and without the coarse level (Table 4; tile building + "
               "traversal, light merge, "
            << o.light_counts.front() << " light(s))\n\n"
            << tiles_md.str();

    // Ghost culling per lens: how many ghost grids each budget drops, the time, and the PSNR
    // against the truth (tiled, light merge, one light).
    doc["cull"] = nlohmann::json::array();
    if (o.cull && !o.quick) {
        out << "\n## Ghost culling (" << o.width << "x" << o.height
            << ", 1 light, light merge; PSNR against every ghost, exact tracer, no merge)\n\n"
            << "| lens | cull_relative_l2 | ghost grids drawn | culled | estimated dropped L2 | "
               "total ms | PSNR dB |\n|---|---|---|---|---|---|---|\n";
        for (size_t li = 0; li < lenses.size(); ++li) {
            const std::string name = std::filesystem::path(o.lens_files[li]).stem().string();
            const auto lights = lightsFor(1);
            render::SceneOptions truth_options = truthAt(o);
            log << "bench render: cull: " << name << ", the truth\n";
            auto truth = timed(lenses[li], lights, truth_options, 1);
            if (!truth) return truth.error();
            for (const double cull : {0.0, 1e-4, 1e-3, 1e-2}) {
                log << "bench render: cull: " << name << ", " << cull << "\n";
                render::SceneOptions options = baseOptions(o);
                options.merge = render::kLightMerge;
                options.cull_relative_l2 = cull;
                auto run = timed(lenses[li], lights, options, o.repeat);
                if (!run) return run.error();
                const double p = psnrOr(run->image, truth->image);
                doc["cull"].push_back({{"name", name},
                                       {"cull_relative_l2", cull},
                                       {"ghost_grids", run->stats.ghosts_drawn},
                                       {"culled", run->stats.ghosts_culled},
                                       {"estimated_dropped_l2", run->stats.culled_relative_l2},
                                       {"total_ms", run->total_ms},
                                       {"psnr_db", finiteOrNull(p)}});
                out << "| " << name << " | " << cull << " | " << run->stats.ghosts_drawn << " | "
                    << run->stats.ghosts_culled << " | " << fixed(run->stats.culled_relative_l2, 5)
                    << " | " << fixed(run->total_ms) << " | " << fixed(p) << " |\n";
                out.flush();
            }
        }
    }

    // Interior edges drawn by pixel centre (MergeOptions::centre_edge_jump) per lens: the time
    // and the PSNR against the truth for each largest density jump (tiled, light merge, one
    // light, no culling, so that the edges alone change).
    doc["centre_edges"] = nlohmann::json::array();
    if (o.centre_edges && !o.quick) {
        out << "\n## Interior edges by pixel centre (" << o.width << "x" << o.height
            << ", 1 light, light merge, no culling; PSNR against every ghost, exact tracer, no "
               "merge)\n\n"
            << "| lens | centre_edge_jump | total ms | draw ms | PSNR dB "
               "|\n|---|---|---|---|---|\n";
        for (size_t li = 0; li < lenses.size(); ++li) {
            const std::string name = std::filesystem::path(o.lens_files[li]).stem().string();
            const auto lights = lightsFor(1);
            log << "bench render: centre edges: " << name << ", the truth\n";
            auto truth = timed(lenses[li], lights, truthAt(o), 1);
            if (!truth) return truth.error();
            for (const double jump : {0.0, 0.003, 0.01, 0.03, 0.1}) {
                log << "bench render: centre edges: " << name << ", " << jump << "\n";
                render::SceneOptions options = baseOptions(o);
                options.merge = render::kLightMerge;
                options.merge.centre_edge_jump = jump;
                options.cull_relative_l2 = 0.0;
                auto run = timed(lenses[li], lights, options, o.repeat);
                if (!run) return run.error();
                const double p = psnrOr(run->image, truth->image);
                doc["centre_edges"].push_back({{"name", name},
                                               {"centre_edge_jump", jump},
                                               {"total_ms", run->total_ms},
                                               {"draw_ms", run->stats.draw_ms},
                                               {"psnr_db", finiteOrNull(p)}});
                out << "| " << name << " | " << jump << " | " << fixed(run->total_ms) << " | "
                    << fixed(run->stats.draw_ms) << " | " << fixed(p) << " |\n";
                out.flush();
            }
        }
    }

    // The speed/accuracy trade, against a dense grid.
    const size_t trade_lens = [&] {
        for (size_t i = 0; i < o.lens_files.size(); ++i)
            if (o.lens_files[i].find("nikon-tele") != std::string::npos) return i;
        return size_t{0};
    }();
    doc["trade"] = nlohmann::json::array();
    if (o.trade) {
        const optics::Lens& lens = lenses[trade_lens];
        const auto lights = lightsFor(1);
        render::SceneOptions dense = truthOptions(baseOptions(o));
        dense.width = o.width / 2;
        dense.height = o.height / 2;
        dense.base_grid = 1024;
        // No splats in the truth: every quad is sampled at pixel centres, as the renderer samples
        // every quad above 1 px^2, so the table measures the grid and the merge, not the
        // difference between point sampling and area integration (see the README).
        dense.raster.min_quad_area_px = 0.0;
        log << "bench render: trade: the dense-grid reference (grid 1024)\n";
        auto truth = timed(lens, lights, dense, 1);
        if (!truth) return truth.error();
        out << "\n## Speed against accuracy: base grid and merge ("
            << std::filesystem::path(o.lens_files[trade_lens]).stem().string() << ", "
            << dense.width << "x" << dense.height
            << ", tiled; PSNR against base grid 1024 without merge, every quad point-sampled)\n\n"
            << "| base grid | merge | primitives | total ms | PSNR dB |\n|---|---|---|---|---|\n";
        for (const int grid : {16, 32, 64, 128, 256, 512})
            for (const NamedMerge& m : kMerges) {
                log << "bench render: trade: grid " << grid << ", merge " << m.name << "\n";
                render::SceneOptions options = dense;
                options.base_grid = grid;
                options.merge = m.merge;
                options.grid_tracer = optics::GridTracer::Auto;  // no culling: grid and merge alone
                auto run = timed(lens, lights, options, o.repeat);
                if (!run) return run.error();
                const double p = psnrOr(run->image, truth->image);
                doc["trade"].push_back({{"grid", grid},
                                        {"merge", m.name},
                                        {"primitives", run->stats.tiles.primitives},
                                        {"total_ms", run->total_ms},
                                        {"psnr_db", finiteOrNull(p)}});
                out << "| " << grid << " | " << m.name << " | " << run->stats.tiles.primitives
                    << " | " << fixed(run->total_ms) << " | " << fixed(p) << " |\n";
                out.flush();
            }
    }

    // Cost against lights and image size.
    doc["lights_scaling"] = nlohmann::json::array();
    doc["size_scaling"] = nlohmann::json::array();
    if (o.scaling) {
        const optics::Lens& lens = lenses[trade_lens];
        out << "\n## Cost against the number of lights (" << o.width << "x" << o.height
            << ", light merge)\n\n| lights | tiled ms | reference ms | speed-up "
               "|\n|---|---|---|---|\n";
        for (const int count : {1, 2, 4, 8}) {
            log << "bench render: scaling: " << count << " light(s)\n";
            render::SceneOptions options = baseOptions(o);
            options.merge = render::kLightMerge;
            auto tiled = timed(lens, lightsFor(count), options, o.repeat);
            if (!tiled) return tiled.error();
            options = truthOptions(options);
            options.tiled = false;
            options.merge = render::kNoMerge;
            auto reference = timed(lens, lightsFor(count), options, o.repeat);
            if (!reference) return reference.error();
            doc["lights_scaling"].push_back({{"lights", count},
                                             {"tiled_ms", tiled->total_ms},
                                             {"reference_ms", reference->total_ms}});
            out << "| " << count << " | " << fixed(tiled->total_ms) << " | "
                << fixed(reference->total_ms) << " | "
                << fixed(reference->total_ms / tiled->total_ms, 2) << " |\n";
            out.flush();
        }
        out << "\n## Cost against the image size (1 light, light merge)\n\n"
            << "| image | tiled ms | tile build + traversal ms | reference ms | speed-up |\n"
            << "|---|---|---|---|---|\n";
        for (const auto& [w, h] : std::vector<std::pair<int64_t, int64_t>>{
                 {854, 480}, {1280, 720}, {1920, 1080}, {2560, 1440}, {3840, 2160}}) {
            log << "bench render: scaling: " << w << "x" << h << "\n";
            render::SceneOptions options = baseOptions(o);
            options.width = w;
            options.height = h;
            options.merge = render::kLightMerge;
            auto tiled = timed(lens, lightsFor(1), options, o.repeat);
            if (!tiled) return tiled.error();
            options = truthOptions(options);
            options.tiled = false;
            options.merge = render::kNoMerge;
            auto reference = timed(lens, lightsFor(1), options, o.repeat);
            if (!reference) return reference.error();
            const double draw = tiled->stats.tiles.build_ms + tiled->stats.tiles.traverse_ms;
            doc["size_scaling"].push_back({{"width", w},
                                           {"height", h},
                                           {"tiled_ms", tiled->total_ms},
                                           {"tiled_draw_ms", draw},
                                           {"reference_ms", reference->total_ms}});
            out << "| " << w << "x" << h << " | " << fixed(tiled->total_ms) << " | " << fixed(draw)
                << " | " << fixed(reference->total_ms) << " | "
                << fixed(reference->total_ms / tiled->total_ms, 2) << " |\n";
            out.flush();
        }
    }
    return doc;
}

}  // namespace flarelab::bench
