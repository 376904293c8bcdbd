#include "render/metrics.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace flarelab::render {

Result<double> psnr(const ImageRGB& test, const ImageRGB& reference) {
    const auto invalid = [](const char* what) {
        return makeError(ErrorCode::InvalidArgument, std::string("psnr: ") + what);
    };
    if (test.width != reference.width || test.height != reference.height)
        return invalid("the images differ in size");
    if (reference.empty()) return invalid("the images are empty");
    double peak = 0.0, squared = 0.0;
    for (size_t i = 0; i < reference.pixels.size(); ++i) {
        const double r = reference.pixels[i], t = test.pixels[i];
        if (!std::isfinite(r) || !std::isfinite(t))
            return invalid("an image holds a non-finite value");
        peak = std::max(peak, r);
        squared += (t - r) * (t - r);
    }
    if (!(peak > 0.0)) return invalid("the reference has no positive value");
    if (squared == 0.0) return std::numeric_limits<double>::infinity();
    const double mse = squared / static_cast<double>(reference.pixels.size());
    return 10.0 * std::log10(peak * peak / mse);
}

double imageSum(const ImageRGB& image) {
    double sum = 0.0;
    for (const float v : image.pixels) sum += v;
    return sum;
}

}  // namespace flarelab::render
