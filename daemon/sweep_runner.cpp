#include "daemon/sweep_runner.h"

#include <fcntl.h>
#include <malloc.h>
#include <sys/statvfs.h>

#include <chrono>
#include <cmath>
#include <condition_variable>
#include <ctime>
#include <filesystem>
#include <iomanip>
#include <mutex>
#include <new>
#include <optional>
#include <set>
#include <sstream>
#include <stop_token>
#include <thread>

#include "common/durable_io.h"
#include "common/file_descriptor.h"
#include "daemon/bounded_queue.h"
#include "daemon/log.h"
#include "drivers/auto_bracket.h"
#include "drivers/lens_settings.h"
#include "drivers/replay.h"
#include "drivers/sim_camera.h"
#include "drivers/sim_head.h"
#include "fit/frame.h"
#include "fit/model_file.h"
#include "fit/sweep_fit.h"
#include "hdr/digest.h"
#include "hdr/merge.h"
#include "hdr/raw_io.h"
#include "hdr/sweep.h"
#include "render/preview.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point t) {
    return std::chrono::duration<double>(Clock::now() - t).count();
}

std::string num(double v) {
    std::ostringstream o;
    o << std::setprecision(6) << v;
    return o.str();
}

int64_t statvfsFree(const std::string& path) {
    struct statvfs s {};
    if (::statvfs(path.c_str(), &s) != 0) return -1;
    return static_cast<int64_t>(s.f_bavail) * static_cast<int64_t>(s.f_frsize);
}

std::string utcStamp() {
    const std::time_t now = std::time(nullptr);
    std::tm tm{};
    gmtime_r(&now, &tm);
    char text[32];
    std::strftime(text, sizeof text, "%Y%m%dT%H%M%SZ", &tm);
    return text;
}

// One frame's bracket on its way from the capture thread to the processing thread.
struct Captured {
    size_t index = 0;
    double angle_deg = 0.0;  // as the head reported it, to a nanodegree
    std::vector<hdr::RawFrame> bracket;
};

// A directory below `parent` named `stem` (or `stem-2`, `stem-3`, ...) that does not exist yet:
// files set aside there never meet older ones. Only this daemon writes below its state directory
// (its lock), and one job captures at a time.
std::string freshDirectory(const fs::path& parent, const std::string& stem) {
    std::error_code ec;
    fs::path candidate = parent / stem;
    for (int n = 2; fs::exists(fs::symlink_status(candidate, ec)); ++n)
        candidate = parent / (stem + "-" + std::to_string(n));
    return candidate.string();
}

// Bytes a bracket holds, for the queue's bound.
size_t bracketBytes(const Captured& captured) {
    size_t bytes = 0;
    for (const hdr::RawFrame& raw : captured.bracket) bytes += raw.samples.size() * 2;
    return bytes;
}

// Stops the rig from a thread of its own once the job must stop: the stop hook runs under the job
// manager's lock, where nothing may wait on a device. The camera's exposure is aborted (the
// bracket under way is dropped: it is not a frame), and the head stopped; as Head::stop() stops
// only a move under way, it is repeated until the capture is over, so that a move begun just
// after the first stop (between the checkpoint and the move) is stopped too. The hook is cleared
// when this ends: it is never called on a finished job's devices.
class RigStopper {
public:
    RigStopper(JobControl& control,
               std::shared_ptr<drivers::Head> head,
               std::shared_ptr<drivers::Camera> camera)
        : control_(control),
          head_(std::move(head)),
          camera_(std::move(camera)),
          camera_uri_(camera_->identity().uri) {
        thread_ = std::jthread([this](std::stop_token done) { run(done); });
        control_.setStopHook([this] {
            {
                std::lock_guard lock(mutex_);
                stop_ = true;
            }
            wake_.notify_all();
        });
    }
    ~RigStopper() {
        control_.setStopHook({});
        thread_.request_stop();
        thread_.join();
    }

private:
    void run(const std::stop_token& done) {
        std::unique_lock lock(mutex_);
        if (!wake_.wait(lock, done, [&] { return stop_; })) return;
        lock.unlock();
        camera_->abort();
        // (Nothing else of the camera here: it is the capture thread's but for abort().)
        logEvent(LogLevel::Info, "sweep.rig_stopping", {{"camera", camera_uri_}});
        while (!done.stop_requested()) {
            (void)head_->stop();
            lock.lock();
            wake_.wait_for(lock, done, std::chrono::milliseconds(100), [] { return false; });
            lock.unlock();
        }
    }

    JobControl& control_;
    const std::shared_ptr<drivers::Head> head_;
    const std::shared_ptr<drivers::Camera> camera_;
    const std::string camera_uri_;
    std::mutex mutex_;
    std::condition_variable_any wake_;
    bool stop_ = false;
    std::jthread thread_;
};

// The job's own sweep may be on disk already (a resumed job): a sweep that is not its own was
// refused when the job was started, and SweepWriter refuses one whose settings differ.
v1::SweepConfig resumable(v1::SweepConfig config) {
    config.set_resume_existing(true);
    return config;
}

class SweepJob {
public:
    SweepJob(const v1::Job& job, const RunnerOptions& options, JobControl& control)
        : job_(job), options_(options), control_(control) {}

    RunResult run();  // capture
    RunResult fit();

private:
    Status makeRig();
    // The bracket of a job that gave none: the one its sweep on disk was taken with, else planned
    // from probes at the first angle (its reasons become warnings). An error stops the job (a
    // Stopped outcome when the job was cancelled meanwhile).
    Status planBracket();
    Result<hdr::SweepWriter> openSweep();
    // Head to angle with the retries of the fault policy; nullopt when the job must stop
    // (the reason, if a failure, in result_).
    std::optional<double> move(double angle_deg, size_t index);
    std::optional<hdr::RawFrame> expose(double exposure_s, size_t index, double angle_deg);
    void captureLoop(size_t first, BoundedQueue<Captured>& queue);  // never throws
    void captureFrames(size_t first, BoundedQueue<Captured>& queue);
    void processLoop(BoundedQueue<Captured>& queue, hdr::SweepWriter& writer);
    Status writeFrame(Captured& captured, hdr::SweepWriter& writer);
    void fitModel();
    // The camera's transport counters, one log line per run of the capture.
    void logStatistics() const {
        const auto stats = camera_->statistics();
        if (stats.empty()) return;
        std::vector<LogField> fields = {{"job", job_.id()}, {"camera", camera_->identity().uri}};
        for (const auto& [name, value] : stats) fields.emplace_back(name, std::to_string(value));
        logEvent(LogLevel::Info, "sweep.camera_statistics", fields);
    }
    // The job fails for `reason` (the first reason stays); `resumable` as sweep_runner.h says.
    void fail(const std::string& reason, bool resumable = true) {
        std::lock_guard lock(mutex_);
        if (result_.outcome != RunOutcome::Failed || result_.reason.empty()) {
            result_.outcome = RunOutcome::Failed;
            result_.reason = reason;
            result_.resumable = resumable;
        }
        failed_ = true;
    }
    // A frame could not be written: nothing after it may be (the sweep has no gaps).
    void failWrite(const std::string& reason, bool resumable) {
        fail(reason, resumable);
        write_failed_ = true;
    }

    const v1::Job& job_;
    const RunnerOptions& options_;
    JobControl& control_;
    PreparedSweep sweep_;
    std::shared_ptr<drivers::Head> head_;
    std::shared_ptr<drivers::Camera> camera_;
    drivers::SimCamera* sim_camera_ = nullptr;                 // camera_, when it is simulated
    const drivers::CameraCalibration* calibration_ = nullptr;  // of camera_, when the daemon has it
    int64_t width_px_ = 0;                                     // of the camera's frames
    int64_t height_px_ = 0;
    std::mutex mutex_;
    RunResult result_;
    std::atomic<bool> failed_{false};        // the capture stops
    std::atomic<bool> write_failed_{false};  // the processing stops writing too
    bool raw_directory_ready_ = false;
    std::atomic<uint32_t> on_disk_{0};
    size_t captures_ = 0;  // exposures attempted by this run (for injected faults)
    Clock::time_point capture_start_;
    size_t captured_this_run_ = 0;
    size_t first_ = 0;
};

Status SweepJob::makeRig() {
    if (const auto& replay = options_.limits.replay) {
        auto head = std::make_shared<drivers::ReplayHead>(replay);
        camera_ = std::make_shared<drivers::ReplayCamera>(replay, head);
        head_ = std::move(head);
    } else {
        auto rig = openJobRig(sweep_, options_.limits);
        if (!rig) return rig.error();
        head_ = std::move(rig->head);
        sim_camera_ = rig->sim_camera;
        camera_ = std::move(rig->camera);
    }
    const v1::SweepConfig& c = sweep_.config;
    if (!c.raw_format().empty()) {
        const std::optional<hdr::RawFormat> format = hdr::parseRawFormat(c.raw_format());
        if (!format)  // checkSweepConfig refuses it before a job exists
            return makeError(ErrorCode::InvalidArgument, "config.raw_format: unknown");
        if (Status ok = camera_->setFormat(*format); !ok)
            return makeError(ok.error().code, "config.raw_format: " + ok.error().message);
    }
    const drivers::CameraCapabilities caps = camera_->capabilities();
    if ((c.width_px() != 0 && c.width_px() != caps.width_px) ||
        (c.height_px() != 0 && c.height_px() != caps.height_px))
        return makeError(ErrorCode::InvalidArgument,
                         "config.width_px: the camera " + camera_->identity().describe() +
                             " delivers " + std::to_string(caps.width_px) + " x " +
                             std::to_string(caps.height_px) + " frames, not " +
                             std::to_string(c.width_px()) + " x " + std::to_string(c.height_px()) +
                             " (leave the size 0, or set a region of interest in its URI)");
    if (caps.width_px * caps.height_px > options_.limits.max_pixels)
        return makeError(ErrorCode::InvalidArgument,
                         "camera " + camera_->identity().describe() + ": its " +
                             std::to_string(caps.width_px) + " x " +
                             std::to_string(caps.height_px) + " frames are more than the " +
                             std::to_string(options_.limits.max_pixels) + " pixels a job may have");
    if (!options_.limits.replay && !sim_camera_)
        if (Status ok = checkMemoryBudget(
                caps.width_px, caps.height_px, static_cast<int64_t>(sweep_.exposure_times_s.size()),
                false, options_.limits, "camera " + camera_->identity().describe());
            !ok)
            return ok.error();
    width_px_ = caps.width_px;
    height_px_ = caps.height_px;
    for (const std::string& note : camera_->notes()) control_.warning("camera: " + note);
    calibration_ = nullptr;
    for (const drivers::CameraCalibration& c : options_.calibrations)
        if (drivers::calibrationCameraName(c) == camera_->identity().describe()) calibration_ = &c;
    if (Status ok = drivers::checkMergeable(caps, calibration_); !ok)
        return ok.error().withContext("camera " + camera_->identity().describe());
    if (!sweep_.camera_uri.empty())
        control_.deviceOpened(sweep_.camera_uri, camera_->identity().model,
                              camera_->identity().serial);
    if (!sweep_.head_uri.empty())
        control_.deviceOpened(sweep_.head_uri, head_->identity().model, head_->identity().serial);
    if (!options_.limits.replay && !sim_camera_)
        if (Status ok = camera_->setGain(c.gain()); !ok) return ok.error();
    return Ok{};
}

Status SweepJob::planBracket() {
    std::error_code ec;
    if (fs::exists(fs::path(sweep_.output_dir) / hdr::kSweepManifestFile, ec)) {
        auto listed = hdr::readSweepManifest(sweep_.output_dir);
        if (!listed) return listed.error();
        sweep_.exposure_times_s = listed->header.capture.exposure_times_s;
        if (!sweep_.exposure_times_s.empty()) return Ok{};
    }
    const auto at = move(sweep_.angles_deg.front(), 0);
    if (!at) {
        if (!failed_) result_.outcome = RunOutcome::Stopped;
        return makeError(ErrorCode::IoError, result_.reason.empty() ? "stopped" : result_.reason);
    }
    drivers::BracketPlanOptions options;
    options.calibration = calibration_;
    options.max_exposures = std::min(options.max_exposures, options_.limits.max_exposures);
    auto plan = drivers::planBrackets(*camera_, options);
    if (!plan) return plan.error().withContext("planning the bracket");
    for (const std::string& reason : plan->reasons) control_.warning("bracket: " + reason);
    if (!plan->core_unclipped)
        control_.warning("bracket: the shortest exposure clips the light's core");
    if (!plan->floor_reached)
        control_.warning("bracket: the longest exposure does not reach the ghosts' noise floor");
    sweep_.exposure_times_s = plan->exposure_times_s;
    return Ok{};
}

Result<hdr::SweepWriter> SweepJob::openSweep() {
    const v1::SweepConfig& c = sweep_.config;
    hdr::SweepHeader header;
    if (const auto& replay = options_.limits.replay) {
        // The lens and camera are the recording's.
        header.software_version =
            options_.software_version + " (replay of " + replay->directory + ")";
        header.lens = replay->header.lens;
        header.camera = replay->header.camera;
        header.camera.bit_depth = camera_->capabilities().bit_depth;
    } else {
        const auto named = [](const std::string& uri) {
            return uri.empty() ? std::string("simulated") : uri;
        };
        header.software_version =
            options_.software_version + (sweep_.camera_uri.empty() && sweep_.head_uri.empty()
                                             ? std::string(" (simulated rig)")
                                             : " (camera " + named(sweep_.camera_uri) + ", head " +
                                                   named(sweep_.head_uri) + ")");
        const optics::Lens* lens = sweep_.lens   ? &*sweep_.lens
                                   : sim_camera_ ? &sim_camera_->lens()
                                                 : nullptr;
        // The lens with its camera settings, as `flarelab capture` records them, so that a score
        // simulates the same lens again.
        if (lens) {
            header.lens = drivers::describeLens(*lens);
            if (sweep_.lens && c.has_sim()) {
                header.lens.prescription_file = c.sim().lens().name();
                // The client sent the file's bytes: their digest is the file's.
                auto digest = hdr::sha256Hex(c.sim().lens().prescription_csv());
                if (!digest) return digest.error().withContext("lens prescription");
                header.lens.prescription_sha256 = std::move(*digest);
            }
        } else {
            header.lens.description = c.lens_description();
        }
        header.camera.description = camera_->identity().model;
        header.camera.serial = camera_->identity().serial;
        header.camera.bit_depth = camera_->capabilities().bit_depth;
        header.camera.raw_format = camera_->format();
        header.camera.light_power_dn_s = camera_->lightPowerDnPerS();
        if (c.pixel_pitch_um() > 0.0)
            header.camera.pixel_pitch_um = c.pixel_pitch_um();
        else if (lens)
            header.camera.pixel_pitch_um =
                1000.0 * lens->camera().sensor_width_mm / static_cast<double>(width_px_);
    }
    header.capture.from_deg = c.from_deg();
    header.capture.to_deg = c.to_deg();
    header.capture.step_deg = c.step_deg();
    header.capture.exposure_times_s = sweep_.exposure_times_s;
    header.capture.gain = camera_->gain();
    header.capture.width_px = width_px_;
    header.capture.height_px = height_px_;

    hdr::SweepWriteOptions write;
    std::error_code ec;
    write.resume =
        fs::exists(fs::symlink_status(fs::path(sweep_.output_dir) / hdr::kSweepManifestFile, ec));
    auto writer = hdr::SweepWriter::create(sweep_.output_dir, header, write);
    if (!writer || !write.resume) return writer;
    // The writer holds the sweep's lock and has checked its header: only now may files the sweep
    // does not list (what an interrupted write leaves) be set aside, never deleted.
    const std::string aside =
        freshDirectory(fs::path(options_.state_dir) / "recovered" / job_.id(), utcStamp());
    auto moved = writer->setAsideUnlisted(aside);
    if (!moved) return moved.error();
    if (!moved->empty())
        control_.warning("resuming: " + std::to_string(moved->size()) +
                         " file(s) the sweep does not list (an interrupted write) moved to " +
                         aside);
    return writer;
}

std::optional<double> SweepJob::move(double angle_deg, size_t index) {
    int timeouts = 0, rehomes = 0;
    for (;;) {
        if (!control_.checkpoint()) return std::nullopt;
        auto at = head_->moveTo(angle_deg, 120.0);
        if (at) return *at;
        const auto fault = drivers::deviceFaultOf(at.error());
        const std::string where = "frame " + std::to_string(index) + " at " + num(angle_deg) +
                                  " deg: " + at.error().message;
        if (fault == drivers::DeviceFault::Stopped) return std::nullopt;  // stop() from control
        if (fault == drivers::DeviceFault::Timeout && timeouts < options_.head_retries) {
            ++timeouts;
            control_.warning(where + " (retry " + std::to_string(timeouts) + " of " +
                             std::to_string(options_.head_retries) + ")");
            continue;
        }
        if (fault == drivers::DeviceFault::LostPosition && rehomes < options_.head_retries) {
            ++rehomes;
            control_.warning(where + "; homing again");
            if (Status homed = head_->home(600.0); !homed)
                control_.warning("homing failed: " + homed.error().message);
            continue;
        }
        std::string reason;
        if (fault == drivers::DeviceFault::Stalled) {
            if (Status stopped = head_->stop(); !stopped)
                control_.warning("stopping the head: " + stopped.error().message);
            reason = "head stalled: " + where +
                     "; the rig is stopped: clear the obstacle, then resume the job";
        } else if (fault == drivers::DeviceFault::Timeout) {
            reason = "head did not arrive after " + std::to_string(timeouts + 1) +
                     " tries: " + where + "; check the head, then resume the job";
        } else if (fault) {
            reason = "head fault: " + where + "; resume the job when the head is back";
        } else {
            fail("head: " + where);
            return std::nullopt;
        }
        if (!control_.pauseForFault(reason)) return std::nullopt;
        timeouts = rehomes = 0;
        if (fault == drivers::DeviceFault::LostPosition || fault == drivers::DeviceFault::Stalled)
            if (Status homed = head_->home(600.0); !homed)
                control_.warning("homing failed: " + homed.error().message);
    }
}

std::optional<hdr::RawFrame> SweepJob::expose(double exposure_s, size_t index, double angle_deg) {
    int timeouts = 0;
    const v1::SimFaults& faults = sweep_.config.sim().faults();
    for (;;) {
        ++captures_;
        if (sim_camera_ && faults.camera_timeouts() > 0 &&
            captures_ == std::max<size_t>(1, faults.camera_timeouts_from_capture())) {
            drivers::SimCameraFaults f = sim_camera_->faults();
            f.time_out_captures = static_cast<int>(faults.camera_timeouts());
            sim_camera_->setFaults(f);
        }
        // Generous: a camera may drop frames exposed before a change (V4L2, libcamera) or wait
        // for its next frame period; a stuck camera is what the timeout is for.
        const double timeout_s = 4.0 * (exposure_s + options_.limits.readout_s) + 10.0;
        auto frame = [&]() -> Result<hdr::RawFrame> {
            if (Status set = camera_->setExposure(exposure_s); !set) return set.error();
            return camera_->capture(timeout_s);
        }();
        if (frame) return std::move(*frame);
        const auto fault = drivers::deviceFaultOf(frame.error());
        if (fault == drivers::DeviceFault::Stopped) return std::nullopt;  // the job must stop
        const std::string where = "frame " + std::to_string(index) + " at " + num(angle_deg) +
                                  " deg, exposure " + num(exposure_s) +
                                  " s: " + frame.error().message;
        // A damaged frame the backend could not retake (packets lost) is as passing as a
        // timeout, and counts against the same retries.
        const bool passing =
            fault == drivers::DeviceFault::Timeout || fault == drivers::DeviceFault::BadFrame;
        if (passing && timeouts < options_.camera_retries) {
            ++timeouts;
            control_.warning(where + " (retry " + std::to_string(timeouts) + " of " +
                             std::to_string(options_.camera_retries) + ")");
            continue;
        }
        if (fault == drivers::DeviceFault::OutOfRange) {
            fail("camera: " + where, false);  // a setting the camera refuses: no resume helps
            return std::nullopt;
        }
        std::string reason;
        if (passing)
            reason = "camera failed " + std::to_string(timeouts + 1) + " times: " + where +
                     "; check the camera, then resume the job";
        else if (fault)
            reason = "camera fault: " + where + "; resume the job when the camera is back";
        else {
            fail("camera: " + where);
            return std::nullopt;
        }
        if (!control_.pauseForFault(reason)) return std::nullopt;
        timeouts = 0;
    }
}

void SweepJob::captureLoop(size_t first, BoundedQueue<Captured>& queue) {
    try {
        captureFrames(first, queue);
    } catch (const std::bad_alloc&) {
        fail("capture: out of memory (std::bad_alloc); the frames captured before are written");
    } catch (const std::exception& e) {
        fail(std::string("capture: ") + e.what() + "; the frames captured before are written");
    }
    queue.close();
}

void SweepJob::captureFrames(size_t first, BoundedQueue<Captured>& queue) {
    const size_t total = sweep_.angles_deg.size();
    const size_t n = sweep_.exposure_times_s.size();
    double bracket_s = 0.0;
    for (const double t : sweep_.exposure_times_s) bracket_s += t + options_.limits.readout_s;
    for (size_t i = first; i < total && !failed_; ++i) {
        if (options_.before_capture) options_.before_capture(i);
        const double target = sweep_.angles_deg[i];
        const auto at = move(target, i);
        if (!at) break;
        Captured captured;
        captured.index = i;
        captured.angle_deg = std::round(*at * 1e9) / 1e9;
        bool complete = true;
        for (size_t k = 0; k < n; ++k) {
            const double t = sweep_.exposure_times_s[k];
            auto frame = expose(t, i, target);
            if (!frame) {
                complete = false;
                break;
            }
            captured.bracket.push_back(std::move(*frame));
            v1::JobEvent e;
            e.set_kind(v1::EXPOSURE);
            e.set_frame_index(static_cast<uint32_t>(i));
            e.set_angle_deg(captured.angle_deg);
            e.set_bracket_index(static_cast<uint32_t>(k));
            e.set_exposure_s(t);
            const double elapsed = secondsSince(capture_start_);
            e.set_elapsed_s(elapsed);
            // Measured once a frame is done; before, the rig's own time (unknown in simulated
            // time, where a frame takes what it renders).
            const double per_frame =
                captured_this_run_ > 0 ? elapsed / static_cast<double>(captured_this_run_)
                : !sweep_.config.has_sim() || sweep_.config.sim().fast() ? 0.0
                                                                         : bracket_s;
            e.set_eta_s(per_frame * static_cast<double>(total - i));
            control_.event(std::move(e));
        }
        // A bracket cut short (the job stopped while paused on a fault) is not a frame; the
        // next run takes the frame again, its camera's sequence set where the frame begins.
        if (!complete) break;
        ++captured_this_run_;
        if (!queue.push(std::move(captured))) break;
    }
}

Status SweepJob::writeFrame(Captured& captured, hdr::SweepWriter& writer) {
    const v1::SweepConfig& c = sweep_.config;
    const std::string dir = sweep_.output_dir;
    // Room for this frame (float RGB, and the raw brackets when kept) and the margin.
    int64_t need = width_px_ * height_px_ * 12 + options_.min_free_bytes;
    if (c.keep_raw()) need += width_px_ * height_px_ * 2 * int64_t(captured.bracket.size());
    const int64_t free = options_.free_bytes ? options_.free_bytes(dir) : statvfsFree(dir);
    if (free >= 0 && free < need)
        return makeError(ErrorCode::IoError, "disk full: " + std::to_string(free >> 20) +
                                                 " MiB free on " + dir + ", a frame and the " +
                                                 std::to_string(options_.min_free_bytes >> 20) +
                                                 " MiB the daemon keeps free need " +
                                                 std::to_string(need >> 20) + " MiB");
    hdr::SweepFrame frame;
    frame.angle_deg = captured.angle_deg;
    frame.exposure_times_s = sweep_.exposure_times_s;
    for (size_t k = 0; k < captured.bracket.size(); ++k) {
        hdr::RawFrame& raw = captured.bracket[k];
        // The raw file keeps the frame as the camera gave it; the merge takes it calibrated.
        if (c.keep_raw()) {
            std::ostringstream name;
            name << "raw/frame_" << std::setw(5) << std::setfill('0') << captured.index << "_" << k
                 << ".pgm";
            if (!raw_directory_ready_) {
                // Its name flushed into the sweep before any frame lists a file in it.
                std::error_code ec;
                fs::create_directory(fs::path(dir) / "raw", ec);
                if (ec)
                    return makeError(ErrorCode::IoError,
                                     dir + "/raw: cannot create: " + ec.message());
                if (Status ok = syncDirectory(dir); !ok) return ok.error();
                raw_directory_ready_ = true;
            }
            if (Status ok = hdr::writeRaw(dir + "/" + name.str(), raw); !ok) return ok.error();
            frame.raw_files.push_back(name.str());
        }
        if (calibration_) {
            auto calibrated = drivers::applyCalibration(raw, *calibration_);
            if (!calibrated)
                return calibrated.error().withContext("frame " + std::to_string(captured.index));
            raw = std::move(*calibrated);
        }
        const auto counts = hdr::countExposure(raw);
        if (!counts) return counts.error().withContext("frame " + std::to_string(captured.index));
        frame.brackets.push_back({raw.exposure_s, static_cast<uint64_t>(counts->usable),
                                  static_cast<uint64_t>(counts->saturated)});
    }
    if (options_.before_merge) options_.before_merge(captured.index);
    auto merged = hdr::mergeBrackets(captured.bracket);
    if (!merged) return merged.error().withContext("frame " + std::to_string(captured.index));
    auto image = hdr::toImage(*merged);
    if (!image) return image.error().withContext("frame " + std::to_string(captured.index));
    auto bounds = hdr::lowerBounds(*merged);
    if (!bounds) return bounds.error().withContext("frame " + std::to_string(captured.index));
    frame.merge_method = merged->method;
    frame.exr_file = hdr::sweepFrameFileName(captured.index, captured.angle_deg);
    auto added = writer.addFrame(*image, frame, {}, *bounds);
    if (!added) return added.error();
    if (c.previews()) {
        const fs::path previews = fs::path(dir) / hdr::kSweepPreviewsDir;
        std::error_code ec;
        fs::create_directories(previews, ec);
        render::ToneMapOptions tone;
        tone.exposure_stops = c.preview_stops();
        const std::string png = (previews / fs::path(added->exr_file).stem()).string() + ".png";
        if (Status ok = render::writePng(*image, png, tone); !ok)
            control_.warning("preview: " + ok.error().message);
    }
    return Ok{};
}

void SweepJob::processLoop(BoundedQueue<Captured>& queue, hdr::SweepWriter& writer) {
    const size_t total = sweep_.angles_deg.size();
    size_t dropped = 0;
    while (auto captured = queue.pop()) {
        // A capture-side failure leaves the brackets already captured to be written; only a
        // frame that could not be written stops the writing (no gap in the sweep).
        if (write_failed_) continue;
        if (control_.dropUnwritten()) {
            ++dropped;  // the daemon stops at once; the frame being written before was finished
            continue;
        }
        Status ok = Ok{};
        try {
            ok = writeFrame(*captured, writer);
        } catch (const std::bad_alloc&) {
            ok = makeError(ErrorCode::Internal, "frame " + std::to_string(captured->index) +
                                                    ": out of memory (std::bad_alloc) while " +
                                                    "merging or writing it");
        } catch (const std::exception& e) {
            ok = makeError(ErrorCode::Internal,
                           "frame " + std::to_string(captured->index) + ": " + e.what());
        }
        if (!ok) {
            // A failed flush is final (the sweep writer refuses more); anything else may pass.
            failWrite(ok.error().message + "; the " + std::to_string(writer.sweep().frames.size()) +
                          " frame(s) written before are intact",
                      writer.broken().empty());
            queue.abort();        // the capture thread stops pushing at once
            (void)head_->stop();  // and ends at its next step
            continue;
        }
        const uint32_t done = static_cast<uint32_t>(writer.sweep().frames.size());
        on_disk_ = done;
        // What the threads' heaps hold free (small buffers; large ones are mapped, see
        // settleAllocator) goes back to the system now and then.
        if (done % 16 == 0) ::malloc_trim(0);
        control_.setFramesDone(done);
        v1::JobEvent e;
        e.set_kind(v1::FRAME);
        e.set_frame_index(static_cast<uint32_t>(captured->index));
        e.set_angle_deg(captured->angle_deg);
        const double elapsed = secondsSince(capture_start_);
        e.set_elapsed_s(elapsed);
        const size_t this_run = done - first_;
        if (this_run > 0) e.set_eta_s(elapsed / this_run * static_cast<double>(total - done));
        control_.event(std::move(e));
    }
    if (dropped > 0)
        control_.warning(std::to_string(dropped) +
                         " captured frame(s) not written: the daemon was told to stop at once; "
                         "they are taken again when the job resumes");
}

void SweepJob::fitModel() {
    const auto start = Clock::now();
    control_.setPhase(v1::FITTING);
    auto sweep = hdr::readSweep(sweep_.output_dir);
    if (!sweep) return fail("fit: " + sweep.error().message, false);
    if (const std::string w =
            hdr::clippingWarning(hdr::clippedFrames(*sweep), sweep->frames.size());
        !w.empty())
        control_.warning(w);
    // The simulated lens's sensor; a recording's pixel pitch.
    std::array<double, 2> sensor = {0.0, 0.0};
    if (sweep_.lens)
        sensor = {sweep_.lens->camera().sensor_width_mm, sweep_.lens->camera().sensor_height_mm};
    auto size = fit::sweepSensorSize(*sweep, sweep_.lens ? &sensor : nullptr);
    if (!size) return fail("fit: " + size.error().message, false);
    fit::SweepFitOptions options;
    options.cancel = &control_.stopFlag();
    const auto progress = [&](const fit::SweepFitProgress& p) {
        v1::JobEvent e;
        e.set_kind(v1::FIT_PROGRESS);
        e.set_frame_index(static_cast<uint32_t>(p.frames_done));
        e.set_fit_frames_total(static_cast<uint32_t>(p.frames_total));
        e.set_angle_deg(p.angle_deg);
        const double elapsed = secondsSince(start);
        e.set_elapsed_s(elapsed);
        if (p.frames_done > 0)
            e.set_eta_s(elapsed / p.frames_done *
                        static_cast<double>(std::max<int64_t>(0, p.frames_total - p.frames_done)));
        e.set_message(std::to_string(p.frames_done) + "/" + std::to_string(p.frames_total) +
                      " frames fitted, " + std::to_string(p.live_ghosts) + " ghosts");
        control_.event(std::move(e));
    };
    fit::SweepFitResult fitted;
    auto model = fit::fitSweep(*sweep, (*size)[0], (*size)[1], options, progress, &fitted);
    if (!model) {
        if (control_.stopFlag()) return;  // stopped, not failed
        return fail("fit: " + model.error().message, false);
    }
    if (sweep_.lens && sweep_.config.has_sim()) {
        model->lens.prescription_file = sweep_.config.sim().lens().name();
        model->lens.prescription_sha256 = sweep->header.lens.prescription_sha256;
        if (!model->lens.f_number && sweep_.lens->camera().f_number > 0.0)
            model->lens.f_number = sweep_.lens->camera().f_number;
    }
    const std::string path = (fs::path(sweep_.output_dir) / hdr::kSweepModelFile).string();
    if (Status ok = fit::writeModel(path, *model); !ok) return fail("fit: " + ok.error().message);
    const std::string text = fit::describeModel(*model, path);
    const fs::path text_path = fs::path(sweep_.output_dir) / hdr::kSweepModelText;
    FileDescriptor dir_fd(::open(sweep_.output_dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (Status ok = replaceFile(sweep_.output_dir, dir_fd.get(), hdr::kSweepModelText, text, {});
        !ok)
        control_.warning("model description: " + ok.error().message);
    result_.model_file = path;
    result_.fit_wall_s = secondsSince(start);
}

RunResult SweepJob::run() {
    auto prepared = prepareSweep(resumable(job_.config()), options_.output_root, options_.limits);
    if (!prepared) {
        result_.reason = prepared.error().message;
        return result_;
    }
    sweep_ = std::move(*prepared);
    // A device that cannot be opened now (unplugged, powered off, busy) pauses the job, and a
    // resume tries again; a request the devices cannot serve fails it.
    for (;;) {
        if (!control_.checkpoint()) {
            result_.outcome = RunOutcome::Stopped;
            return result_;
        }
        Status ok = makeRig();
        if (ok) break;
        const ErrorCode code = ok.error().code;
        if (code == ErrorCode::InvalidArgument || code == ErrorCode::Unsupported ||
            code == ErrorCode::ParseError) {
            result_.reason = "rig: " + ok.error().message;
            return result_;
        }
        if (!control_.pauseForFault("rig: " + ok.error().message +
                                    "; resume the job when the device is back")) {
            result_.outcome = RunOutcome::Stopped;
            return result_;
        }
    }
    std::optional<RigStopper> stopper(std::in_place, control_, head_, camera_);
    control_.setPhase(v1::HOMING);
    for (int tries = 0;; ++tries) {
        if (!control_.checkpoint()) {
            result_.outcome = RunOutcome::Stopped;
            return result_;
        }
        Status homed = head_->home(600.0);
        if (homed) break;
        if (tries < options_.head_retries) continue;
        if (!control_.pauseForFault("head could not be homed: " + homed.error().message +
                                    "; check the head, then resume the job")) {
            result_.outcome = RunOutcome::Stopped;
            return result_;
        }
        tries = -1;
    }
    if (sweep_.exposure_times_s.empty()) {
        if (Status ok = planBracket(); !ok) {
            if (result_.outcome != RunOutcome::Stopped) result_.reason = ok.error().message;
            return result_;
        }
    }
    auto opened = openSweep();
    if (!opened) {
        result_.reason = opened.error().message;
        // A disk that refused may come back; another sweep in the directory stays.
        result_.resumable = opened.error().code == ErrorCode::IoError;
        return result_;
    }
    std::optional<hdr::SweepWriter> writer(std::move(*opened));
    // Resume where the sweep on disk ends: its frames must be this job's first angles.
    const auto& listed = writer->sweep().frames;
    if (listed.size() > sweep_.angles_deg.size()) {
        result_.reason = sweep_.output_dir + " holds " + std::to_string(listed.size()) +
                         " frames, more than this sweep's " +
                         std::to_string(sweep_.angles_deg.size());
        return result_;
    }
    for (size_t i = 0; i < listed.size(); ++i)
        if (std::abs(listed[i].angle_deg - sweep_.angles_deg[i]) > 0.5 * sweep_.config.step_deg()) {
            result_.reason = sweep_.output_dir + ": frame " + std::to_string(i) + " lies at " +
                             num(listed[i].angle_deg) + " deg, but this sweep's is at " +
                             num(sweep_.angles_deg[i]) + " deg: not this sweep";
            return result_;
        }
    first_ = listed.size();
    on_disk_ = static_cast<uint32_t>(first_);
    control_.setFramesDone(on_disk_);
    if (first_ > 0)
        control_.warning("resuming at frame " + std::to_string(first_) + " of " +
                         std::to_string(sweep_.angles_deg.size()) + " (" +
                         num(sweep_.angles_deg[std::min(first_, sweep_.angles_deg.size() - 1)]) +
                         " deg): the frames before are on disk");
    if (sim_camera_)
        sim_camera_->setSequence(static_cast<int64_t>(first_ * sweep_.exposure_times_s.size()));

    control_.setPhase(v1::CAPTURE);
    capture_start_ = Clock::now();
    // The queue holds what the memory budget leaves once the rest of the job is counted (at least
    // one bracket: prepareSweep and makeRig refused jobs that do not fit).
    const JobMemory memory =
        jobMemory(width_px_, height_px_, static_cast<int64_t>(sweep_.exposure_times_s.size()),
                  sim_camera_ != nullptr);
    const int64_t queue_bytes =
        std::max(memory.bracket_bytes, options_.limits.memory_budget_bytes - memory.fixed_bytes);
    BoundedQueue<Captured> queue(std::max<size_t>(1, options_.queue_frames),
                                 static_cast<size_t>(queue_bytes), bracketBytes);
    std::thread processing([&] { processLoop(queue, *writer); });
    captureLoop(first_, queue);
    stopper.reset();  // the rig is left alone from here
    processing.join();
    result_.queue_high_water = queue.highWater();
    result_.queue_high_water_bytes = queue.highWaterBytes();
    result_.capture_wall_s = secondsSince(capture_start_);
    logStatistics();
    // Whatever the outcome, the frames written are listed in the compacted manifest; a failed
    // compaction leaves them listed in the frame log.
    if (writer->broken().empty())
        if (Status finished = writer->finish(); !finished) {
            if (!writer->broken().empty())
                failWrite(finished.error().message, false);
            else
                control_.warning("sweep: " + finished.error().message +
                                 " (the frame log still lists every frame)");
        }
    result_.frames_on_disk = on_disk_;
    if (failed_) return result_;
    if (on_disk_ < sweep_.angles_deg.size()) {
        result_.outcome = RunOutcome::Stopped;
        return result_;
    }
    result_.outcome = sweep_.config.fit() ? RunOutcome::Captured : RunOutcome::Succeeded;
    return result_;
}

RunResult SweepJob::fit() {
    auto prepared = prepareSweep(resumable(job_.config()), options_.output_root, options_.limits);
    if (!prepared) {
        result_.reason = prepared.error().message;
        return result_;
    }
    sweep_ = std::move(*prepared);
    fitModel();
    if (failed_) return result_;
    result_.outcome = result_.model_file.empty() ? RunOutcome::Stopped : RunOutcome::Succeeded;
    return result_;
}

}  // namespace

void settleAllocator() { ::mallopt(M_MMAP_THRESHOLD, 256 * 1024); }

Result<drivers::Rig> openJobRig(const PreparedSweep& sweep, const SweepLimits& limits) {
    const v1::SweepConfig& c = sweep.config;
    const v1::SimSettings& sim = c.sim();  // the defaults when the job simulates nothing
    drivers::RigOptions options;
    options.sim_clock = std::make_shared<drivers::SimClock>(
        c.has_sim() && sim.fast() ? drivers::SimTime::Fast : drivers::SimTime::RealTime);
    drivers::SimHeadOptions& head = options.sim_head;
    head.seed = c.has_sim() ? sim.seed() : 1;
    head.min_deg = limits.head_min_deg;
    head.max_deg = limits.head_max_deg;
    head.speed_deg_s = limits.head_speed_deg_s;
    head.acceleration_deg_s2 = limits.head_acceleration_deg_s2;
    head.settle_s = limits.head_settle_s;
    if (sim.faults().has_head_stall_at_deg())
        head.faults.stall_at_deg = sim.faults().head_stall_at_deg();
    head.faults.hang_moves = static_cast<int>(sim.faults().head_hangs());
    drivers::SimCameraOptions& camera = options.sim_camera;
    if (c.width_px() > 0) camera.width_px = c.width_px();
    if (c.height_px() > 0) camera.height_px = c.height_px();
    camera.seed = head.seed;
    camera.gain = c.gain();
    camera.readout_s = limits.readout_s;
    options.sim_lens = sweep.lens;
    auto registries = drivers::makeRigRegistries(options);
    if (!registries) return registries.error();
    return drivers::openRig(*registries, sweep.camera_uri.empty() ? "sim:" : sweep.camera_uri,
                            sweep.head_uri.empty() ? "sim:" : sweep.head_uri, options);
}

namespace {

// A job that runs out of memory (or meets another exception) outside its pipeline's threads, which
// catch their own, fails; the daemon goes on.
template <typename Stage>
RunResult guarded(const char* what, Stage stage) {
    try {
        return stage();
    } catch (const std::bad_alloc&) {
        RunResult failed;
        failed.reason = std::string(what) + ": out of memory (std::bad_alloc)";
        failed.resumable = true;
        return failed;
    } catch (const std::exception& e) {
        RunResult failed;
        failed.reason = std::string(what) + ": " + e.what();
        return failed;
    }
}

}  // namespace

RunResult runSweepJob(const v1::Job& job, const RunnerOptions& options, JobControl& control) {
    return guarded("capture", [&] {
        SweepJob sweep(job, options, control);
        return sweep.run();
    });
}

RunResult fitSweepJob(const v1::Job& job, const RunnerOptions& options, JobControl& control) {
    return guarded("fit", [&] {
        SweepJob sweep(job, options, control);
        return sweep.fit();
    });
}

}  // namespace flarelab::daemon
