// ============================================================================
//  flarelab drivers: SimCamera, SimCameraOptions, simRenderDefaults, addSimCameraBackend
// ============================================================================
//
// The virtual camera of the simulated rig. It looks at a point light from the angle of a head:
// for a head angle a the light stands at theta = |a| from the optical axis, on the horizontal
// (phi = 0 for a >= 0, 180 for a < 0). The optics: render::renderScene of the configured lens
// draws every ghost of a point light of irradiance light_rgb; the light's own image (the
// aperture's starburst) is added here; a dim uniform background lies under both. The result is
// cached per angle, so the exposures of a bracket render once.
//
// The light's own image. renderScene's starburst samples the pattern at pixel centres, which
// loses or invents energy where a pattern pixel is much smaller than an image pixel (the Heliar
// at f/16 on 640 px: 0.06 px), so the light's power in the frame jumped between 1.2 and 51
// (scene units) from 0 to 2 deg. Here the pattern is rendered once per camera and every pattern
// sample is splatted bilinearly onto the pixel centres around it (magnified patterns, 1 image
// pixel or less per pattern pixel, go through render::addStarburst), centred where the real
// chief ray lands, scaled by the power a 32 x 32 imaging ray grid carries through the stop.
// render.starburst = false leaves the light's image out.
//
// Colour to one channel. Mono sensors (RawFormat::Mono) take, by default, the green channel
// (550 nm): a monochrome sensor behind a green filter. Only the green ghost grids are traced
// then, a third of the work. MonoResponse::Luminance takes Rec. 709 luminance,
// 0.2126 R + 0.7152 G + 0.0722 B, and traces all three. BayerRGGB gives each pixel its filter's
// channel (red at (0, 0)).
//
// The sensor, per pixel, for exposure t and gain g (DN: digital numbers; E: the pixel's
// image-plane irradiance, its rendered power over its area in mm^2):
//   rate_e_s = quantum_scale * E + background_e_s
//   mean_e   = (rate_e_s + dark_current_e_s + hot pixel extra) * t
//   e        ~ Poisson(mean_e)                   photon shot and dark current noise
//   read_dn  = read_noise_e * g / electrons_per_dn
//   DN       = e * g / electrons_per_dn + black_level_dn + N(0, read_dn^2)
//   sample   = round(DN) clipped to [0, white],  white = 2^bit_depth - 1
// Poisson draws are exact (Hoermann's PTRS) up to 1e7 electrons, far beyond any white level. The
// frame's metadata says electrons_per_dn / g and read_noise_e * g / electrons_per_dn,
// so the merge can weight samples. Hot pixels (a fixed pattern drawn once from `seed`) carry an
// extra dark current. Noise of frame n is drawn from (seed, n, row): the same options and the same
// sequence of calls give the same frames, on any number of threads.
//
// Default calibration. With the Heliar (data/lenses/heliar-tronnier.csv, f/16) at 640 x 427,
// quantum_scale 5e7 puts the broad ghosts near 1000 e/s, a quarter of white in 1 s at gain 1
// (4 e/DN, 12 bits), while the light's core saturates every exposure of a 0.25 / 1 / 4 s bracket,
// as on the rig. The default render settings (simRenderDefaults) trade accuracy for speed: a
// 0..30 deg sweep at 0.2 deg (151 angles x 3 exposures) at 640 x 427 takes about 20 s on two
// shared cores in fast mode (SimCameraTiming.DISABLED_SweepTiming measures it). Ghosts are
// culled against the sensor's noise floor, not the renderer's relative budget: one whose mean is
// below 1 % of a pixel's noise at max_exposure_s is not drawn (render::SceneOptions).
//
// Response. By default the converter is linear, as above. SimResponse::Gamma and ::Log stand for
// cameras that bend their output before they hand it out (a webcam's gamma curve; a logarithmic
// curve like that of Aravis's fake camera), so that calibration (calibration.h) is tested against
// a curve it must recover: with u = (DN - black_level_dn) / (white - black_level_dn) the linear
// sample above, clipped to [0, 1], the camera gives black_level_dn + (white - black_level_dn) *
// curve(u), curve(u) = u^(1 / response_gamma) or log(1 + a u) / log(1 + a), a =
// response_log_range, before rounding. simResponseCurve and simResponseInverse are the curve and
// its inverse, the ground truth for those tests.
//
// Lens cap. lens_capped (or setLensCapped) takes the light and the background away: frames hold
// dark current, hot pixels, read noise and the black level only, as with a capped lens on the
// rig; nothing is rendered for them.
//
// Time runs on the head's SimClock (sim_clock.h): a capture takes exposure_s + readout_s of
// rig time; real-time mode sleeps that long, fast mode does not. The frame's timestamp is the
// start of its exposure.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "drivers/camera.h"
#include "drivers/head.h"
#include "drivers/sim_clock.h"
#include "drivers/sim_head.h"
#include "optics/lens.h"
#include "render/scene.h"

namespace flarelab::drivers {

enum class MonoResponse { Green, Luminance };

// The converter's response (see the top of this file).
enum class SimResponse { Linear, Gamma, Log };

// Where the light's own image lands (sensor mm, the real chief ray at the green wavelength) and
// the power of each channel that passes the stop on the imaging path, in the scene's units;
// placed is false when no chief ray reaches the sensor.
struct SimLightSpot {
    Eigen::Vector2d centre_mm = Eigen::Vector2d::Zero();
    std::array<double, 3> power = {0.0, 0.0, 0.0};
    bool placed = false;
};
SimLightSpot simLightSpot(const optics::Lens& lens, const render::Light& light);

// Base grid 64, probe grid 8, the paper's light primitive merge; starburst mask 256 / FFT 512
// (a pattern 33 px wide at 640 px with the Heliar at f/16, rendered once per camera).
render::SceneOptions simRenderDefaults();

struct SimCameraFaults {
    int time_out_captures = 0;  // the next n captures wait out their timeout: [timeout]
    bool disconnected = false;  // every call answers [disconnected]
};

struct SimCameraOptions {
    std::string serial = "SIMCAM-0";
    int64_t width_px = 640;  // 1..32768
    int64_t height_px = 427;
    hdr::RawFormat format = hdr::RawFormat::Mono;  // Mono or BayerRGGB
    MonoResponse mono = MonoResponse::Green;
    int bit_depth = 12;                  // 8..16
    double black_level_dn = 64.0;        // >= 0, below white
    double electrons_per_dn = 4.0;       // > 0, at gain 1
    double read_noise_e = 3.0;           // >= 0
    double dark_current_e_s = 1.0;       // >= 0
    double hot_pixel_fraction = 0.0;     // in [0, 1]
    double hot_pixel_dark_e_s = 2000.0;  // extra dark current of a hot pixel, >= 0
    double quantum_scale = 5e7;          // e/s per unit of image-plane irradiance, >= 0
    std::array<float, 3> light_rgb = {1.0f, 1.0f, 1.0f};  // irradiance at the lens, >= 0
    double background_e_s = 20.0;                         // >= 0
    // Down to 1 ns, wider than a real camera's range: the simulated light's core is 5e10 to 3e12
    // e-/s on its brightest pixel, and auto-bracketing (auto_bracket.h) can then keep it
    // unclipped on every shipped lens. A real camera's plan says when its shortest exposure
    // still clips the core.
    double min_exposure_s = 1e-9;
    double max_exposure_s = 60.0;
    double min_gain = 1.0;
    double max_gain = 16.0;
    double exposure_s = 1.0;  // initial settings
    double gain = 1.0;
    double readout_s = 0.03;       // >= 0, rig time per frame after the exposure
    double fixed_angle_deg = 0.0;  // the light's angle when no head is attached
    SimResponse response = SimResponse::Linear;
    double response_gamma = 2.2;         // > 0, for SimResponse::Gamma
    double response_log_range = 1000.0;  // a > 0, for SimResponse::Log
    bool lens_capped = false;            // no light and no background (see the top of this file)
    int cache_angles = 4;                // rendered angles kept, >= 1
    uint64_t seed = 1;
    render::SceneOptions render = simRenderDefaults();  // width and height are taken from above
    SimCameraFaults faults;

    // InvalidArgument naming the first field out of range.
    Status validate() const;
};

// The response curve of `options` at u in [0, 1] (u outside is clipped), and its inverse at v in
// [0, 1]: the linear fraction of the converter's range that the camera reports as v. Identity
// for SimResponse::Linear.
double simResponseCurve(const SimCameraOptions& options, double u);
double simResponseInverse(const SimCameraOptions& options, double v);

// The power of the light's own image on axis as a camera of `options` (its light, quantum scale,
// electrons per DN, size and format) records it, summed over the sensor, in DN/s at unity gain:
// the green channel for a monochrome sensor that sees green, Rec. 709 luminance otherwise (a
// colour sensor's demosaiced frames; predict's figures take luminance). nullopt for options the
// camera refuses or a lens that passes no light on axis.
std::optional<double> simLightPower(const optics::Lens& lens, const SimCameraOptions& options);

class SimCamera final : public Camera {
public:
    // Bound to a simulated head: renders at its true angle (backlash, noise and lost steps show
    // in the image) and stamps frames with the angle it reports. Shares its clock.
    static Result<std::unique_ptr<SimCamera>> make(optics::Lens lens,
                                                   const SimCameraOptions& options,
                                                   std::shared_ptr<SimHead> head);
    // Bound to any head: renders at and stamps with the angle it reports; clock: a fast one when
    // null.
    static Result<std::unique_ptr<SimCamera>> make(optics::Lens lens,
                                                   const SimCameraOptions& options,
                                                   std::shared_ptr<Head> head,
                                                   std::shared_ptr<SimClock> clock);
    // No head: the light stays at options.fixed_angle_deg; a fast clock when null.
    static Result<std::unique_ptr<SimCamera>> make(optics::Lens lens,
                                                   const SimCameraOptions& options,
                                                   std::shared_ptr<SimClock> clock = nullptr);

    DeviceIdentity identity() const override;
    CameraCapabilities capabilities() const override;
    Status setExposure(double exposure_s) override;
    double exposure_s() const override { return exposure_s_; }
    Status setGain(double gain) override;
    double gain() const override { return gain_; }
    Status setFormat(hdr::RawFormat format) override;
    hdr::RawFormat format() const override { return format_; }
    // simLightPower of this camera's lens and options (in the format it is set to).
    std::optional<double> lightPowerDnPerS() const override;
    // A head that cannot report its angle fails the capture with the head's error as context.
    Result<hdr::RawFrame> capture(double timeout_s) override;
    // Real time: the exposure's wait ends within its 5 ms slice. Fast mode has nothing to wait
    // for; a capture rendering when it comes returns [stopped] once the render is done.
    void abort() override { aborted_ = true; }

    void setFaults(const SimCameraFaults& faults) { faults_ = faults; }
    // The operator puts the lens cap on (true) or takes it off.
    void setLensCapped(bool capped) { lens_capped_ = capped; }
    bool lensCapped() const { return lens_capped_; }
    // Extra dark current of every pixel (e/s), row-major; empty when there are no hot pixels.
    const std::vector<float>& hotPixelDark_e_s() const { return hot_e_s_; }
    const SimCameraFaults& faults() const { return faults_; }
    // The sequence number the next frame gets (>= 0); its noise is drawn from it. A sweep resumed
    // at frame i of a bracket of n sets i * n, and its frames equal an uninterrupted run's.
    void setSequence(int64_t next) { sequence_ = next; }
    int64_t sequence() const { return sequence_; }
    // The noise-free electron rate (e/s) of every pixel, dark current excluded, for the light at
    // head angle angle_deg: what the sensor integrates (cached like captures).
    Result<std::vector<float>> meanRate_e_s(double angle_deg);
    // The same for a sensor that sees every colour at every pixel (red, green, blue at 650, 550,
    // 450 nm), whatever the format: what a Bayer sensor's demosaiced frames estimate. Not cached.
    Result<ImageRGB> meanRateRgb_e_s(double angle_deg);
    int64_t renders() const { return renders_; }  // renderScene calls so far (cache misses)
    double lastRender_ms() const { return last_render_ms_; }
    const std::shared_ptr<SimClock>& clock() const { return clock_; }
    const optics::Lens& lens() const { return lens_; }

private:
    struct Key {
        explicit Key() = default;
    };

public:
    // The light's starburst, rendered once, and the image pixels one pattern pixel spans.
    struct LightImage {
        ImageRGB pattern;
        double scale_x = 0.0;
        double scale_y = 0.0;
    };
    // (angle to render at, angle to stamp)
    using AngleSource = std::function<Result<std::pair<double, double>>()>;
    // Through make() only (the key is private); the options must be valid.
    SimCamera(Key,
              optics::Lens lens,
              const SimCameraOptions& options,
              AngleSource angles,
              std::shared_ptr<SimClock> clock,
              std::optional<LightImage> light_image);

private:
    static Result<std::unique_ptr<SimCamera>> build(optics::Lens lens,
                                                    const SimCameraOptions& options,
                                                    AngleSource angles,
                                                    std::shared_ptr<SimClock> clock);
    Result<const std::vector<float>*> rate(double angle_deg);
    // The scene at the head angle: power per pixel and channel (green alone when green_only).
    Result<ImageRGB> renderPower(double angle_deg, bool green_only);
    double powerToRate() const;  // e/s per unit of rendered power in a pixel
    std::string name() const;

    optics::Lens lens_;
    SimCameraOptions options_;
    AngleSource angles_;
    std::shared_ptr<SimClock> clock_;
    double exposure_s_;
    double gain_;
    hdr::RawFormat format_;
    SimCameraFaults faults_;
    bool lens_capped_ = false;
    std::optional<LightImage> light_image_;  // none when options.render.starburst is false
    std::vector<float> hot_e_s_;  // extra dark current per pixel; empty without hot pixels
    std::deque<std::pair<double, std::vector<float>>> cache_;
    int64_t sequence_ = 0;
    std::atomic<bool> aborted_{false};
    int64_t renders_ = 0;
    double last_render_ms_ = 0.0;
};

// The lens and options a "sim:" camera URI asks for (the parameters as for addSimCameraBackend
// below), from `defaults` and `lens`; NotFound naming the lens parameter when there is no lens,
// InvalidArgument naming the parameter that is out of range.
struct SimCameraSetup {
    optics::Lens lens;
    SimCameraOptions options;
};
Result<SimCameraSetup> simCameraSetup(const DeviceUri& uri,
                                      const SimCameraOptions& defaults,
                                      const std::optional<optics::Lens>& lens);

// Adds the "sim" scheme to a registry: "sim:" opens a SimCamera bound to `head` (or with no head
// when null) with `defaults`, its lens `lens` when given. URI parameters override: lens=<path of
// a prescription> (loaded with the default camera description), width, height, bits, seed,
// format=mono|rggb, angle_deg (fixed angle without a head), response=linear|gamma|log (the
// converter's curve), cap=0|1 (the lens cap). NotFound naming the lens parameter
// when there is no lens.
Status addSimCameraBackend(CameraRegistry& registry,
                           std::shared_ptr<SimHead> head,
                           const SimCameraOptions& defaults = {},
                           std::optional<optics::Lens> lens = std::nullopt);

}  // namespace flarelab::drivers
