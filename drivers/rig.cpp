#include "drivers/rig.h"

#include <algorithm>
#include <utility>

// The hardware backends. Each header declares add<Name>Backend(registry); those of backends
// that need a library are compiled only with it (drivers/CMakeLists.txt sets FLARELAB_HAVE_*).
#include "drivers/apt_head.h"
#include "drivers/serial_port.h"
#include "drivers/v4l2_camera.h"
#include "drivers/zaber_head.h"
#if FLARELAB_HAVE_ARAVIS
#include "drivers/aravis_camera.h"
#endif
#if FLARELAB_HAVE_LIBCAMERA
#include "drivers/libcamera_camera.h"
#endif

namespace flarelab::drivers {
namespace {

#if FLARELAB_HAVE_ARAVIS
constexpr bool kHaveAravis = true;
#else
constexpr bool kHaveAravis = false;
#endif
#if FLARELAB_HAVE_LIBCAMERA
constexpr bool kHaveLibcamera = true;
#else
constexpr bool kHaveLibcamera = false;
#endif

}  // namespace

template <typename Device>
Status addUnavailableBackend(DeviceRegistry<Device>& registry,
                             const std::string& scheme,
                             const std::string& description,
                             const std::string& library) {
    auto open = [scheme, library](const DeviceUri& uri) -> Result<std::unique_ptr<Device>> {
        return makeError(ErrorCode::Unsupported,
                         "device uri '" + uri.text + "': this build of flarelab has no " + scheme +
                             " backend: " + library +
                             " was not installed when it was built (install it, then build "
                             "again; README, 'Which library does what')");
    };
    return registry.addBackend(scheme, description + " (not in this build: needs " + library + ")",
                               std::move(open));
}
template Status addUnavailableBackend(CameraRegistry&,
                                      const std::string&,
                                      const std::string&,
                                      const std::string&);
template Status addUnavailableBackend(HeadRegistry&,
                                      const std::string&,
                                      const std::string&,
                                      const std::string&);

std::vector<BackendStatus> backendStatus() {
    return {
        {"sim", "camera", "simulated camera", true, ""},
        {"aravis", "camera", "GigE Vision and USB3 Vision cameras through Aravis", kHaveAravis,
         kHaveAravis ? "" : "aravis-0.8 (Debian: libaravis-dev)"},
        {"v4l2", "camera", "Video4Linux2 cameras", true, ""},
        {"libcamera", "camera", "libcamera cameras", kHaveLibcamera,
         kHaveLibcamera ? "" : "libcamera (Debian: libcamera-dev)"},
        {"sim", "head", "simulated panorama head", true, ""},
        {"zaber", "head", "Zaber rotation stages (ASCII protocol, serial)", true, ""},
        {"apt", "head", "Thorlabs rotation mounts (APT protocol, serial)", true, ""},
    };
}

Result<RigRegistries> makeRigRegistries(const RigOptions& options) {
    RigRegistries r;
    if (Status ok = addSimCameraBackend(r.cameras, nullptr, options.sim_camera, options.sim_lens);
        !ok)
        return ok.error();
#if FLARELAB_HAVE_ARAVIS
    if (Status ok = addAravisCameraBackend(r.cameras); !ok) return ok.error();
#else
    if (Status ok = addUnavailableBackend(r.cameras, "aravis", "GigE Vision cameras", "aravis-0.8");
        !ok)
        return ok.error();
#endif
    if (Status ok = addV4l2CameraBackend(r.cameras); !ok) return ok.error();
#if FLARELAB_HAVE_LIBCAMERA
    if (Status ok = addLibcameraCameraBackend(r.cameras); !ok) return ok.error();
#else
    if (Status ok = addUnavailableBackend(r.cameras, "libcamera", "libcamera cameras", "libcamera");
        !ok)
        return ok.error();
#endif
    if (Status ok = addSimHeadBackend(r.heads, options.sim_head, options.sim_clock); !ok)
        return ok.error();
    if (Status ok = addZaberHeadBackend(r.heads); !ok) return ok.error();
    if (Status ok = addAptHeadBackend(r.heads); !ok) return ok.error();
    return r;
}

Result<Rig> openRig(const RigRegistries& registries,
                    const std::string& camera_uri,
                    const std::string& head_uri,
                    const RigOptions& options) {
    Rig rig;
    auto head = registries.heads.open(head_uri);
    if (!head) return head.error().withContext("head '" + head_uri + "'");
    rig.head = std::shared_ptr<Head>(std::move(*head));
    rig.sim_head = std::dynamic_pointer_cast<SimHead>(rig.head);

    auto parsed = parseDeviceUri(camera_uri);
    if (parsed && parsed->scheme == "sim") {
        // Bound to the head: it renders where the head points.
        auto setup = simCameraSetup(*parsed, options.sim_camera, options.sim_lens);
        if (!setup) return setup.error().withContext("camera '" + camera_uri + "'");
        auto clock =
            options.sim_clock ? options.sim_clock : std::make_shared<SimClock>(SimTime::RealTime);
        auto camera = rig.sim_head
                          ? SimCamera::make(std::move(setup->lens), setup->options, rig.sim_head)
                          : SimCamera::make(std::move(setup->lens), setup->options, rig.head,
                                            std::move(clock));
        if (!camera) return camera.error().withContext("camera '" + camera_uri + "'");
        rig.sim_camera = camera->get();
        rig.camera = std::shared_ptr<Camera>(std::move(*camera));
        return rig;
    }
    auto camera = registries.cameras.open(camera_uri);
    if (!camera) return camera.error().withContext("camera '" + camera_uri + "'");
    rig.camera = std::shared_ptr<Camera>(std::move(*camera));
    return rig;
}

std::vector<DeviceListing> listDevices(const RigRegistries& registries) {
    std::vector<DeviceListing> found = registries.cameras.enumerate();
    for (DeviceListing& d : registries.heads.enumerate()) found.push_back(std::move(d));
    // A port a stage backend recognised is listed once, as that backend's head.
    for (DeviceListing& d : listSerialPorts()) {
        const bool listed = std::any_of(found.begin(), found.end(), [&](const DeviceListing& h) {
            return h.kind == "head" && h.uri == d.uri;
        });
        if (!listed) found.push_back(std::move(d));
    }
    return found;
}

}  // namespace flarelab::drivers
