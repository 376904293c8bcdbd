#include "drivers/path_seeds.h"

#include <tbb/parallel_for.h>

#include <cmath>
#include <memory>
#include <string>

#include "optics/ghosts.h"
#include "optics/ray_grid.h"
#include "render/ghost_shape.h"

namespace flarelab::drivers {
namespace {

constexpr double kSeedWavelength_nm = 550.0;
constexpr int kSeedGrid = 48;

}  // namespace

Result<fit::PathSeeder> pathSeeder(const optics::Lens& lens, double min_share) {
    if (!(min_share >= 0.0 && min_share < 1.0))
        return makeError(ErrorCode::InvalidArgument, "path seeds: min_share must lie in [0, 1)");
    auto enumeration = optics::enumerateGhosts(lens);
    if (!enumeration) return enumeration.error().withContext("path seeds");
    auto shared = std::make_shared<const optics::Lens>(lens);
    auto paths = std::make_shared<const std::vector<optics::GhostPath>>(enumeration->ghosts);
    return fit::PathSeeder([shared, paths,
                            min_share](double angle_deg) -> Result<std::vector<fit::PathSeed>> {
        if (!std::isfinite(angle_deg) || std::abs(angle_deg) >= 90.0)
            return makeError(
                ErrorCode::InvalidArgument,
                "path seeds: head angle " + std::to_string(angle_deg) + " deg is not in (-90, 90)");
        optics::LightDirectionDeg light;
        light.theta_deg = std::abs(angle_deg);
        light.phi_deg = angle_deg < 0.0 ? 180.0 : 0.0;
        const double theta = light.theta_deg * M_PI / 180.0, phi = light.phi_deg * M_PI / 180.0;
        // Each path's rays through the stop and every clear aperture: their power and the
        // box their sensor positions span (the ghost as vignetting leaves it).
        struct Footprint {
            double power = 0.0;
            Eigen::Vector4d box{1e300, 1e300, -1e300, -1e300};
            int rays = 0;
        };
        // Paths are traced on every core (a zoom has some 200; one grid is a few ms), each into
        // its own footprint, and summed in path order: the seeds do not depend on the threads.
        std::vector<Footprint> feet(paths->size());
        tbb::parallel_for(size_t{0}, paths->size(), [&](size_t k) {
            auto grid = optics::traceRayGrid(*shared, (*paths)[k], theta, phi, kSeedWavelength_nm,
                                             kSeedGrid);
            if (!grid) return;  // a path no ray gets through carries nothing
            Footprint& f = feet[k];
            for (const optics::GridSample& g : grid->samples) {
                if (!g.valid || !shared->aperture().contains(g.stop_u, g.stop_v)) continue;
                f.power += g.throughput;
                f.box[0] = std::min(f.box[0], double{g.sensor_x_mm});
                f.box[1] = std::min(f.box[1], double{g.sensor_y_mm});
                f.box[2] = std::max(f.box[2], double{g.sensor_x_mm});
                f.box[3] = std::max(f.box[3], double{g.sensor_y_mm});
                ++f.rays;
            }
        });
        double total = 0.0;
        for (const Footprint& f : feet) total += f.power;
        std::vector<fit::PathSeed> seeds;
        for (size_t k = 0; k < paths->size(); ++k) {
            const Footprint& f = feet[k];
            if (f.rays < 4 || !(f.power > 0.0) || f.power < min_share * total) continue;
            const Eigen::Vector4d& e = f.box;  // min x, min y, max x, max y
            if (!e.allFinite() || !(e[2] > e[0]) || !(e[3] > e[1])) continue;
            fit::PathSeed seed;
            seed.path = static_cast<int64_t>(k);
            const double cx = 0.5 * (e[0] + e[2]), cy = 0.5 * (e[1] + e[3]);
            // The ellipse through the extent: each handle the circle's fraction of the
            // semi-axis it runs along.
            auto& s = seed.shape;
            s.centre_x_mm = cx;
            s.centre_y_mm = cy;
            s.left_mm = cx - e[0];
            s.right_mm = e[2] - cx;
            s.half_height_mm = 0.5 * (e[3] - e[1]);
            s.left_handle_x_mm = render::kCircleHandle * s.left_mm;
            s.left_handle_y_mm = render::kCircleHandle * s.half_height_mm;
            s.right_handle_x_mm = render::kCircleHandle * s.right_mm;
            s.right_handle_y_mm = render::kCircleHandle * s.half_height_mm;
            seeds.push_back(seed);
        }
        return seeds;
    });
}

}  // namespace flarelab::drivers
