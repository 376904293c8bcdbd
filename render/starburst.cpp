#include "render/starburst.h"

#include <fftw3.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <vector>

namespace flarelab::render {
namespace {

bool isPowerOfTwo(int n) { return n > 0 && (n & (n - 1)) == 0; }

Error invalid(const std::string& field, const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "starburst option " + field + ": " + what);
}

// The FFTW planner is not thread-safe; execution is. One lock serializes planning and
// destruction for every caller in the process.
std::mutex& fftwPlannerMutex() {
    static std::mutex mutex;
    return mutex;
}

struct FftwFree {
    void operator()(void* p) const { fftwf_free(p); }
};

// The wavelengths sampled for channel c, in nanometres.
std::vector<double> bandWavelengths(const StarburstOptions& options, int c) {
    std::vector<double> bands;
    const int n = options.bands_per_channel;
    for (int b = 0; b < n; ++b)
        bands.push_back(options.wavelengths_nm[c] + options.band_width_nm * ((b + 0.5) / n - 0.5));
    return bands;
}

double referenceWavelength(const StarburstOptions& options) {
    double shortest = options.wavelengths_nm[0];
    for (int c = 0; c < 3; ++c)
        for (double lambda : bandWavelengths(options, c)) shortest = std::min(shortest, lambda);
    return shortest;
}

// Transmission of the clean aperture, area-averaged over each mask sample: 4 x 4 subsamples where
// the edge passes through the sample, a single test elsewhere. edgeRatio grows at most 1/apothem
// per stop radius, so a sample whose centre is further than its half-diagonal from the edge (in
// that measure) lies entirely on one side.
std::vector<float> rasterizeAperture(const optics::ApertureShape& shape, int n) {
    std::vector<float> mask(static_cast<size_t>(n) * n, 0.0f);
    const double pitch = 2.0 / n;  // stop radii per sample
    const double apothem = shape.blades >= 3 ? std::cos(kPi / shape.blades) : 1.0;
    const double margin = 0.75 * pitch / apothem;  // > half-diagonal (0.707 pitch) / apothem
    constexpr int kSub = 4;
    for (int j = 0; j < n; ++j) {
        const double v = -1.0 + (j + 0.5) * pitch;
        for (int i = 0; i < n; ++i) {
            const double u = -1.0 + (i + 0.5) * pitch;
            const double ratio = shape.edgeRatio(u, v);
            float value = 0.0f;
            if (ratio < 1.0 - margin) {
                value = 1.0f;
            } else if (ratio <= 1.0 + margin) {
                int inside = 0;
                for (int sj = 0; sj < kSub; ++sj)
                    for (int si = 0; si < kSub; ++si)
                        inside += shape.contains(u + ((si + 0.5) / kSub - 0.5) * pitch,
                                                 v + ((sj + 0.5) / kSub - 0.5) * pitch);
                value = static_cast<float>(inside) / (kSub * kSub);
            }
            mask[static_cast<size_t>(j) * n + i] = value;
        }
    }
    return mask;
}

// Multiplies the mask by (1 - coverage) of an opaque region given by `blocks(u, v)` over the
// samples of the box [u0, u1] x [v0, v1] (stop radii), coverage from 4 x 4 subsamples.
template <typename Blocks>
void blockRegion(std::vector<float>& mask,
                 int n,
                 double u0,
                 double u1,
                 double v0,
                 double v1,
                 const Blocks& blocks) {
    const double pitch = 2.0 / n;
    const auto index = [&](double x) {
        return static_cast<int>(std::clamp(std::floor((x + 1.0) / pitch), 0.0, n - 1.0));
    };
    constexpr int kSub = 4;
    for (int j = index(v0); j <= index(v1); ++j) {
        for (int i = index(u0); i <= index(u1); ++i) {
            int covered = 0;
            for (int sj = 0; sj < kSub; ++sj)
                for (int si = 0; si < kSub; ++si)
                    covered += blocks(-1.0 + (i + (si + 0.5) / kSub) * pitch,
                                      -1.0 + (j + (sj + 0.5) / kSub) * pitch);
            mask[static_cast<size_t>(j) * n + i] *=
                1.0f - static_cast<float>(covered) / (kSub * kSub);
        }
    }
}

// Dust and scratches, drawn from one seeded generator in a fixed order.
void addDirt(std::vector<float>& mask, int n, const StarburstOptions& options) {
    std::mt19937_64 rng(options.seed);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    const auto pointInStop = [&]() {
        const double r = std::sqrt(unit(rng)), a = 2.0 * kPi * unit(rng);
        return std::array<double, 2>{r * std::cos(a), r * std::sin(a)};
    };
    for (int k = 0; k < options.dust_count; ++k) {
        const auto c = pointInStop();
        const double radius = options.dust_radius_min +
                              (options.dust_radius_max - options.dust_radius_min) * unit(rng);
        blockRegion(mask, n, c[0] - radius, c[0] + radius, c[1] - radius, c[1] + radius,
                    [&](double u, double v) {
                        const double du = u - c[0], dv = v - c[1];
                        return du * du + dv * dv <= radius * radius;
                    });
    }
    for (int k = 0; k < options.scratch_count; ++k) {
        const auto c = pointInStop();
        const double angle = kPi * unit(rng);
        const double half_length =
            0.5 * (options.scratch_length_min +
                   (options.scratch_length_max - options.scratch_length_min) * unit(rng));
        const double half_width = 0.5 * options.scratch_width;
        const double du = std::cos(angle), dv = std::sin(angle);
        const double reach_u = std::abs(du) * half_length + half_width;
        const double reach_v = std::abs(dv) * half_length + half_width;
        blockRegion(mask, n, c[0] - reach_u, c[0] + reach_u, c[1] - reach_v, c[1] + reach_v,
                    [&](double u, double v) {
                        const double along = (u - c[0]) * du + (v - c[1]) * dv;
                        const double across = -(u - c[0]) * dv + (v - c[1]) * du;
                        return std::abs(along) <= half_length && std::abs(across) <= half_width;
                    });
    }
}

// |FFT|^2 of the zero-padded mask, centred: element (y, x) is frequency (x - m/2, y - m/2).
Result<std::vector<float>> powerSpectrum(const std::vector<float>& mask, int n, int m) {
    const size_t real_count = static_cast<size_t>(m) * m;
    const size_t half = static_cast<size_t>(m / 2 + 1);
    std::unique_ptr<float, FftwFree> in(
        static_cast<float*>(fftwf_malloc(sizeof(float) * real_count)));
    std::unique_ptr<fftwf_complex, FftwFree> out(
        static_cast<fftwf_complex*>(fftwf_malloc(sizeof(fftwf_complex) * m * half)));
    if (!in || !out) return makeError(ErrorCode::Internal, "starburst: out of memory for the FFT");
    fftwf_plan plan = nullptr;
    {
        const std::lock_guard lock(fftwPlannerMutex());
        plan = fftwf_plan_dft_r2c_2d(m, m, in.get(), out.get(), FFTW_ESTIMATE);
    }
    if (plan == nullptr) return makeError(ErrorCode::Internal, "starburst: FFTW planning failed");
    // Planning may scribble on the arrays: fill the input afterwards.
    std::fill(in.get(), in.get() + real_count, 0.0f);
    for (int j = 0; j < n; ++j)
        std::copy_n(mask.data() + static_cast<size_t>(j) * n, n,
                    in.get() + static_cast<size_t>(j) * m);
    fftwf_execute(plan);
    {
        const std::lock_guard lock(fftwPlannerMutex());
        fftwf_destroy_plan(plan);
    }
    std::vector<float> power(real_count);
    for (int y = 0; y < m; ++y) {
        for (int x = 0; x < m; ++x) {
            int kx = x - m / 2, ky = y - m / 2;
            // A real input's spectrum is conjugate-symmetric: F(-k) = conj F(k).
            if (kx < 0) {
                kx = -kx;
                ky = -ky;
            }
            const size_t row = static_cast<size_t>((ky % m + m) % m);
            const fftwf_complex& f = out.get()[row * half + static_cast<size_t>(kx)];
            power[static_cast<size_t>(y) * m + x] = f[0] * f[0] + f[1] * f[1];
        }
    }
    return power;
}

// Bilinear sample of an m x m array at continuous index (x, y), zero outside.
float sampleBilinear(const std::vector<float>& a, int m, double x, double y) {
    const double fx = std::floor(x), fy = std::floor(y);
    const int x0 = static_cast<int>(fx), y0 = static_cast<int>(fy);
    const double tx = x - fx, ty = y - fy;
    double sum = 0.0;
    for (int dy = 0; dy < 2; ++dy) {
        for (int dx = 0; dx < 2; ++dx) {
            const int xi = x0 + dx, yi = y0 + dy;
            if (xi < 0 || yi < 0 || xi >= m || yi >= m) continue;
            const double w = (dx ? tx : 1.0 - tx) * (dy ? ty : 1.0 - ty);
            sum += w * a[static_cast<size_t>(yi) * m + xi];
        }
    }
    return static_cast<float>(sum);
}

}  // namespace

Status validateStarburstOptions(const StarburstOptions& o) {
    if (o.aperture.blades < 0 || o.aperture.blades == 1 || o.aperture.blades == 2 ||
        o.aperture.blades > 64)
        return invalid("aperture.blades",
                       "must be 0 (circle) or 3..64, got " + std::to_string(o.aperture.blades));
    if (!std::isfinite(o.aperture.rotation_rad))
        return invalid("aperture.rotation_rad", "must be finite");
    if (!isPowerOfTwo(o.mask_size) || o.mask_size < 16 || o.mask_size > 2048)
        return invalid("mask_size",
                       "must be a power of two in 16..2048, got " + std::to_string(o.mask_size));
    if (!isPowerOfTwo(o.fft_size) || o.fft_size < 2 * o.mask_size || o.fft_size > 4096)
        return invalid("fft_size", "must be a power of two in 2 * mask_size (" +
                                       std::to_string(2 * o.mask_size) + ")..4096, got " +
                                       std::to_string(o.fft_size));
    for (int c = 0; c < 3; ++c)
        if (!(o.wavelengths_nm[c] >= 200.0 && o.wavelengths_nm[c] <= 3000.0))
            return invalid("wavelengths_nm[" + std::to_string(c) + "]",
                           "must be in 200..3000 nm, got " + std::to_string(o.wavelengths_nm[c]));
    if (o.bands_per_channel < 1 || o.bands_per_channel > 16)
        return invalid("bands_per_channel",
                       "must be in 1..16, got " + std::to_string(o.bands_per_channel));
    if (!(o.band_width_nm >= 0.0 && o.band_width_nm <= 200.0))
        return invalid("band_width_nm",
                       "must be in 0..200 nm, got " + std::to_string(o.band_width_nm));
    if (o.dust_count < 0 || o.dust_count > 10000)
        return invalid("dust_count", "must be in 0..10000, got " + std::to_string(o.dust_count));
    if (!(o.dust_radius_min > 0.0 && o.dust_radius_min <= o.dust_radius_max &&
          o.dust_radius_max <= 1.0))
        return invalid("dust_radius_min/max", "need 0 < min <= max <= 1 (stop radii), got " +
                                                  std::to_string(o.dust_radius_min) + ", " +
                                                  std::to_string(o.dust_radius_max));
    if (o.scratch_count < 0 || o.scratch_count > 1000)
        return invalid("scratch_count",
                       "must be in 0..1000, got " + std::to_string(o.scratch_count));
    if (!(o.scratch_width > 0.0 && o.scratch_width <= 1.0))
        return invalid("scratch_width",
                       "must be in (0, 1] stop radii, got " + std::to_string(o.scratch_width));
    if (!(o.scratch_length_min > 0.0 && o.scratch_length_min <= o.scratch_length_max &&
          o.scratch_length_max <= 4.0))
        return invalid("scratch_length_min/max", "need 0 < min <= max <= 4 (stop radii), got " +
                                                     std::to_string(o.scratch_length_min) + ", " +
                                                     std::to_string(o.scratch_length_max));
    return Ok{};
}

double starburstPixelAngle(const StarburstOptions& options, double aperture_diameter_mm) {
    FLARELAB_CHECK_GT(aperture_diameter_mm, 0.0);
    const double lambda_mm = referenceWavelength(options) * 1e-6;
    return lambda_mm * options.mask_size / (options.fft_size * aperture_diameter_mm);
}

Result<ImageRGB> renderStarburst(const StarburstOptions& options) {
    if (Status valid = validateStarburstOptions(options); !valid) return valid.error();
    const int n = options.mask_size, m = options.fft_size;
    std::vector<float> mask = rasterizeAperture(options.aperture, n);
    addDirt(mask, n, options);
    double open = 0.0;
    for (float x : mask) open += x;
    if (!(open > 0.0))
        return makeError(ErrorCode::Internal,
                         "starburst: dust and scratches block the whole aperture");

    Result<std::vector<float>> power = powerSpectrum(mask, n, m);
    if (!power) return power.error();

    // Each band is resampled so that its rings sit at lambda / lambda_ref times the reference
    // radius, normalized to unit energy (every band carries the same power), and averaged.
    const double lambda_ref = referenceWavelength(options);
    ImageRGB pattern(m, m);
    std::vector<float> band(static_cast<size_t>(m) * m);
    for (int c = 0; c < 3; ++c) {
        const std::vector<double> lambdas = bandWavelengths(options, c);
        for (double lambda : lambdas) {
            const double shrink = lambda_ref / lambda;  // <= 1: reads bins inside the spectrum
            tbb::parallel_for(tbb::blocked_range<int>(0, m), [&](const tbb::blocked_range<int>& r) {
                for (int y = r.begin(); y < r.end(); ++y)
                    for (int x = 0; x < m; ++x)
                        band[static_cast<size_t>(y) * m + x] = sampleBilinear(
                            *power, m, m / 2 + (x - m / 2) * shrink, m / 2 + (y - m / 2) * shrink);
            });
            // The spectrum's domain is a square, but a lens's starburst has no corners: fade the
            // pattern to zero between 70 % and 100 % of the inscribed circle (a raised cosine),
            // so its edge never shows however bright the light. The tail cut off holds about 1 %
            // of the power of a round stop; normalization below gives it back to the rest.
            const double edge = 0.5 * m, fade_start = 0.7 * edge;
            for (int y = 0; y < m; ++y) {
                for (int x = 0; x < m; ++x) {
                    const double r = std::hypot(x - m / 2, y - m / 2);
                    if (r <= fade_start) continue;
                    const double t = std::min(1.0, (r - fade_start) / (edge - fade_start));
                    band[static_cast<size_t>(y) * m + x] *=
                        static_cast<float>(0.5 * (1.0 + std::cos(kPi * t)));
                }
            }
            double total = 0.0;
            for (float x : band) total += x;
            if (!(total > 0.0) || !std::isfinite(total))
                return makeError(ErrorCode::Internal,
                                 "starburst: diffraction pattern has no energy");
            const double weight = 1.0 / (total * static_cast<double>(lambdas.size()));
            for (size_t i = 0; i < band.size(); ++i)
                pattern.pixels[i * 3 + c] += static_cast<float>(band[i] * weight);
        }
    }
    // Renormalize in double: float accumulation leaves each channel a few ulps off 1.
    for (int c = 0; c < 3; ++c) {
        double total = 0.0;
        for (size_t i = 0; i < band.size(); ++i) total += pattern.pixels[i * 3 + c];
        for (size_t i = 0; i < band.size(); ++i)
            pattern.pixels[i * 3 + c] = static_cast<float>(pattern.pixels[i * 3 + c] / total);
    }
    return pattern;
}

void addStarburst(ImageRGB& image,
                  const ImageRGB& pattern,
                  double centre_x_px,
                  double centre_y_px,
                  const float rgb_intensity[3],
                  double scale) {
    FLARELAB_CHECK(std::isfinite(scale) && scale > 0.0);
    FLARELAB_CHECK(std::isfinite(centre_x_px) && std::isfinite(centre_y_px));
    for (int c = 0; c < 3; ++c) FLARELAB_CHECK(std::isfinite(rgb_intensity[c]));
    if (image.empty() || pattern.empty()) return;

    // The pattern's zero angle is the centre of its pixel (width / 2, height / 2).
    const double pcx = static_cast<double>(pattern.width / 2) + 0.5;
    const double pcy = static_cast<double>(pattern.height / 2) + 0.5;
    // Image pixels the magnified pattern can reach (one extra for the bilinear support), clamped
    // in double before conversion so that a far-away centre cannot overflow an index.
    const auto range = [&](double centre, double pc, int64_t pattern_size, int64_t image_size) {
        const double lo = std::floor(centre - pc * scale) - 1.0;
        const double hi =
            std::ceil(centre + (static_cast<double>(pattern_size) - pc) * scale) + 1.0;
        const double last = static_cast<double>(image_size - 1);
        return std::array<int64_t, 2>{static_cast<int64_t>(std::clamp(lo, 0.0, last)),
                                      static_cast<int64_t>(std::clamp(hi, -1.0, last))};
    };
    if (scale < 1.0) {
        // Pattern pixels smaller than image pixels: sampling the pattern at pixel centres would
        // skip most of its samples (and the energy they hold), so each pattern sample is spread
        // instead over the four image pixels around its position, with bilinear weights that sum
        // to 1: the energy added is exactly the pattern's inside the image.
        for (int64_t j = 0; j < pattern.height; ++j) {
            const double v = centre_y_px + (static_cast<double>(j) + 0.5 - pcy) * scale - 0.5;
            const double fy = std::floor(v);
            const double ty = v - fy;
            if (fy + 1.0 < 0.0 || fy > static_cast<double>(image.height - 1)) continue;
            for (int64_t i = 0; i < pattern.width; ++i) {
                const double u = centre_x_px + (static_cast<double>(i) + 0.5 - pcx) * scale - 0.5;
                const double fx = std::floor(u);
                const double tx = u - fx;
                if (fx + 1.0 < 0.0 || fx > static_cast<double>(image.width - 1)) continue;
                const float* p = pattern.at(i, j);
                for (int dy = 0; dy < 2; ++dy) {
                    const double yi = fy + dy;
                    if (yi < 0.0 || yi > static_cast<double>(image.height - 1)) continue;
                    for (int dx = 0; dx < 2; ++dx) {
                        const double xi = fx + dx;
                        if (xi < 0.0 || xi > static_cast<double>(image.width - 1)) continue;
                        const double w = (dx ? tx : 1.0 - tx) * (dy ? ty : 1.0 - ty);
                        float* out = image.at(static_cast<int64_t>(xi), static_cast<int64_t>(yi));
                        for (int c = 0; c < 3; ++c)
                            out[c] += static_cast<float>(w * p[c] * rgb_intensity[c]);
                    }
                }
            }
        }
        return;
    }
    const auto xs = range(centre_x_px, pcx, pattern.width, image.width);
    const auto ys = range(centre_y_px, pcy, pattern.height, image.height);
    const double area = 1.0 / (scale * scale);
    for (int64_t y = ys[0]; y <= ys[1]; ++y) {
        // Continuous pattern coordinate of this pixel's centre, then the sample index (- 0.5).
        const double sy = pcy + (static_cast<double>(y) + 0.5 - centre_y_px) / scale - 0.5;
        const double fy = std::floor(sy);
        const double ty = sy - fy;
        for (int64_t x = xs[0]; x <= xs[1]; ++x) {
            const double sx = pcx + (static_cast<double>(x) + 0.5 - centre_x_px) / scale - 0.5;
            const double fx = std::floor(sx);
            const double tx = sx - fx;
            double rgb[3] = {0.0, 0.0, 0.0};
            for (int dy = 0; dy < 2; ++dy) {
                const double yi = fy + dy;
                if (yi < 0.0 || yi >= static_cast<double>(pattern.height)) continue;
                for (int dx = 0; dx < 2; ++dx) {
                    const double xi = fx + dx;
                    if (xi < 0.0 || xi >= static_cast<double>(pattern.width)) continue;
                    const double w = (dx ? tx : 1.0 - tx) * (dy ? ty : 1.0 - ty);
                    const float* p = pattern.at(static_cast<int64_t>(xi), static_cast<int64_t>(yi));
                    for (int c = 0; c < 3; ++c) rgb[c] += w * p[c];
                }
            }
            float* out = image.at(x, y);
            for (int c = 0; c < 3; ++c)
                out[c] += static_cast<float>(rgb[c] * area * rgb_intensity[c]);
        }
    }
}

}  // namespace flarelab::render
