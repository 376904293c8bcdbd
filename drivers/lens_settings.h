// ============================================================================
//  flarelab drivers: describeLens, RebuiltLens, rebuildLens
// ============================================================================
//
// A simulated capture's lens, recorded and built again. A simulated frame depends on more than
// the prescription, f-number and focal length: the aperture blades and their rotation, the stop
// semi-aperture the lens really used (scaled for the f-number, or the table's), whether surfaces
// the prescription gives no coating got the default one, and the sensor size. The sweep manifest
// records them (hdr/sweep.h, format version 3), the model copies them (fit/model_file.h, version
// 2), and `flarelab score` simulates that same lens again, so that a capture taken with six
// blades is scored against a six-bladed truth. `flarelab capture` and the daemon record with
// describeLens; `flarelab score` and `flarelab fit --lens` build the lens with rebuildLens.
#pragma once

#include <string>
#include <vector>

#include "common/result.h"
#include "fit/model_file.h"
#include "hdr/sweep.h"
#include "optics/lens.h"
#include "optics/prescription.h"

namespace flarelab::drivers {

// The lens as a sweep records it: its name, the f-number and focal length its camera resolved,
// the aperture blades and their rotation, the stop semi-aperture it uses, the coating choice and
// the sensor size. Serial, prescription file and digest are left empty: the Lens does not know
// them.
hdr::SweepLens describeLens(const optics::Lens& lens);

struct RebuiltLens {
    optics::Lens lens;
    // The settings the record lacks (an older sweep or model), each with what was assumed in its
    // place: "aperture blades (assumed a circular stop)". Empty when every one was recorded.
    std::vector<std::string> assumed;
};

// `prescription` with the camera settings `recorded` holds: f-number, focal length, sensor size,
// aperture blades and rotation, coating choice, and last the exact stop semi-aperture (which
// overrides the f-number's scaling, as Lens::withStopSemiAperture does). A setting not recorded
// takes what `flarelab capture` takes without its flag: the file's labels for f-number and focal
// length, a circular stop, the stop scaled for the f-number, bare unspecified surfaces. Errors:
// settings the optics refuse (Lens::make), naming the prescription.
Result<RebuiltLens> rebuildLens(const optics::Prescription& prescription,
                                const fit::ModelLens& recorded);

}  // namespace flarelab::drivers
