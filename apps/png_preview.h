// The optional tone-mapped PNG beside a command's HDR output (simulate, merge, model render).
#pragma once

#include <optional>
#include <ostream>
#include <string>

#include "common/image.h"
#include "render/preview.h"

namespace flarelab::apps {

// Writes `image` to `png_path` when a path is given, at `exposure_stops`, or, when none is given,
// at render::autoExposureStops (said on `out`, so that the next preview can be given the same);
// false (with the error on `err`) when writing fails.
inline bool writePngPreview(const ImageRGB& image,
                            const std::string& png_path,
                            std::optional<double> exposure_stops,
                            std::ostream& out,
                            std::ostream& err) {
    if (png_path.empty()) return true;
    render::ToneMapOptions tone;
    if (exposure_stops) {
        tone.exposure_stops = *exposure_stops;
    } else {
        tone.exposure_stops = render::autoExposureStops(image);
        out << "PNG exposure " << tone.exposure_stops
            << " stops (automatic: the 99th percentile of lit pixels at mid-grey; "
               "--exposure-stops sets it)\n";
    }
    if (Status ok = render::writePng(image, png_path, tone); !ok) {
        err << "flarelab: " << ok.error().message << "\n";
        return false;
    }
    return true;
}

}  // namespace flarelab::apps
