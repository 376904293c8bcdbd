// ============================================================================
//  flarelab command line: CameraFlags, addCameraFlags, loadLens
// ============================================================================
//
// The flags every command that uses a lens shares (f-number, focal length, sensor, blades), and
// loading a lens file with them applied. Errors go to the given stream, prefixed "flarelab: ".
#pragma once

#include <CLI/CLI.hpp>
#include <optional>
#include <ostream>
#include <string>

#include "optics/lens.h"
#include "optics/prescription.h"

namespace flarelab::apps {

struct CameraFlags {
    double focal_mm = 0.0;
    double f_number = 0.0;
    std::string sensor = "36x24";
    int blades = 0;
    double blade_rotation_deg = 0.0;
    bool table_stop = false;
    bool coat_unspecified = false;
};

void addCameraFlags(CLI::App* cmd, CameraFlags& flags);

// "36x24" (or "36X24") as width and height in mm; false when it is not WIDTHxHEIGHT.
bool parseSensorMm(const std::string& text, double& width_mm, double& height_mm);

// Loads the lens file and applies the camera flags; on failure writes the error to `err`.
// The same for a prescription already loaded.
std::optional<optics::Lens> makeLens(const optics::Prescription& prescription,
                                     const CameraFlags& flags,
                                     std::ostream& err);

std::optional<optics::Lens> loadLens(const std::string& path,
                                     const CameraFlags& flags,
                                     std::ostream& err);

}  // namespace flarelab::apps
