// Fuzz target: arbitrary bytes as the --time of `flarelab sun` (predict/utc_time.h). What parses
// must format and parse back to the same instant, and the sun at that instant must be a finite
// position or a clear InvalidArgument (a year outside -2000..6000); nothing may crash, hang, read
// out of bounds or overflow.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string_view>

#include "predict/sun.h"
#include "predict/utc_time.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace flarelab::predict;
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    auto instant = parseIso8601(text);
    if (!instant) {
        if (instant.error().message.empty()) std::abort();
        return 0;
    }
    auto again = parseIso8601(formatIso8601(*instant));
    if (!again || *again != *instant) std::abort();

    SunSite site;
    site.latitude_deg = 39.742476;
    site.longitude_deg = -105.1786;
    site.elevation_m = 1830.14;
    auto sun = sunPosition(site, *instant);
    if (!sun) {
        if (sun.error().code != flarelab::ErrorCode::InvalidArgument) std::abort();
        return 0;
    }
    if (!std::isfinite(sun->zenith_deg) || sun->zenith_deg < 0.0 || sun->zenith_deg > 180.0 ||
        !(sun->azimuth_deg >= 0.0 && sun->azimuth_deg < 360.0))
        std::abort();
    return 0;
}
