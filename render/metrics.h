// ============================================================================
//  flarelab render: psnr, imageSum
// ============================================================================
//
// How far one rendering is from another. PSNR on linear values: 10 log10(peak^2 / MSE), the peak
// being the largest value of the reference and the mean taken over every channel of every pixel.
// Renderings are HDR, so the peak is whatever the brightest ghost reaches; compare images without
// the starburst when the ghosts are what is measured (its peak would dwarf them).
#pragma once

#include "common/image.h"
#include "common/result.h"

namespace flarelab::render {

// InvalidArgument for images of different sizes, an empty image, a non-finite value in either,
// or a reference with no positive value. Identical images give +infinity.
Result<double> psnr(const ImageRGB& test, const ImageRGB& reference);

// The sum of every channel of every pixel (double), for energy checks.
double imageSum(const ImageRGB& image);

}  // namespace flarelab::render
