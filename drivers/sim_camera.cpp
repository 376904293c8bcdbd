#include "drivers/sim_camera.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>
#include <sstream>

#include "common/check.h"
#include "common/units.h"
#include "optics/aim.h"
#include "optics/paraxial.h"
#include "optics/prescription.h"
#include "optics/ray_grid.h"
#include "optics/tracer.h"
#include "render/ghost_quads.h"

namespace flarelab::drivers {
namespace {

std::string fmt(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

bool finite(double x) { return std::isfinite(x); }

Error badOption(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "sim camera options: " + what);
}

// SplitMix64 (Steele, Lea & Flood 2014): decorrelates the seeds of neighbouring rows and frames.
uint64_t mix(uint64_t x) {
    x += 0x9e3779b97f4a7c15ull;
    x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
    x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
    return x ^ (x >> 31);
}

// A uniform double in [0, 1) from the top 53 bits.
double uniform(std::mt19937_64& rng) { return static_cast<double>(rng() >> 11) * 0x1.0p-53; }

// Poisson(mean) electrons. Below 10: Knuth's product of uniforms; up to 1e7: the transformed
// rejection PTRS of Hoermann, "The transformed rejection method for generating Poisson random
// variables" (1993), with constants as in his paper; the setup costs a square root and two
// logarithms, so it may change per pixel. Beyond 1e7 (pixels far past white) the normal
// approximation, exact in mean and variance.
double shotNoise(double mean, std::mt19937_64& rng, std::normal_distribution<double>& normal) {
    if (!(mean > 0.0)) return 0.0;
    if (mean < 10.0) {
        const double limit = std::exp(-mean);
        double product = uniform(rng);
        int64_t k = 0;
        while (product > limit) {
            product *= uniform(rng);
            ++k;
        }
        return static_cast<double>(k);
    }
    if (mean >= 1e7) return std::max(0.0, std::round(mean + std::sqrt(mean) * normal(rng)));
    const double log_mean = std::log(mean);
    const double b = 0.931 + 2.53 * std::sqrt(mean);
    const double a = -0.059 + 0.02483 * b;
    const double inv_alpha = 1.1239 + 1.1328 / (b - 3.4);
    const double v_r = 0.9277 - 3.6224 / (b - 2.0);
    for (;;) {
        const double u = uniform(rng) - 0.5;
        const double v = uniform(rng);
        const double us = 0.5 - std::abs(u);
        const double k = std::floor((2.0 * a / us + b) * u + mean + 0.43);
        if (us >= 0.07 && v <= v_r) return k;
        if (k < 0.0 || (us < 0.013 && v > us)) continue;
        if (std::log(v) + std::log(inv_alpha) - std::log(a / (us * us) + b) <=
            -mean + k * log_mean - std::lgamma(k + 1.0))
            return k;
    }
}

// Which colour channel a pixel of a format sees; -1: mono.
int bayerChannel(hdr::RawFormat format, int64_t x, int64_t y) {
    if (format != hdr::RawFormat::BayerRGGB) return -1;
    const bool odd_x = x & 1, odd_y = y & 1;
    if (!odd_x && !odd_y) return 0;
    if (odd_x && odd_y) return 2;
    return 1;
}

constexpr double kChannel_nm[3] = {kLambdaRed_nm, kLambdaGreen_nm, kLambdaBlue_nm};
// Rays per side of the grid that measures the power of the light's own image.
constexpr int kLightGrid = 32;

}  // namespace

SimLightSpot simLightSpot(const optics::Lens& lens, const render::Light& light) {
    SimLightSpot spot;
    const double theta = degToRad(light.theta_deg), phi = degToRad(light.phi_deg);
    const optics::GhostPath imaging{};
    for (int c = 0; c < 3; ++c) {
        if (light.rgb[c] <= 0.0f && c != 1) continue;
        const auto grid =
            optics::traceRayGrid(lens, imaging, theta, phi, kChannel_nm[c], kLightGrid);
        if (!grid || grid->n < 2) continue;
        spot.power[c] = light.rgb[c] * render::imagingPower(*grid, lens.aperture());
        if (c != 1) continue;
        const Eigen::Vector3d direction = optics::lightDirection(theta, phi);
        const optics::EntryPlane plane = optics::defaultEntryPlane(lens);
        const optics::TraceOptions aim_options{
            .clip_apertures = false, .clip_stop = false, .fresnel = false};
        const auto entry =
            optics::aimAtStop(optics::PathTracer(lens, imaging, kLambdaGreen_nm, aim_options),
                              plane, direction, Eigen::Vector2d::Zero(), grid->entry_centre_mm);
        if (!entry) continue;
        const auto traced =
            optics::PathTracer(lens, imaging, kLambdaGreen_nm)
                .trace(optics::rayThroughEntry(plane, *entry, direction, kLambdaGreen_nm));
        if (!traced) continue;
        spot.centre_mm = traced->ray.position.head<2>();
        spot.placed = spot.centre_mm.allFinite();
    }
    return spot;
}

namespace {

// Adds the starburst pattern (each channel summing to 1) times power at (cx, cy) in image space,
// one pattern pixel spanning (sx, sy) image pixels, by splatting every pattern sample bilinearly
// onto the four pixel centres around it. Unlike sampling the pattern at pixel centres
// (render::addStarburst), this keeps the energy when a pattern pixel is much smaller than an
// image pixel.
void splatStarburst(ImageRGB& image,
                    const ImageRGB& pattern,
                    double cx,
                    double cy,
                    double sx,
                    double sy,
                    const std::array<double, 3>& power) {
    const int64_t half_x = pattern.width / 2, half_y = pattern.height / 2;
    for (int64_t j = 0; j < pattern.height; ++j) {
        const double fy = cy + static_cast<double>(j - half_y) * sy - 0.5;
        const double y0 = std::floor(fy);
        if (y0 < -1.0 || y0 >= static_cast<double>(image.height)) continue;
        const double wy = fy - y0;
        for (int64_t i = 0; i < pattern.width; ++i) {
            const double fx = cx + static_cast<double>(i - half_x) * sx - 0.5;
            const double x0 = std::floor(fx);
            if (x0 < -1.0 || x0 >= static_cast<double>(image.width)) continue;
            const double wx = fx - x0;
            const float* v = pattern.at(i, j);
            for (int dy = 0; dy < 2; ++dy) {
                const auto y = static_cast<int64_t>(y0) + dy;
                if (y < 0 || y >= image.height) continue;
                const double w_y = dy ? wy : 1.0 - wy;
                for (int dx = 0; dx < 2; ++dx) {
                    const auto x = static_cast<int64_t>(x0) + dx;
                    if (x < 0 || x >= image.width) continue;
                    const double w = w_y * (dx ? wx : 1.0 - wx);
                    float* out = image.at(x, y);
                    for (int c = 0; c < 3; ++c)
                        if (power[c] > 0.0) out[c] += static_cast<float>(w * power[c] * v[c]);
                }
            }
        }
    }
}

}  // namespace

render::SceneOptions simRenderDefaults() {
    render::SceneOptions o;
    o.base_grid = 64;
    o.probe_grid = 8;
    o.merge = render::kLightMerge;
    o.starburst_options.mask_size = 256;
    o.starburst_options.fft_size = 512;
    return o;
}

Status SimCameraOptions::validate() const {
    if (width_px < 1 || height_px < 1 || width_px > 32768 || height_px > 32768)
        return badOption("width_px and height_px must lie in 1..32768");
    if (format != hdr::RawFormat::Mono && format != hdr::RawFormat::BayerRGGB)
        return badOption("format must be Mono or BayerRGGB");
    if (bit_depth < 8 || bit_depth > 16) return badOption("bit_depth must lie in 8..16");
    const double white = std::ldexp(1.0, bit_depth) - 1.0;
    if (!finite(black_level_dn) || black_level_dn < 0.0 || black_level_dn >= white)
        return badOption("black_level_dn = " + fmt(black_level_dn) + " must lie in [0, " +
                         fmt(white) + ")");
    if (!finite(electrons_per_dn) || !(electrons_per_dn > 0.0))
        return badOption("electrons_per_dn must be positive");
    if (!finite(read_noise_e) || read_noise_e < 0.0) return badOption("read_noise_e must be >= 0");
    if (!finite(dark_current_e_s) || dark_current_e_s < 0.0)
        return badOption("dark_current_e_s must be >= 0");
    if (!(hot_pixel_fraction >= 0.0 && hot_pixel_fraction <= 1.0))
        return badOption("hot_pixel_fraction must lie in [0, 1]");
    if (!finite(hot_pixel_dark_e_s) || hot_pixel_dark_e_s < 0.0)
        return badOption("hot_pixel_dark_e_s must be >= 0");
    if (!finite(quantum_scale) || quantum_scale < 0.0)
        return badOption("quantum_scale must be >= 0");
    for (float c : light_rgb)
        if (!std::isfinite(c) || c < 0.0f) return badOption("light_rgb must be finite and >= 0");
    if (!finite(background_e_s) || background_e_s < 0.0)
        return badOption("background_e_s must be >= 0");
    if (!finite(min_exposure_s) || !finite(max_exposure_s) || !(min_exposure_s > 0.0) ||
        min_exposure_s > max_exposure_s)
        return badOption("0 < min_exposure_s <= max_exposure_s is required");
    if (!finite(min_gain) || !finite(max_gain) || !(min_gain > 0.0) || min_gain > max_gain)
        return badOption("0 < min_gain <= max_gain is required");
    if (!(exposure_s >= min_exposure_s && exposure_s <= max_exposure_s))
        return badOption("exposure_s must lie in [min_exposure_s, max_exposure_s]");
    if (!(gain >= min_gain && gain <= max_gain))
        return badOption("gain must lie in [min_gain, max_gain]");
    if (!finite(readout_s) || readout_s < 0.0) return badOption("readout_s must be >= 0");
    if (!finite(fixed_angle_deg)) return badOption("fixed_angle_deg must be finite");
    if (cache_angles < 1) return badOption("cache_angles must be >= 1");
    if (response != SimResponse::Linear && response != SimResponse::Gamma &&
        response != SimResponse::Log)
        return badOption("response must be Linear, Gamma or Log");
    if (!finite(response_gamma) || !(response_gamma > 0.0))
        return badOption("response_gamma must be positive");
    if (!finite(response_log_range) || !(response_log_range > 0.0))
        return badOption("response_log_range must be positive");
    if (faults.time_out_captures < 0) return badOption("faults.time_out_captures must be >= 0");
    return Ok{};
}

double simResponseCurve(const SimCameraOptions& options, double u) {
    u = std::clamp(u, 0.0, 1.0);
    switch (options.response) {
        case SimResponse::Linear:
            return u;
        case SimResponse::Gamma:
            return std::pow(u, 1.0 / options.response_gamma);
        case SimResponse::Log:
            return std::log1p(options.response_log_range * u) /
                   std::log1p(options.response_log_range);
    }
    return u;
}

double simResponseInverse(const SimCameraOptions& options, double v) {
    v = std::clamp(v, 0.0, 1.0);
    switch (options.response) {
        case SimResponse::Linear:
            return v;
        case SimResponse::Gamma:
            return std::pow(v, options.response_gamma);
        case SimResponse::Log:
            return std::expm1(v * std::log1p(options.response_log_range)) /
                   options.response_log_range;
    }
    return v;
}

SimCamera::SimCamera(Key,
                     optics::Lens lens,
                     const SimCameraOptions& options,
                     AngleSource angles,
                     std::shared_ptr<SimClock> clock,
                     std::optional<LightImage> light_image)
    : lens_(std::move(lens)),
      options_(options),
      angles_(std::move(angles)),
      clock_(std::move(clock)),
      exposure_s_(options.exposure_s),
      gain_(options.gain),
      format_(options.format),
      faults_(options.faults),
      lens_capped_(options.lens_capped),
      light_image_(std::move(light_image)) {
    FLARELAB_CHECK(options.validate().has_value());
    options_.render.width = options_.width_px;
    options_.render.height = options_.height_px;
    options_.render.starburst = false;  // the light's image is drawn here (light_image_)
    // A simulated capture keeps every ghost a camera could record: it drops only those whose mean
    // falls below 1 % of one pixel's noise (background and dark shot noise and read noise) at the
    // longest exposure the camera allows, in image units.
    {
        const optics::CameraDescription& sensor = lens_.camera();
        const double pixel_area_mm2 =
            (sensor.sensor_width_mm / static_cast<double>(options_.width_px)) *
            (sensor.sensor_height_mm / static_cast<double>(options_.height_px));
        const double to_e_s = options_.quantum_scale / pixel_area_mm2;
        const double t = options_.max_exposure_s;
        const double noise_e = std::sqrt((options_.background_e_s + options_.dark_current_e_s) * t +
                                         options_.read_noise_e * options_.read_noise_e);
        options_.render.cull_relative_l2 = 0.0;
        options_.render.cull_mean_below =
            to_e_s > 0.0 && t > 0.0 && std::isfinite(to_e_s) ? 0.01 * noise_e / (t * to_e_s) : 0.0;
    }
    const int64_t n = options_.width_px * options_.height_px;
    const auto hot = static_cast<int64_t>(std::llround(options_.hot_pixel_fraction * n));
    if (hot > 0) {
        hot_e_s_.assign(static_cast<size_t>(n), 0.0f);
        std::mt19937_64 rng(mix(options_.seed ^ 0x486f7450697865ull));  // "HotPixe"
        std::uniform_int_distribution<int64_t> pick(0, n - 1);
        for (int64_t i = 0; i < hot; ++i)
            hot_e_s_[static_cast<size_t>(pick(rng))] =
                static_cast<float>(options_.hot_pixel_dark_e_s);
    }
}

Result<std::unique_ptr<SimCamera>> SimCamera::build(optics::Lens lens,
                                                    const SimCameraOptions& options,
                                                    AngleSource angles,
                                                    std::shared_ptr<SimClock> clock) {
    if (Status ok = options.validate(); !ok) return ok.error();
    render::SceneOptions check = options.render;
    check.width = options.width_px;
    check.height = options.height_px;
    check.starburst = false;  // renderStarburst below checks its options
    // Validate the render options once, on an empty scene, so that bad ones fail here.
    if (auto empty = render::renderScene(lens, {}, check); !empty)
        return empty.error().withContext("sim camera options: render");
    if (!clock) clock = std::make_shared<SimClock>(SimTime::Fast);
    // The starburst does not depend on the angle: render it once.
    std::optional<LightImage> light_image;
    if (options.render.starburst) {
        render::StarburstOptions burst = options.render.starburst_options;
        burst.aperture = lens.aperture();
        auto pattern = render::renderStarburst(burst);
        if (!pattern) return pattern.error().withContext("sim camera options: starburst");
        const auto paraxial = optics::paraxialProperties(lens, kLambdaGreen_nm);
        if (!paraxial || !(paraxial->entrance_pupil_radius_mm > 0.0))
            return makeError(ErrorCode::Unsupported, "sim camera: lens '" + lens.name() +
                                                         "' has no paraxial entrance pupil");
        const double pattern_rad =
            render::starburstPixelAngle(burst, 2.0 * paraxial->entrance_pupil_radius_mm);
        const render::SensorToImage mapping =
            render::sensorToImage(lens.camera(), options.width_px, options.height_px);
        light_image = LightImage{std::move(*pattern),
                                 pattern_rad * mapping.px_per_mm_x * std::abs(paraxial->efl_mm),
                                 pattern_rad * mapping.px_per_mm_y * std::abs(paraxial->efl_mm)};
    }
    return std::make_unique<SimCamera>(Key{}, std::move(lens), options, std::move(angles),
                                       std::move(clock), std::move(light_image));
}

Result<std::unique_ptr<SimCamera>> SimCamera::make(optics::Lens lens,
                                                   const SimCameraOptions& options,
                                                   std::shared_ptr<SimHead> head) {
    FLARELAB_CHECK(head != nullptr);
    auto clock = head->clock();
    AngleSource angles = [head]() -> Result<std::pair<double, double>> {
        const double seen = head->trueAngle_deg();
        auto reported = head->position();
        if (!reported) return reported.error();
        return std::pair{seen, *reported};
    };
    return build(std::move(lens), options, std::move(angles), std::move(clock));
}

Result<std::unique_ptr<SimCamera>> SimCamera::make(optics::Lens lens,
                                                   const SimCameraOptions& options,
                                                   std::shared_ptr<Head> head,
                                                   std::shared_ptr<SimClock> clock) {
    FLARELAB_CHECK(head != nullptr);
    AngleSource angles = [head]() -> Result<std::pair<double, double>> {
        auto reported = head->position();
        if (!reported) return reported.error();
        return std::pair{*reported, *reported};
    };
    return build(std::move(lens), options, std::move(angles), std::move(clock));
}

Result<std::unique_ptr<SimCamera>> SimCamera::make(optics::Lens lens,
                                                   const SimCameraOptions& options,
                                                   std::shared_ptr<SimClock> clock) {
    const double angle = options.fixed_angle_deg;
    AngleSource angles = [angle]() -> Result<std::pair<double, double>> {
        return std::pair{angle, angle};
    };
    return build(std::move(lens), options, std::move(angles), std::move(clock));
}

std::string SimCamera::name() const { return "sim camera " + options_.serial; }

DeviceIdentity SimCamera::identity() const {
    return DeviceIdentity{"sim", "flarelab SimCamera (" + lens_.name() + ")", options_.serial,
                          "sim:"};
}

CameraCapabilities SimCamera::capabilities() const {
    CameraCapabilities c;
    c.width_px = options_.width_px;
    c.height_px = options_.height_px;
    c.formats = {hdr::RawFormat::Mono, hdr::RawFormat::BayerRGGB};
    c.bit_depth = options_.bit_depth;
    c.min_exposure_s = options_.min_exposure_s;
    c.max_exposure_s = options_.max_exposure_s;
    c.min_gain = options_.min_gain;
    c.max_gain = options_.max_gain;
    c.black_level_dn = options_.black_level_dn;
    c.white_level_dn = std::ldexp(1.0, options_.bit_depth) - 1.0;
    c.read_noise_e = options_.read_noise_e;
    c.electrons_per_dn = options_.electrons_per_dn;
    if (options_.response == SimResponse::Gamma) {
        c.response = CameraResponse::NonLinear;
        c.response_note = "simulated gamma curve, gamma " + fmt(options_.response_gamma);
    } else if (options_.response == SimResponse::Log) {
        c.response = CameraResponse::NonLinear;
        c.response_note = "simulated logarithmic curve, range " + fmt(options_.response_log_range);
    }
    return c;
}

Status SimCamera::setExposure(double exposure_s) {
    if (faults_.disconnected)
        return deviceError(DeviceFault::Disconnected, name(), "not connected");
    if (!finite(exposure_s) || exposure_s < options_.min_exposure_s ||
        exposure_s > options_.max_exposure_s)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "exposure_s = " + fmt(exposure_s) + " outside [" +
                               fmt(options_.min_exposure_s) + ", " + fmt(options_.max_exposure_s) +
                               "]");
    exposure_s_ = exposure_s;
    return Ok{};
}

Status SimCamera::setGain(double gain) {
    if (faults_.disconnected)
        return deviceError(DeviceFault::Disconnected, name(), "not connected");
    if (!finite(gain) || gain < options_.min_gain || gain > options_.max_gain)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "gain = " + fmt(gain) + " outside [" + fmt(options_.min_gain) + ", " +
                               fmt(options_.max_gain) + "]");
    gain_ = gain;
    return Ok{};
}

Status SimCamera::setFormat(hdr::RawFormat format) {
    if (faults_.disconnected)
        return deviceError(DeviceFault::Disconnected, name(), "not connected");
    if (format != hdr::RawFormat::Mono && format != hdr::RawFormat::BayerRGGB)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "format: only Mono and BayerRGGB are supported");
    if (format != format_) cache_.clear();  // the cached planes are per format
    format_ = format;
    return Ok{};
}

Result<ImageRGB> SimCamera::renderPower(double angle_deg, bool green_only) {
    if (!finite(angle_deg))
        return makeError(ErrorCode::Internal, name() + ": head angle is not finite");
    const int64_t w = options_.width_px, h = options_.height_px;
    render::Light light;
    light.theta_deg = std::abs(angle_deg);
    light.phi_deg = angle_deg < 0.0 ? 180.0 : 0.0;
    light.rgb = options_.light_rgb;
    if (green_only) light.rgb[0] = light.rgb[2] = 0.0f;
    const bool dark = light.rgb[0] == 0.0f && light.rgb[1] == 0.0f && light.rgb[2] == 0.0f;

    auto image = render::renderScene(
        lens_, dark ? std::span<const render::Light>{} : std::span<const render::Light>(&light, 1),
        options_.render);
    if (!image) return image.error().withContext(name() + ": rendering " + fmt(angle_deg) + " deg");
    ++renders_;
    if (light_image_ && !dark && light.theta_deg < 90.0) {
        const SimLightSpot spot = simLightSpot(lens_, light);
        if (spot.placed) {
            const render::SensorToImage mapping = render::sensorToImage(lens_.camera(), w, h);
            const Eigen::Vector2d centre = mapping.toPixels(spot.centre_mm.x(), spot.centre_mm.y());
            const LightImage& li = *light_image_;
            if (li.scale_x >= 1.0 && li.scale_y >= 1.0) {
                // Pattern pixels at least as large as image pixels: sampling keeps the energy.
                const float power[3] = {static_cast<float>(spot.power[0]),
                                        static_cast<float>(spot.power[1]),
                                        static_cast<float>(spot.power[2])};
                render::addStarburst(*image, li.pattern, centre.x(), centre.y(), power, li.scale_x);
            } else {
                splatStarburst(*image, li.pattern, centre.x(), centre.y(), li.scale_x, li.scale_y,
                               spot.power);
            }
        }
    }
    return std::move(*image);
}

std::optional<double> simLightPower(const optics::Lens& lens, const SimCameraOptions& options) {
    if (!options.validate()) return std::nullopt;
    render::Light light;
    light.rgb = options.light_rgb;
    const SimLightSpot spot = simLightSpot(lens, light);
    const bool green = options.format == hdr::RawFormat::Mono && options.mono == MonoResponse::Green;
    const double power =
        green ? spot.power[1]
              : 0.2126 * spot.power[0] + 0.7152 * spot.power[1] + 0.0722 * spot.power[2];
    // A pixel holding rendered power p records quantum_scale p / (pixel area) e/s (the top of
    // sim_camera.h); the light's image spreads its power over pixels that together hold all of it.
    const optics::CameraDescription& sensor = lens.camera();
    const double pixel_area_mm2 =
        (sensor.sensor_width_mm / static_cast<double>(options.width_px)) *
        (sensor.sensor_height_mm / static_cast<double>(options.height_px));
    const double dn_s = power * options.quantum_scale / pixel_area_mm2 / options.electrons_per_dn;
    if (!(dn_s > 0.0) || !std::isfinite(dn_s)) return std::nullopt;
    return dn_s;
}

std::optional<double> SimCamera::lightPowerDnPerS() const {
    SimCameraOptions options = options_;
    options.format = format_;
    return simLightPower(lens_, options);
}

double SimCamera::powerToRate() const {
    // Power per pixel to image-plane irradiance (per mm^2 of sensor), then to electrons.
    const optics::CameraDescription& sensor = lens_.camera();
    const double pixel_area_mm2 =
        (sensor.sensor_width_mm / static_cast<double>(options_.width_px)) *
        (sensor.sensor_height_mm / static_cast<double>(options_.height_px));
    return options_.quantum_scale / pixel_area_mm2;
}

Result<const std::vector<float>*> SimCamera::rate(double angle_deg) {
    for (const auto& [angle, plane] : cache_)
        if (angle == angle_deg) return &plane;
    const int64_t w = options_.width_px, h = options_.height_px;
    const bool green_only = format_ == hdr::RawFormat::Mono && options_.mono == MonoResponse::Green;
    const auto start = std::chrono::steady_clock::now();
    auto image = renderPower(angle_deg, green_only);
    if (!image) return image.error();
    const double to_e_s = powerToRate();
    std::vector<float> plane(static_cast<size_t>(w * h));
    bool all_finite = true;
    for (int64_t y = 0; y < h; ++y)
        for (int64_t x = 0; x < w; ++x) {
            const float* rgb = image->at(x, y);
            const int channel = bayerChannel(format_, x, y);
            double value = 0.0;
            if (channel >= 0)
                value = rgb[channel];
            else if (green_only)
                value = rgb[1];
            else
                value = 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2];
            const double e_s = value * to_e_s + options_.background_e_s;
            all_finite = all_finite && std::isfinite(e_s);
            plane[static_cast<size_t>(y * w + x)] = static_cast<float>(std::max(0.0, e_s));
        }
    if (!all_finite)
        return makeError(ErrorCode::Internal, name() + ": the rendered image at " + fmt(angle_deg) +
                                                  " deg is not finite");
    last_render_ms_ =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    cache_.emplace_back(angle_deg, std::move(plane));
    while (static_cast<int>(cache_.size()) > options_.cache_angles) cache_.pop_front();
    return &cache_.back().second;
}

Result<std::vector<float>> SimCamera::meanRate_e_s(double angle_deg) {
    auto plane = rate(angle_deg);
    if (!plane) return plane.error();
    return **plane;
}

Result<ImageRGB> SimCamera::meanRateRgb_e_s(double angle_deg) {
    auto image = renderPower(angle_deg, false);
    if (!image) return image.error();
    const double to_e_s = powerToRate();
    for (float& v : image->pixels) {
        const double e_s = v * to_e_s + options_.background_e_s;
        if (!std::isfinite(e_s))
            return makeError(ErrorCode::Internal, name() + ": the rendered image at " +
                                                      fmt(angle_deg) + " deg is not finite");
        v = static_cast<float>(std::max(0.0, e_s));
    }
    return std::move(*image);
}

Result<hdr::RawFrame> SimCamera::capture(double timeout_s) {
    if (faults_.disconnected)
        return deviceError(DeviceFault::Disconnected, name(), "not connected");
    if (!finite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, name(), "timeout_s must be positive");
    const auto stopped = [&] {
        return deviceError(DeviceFault::Stopped, name(), "the capture was aborted");
    };
    if (aborted_) return stopped();
    if (faults_.time_out_captures > 0) {
        --faults_.time_out_captures;
        if (!clock_->wait(timeout_s, &aborted_) || aborted_) return stopped();
        return deviceError(DeviceFault::Timeout, name(),
                           "no frame within timeout_s = " + fmt(timeout_s));
    }
    // The exposure starts now: in real time the rendering below happens during it, as a real
    // sensor integrates while the host waits, so a frame takes exposure + readout whatever the
    // render costs (unless the render takes longer).
    const int64_t start_ns = clock_->now_ns();
    const double frame_s = exposure_s_ + options_.readout_s;
    if (frame_s > timeout_s) {
        if (!clock_->wait(timeout_s, &aborted_) || aborted_) return stopped();
        return deviceError(
            DeviceFault::Timeout, name(),
            "a frame takes " + fmt(frame_s) +
                " s (exposure_s + readout), more than timeout_s = " + fmt(timeout_s));
    }
    auto angles = angles_();
    if (!angles) return angles.error().withContext(name() + ": head angle");
    const auto [seen_deg, stamp_deg] = *angles;
    // A capped lens lets no light through: nothing to render.
    const std::vector<float>* plane_pointer = nullptr;
    if (!lens_capped_) {
        auto plane_or = rate(seen_deg);
        if (!plane_or) return plane_or.error();
        plane_pointer = *plane_or;
    }

    hdr::RawFrame frame;
    frame.width = options_.width_px;
    frame.height = options_.height_px;
    frame.format = format_;
    frame.exposure_s = exposure_s_;
    frame.gain = gain_;
    frame.bit_depth = options_.bit_depth;
    frame.black_level_dn = options_.black_level_dn;
    frame.white_level_dn = std::ldexp(1.0, options_.bit_depth) - 1.0;
    frame.electrons_per_dn = options_.electrons_per_dn / gain_;
    frame.read_noise_dn = options_.read_noise_e / frame.electrons_per_dn;
    frame.angle_deg = stamp_deg;
    frame.timestamp_ns = clock_->now_ns();
    // host_timestamp_ns stays 0: a simulated frame is a function of (seed, sequence) alone, so
    // that a resumed sweep's raw files equal an uninterrupted one's.
    frame.timestamp_marks = hdr::TimestampMark::ExposureStart;
    frame.sequence = sequence_++;
    frame.camera = identity().describe();
    frame.samples.resize(static_cast<size_t>(frame.width * frame.height));

    // Sensor: shot noise on light and dark electrons, gain, read noise, black level, converter.
    const double t = exposure_s_;
    const double dn_per_e = 1.0 / frame.electrons_per_dn;
    const double white = frame.white_level_dn;
    // Beyond this many electrons a pixel clips whatever its noise.
    const double surely_white_e = 2.0 * (white + 10.0 * frame.read_noise_dn) / dn_per_e + 1e4;
    const uint64_t frame_seed = mix(options_.seed ^ mix(static_cast<uint64_t>(frame.sequence)));
    const bool curved = options_.response != SimResponse::Linear;
    const double black = frame.black_level_dn, range = white - frame.black_level_dn;
    const int64_t w = frame.width;
    tbb::parallel_for(int64_t{0}, frame.height, [&](int64_t y) {
        std::mt19937_64 rng(mix(frame_seed ^ static_cast<uint64_t>(y)));
        std::normal_distribution<double> normal;
        for (int64_t x = 0; x < w; ++x) {
            const size_t i = static_cast<size_t>(y * w + x);
            double dark_e_s = options_.dark_current_e_s;
            if (!hot_e_s_.empty()) dark_e_s += hot_e_s_[i];
            const double light_e_s = plane_pointer ? static_cast<double>((*plane_pointer)[i]) : 0.0;
            const double mean_e = (light_e_s + dark_e_s) * t;
            double dn = white;
            if (mean_e < surely_white_e) {
                const double e = shotNoise(mean_e, rng, normal);
                dn = e * dn_per_e + frame.black_level_dn + frame.read_noise_dn * normal(rng);
            }
            if (curved) dn = black + range * simResponseCurve(options_, (dn - black) / range);
            frame.samples[i] = static_cast<uint16_t>(std::clamp(std::round(dn), 0.0, white));
        }
    });
    if (!clock_->waitUntil(start_ns + secondsToNs(frame_s), &aborted_) || aborted_)
        return stopped();
    return frame;
}

Result<SimCameraSetup> simCameraSetup(const DeviceUri& uri,
                                      const SimCameraOptions& defaults,
                                      const std::optional<optics::Lens>& lens) {
    if (Status ok = uri.onlyParams(
            {"lens", "width", "height", "bits", "seed", "format", "angle_deg", "response", "cap"});
        !ok)
        return ok.error();
    SimCameraOptions options = defaults;
    std::optional<optics::Lens> chosen = lens;
    if (auto it = uri.params.find("lens"); it != uri.params.end()) {
        auto prescription = optics::loadPrescription(it->second);
        if (!prescription) return prescription.error().withContext("sim camera lens");
        auto made = optics::Lens::make(*prescription, optics::CameraDescription{});
        if (!made) return made.error().withContext("sim camera lens");
        chosen = std::move(*made);
    }
    if (!chosen)
        return makeError(ErrorCode::NotFound, "device uri '" + uri.text +
                                                  "': the sim camera needs a lens "
                                                  "(sim:?lens=data/lenses/<file>.csv)");
    const auto integer = [&](const std::string& key, int64_t& field) -> Status {
        auto value = uri.number(key, static_cast<double>(field));
        if (!value) return value.error();
        if (*value != std::floor(*value) || std::abs(*value) > 9.007199254740992e15)
            return makeError(ErrorCode::InvalidArgument,
                             "device uri '" + uri.text + "': " + key + " must be an integer");
        field = static_cast<int64_t>(*value);
        return Ok{};
    };
    int64_t bits = options.bit_depth, seed = static_cast<int64_t>(options.seed);
    for (auto [key, field] : {std::pair<const char*, int64_t*>{"width", &options.width_px},
                              {"height", &options.height_px},
                              {"bits", &bits},
                              {"seed", &seed}})
        if (Status ok = integer(key, *field); !ok) return ok.error();
    if (bits < 8 || bits > 16)
        return makeError(ErrorCode::InvalidArgument,
                         "device uri '" + uri.text + "': bits must lie in 8..16");
    options.bit_depth = static_cast<int>(bits);
    options.seed = static_cast<uint64_t>(seed);
    if (auto it = uri.params.find("format"); it != uri.params.end()) {
        if (it->second == "mono")
            options.format = hdr::RawFormat::Mono;
        else if (it->second == "bayer-rggb" || it->second == "rggb")  // capture's name, short
            options.format = hdr::RawFormat::BayerRGGB;
        else
            return makeError(
                ErrorCode::InvalidArgument,
                "device uri '" + uri.text + "': format must be mono or bayer-rggb (or rggb)");
    }
    if (auto it = uri.params.find("response"); it != uri.params.end()) {
        if (it->second == "linear")
            options.response = SimResponse::Linear;
        else if (it->second == "gamma")
            options.response = SimResponse::Gamma;
        else if (it->second == "log")
            options.response = SimResponse::Log;
        else
            return makeError(ErrorCode::InvalidArgument, "device uri '" + uri.text +
                                                             "': response must be linear, gamma "
                                                             "or log");
    }
    if (auto it = uri.params.find("cap"); it != uri.params.end()) {
        if (it->second != "0" && it->second != "1")
            return makeError(ErrorCode::InvalidArgument,
                             "device uri '" + uri.text + "': cap must be 0 or 1");
        options.lens_capped = it->second == "1";
    }
    auto angle = uri.number("angle_deg", options.fixed_angle_deg);
    if (!angle) return angle.error();
    options.fixed_angle_deg = *angle;
    if (Status ok = options.validate(); !ok)
        return ok.error().withContext("device uri '" + uri.text + "'");
    return SimCameraSetup{std::move(*chosen), options};
}

Status addSimCameraBackend(CameraRegistry& registry,
                           std::shared_ptr<SimHead> head,
                           const SimCameraOptions& defaults,
                           std::optional<optics::Lens> lens) {
    auto open = [head, defaults, lens](const DeviceUri& uri) -> Result<std::unique_ptr<Camera>> {
        auto setup = simCameraSetup(uri, defaults, lens);
        if (!setup) return setup.error();
        auto camera = head ? SimCamera::make(std::move(setup->lens), setup->options, head)
                           : SimCamera::make(std::move(setup->lens), setup->options);
        if (!camera) return camera.error();
        return std::unique_ptr<Camera>(std::move(*camera));
    };
    const SimCameraOptions listed = defaults;
    return registry.addBackend(
        "sim", "simulated camera (flarelab renderer)", std::move(open), [listed] {
            DeviceListing d;
            d.uri = "sim:";
            d.kind = "camera";
            d.backend = "sim";
            d.model = "flarelab simulated camera";
            d.serial = listed.serial;
            d.details = {"size: " + std::to_string(listed.width_px) + "x" +
                             std::to_string(listed.height_px) + " (uri: width=, height=)",
                         "bits: " + std::to_string(listed.bit_depth),
                         "formats: mono, rggb (uri: format=)",
                         "response: linear (uri: response=linear|gamma|log; cap=1 caps the lens)",
                         "lens: uri parameter lens=<prescription csv>"};
            return std::vector<DeviceListing>{d};
        });
}

}  // namespace flarelab::drivers
