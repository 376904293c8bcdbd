// ============================================================================
//  flarelab render: StarburstOptions, renderStarburst, addStarburst
// ============================================================================
//
// The starburst around a bright light: the Fraunhofer diffraction pattern of the aperture. In the
// far field the amplitude at angle theta is the Fourier transform of the aperture function at
// spatial frequency theta / lambda, so the pattern is |FFT|^2 of the aperture mask, stretched in
// angle in proportion to the wavelength. Dust dots and scratch lines on the mask add the faint
// rings and streaks a real lens shows (as in the course report on physically based lens flare).
//
// renderStarburst rasterizes the mask (the aperture's circumscribed circle spans mask_size
// samples), zero-pads it to fft_size, transforms it with FFTW and resamples |FFT|^2 once per
// wavelength band. The reference wavelength lambda_ref is the shortest wavelength sampled (the
// shortest channel's wavelength, or its lowest band when channels have several): there one
// pattern pixel is one FFT bin, an angle of
//     lambda_ref / (fft_size / mask_size * D)   radians (D: aperture diameter),
// and a longer wavelength lambda reads bin r * lambda_ref / lambda at pattern radius r, so its
// rings lie lambda / lambda_ref times further out. The pattern is fft_size x fft_size with the
// zero angle at the centre of pixel (fft_size / 2, fft_size / 2), faded to zero towards the
// edge of its inscribed circle so that the square domain never shows; each channel sums to 1, so
// the caller scales it by the light's intensity.
#pragma once

#include <array>
#include <cstdint>

#include "common/image.h"
#include "common/result.h"
#include "common/units.h"
#include "optics/aperture.h"

namespace flarelab::render {

struct StarburstOptions {
    optics::ApertureShape aperture;  // circle or n-blade polygon, stop-normalized
    int mask_size = 512;             // samples across the stop's diameter: power of two, 16..2048
    int fft_size = 1024;             // power of two, 2 * mask_size .. 4096
    // Wavelength of the red, green and blue channel, each in 200..3000 nm.
    std::array<double, 3> wavelengths_nm = {kLambdaRed_nm, kLambdaGreen_nm, kLambdaBlue_nm};
    // Wavelengths averaged per channel (1..16; more soften the rings), at the centres of equal
    // parts of [lambda - band_width_nm / 2, lambda + band_width_nm / 2]; the width is 0..200 nm.
    int bands_per_channel = 1;
    double band_width_nm = 60.0;
    // Dust: opaque discs centred uniformly in the stop; radii in stop radii, 0 < min <= max <= 1.
    int dust_count = 0;  // 0..10000
    double dust_radius_min = 0.005;
    double dust_radius_max = 0.02;
    // Scratches: opaque straight lines through random points of the stop at random angles;
    // width and length in stop radii.
    int scratch_count = 0;            // 0..1000
    double scratch_width = 0.004;     // in (0, 1]
    double scratch_length_min = 0.3;  // 0 < min <= max <= 4
    double scratch_length_max = 1.0;
    uint64_t seed = 1;  // the same options draw the same dust and scratches
};

// InvalidArgument naming the field when an option is outside its documented range.
Status validateStarburstOptions(const StarburstOptions& options);

// The angle one pattern pixel spans, in radians, for a stop (entrance pupil) of the given
// diameter in millimetres: lambda_ref / (fft_size / mask_size * D) with lambda_ref as above.
// The options must be valid. The caller turns it into addStarburst's scale with its pixels per
// radian.
double starburstPixelAngle(const StarburstOptions& options, double aperture_diameter_mm);

// The normalized pattern described above, or InvalidArgument for bad options, or Internal when
// dust and scratches block the whole aperture (no light, nothing to normalize).
Result<ImageRGB> renderStarburst(const StarburstOptions& options);

// Adds pattern * rgb_intensity to `image`, centred at (centre_x_px, centre_y_px) in image space
// (pixel centres at half-integers; the centre may lie outside the image), magnified by `scale`
// image pixels per pattern pixel. Magnified (scale >= 1) the pattern is sampled bilinearly at
// pixel centres and divided by scale^2; reduced (scale < 1), each pattern sample is spread over the
// four image pixels around it with bilinear weights. Either way the energy added per channel
// equals the intensity times the part of the pattern inside the image (reduced: exactly;
// magnified: to the accuracy of bilinear sampling).
// Contract: scale > 0 and all values finite (checked); intensities >= 0.
void addStarburst(ImageRGB& image,
                  const ImageRGB& pattern,
                  double centre_x_px,
                  double centre_y_px,
                  const float rgb_intensity[3],
                  double scale);

}  // namespace flarelab::render
