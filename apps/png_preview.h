// The optional tone-mapped PNG beside a command's HDR output (simulate, merge, model render).
#pragma once

#include <ostream>
#include <string>

#include "common/image.h"
#include "render/preview.h"

namespace flarelab::apps {

// Writes `image` to `png_path` at `exposure_stops` when a path is given; false (with the error on
// `err`) when writing fails.
inline bool writePngPreview(const ImageRGB& image,
                            const std::string& png_path,
                            double exposure_stops,
                            std::ostream& err) {
    if (png_path.empty()) return true;
    render::ToneMapOptions tone;
    tone.exposure_stops = exposure_stops;
    if (Status ok = render::writePng(image, png_path, tone); !ok) {
        err << "flarelab: " << ok.error().message << "\n";
        return false;
    }
    return true;
}

}  // namespace flarelab::apps
