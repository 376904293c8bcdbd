// ============================================================================
//  flarelab common: ImageRGB
// ============================================================================
//
// The value type every renderer writes and every writer reads: linear relative radiance, float32,
// three channels (red, green, blue) interleaved, rows top to bottom. Image space follows DESIGN.md:
// origin top-left, x right, y down, pixel centres at half-integers; the optical axis hits the
// image centre. Pixel offsets are int64_t so that no image size can overflow them.
#pragma once

#include <cstdint>
#include <vector>

#include "common/check.h"
#include "common/large_pages.h"

namespace flarelab {

struct ImageRGB {
    int64_t width = 0;
    int64_t height = 0;
    std::vector<float> pixels;  // width * height * 3, RGB interleaved, row-major

    ImageRGB() = default;
    // Zeroed; a large image's storage on large pages (common/large_pages.h).
    ImageRGB(int64_t w, int64_t h) : width(w), height(h) {
        FLARELAB_CHECK_GE(w, 0);
        FLARELAB_CHECK_GE(h, 0);
        const size_t n = static_cast<size_t>(w * h * 3);
        reserveLargePages(pixels, n);
        pixels.resize(n);
    }
    float* at(int64_t x, int64_t y) {
        FLARELAB_DCHECK(x >= 0 && x < width && y >= 0 && y < height);
        return pixels.data() + (y * width + x) * 3;
    }
    const float* at(int64_t x, int64_t y) const {
        FLARELAB_DCHECK(x >= 0 && x < width && y >= 0 && y < height);
        return pixels.data() + (y * width + x) * 3;
    }
    bool empty() const { return width == 0 || height == 0; }
};

}  // namespace flarelab
