#include "drivers/sim_truth.h"

#include <cmath>
#include <memory>

#include "drivers/sim_camera.h"

namespace flarelab::drivers {

Result<fit::TruthSource> simulatedGhostTruth(const optics::Lens& lens,
                                             int64_t width,
                                             int64_t height,
                                             const std::vector<optics::GhostPath>& only_paths,
                                             bool colour) {
    SimCameraOptions options;
    if (colour) options.format = hdr::RawFormat::BayerRGGB;  // all three channels traced
    options.render.only_paths = only_paths;
    options.width_px = width;
    options.height_px = height;
    options.render.starburst = false;  // the ghosts alone
    options.background_e_s = 0.0;
    options.cache_angles = 1;
    auto made = SimCamera::make(lens, options);
    if (!made) return made.error().withContext("ground truth");
    std::shared_ptr<SimCamera> camera(std::move(*made));
    const double to_dn = 1.0 / options.electrons_per_dn;
    return fit::TruthSource(
        [camera, lens, width, height, to_dn, colour](double angle_deg) -> Result<fit::TruthFrame> {
            fit::TruthFrame t;
            if (colour) {
                auto rgb = camera->meanRateRgb_e_s(angle_deg);
                if (!rgb) return rgb.error();
                t.image = std::move(*rgb);
                for (float& v : t.image.pixels) v = static_cast<float>(v * to_dn);
            } else {
                auto rate = camera->meanRate_e_s(angle_deg);
                if (!rate) return rate.error();
                t.image = ImageRGB(width, height);
                for (size_t i = 0; i < rate->size(); ++i)
                    for (int c = 0; c < 3; ++c)
                        t.image.pixels[3 * i + static_cast<size_t>(c)] =
                            static_cast<float>((*rate)[i] * to_dn);
            }
            render::Light light;
            light.theta_deg = std::abs(angle_deg);
            light.phi_deg = angle_deg < 0.0 ? 180.0 : 0.0;
            const SimLightSpot spot = simLightSpot(lens, light);
            if (spot.placed) {
                const auto m = render::sensorToImage(lens.camera(), width, height);
                t.light_px = m.toPixels(spot.centre_mm.x(), spot.centre_mm.y());
            }
            return t;
        });
}

}  // namespace flarelab::drivers
