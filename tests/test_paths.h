// Paths to shipped data for the tests.
#pragma once

#include <string>

namespace flarelab::testing {

inline std::string sourcePath(const std::string& relative) {
    return std::string(FLARELAB_SOURCE_DIR) + "/" + relative;
}

// The lens files flarelab ships (data/lenses/*.csv).
inline const char* const kShippedLenses[] = {
    "canon-tele-zoom-135.csv",
    "canon-tele-zoom-200.csv",
    "double-gauss-tronnier-50mm.csv",
    "heliar-tronnier-paper2023.csv",
    "heliar-tronnier.csv",
    "itoh-wide-zoom.csv",
    "lensbaby-toy.csv",
    "nikon-28-75mm.csv",
    "nikon-tele-zoom.csv",
};

inline std::string lensPath(const std::string& file) { return sourcePath("data/lenses/" + file); }

}  // namespace flarelab::testing
