// The shipped lenses the tests load again and again, made once per test binary.
#pragma once

#include "optics/prescription.h"
#include "tests/test_paths.h"

namespace flarelab::testing {

// The Heliar (data/lenses/heliar-tronnier.csv) as its file describes it, default camera.
inline const optics::Lens& heliar() {
    static const optics::Lens lens = *optics::Lens::make(
        *optics::loadPrescription(lensPath("heliar-tronnier.csv")), optics::CameraDescription{});
    return lens;
}

}  // namespace flarelab::testing
