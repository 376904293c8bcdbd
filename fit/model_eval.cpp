#include "fit/model_eval.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <optional>
#include <string>

#include "fit/polyfit.h"
#include "hdr/raw_frame.h"
#include "render/model_ghost.h"

namespace flarelab::fit {
namespace {

constexpr double kMinExponent = 0.25;
constexpr double kMaxExponent = 4.0;

const std::array<GhostParameterInfo, kGhostParameterCount> kInfo = {{
    {"centre_x_mm", "mm", std::nullopt, std::nullopt},
    {"centre_y_mm", "mm", std::nullopt, std::nullopt},
    {"half_height_mm", "mm", kMinExtentMm, std::nullopt},
    {"left_mm", "mm", kMinExtentMm, std::nullopt},
    {"right_mm", "mm", kMinExtentMm, std::nullopt},
    {"left_handle_x_fraction", "1", 0.0, 1.0},
    {"left_handle_y_fraction", "1", 0.0, 1.0},
    {"right_handle_x_fraction", "1", 0.0, 1.0},
    {"right_handle_y_fraction", "1", 0.0, 1.0},
    {"ln_border_rgb[0]", "ln(frame unit)", kMinLnIntensity, std::nullopt},
    {"ln_border_rgb[1]", "ln(frame unit)", kMinLnIntensity, std::nullopt},
    {"ln_border_rgb[2]", "ln(frame unit)", kMinLnIntensity, std::nullopt},
    {"ln_inner_rgb[0]", "ln(frame unit)", kMinLnIntensity, std::nullopt},
    {"ln_inner_rgb[1]", "ln(frame unit)", kMinLnIntensity, std::nullopt},
    {"ln_inner_rgb[2]", "ln(frame unit)", kMinLnIntensity, std::nullopt},
    {"inner_falloff_mm", "mm", kMinExtentMm, std::nullopt},
    {"outer_falloff_mm", "mm", kMinExtentMm, std::nullopt},
    {"inner_exponent", "1", kMinExponent, kMaxExponent},
    {"outer_exponent", "1", kMinExponent, kMaxExponent},
}};

double fraction(double handle, double extent) {
    return extent > 0.0 ? std::clamp(handle / extent, 0.0, 1.0) : 0.0;
}

// Rotation by `angle` (radians) about the optical axis, of a state's shape. The default shape is
// axis-aligned, so only a rotation by a multiple of 180 degrees keeps it a default shape; other
// rotations are applied to the loop by the renderers (renderGhostStates takes rotated loops).
render::BezierLoop rotatedLoop(const GhostState& state, double angle) {
    render::BezierLoop loop = render::toBezierLoop(state.shape);
    if (angle == 0.0) return loop;
    const double c = std::cos(angle), s = std::sin(angle);
    for (auto& p : loop.control_points_mm)
        p = Eigen::Vector2d(c * p.x() - s * p.y(), s * p.x() + c * p.y());
    return loop;
}

}  // namespace

const GhostParameterInfo& ghostParameterInfo(int index) {
    FLARELAB_CHECK(index >= 0 && index < kGhostParameterCount);
    return kInfo[static_cast<size_t>(index)];
}

GhostParameters ghostParameters(const GhostState& state, double ln_floor) {
    const auto& s = state.shape;
    const auto& h = state.shading;
    GhostParameters v{};
    v[0] = s.centre_x_mm;
    v[1] = s.centre_y_mm;
    v[2] = s.half_height_mm;
    v[3] = s.left_mm;
    v[4] = s.right_mm;
    v[5] = fraction(s.left_handle_x_mm, s.left_mm);
    v[6] = fraction(s.left_handle_y_mm, s.half_height_mm);
    v[7] = fraction(s.right_handle_x_mm, s.right_mm);
    v[8] = fraction(s.right_handle_y_mm, s.half_height_mm);
    const double floor = std::max(kMinLnIntensity, ln_floor);
    for (int c = 0; c < 3; ++c) {
        const double border = h.border_rgb[c], inner = h.inner_rgb[c];
        v[9 + c] = border > 0.0 ? std::max(floor, std::log(border)) : floor;
        v[12 + c] = inner > 0.0 ? std::max(floor, std::log(inner)) : floor;
    }
    v[15] = h.inner_falloff_mm;
    v[16] = h.outer_falloff_mm;
    v[17] = h.inner_exponent;
    v[18] = h.outer_exponent;
    return v;
}

Result<GhostState> ghostStateFromParameters(std::span<const double> values) {
    if (values.size() != kGhostParameterCount)
        return makeError(ErrorCode::InvalidArgument,
                         "ghost parameters: " + std::to_string(values.size()) + " values, not " +
                             std::to_string(kGhostParameterCount));
    GhostParameters v{};
    for (int i = 0; i < kGhostParameterCount; ++i) {
        const double x = values[static_cast<size_t>(i)];
        if (!std::isfinite(x))
            return makeError(ErrorCode::InvalidArgument,
                             std::string("ghost parameters: ") + kInfo[i].name + " is not finite");
        double clamped = x;
        if (kInfo[i].lower_bound) clamped = std::max(clamped, *kInfo[i].lower_bound);
        if (kInfo[i].upper_bound) clamped = std::min(clamped, *kInfo[i].upper_bound);
        v[static_cast<size_t>(i)] = clamped;
    }
    GhostState state;
    auto& s = state.shape;
    s.centre_x_mm = v[0];
    s.centre_y_mm = v[1];
    s.half_height_mm = v[2];
    s.left_mm = v[3];
    s.right_mm = v[4];
    s.left_handle_x_mm = v[5] * s.left_mm;
    s.left_handle_y_mm = v[6] * s.half_height_mm;
    s.right_handle_x_mm = v[7] * s.right_mm;
    s.right_handle_y_mm = v[8] * s.half_height_mm;
    auto& h = state.shading;
    for (int c = 0; c < 3; ++c) {
        // ln intensities far above any float are clamped so that the image stays finite.
        h.border_rgb[c] = v[9 + c] <= kMinLnIntensity ? 0.0 : std::exp(std::min(v[9 + c], 80.0));
        h.inner_rgb[c] = v[12 + c] <= kMinLnIntensity ? 0.0 : std::exp(std::min(v[12 + c], 80.0));
    }
    h.inner_falloff_mm = v[15];
    h.outer_falloff_mm = v[16];
    h.inner_exponent = v[17];
    h.outer_exponent = v[18];
    return state;
}

namespace {

// See modelGhostsAt.
constexpr double kBetweenFramesSlack = 1.25;

}  // namespace

// The inside at the inner intensity, plus eq. 6.4's border profile integrated across the edge
// (inside over the inner falloff, at most the ghost's smaller half size; outside over the outer
// one) times the perimeter, the shape taken as the ellipse through its extents.
double roughGhostEnergy(const GhostState& g) {
    const double w = 0.5 * (g.shape.left_mm + g.shape.right_mm);
    const double h = g.shape.half_height_mm;
    const double area = std::numbers::pi * w * h;
    const double perimeter =
        std::numbers::pi * (3.0 * (w + h) - std::sqrt((3.0 * w + h) * (w + 3.0 * h)));
    const auto& s = g.shading;
    const double fi = std::min(s.inner_falloff_mm, std::min(w, h));
    const double inner_band = fi * s.inner_exponent / (s.inner_exponent + 1.0);
    const double outer_band = s.outer_falloff_mm * s.outer_exponent / (s.outer_exponent + 1.0);
    double energy = 0.0;
    for (int c = 0; c < 3; ++c)
        energy += s.inner_rgb[c] * area +
                  (s.border_rgb[c] - s.inner_rgb[c]) * perimeter * inner_band +
                  s.border_rgb[c] * perimeter * outer_band;
    return std::max(energy, 0.0);
}

Result<std::vector<ModelGhostAt>> modelGhostsAt(const FlareModel& model,
                                                double angle_deg,
                                                double roll_deg) {
    if (!std::isfinite(angle_deg) || !std::isfinite(roll_deg))
        return makeError(ErrorCode::InvalidArgument, "model: the angle and roll must be finite");
    if (angle_deg < model.valid_from_deg || angle_deg > model.valid_to_deg)
        return makeError(ErrorCode::InvalidArgument,
                         "model: angle " + std::to_string(angle_deg) +
                             " deg lies outside the model's valid range " +
                             std::to_string(model.valid_from_deg) + " to " +
                             std::to_string(model.valid_to_deg) + " deg");
    std::vector<ModelGhostAt> out;
    for (const ModelGhost& ghost : model.ghosts) {
        if (ghost.parameters.size() != kGhostParameterCount) continue;  // not a ghost of this kind
        const auto& first = ghost.parameters.front().pieces;
        if (first.empty()) continue;
        // Within its fitted range a ghost is drawn as fitted; beyond it, it fades out over one
        // capture step (see model_eval.h); at the next captured angle it was not seen.
        const double step = std::isfinite(model.capture.step_deg) ? model.capture.step_deg : 0.0;
        double weight = 1.0;
        if (angle_deg < first.front().angle_from_deg)
            weight = step > 0.0 ? 1.0 - (first.front().angle_from_deg - angle_deg) / step : 0.0;
        if (angle_deg > first.back().angle_to_deg)
            weight = step > 0.0 ? 1.0 - (angle_deg - first.back().angle_to_deg) / step : 0.0;
        if (!(weight > 1e-9)) continue;  // the ghost was not seen at this angle
        // The ghost's parameters at angle a, each series in its piece and bounds.
        const auto stateAt = [&](double a) -> std::optional<GhostState> {
            GhostParameters values{};
            for (int i = 0; i < kGhostParameterCount; ++i) {
                const ModelParameter* parameter = nullptr;
                for (const auto& p : ghost.parameters)
                    if (p.name == kInfo[i].name) parameter = &p;
                if (!parameter) return std::nullopt;
                // The piece holding the angle: the later one at a shared end.
                const ModelPiece* piece = &parameter->pieces.front();
                for (const auto& candidate : parameter->pieces)
                    if (a >= candidate.angle_from_deg) piece = &candidate;
                const double span = piece->angle_to_deg - piece->angle_from_deg;
                const double x =
                    span > 0.0
                        ? std::clamp(2.0 * (a - piece->angle_from_deg) / span - 1.0, -1.0, 1.0)
                        : 0.0;
                double value = chebyshevValue(piece->coefficients, x);
                // The model's own bounds for this ghost (the fitter writes the range its frames
                // spanned): a series never leaves them.
                if (parameter->lower_bound) value = std::max(value, *parameter->lower_bound);
                if (parameter->upper_bound) value = std::min(value, *parameter->upper_bound);
                values[static_cast<size_t>(i)] = value;
            }
            auto made = ghostStateFromParameters(values);
            if (!made) return std::nullopt;  // non-finite: a model validateModel would refuse
            return *made;
        };
        auto state = stateAt(angle_deg);
        if (!state) continue;
        // Between two captured angles a ghost's light stays within what it has at them (give or
        // take kBetweenFramesSlack): each parameter has its own series, and where two trade (a
        // thin bright rim against a wide dim one) their series can meet between frames in a
        // combination no frame had, a rim of 2700 DN/s half a millimetre wide where the frames
        // held a sliver (Nikon tele, 12.4 deg: relative L2 1.42). Its intensities are scaled down.
        const double lo = first.front().angle_from_deg, hi = first.back().angle_to_deg;
        if (step > 0.0 && angle_deg > lo && angle_deg < hi) {
            const double k = std::floor((angle_deg - model.capture.from_deg) / step);
            const double a0 = std::max(lo, model.capture.from_deg + k * step);
            const double a1 = std::min(hi, model.capture.from_deg + (k + 1.0) * step);
            if (angle_deg - a0 > 1e-9 * step && a1 - angle_deg > 1e-9 * step) {
                const auto s0 = stateAt(a0), s1 = stateAt(a1);
                const double e = roughGhostEnergy(*state);
                const double bound =
                    kBetweenFramesSlack *
                    std::max(s0 ? roughGhostEnergy(*s0) : 0.0, s1 ? roughGhostEnergy(*s1) : 0.0);
                if (e > bound && e > 0.0) weight *= bound / e;
            }
        }
        for (int c = 0; c < 3; ++c) {
            state->shading.border_rgb[c] *= weight;
            state->shading.inner_rgb[c] *= weight;
        }
        out.push_back({ghost.id, *state});
    }
    // The roll: kept as the state's shape rotated when drawn (see renderModel); states carry the
    // unrotated shape here, and a roll of a multiple of 180 degrees is folded in exactly.
    const double turn = roll_deg - model.capture.roll_deg;
    const double half_turns = std::remainder(turn, 360.0);
    if (std::abs(std::abs(half_turns) - 180.0) < 1e-12) {
        for (auto& g : out) {
            auto& s = g.state.shape;
            s.centre_x_mm = -s.centre_x_mm;
            s.centre_y_mm = -s.centre_y_mm;
            std::swap(s.left_mm, s.right_mm);
            std::swap(s.left_handle_x_mm, s.right_handle_x_mm);
            std::swap(s.left_handle_y_mm, s.right_handle_y_mm);
        }
    }
    return out;
}

ImageRGB renderGhostStates(std::span<const GhostState> ghosts,
                           const render::SensorToImage& mapping,
                           int64_t width,
                           int64_t height,
                           const ModelRenderOptions& options) {
    return renderRotatedGhostStates(ghosts, 0.0, mapping, width, height, options);
}

ImageRGB renderRotatedGhostStates(std::span<const GhostState> ghosts,
                                  double rotation_deg,
                                  const render::SensorToImage& mapping,
                                  int64_t width,
                                  int64_t height,
                                  const ModelRenderOptions& options) {
    ImageRGB image(width, height);
    // Each ghost is flattened and its row spans built on its own (prepareGhostPrimitive), so
    // they are prepared on every core; the array keeps the ghosts' order.
    std::vector<std::optional<render::GhostPrimitive>> prepared(ghosts.size());
    const double angle = rotation_deg * std::numbers::pi / 180.0;
    double frame_peak = 0.0;
    if (options.frame_tolerance)
        for (const GhostState& g : ghosts)
            if (const double scaled = render::shadingPeak(g.shading) * options.intensity_scale;
                std::isfinite(scaled))
                frame_peak = std::max(frame_peak, scaled);
    tbb::parallel_for(size_t{0}, ghosts.size(), [&](size_t i) {
        const GhostState& g = ghosts[i];
        render::GhostShading shading = g.shading;
        for (int c = 0; c < 3; ++c) {
            shading.border_rgb[c] *= options.intensity_scale;
            shading.inner_rgb[c] *= options.intensity_scale;
        }
        render::GhostDrawOptions draw;
        draw.distance = options.distance;
        draw.evaluation = options.evaluation;
        draw.smooth_tolerance = options.smooth_tolerance;
        draw.tolerance_peak = frame_peak;
        prepared[i] = render::prepareGhostPrimitive(rotatedLoop(g, angle), shading, mapping, width,
                                                    height, draw);
    });
    std::vector<render::GhostPrimitive> primitives;
    primitives.reserve(ghosts.size());
    for (auto& p : prepared)
        if (p) primitives.push_back(std::move(*p));
    const Status drawn = render::renderTiled(image, {}, primitives, optics::ApertureShape{},
                                             options.tiles, options.stats);
    FLARELAB_CHECK(
        drawn.has_value());  // ranges come from prepareGhostPrimitive, tiles from the caller
    return image;
}

Result<ImageRGB> renderModel(const FlareModel& model,
                             double angle_deg,
                             double roll_deg,
                             int64_t width,
                             int64_t height,
                             const ModelRenderOptions& options) {
    if (width < 1 || height < 1 || width > kModelMaxSide || height > kModelMaxSide)
        return makeError(ErrorCode::InvalidArgument,
                         "render model: the image size must be 1..32768 pixels per side");
    if (!(options.intensity_scale >= 0.0) || !std::isfinite(options.intensity_scale))
        return makeError(ErrorCode::InvalidArgument,
                         "render model: intensity_scale must be finite and >= 0");
    if (!(options.smooth_tolerance > 0.0 && options.smooth_tolerance <= 0.1))
        return makeError(ErrorCode::InvalidArgument,
                         "render model: smooth_tolerance must lie in (0, 0.1]");
    if (!(model.lens.sensor_width_mm > 0.0) || !(model.lens.sensor_height_mm > 0.0))
        return makeError(ErrorCode::InvalidArgument, "render model: the model has no sensor size");
    const int dense = options.tiles.dense_tile_px, coarse = options.tiles.coarse_tile_px;
    if (dense < 1 || dense > 256 || coarse < dense || coarse > 4096 || coarse % dense != 0)
        return makeError(ErrorCode::InvalidArgument, "render model: tile sizes out of range");
    auto ghosts = modelGhostsAt(model, angle_deg, roll_deg);
    if (!ghosts) return ghosts.error();
    std::vector<GhostState> states;
    for (const auto& g : *ghosts) states.push_back(g.state);
    render::SensorToImage mapping;
    mapping.px_per_mm_x = static_cast<double>(width) / model.lens.sensor_width_mm;
    mapping.px_per_mm_y = static_cast<double>(height) / model.lens.sensor_height_mm;
    mapping.centre_x_px = 0.5 * static_cast<double>(width);
    mapping.centre_y_px = 0.5 * static_cast<double>(height);
    // modelGhostsAt folded in half turns; any other roll rotates the loops.
    double turn = std::remainder(roll_deg - model.capture.roll_deg, 360.0);
    if (std::abs(std::abs(turn) - 180.0) < 1e-12) turn = 0.0;
    return renderRotatedGhostStates(states, turn, mapping, width, height, options);
}

bool fittedInColour(const FlareModel& model, bool* recorded) {
    if (recorded) *recorded = !model.capture.raw_format.empty();
    if (!model.capture.raw_format.empty()) {
        const std::optional<hdr::RawFormat> format = hdr::parseRawFormat(model.capture.raw_format);
        return format && hdr::isBayer(*format);  // validateModel refuses other names
    }
    for (const ModelGhost& g : model.ghosts) {
        const auto find = [&](const std::string& name) -> const ModelParameter* {
            for (const ModelParameter& p : g.parameters)
                if (p.name == name) return &p;
            return nullptr;
        };
        for (const char* kind : {"ln_border_rgb", "ln_inner_rgb"}) {
            const ModelParameter* red = find(std::string(kind) + "[0]");
            for (const char* channel : {"[1]", "[2]"}) {
                const ModelParameter* other = find(std::string(kind) + channel);
                if (red && other && red->pieces != other->pieces) return true;
            }
        }
    }
    return false;
}

}  // namespace flarelab::fit
