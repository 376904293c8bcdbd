// ============================================================================
//  flarelab drivers: ReplayRig, ReplayHead, ReplayCamera, openReplay
// ============================================================================
//
// A recorded sweep (hdr/sweep.h) played back through the camera and head interfaces as if live,
// so every stage after the rig runs on recorded data in tests.
//
// The head homes to 0 as a real head does and then moves, at once, to any angle between 0 and the
// sweep's frames (its limits); the camera delivers what was recorded at the frame nearest the
// head's angle, when one lies within angle_tolerance_deg (else an OutOfRange error naming the
// angle: nothing was recorded there).
//
// What a capture delivers, for the current exposure time:
//   - the recorded raw bracket of that exposure (exactly the bytes captured), when the frame has
//     raw files and one of them was taken at this exposure (within 1e-9 relative);
//   - otherwise the frame's HDR radiance exposed again, noiselessly: DN = radiance (green
//     channel, DN per second at unity gain) x exposure_s x gain + black, rounded and clipped at
//     white; a camera description from the sweep, 16-bit converter, black 0 unless configured.
//     This lets any HDR-only sweep run through the merge and everything after it.
// Sequence numbers count captures; timestamps advance by the exposure time.
#pragma once

#include <atomic>
#include <memory>
#include <string>

#include "common/result.h"
#include "drivers/camera.h"
#include "drivers/head.h"
#include "hdr/sweep.h"

namespace flarelab::drivers {

struct ReplayOptions {
    double angle_tolerance_deg = 1e-6;  // how near a frame the head must stand
    // For sweeps without raw brackets: the converter of the re-exposed frames.
    int bit_depth = 16;
    double black_level_dn = 0.0;
    double initial_exposure_s = 1.0;
};

class ReplayHead final : public Head {
public:
    explicit ReplayHead(std::shared_ptr<const hdr::Sweep> sweep);
    DeviceIdentity identity() const override;
    HeadLimits limits() const override;
    Status home(double timeout_s) override;
    Result<double> moveTo(double angle_deg, double timeout_s) override;
    Result<double> position() override;
    double speed_deg_s() const override { return speed_deg_s_; }
    Status setSpeed(double speed_deg_s) override;
    Status stop() override { return Ok{}; }

private:
    std::shared_ptr<const hdr::Sweep> sweep_;
    double position_deg_ = 0.0;
    bool homed_ = false;
    double speed_deg_s_ = 10.0;
};

class ReplayCamera final : public Camera {
public:
    ReplayCamera(std::shared_ptr<const hdr::Sweep> sweep,
                 std::shared_ptr<Head> head,
                 ReplayOptions options = {});
    DeviceIdentity identity() const override;
    CameraCapabilities capabilities() const override;
    Status setExposure(double exposure_s) override;
    double exposure_s() const override { return exposure_s_; }
    Status setGain(double gain) override;
    double gain() const override { return gain_; }
    Status setFormat(hdr::RawFormat format) override;
    hdr::RawFormat format() const override { return format_; }
    // What the replayed sweep recorded.
    std::optional<double> lightPowerDnPerS() const override {
        return sweep_->header.camera.light_power_dn_s;
    }
    Result<hdr::RawFrame> capture(double timeout_s) override;
    // A replayed capture reads a recorded file and waits for nothing: an abort is seen when the
    // next capture begins.
    void abort() override { aborted_ = true; }

private:
    std::shared_ptr<const hdr::Sweep> sweep_;
    std::shared_ptr<Head> head_;
    ReplayOptions options_;
    double exposure_s_;
    double gain_ = 1.0;
    hdr::RawFormat format_ = hdr::RawFormat::Mono;
    int64_t sequence_ = 0;
    int64_t clock_ns_ = 0;
    std::atomic<bool> aborted_{false};
};

struct ReplayRig {
    std::shared_ptr<const hdr::Sweep> sweep;
    std::shared_ptr<ReplayHead> head;
    std::shared_ptr<ReplayCamera> camera;
};

// Reads and validates the sweep in `directory` (readSweep) and sets up a head and a camera on it.
Result<ReplayRig> openReplay(const std::string& directory, const ReplayOptions& options = {});

}  // namespace flarelab::drivers
