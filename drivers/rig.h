// ============================================================================
//  flarelab drivers: RigOptions, Rig, RigRegistries, BackendStatus, makeRigRegistries, openRig,
//                    listDevices
// ============================================================================
//
// Every camera and head backend of this build in one place, so that every program that chooses
// a device (flarelab capture, rig, calibrate; flarelabd) opens it by the same URI:
//
//     camera  sim:?lens=FILE                the simulated camera (sim_camera.h)
//             aravis:ID                     GigE Vision through Aravis (aravis_camera.h)
//             v4l2:/dev/videoN              Video4Linux2 (v4l2_camera.h)
//             libcamera:NAME                libcamera (libcamera_camera.h)
//     head    sim:                          the simulated head (sim_head.h)
//             zaber:/dev/ttyUSB0?axis=1     Zaber ASCII protocol (zaber_head.h)
//             apt:/dev/ttyUSB0              Thorlabs APT protocol (apt_head.h)
//
// A backend whose library was not installed when flarelab was built keeps its scheme: opening it
// answers Unsupported, saying which library is missing, instead of "no backend".
//
// openRig opens the head first, then the camera, so that a simulated camera renders where the
// head points: at the true angle of a simulated head (backlash and noise included), at the
// reported angle of any other.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/result.h"
#include "drivers/camera.h"
#include "drivers/head.h"
#include "drivers/sim_camera.h"
#include "drivers/sim_head.h"
#include "optics/lens.h"

namespace flarelab::drivers {

struct RigOptions {
    // The simulated devices' settings; the sim camera's lens when its URI names none.
    SimCameraOptions sim_camera;
    std::optional<optics::Lens> sim_lens;
    SimHeadOptions sim_head;
    // The simulated rig's clock (fast: simulated time); a real-time one when null.
    std::shared_ptr<SimClock> sim_clock;
};

struct RigRegistries {
    CameraRegistry cameras;
    HeadRegistry heads;
};

// Whether this build has a backend, and what it needs when it has not.
struct BackendStatus {
    std::string scheme;
    std::string kind;  // "camera" or "head"
    std::string description;
    bool built = false;
    std::string missing;  // the library it was built without, when not built
};
std::vector<BackendStatus> backendStatus();

// Registers `scheme` for a backend this build left out: opening one of its URIs answers
// Unsupported, naming the scheme and the missing library.
template <typename Device>
Status addUnavailableBackend(DeviceRegistry<Device>& registry,
                             const std::string& scheme,
                             const std::string& description,
                             const std::string& library);

// The registries with every backend of this build (see the top of this file). The sim camera of
// this registry has no head (its light stays at sim_camera.fixed_angle_deg); openRig binds it.
Result<RigRegistries> makeRigRegistries(const RigOptions& options);

struct Rig {
    std::shared_ptr<Head> head;
    std::shared_ptr<Camera> camera;
    // The simulated devices, when the rig has them (faults, sequence, clock for tests).
    std::shared_ptr<SimHead> sim_head;
    SimCamera* sim_camera = nullptr;  // owned by `camera`
};

// Opens a head and a camera by URI or alias. A "sim:" camera is bound to the opened head. Errors
// carry "camera" or "head" and the URI as context.
Result<Rig> openRig(const RigRegistries& registries,
                    const std::string& camera_uri,
                    const std::string& head_uri,
                    const RigOptions& options);

// What every backend sees now: cameras, heads and serial ports (with their USB identity), for
// `flarelab rig devices`.
std::vector<DeviceListing> listDevices(const RigRegistries& registries);

}  // namespace flarelab::drivers
