// ============================================================================
//  flarelab predict: GltfCamera, GltfLight, GltfImport, importGltf, importGltfFromMemory
// ============================================================================
//
// A venue from a planner's 3D tool: the cameras and the punctual lights (KHR_lights_punctual) of a
// glTF 2.0 file, placed in flarelab's world frame, so that a scene need not be typed by hand.
// Meshes, materials, images and animations are not read; images are never loaded or decoded.
//
// Frames. glTF is right-handed, Y up, in metres; a camera looks along its node's -Z with +Y up
// and +X to the right of its image, and a light shines along its node's -Z. flarelab's world
// (predict/constellation.h) is x east, y north, z up. The import maps a glTF point (x, y, z) to
//
//     east = x,   north = -z,   up = y
//
// so a glTF scene's -Z is north and its +X east (a rotation: no mirror). A camera's pose is the
// pan, tilt and roll whose cameraFrame() has the node's -Z as forward and +Y as up; one looking
// straight up or down gets roll 0 and the pan that turns its up vector into place. Pan comes out
// in [0, 360), tilt in [-90, 90], roll in (-180, 180].
//
// Which nodes. The default scene's (the file's "scene"), else scene 0's, else, with no scenes,
// every node that is no other node's child; transforms (a matrix, or translation, rotation as a
// quaternion, scale) compose from the root down. A camera or light is imported once for every
// node in the scene that refers to it, in depth-first order from the scene's roots.
//
// Lights. KHR_lights_punctual's units: point and spot lights in candela, directional lights in
// lux; colour is linear RGB. A point or spot light stands at its node's origin; a directional
// light's `direction` is the unit vector towards the light, the node's +Z. A spot light's cone
// is not modelled: it is imported as a point light, and a note says so.
//
// Refused, as ParseError naming the file and the field or node ("venue.gltf: nodes[3].children[0]:
// node index 9 out of range (5 nodes)"): what is not JSON or GLB, a key given twice, nesting
// deeper than kGltfMaxJsonDepth, a field of the wrong type or length, an index out of range (a
// node's camera or light, a child, a scene's node), a node that is the child of two nodes or of
// itself, a cycle, nodes nested deeper than kGltfMaxNodeDepth, a matrix that is not affine, a
// zero quaternion, a world transform that overflows, a negative intensity or colour, a range
// <= 0, a field of view outside (0, 180) degrees; a buffer URI that is absolute, has a "..",
// a scheme other than a base64 data: URI, or (from memory) names a file at all. Unsupported: a
// glTF version other than 2.x. What tinygltf refuses comes back as ParseError with its message.
//
// Noted and skipped, not refused (GltfImport::notes): lights of a type other than point, spot
// and directional, lights with intensity 0 or colour black, cameras and lights on nodes whose
// transform collapses their axes (scale 0); noted and imported: spot cones, cameras whose
// transform scales unevenly, shears or mirrors (the optical axis is kept, up is squared to it),
// quaternions that were not of unit length, a file with no cameras or no lights, and the
// extensions a file requires that flarelab does not read.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"
#include "predict/constellation.h"

namespace flarelab::predict {

// What one import reads at most: the .gltf or .glb and the buffers it names, together.
inline constexpr int64_t kGltfMaxBytes = int64_t{64} << 20;
inline constexpr int kGltfMaxNodeDepth = 64;   // a root node is at depth 1
inline constexpr int kGltfMaxJsonDepth = 128;  // nested JSON objects and arrays

struct GltfCamera {
    std::string name;  // the node's name, else the camera's, else "node N"
    std::string type;  // "perspective" or "orthographic"
    CameraPose pose;
    std::optional<double> yfov_deg;  // perspective cameras: the vertical field of view, (0, 180)
};

struct GltfLight {
    std::string name;                // the node's name, else the light's, else "node N"
    std::string type;                // "point", "spot" (imported as a point light) or "directional"
    std::optional<Vec3> position_m;  // point and spot lights
    std::optional<Vec3> direction;   // directional lights: unit vector towards the light
    std::array<double, 3> colour = {1.0, 1.0, 1.0};  // linear RGB factors >= 0, not all 0
    double intensity = 0.0;  // > 0: candela for point and spot lights, lux for directional ones
    std::optional<double> range_m;  // > 0 where the file gives one; unset: no cut-off
};

struct GltfImport {
    std::vector<GltfCamera> cameras;
    std::vector<GltfLight> lights;
    std::vector<std::string> notes;  // what was skipped or approximated, and why; for the planner
};

// Reads the glTF at `path`: a .glb when the file starts with the GLB magic "glTF", else .gltf
// JSON. External buffers are read from the file's folder (never above it), all files together at
// most kGltfMaxBytes. NotFound or IoError for the file itself; a missing buffer is NotFound; the
// file and its buffers must be regular files, not symbolic links (IoError), as for loadScene.
Result<GltfImport> importGltf(const std::string& path);

// The same from bytes in memory: GLB when `binary`, else JSON. `name` stands for the file in
// messages. No file is read: a buffer must be in the GLB's binary chunk or a data: URI.
Result<GltfImport> importGltfFromMemory(std::string_view bytes,
                                        const std::string& name,
                                        bool binary);

}  // namespace flarelab::predict
