// ============================================================================
//  flarelab drivers: Head, HeadLimits, HeadRegistry
// ============================================================================
//
// The interface of a motorized panorama head that turns the camera about a vertical axis, away
// from the light: the simulated head (sim_head.h), and rotation stages on a serial line: Zaber
// (zaber_head.h) and Thorlabs APT (apt_head.h). Angles are in degrees in the head's own frame: 0 is
// where home() puts it (the camera facing the light on a calibrated rig), positive turns the light
// towards +x in the image.
//
// A head must be homed before it knows its position: until then, and after it lost position,
// position() and moveTo() answer [not-homed]. moveTo blocks until the head has arrived and
// settled, or the timeout passed. Errors are device errors (device.h): [out-of-range] naming
// angle_deg, speed_deg_s or timeout_s; [timeout]; [stalled] (the head stopped short, at the
// position it reports); [lost-position] (re-home); [stopped] (stop() interrupted the move);
// [busy]; [disconnected]. Implementations are safe to call from several threads, so that stop()
// and position() can be called while another thread waits in moveTo().
#pragma once

#include "common/result.h"
#include "drivers/device.h"

namespace flarelab::drivers {

struct HeadLimits {
    double min_deg = 0.0;
    double max_deg = 0.0;
    double max_speed_deg_s = 0.0;
};

class Head {
public:
    Head() = default;
    Head(const Head&) = delete;
    Head& operator=(const Head&) = delete;
    virtual ~Head() = default;

    virtual DeviceIdentity identity() const = 0;
    virtual HeadLimits limits() const = 0;

    // Finds the home switch and sets the position to 0 there; then the head is homed.
    virtual Status home(double timeout_s) = 0;
    // Moves to angle_deg in [min_deg, max_deg] and waits until it settled there; returns the
    // position the head reports on arrival.
    virtual Result<double> moveTo(double angle_deg, double timeout_s) = 0;
    // Where the head reports it is (deg); during a move, where it is now.
    virtual Result<double> position() = 0;

    virtual double speed_deg_s() const = 0;
    // speed_deg_s in (0, max_speed_deg_s].
    virtual Status setSpeed(double speed_deg_s) = 0;

    // Stops a move in progress (a moveTo waiting in another thread returns [stopped]); does
    // nothing when the head stands still.
    virtual Status stop() = 0;
};

// Heads by URI: "sim:", "zaber:/dev/ttyUSB0?axis=1", "apt:/dev/ttyUSB0" (rig.h opens them all).
using HeadRegistry = DeviceRegistry<Head>;

}  // namespace flarelab::drivers
