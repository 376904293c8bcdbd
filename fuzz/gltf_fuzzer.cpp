// Fuzz target: arbitrary bytes as a planner's glTF venue (predict/gltf_import.h), read as GLB when
// they start with the magic "glTF" and as JSON otherwise, then once more in the other mode. A
// refusal must be a ParseError or Unsupported naming the file, in valid UTF-8; never Internal
// (which would mean tinygltf and the document check disagree) and never a file error (nothing is
// read from disk in memory). What is imported must be usable without further checks: finite
// poses in their ranges, unit directions, positive intensities. Nothing may crash, hang, read out
// of bounds or overflow, in our code or in tinygltf as we call it.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <string_view>

#include "common/result.h"
#include "common/utf8.h"
#include "predict/constellation.h"
#include "predict/gltf_import.h"

namespace {

using namespace flarelab;
using namespace flarelab::predict;

const std::string kName = "fuzz.gltf";

void require(bool condition) {
    if (!condition) std::abort();
}

bool finite(const Vec3& v) {
    return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]);
}

bool unit(const Vec3& v) {
    return finite(v) && std::abs(std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) - 1.0) < 1e-9;
}

void checkCamera(const GltfCamera& camera) {
    require(validUtf8(camera.name) && !camera.name.empty());
    const CameraPose& pose = camera.pose;
    require(finite(pose.position_m));
    require(pose.pan_deg >= 0.0 && pose.pan_deg < 360.0);
    require(pose.tilt_deg >= -90.0 && pose.tilt_deg <= 90.0);
    require(pose.roll_deg > -180.0 && pose.roll_deg <= 180.0);
    const CameraFrame frame = cameraFrame(pose);
    require(unit(frame.forward) && unit(frame.right) && unit(frame.up));
    if (camera.type == "perspective") {
        require(camera.yfov_deg.has_value() && *camera.yfov_deg > 0.0 && *camera.yfov_deg < 180.0);
    } else {
        require(camera.type == "orthographic" && !camera.yfov_deg.has_value());
    }
}

void checkLight(const GltfLight& light) {
    require(validUtf8(light.name) && !light.name.empty());
    if (light.type == "directional") {
        require(!light.position_m.has_value() && light.direction.has_value());
        require(unit(*light.direction));
    } else {
        require(light.type == "point" || light.type == "spot");
        require(light.position_m.has_value() && !light.direction.has_value());
        require(finite(*light.position_m));
    }
    for (const double c : light.colour) require(std::isfinite(c) && c >= 0.0);
    require(light.colour[0] > 0.0 || light.colour[1] > 0.0 || light.colour[2] > 0.0);
    require(std::isfinite(light.intensity) && light.intensity > 0.0);
    if (light.range_m) require(std::isfinite(*light.range_m) && *light.range_m > 0.0);
}

void check(const Result<GltfImport>& imported) {
    if (!imported) {
        const Error& error = imported.error();
        require(error.code == ErrorCode::ParseError || error.code == ErrorCode::Unsupported);
        require(error.message.size() > kName.size() + 2);
        require(error.message.compare(0, kName.size() + 2, kName + ": ") == 0);
        require(validUtf8(error.message));
        return;
    }
    for (const GltfCamera& camera : imported->cameras) checkCamera(camera);
    for (const GltfLight& light : imported->lights) checkLight(light);
    for (const std::string& note : imported->notes) require(!note.empty() && validUtf8(note));
    // An empty list is always explained.
    if (imported->cameras.empty() || imported->lights.empty()) require(!imported->notes.empty());
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);
    const bool glb = bytes.substr(0, 4) == "glTF";
    check(importGltfFromMemory(bytes, kName, glb));
    check(importGltfFromMemory(bytes, kName, !glb));
    return 0;
}
