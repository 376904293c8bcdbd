#include "daemon/sweep_config.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <sstream>

#include "drivers/sim_head.h"
#include "hdr/sweep.h"
#include "optics/prescription.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;

std::string num(double v) {
    std::ostringstream o;
    o.precision(10);
    o << v;
    return o.str();
}

Error bad(const std::string& field, const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, field + ": " + what);
}

// A finite number in [lo, hi] (bounds in the message).
Status inRange(const std::string& field, double v, double lo, double hi) {
    if (!std::isfinite(v) || v < lo || v > hi)
        return bad(field, "must be a finite number in [" + num(lo) + ", " + num(hi) + "] (got " +
                              num(v) + ")");
    return Ok{};
}

bool hasControl(const std::string& s) {
    for (const unsigned char c : s)
        if (c < 0x20 || c == 0x7f) return true;
    return false;
}

bool within(const fs::path& inner, const fs::path& root) {
    auto r = root.begin(), i = inner.begin();
    for (; r != root.end(); ++r, ++i)
        if (i == inner.end() || *i != *r) return false;
    return true;
}

// The simulated camera's lens and settings (config.sim) into p.lens; c's seed defaulted.
Status prepareSimLens(v1::SweepConfig& c, const SweepLimits& limits, PreparedSweep& p) {
    // The simulated camera's lens.
    const v1::SimLens& sl = c.sim().lens();
    if (sl.prescription_csv().empty())
        return bad("config.sim.lens.prescription_csv", "is empty: send the lens file's text");
    if (static_cast<int64_t>(sl.prescription_csv().size()) > limits.max_prescription_bytes)
        return bad("config.sim.lens.prescription_csv",
                   "is " + std::to_string(sl.prescription_csv().size()) + " bytes, more than " +
                       std::to_string(limits.max_prescription_bytes));
    if (sl.name().size() > 255 || hasControl(sl.name()))
        return bad("config.sim.lens.name", "must be at most 255 printable characters");
    const std::string lens_name = sl.name().empty() ? "lens" : sl.name();
    auto prescription = optics::parsePrescription(sl.prescription_csv(), lens_name);
    if (!prescription) return bad("config.sim.lens.prescription_csv", prescription.error().message);
    for (const auto& [field, value] :
         {std::pair<const char*, double>{"focal_length_mm", sl.focal_length_mm()},
          {"f_number", sl.f_number()},
          {"sensor_width_mm", sl.sensor_width_mm()},
          {"sensor_height_mm", sl.sensor_height_mm()}})
        if (Status ok = inRange(std::string("config.sim.lens.") + field, value, 0.0, 1e4); !ok)
            return ok.error();
    if (Status ok =
            inRange("config.sim.lens.blade_rotation_deg", sl.blade_rotation_deg(), -360.0, 360.0);
        !ok)
        return ok.error();
    if (sl.aperture_blades() == 1 || sl.aperture_blades() == 2 || sl.aperture_blades() > 64)
        return bad(
            "config.sim.lens.aperture_blades",
            "must be 0 (a circle) or 3..64 (got " + std::to_string(sl.aperture_blades()) + ")");
    optics::CameraDescription camera;
    camera.focal_length_mm = sl.focal_length_mm();
    camera.f_number = sl.f_number();
    if (sl.sensor_width_mm() > 0.0) camera.sensor_width_mm = sl.sensor_width_mm();
    if (sl.sensor_height_mm() > 0.0) camera.sensor_height_mm = sl.sensor_height_mm();
    camera.aperture_blades = static_cast<int>(sl.aperture_blades());
    camera.aperture_rotation_deg = sl.blade_rotation_deg();
    camera.coat_unspecified_surfaces = sl.coat_unspecified();
    auto lens = optics::Lens::make(*prescription, camera);
    if (!lens) return bad("config.sim.lens", lens.error().message);
    p.lens = sl.table_stop() ? lens->withStopSemiAperture(lens->tableStopSemiAperture_mm()) : *lens;
    return Ok{};
}

}  // namespace

JobMemory jobMemory(int64_t width_px, int64_t height_px, int64_t exposures, bool simulated_camera) {
    const int64_t pixels = width_px * height_px;
    // A simulated camera renders the scene as RGB floats (12 bytes a pixel) and keeps the last
    // four angles' planes (16); a real camera's driver keeps a few frames of its own.
    const int64_t capture_work = pixels * (simulated_camera ? 28 : 8);
    const int64_t processing_work = pixels * (5 + 12 + 3);
    JobMemory m;
    m.bracket_bytes = pixels * 2 * std::max<int64_t>(1, exposures);
    m.fixed_bytes = kDaemonBaselineBytes + 2 * m.bracket_bytes + capture_work + processing_work;
    m.minimum_bytes = m.fixed_bytes + m.bracket_bytes;
    return m;
}

Status checkMemoryBudget(int64_t width_px,
                         int64_t height_px,
                         int64_t exposures,
                         bool simulated_camera,
                         const SweepLimits& limits,
                         const std::string& field) {
    const JobMemory m = jobMemory(width_px, height_px, exposures, simulated_camera);
    if (m.minimum_bytes <= limits.memory_budget_bytes) return Ok{};
    const auto mib = [](int64_t bytes) { return std::to_string((bytes + (1 << 20) - 1) >> 20); };
    return bad(field,
               std::to_string(width_px) + " x " + std::to_string(height_px) +
                   " frames with a bracket of " + std::to_string(exposures) +
                   " exposures need at least " + mib(m.minimum_bytes) + " MiB in the daemon (" +
                   mib(m.bracket_bytes) +
                   " MiB per bracket, three held at once, and the merge, image and files), " +
                   "more than its memory budget of " + mib(limits.memory_budget_bytes) +
                   " MiB (flarelabd --memory-budget-mb)");
}

std::vector<double> sweepAngles(double from_deg, double to_deg, double step_deg) {
    std::vector<double> angles;
    const size_t frames =
        static_cast<size_t>(std::floor((to_deg - from_deg) / step_deg + 1e-9)) + 1;
    angles.reserve(frames);
    for (size_t i = 0; i < frames; ++i)
        angles.push_back(std::min(
            to_deg, std::round((from_deg + static_cast<double>(i) * step_deg) * 1e9) / 1e9));
    return angles;
}

Result<std::string> resolveOutputDir(const std::string& requested,
                                     const std::string& root,
                                     const std::string& field) {
    if (requested.empty()) return bad(field, "is empty: name the sweep directory");
    if (requested.size() > 4096) return bad(field, "is longer than 4096 bytes");
    if (requested.find('\0') != std::string::npos || hasControl(requested))
        return bad(field, "holds a control character");
    const fs::path given(requested);
    for (const fs::path& part : given)
        if (part == "..") return bad(field, "'" + requested + "' has a '..' component");
    const fs::path root_path(root);
    const fs::path full = (given.is_absolute() ? given : root_path / given).lexically_normal();
    const fs::path clean = full.has_filename() ? full : full.parent_path();
    if (!within(clean, root_path) || clean == root_path)
        return bad(field, "'" + requested + "' is not below the output root " + root);
    // The deepest part that exists, with its links resolved, must still lie below the root.
    fs::path existing = clean;
    std::error_code ec;
    while (!fs::exists(fs::symlink_status(existing, ec)) && existing != root_path)
        existing = existing.parent_path();
    const fs::path real = fs::canonical(existing, ec);
    if (ec) return bad(field, existing.string() + " cannot be resolved: " + ec.message());
    if (!within(real, root_path))
        return bad(field, "'" + requested + "' leads through '" + existing.string() + "' to " +
                              real.string() + ", outside the output root " + root);
    if (fs::exists(clean, ec) && !fs::is_directory(clean, ec))
        return bad(field, "'" + clean.string() + "' exists and is not a directory");
    return clean.string();
}

Result<PreparedSweep> prepareSweep(const v1::SweepConfig& given,
                                   const std::string& output_root,
                                   const SweepLimits& limits) {
    PreparedSweep p;
    p.config = given;
    v1::SweepConfig& c = p.config;
    if (limits.replay) {
        if (c.has_sim())
            return bad("config.sim", "this daemon replays the recorded sweep in " +
                                         limits.replay->directory +
                                         " (flarelabd --replay): leave sim out");
        if (!c.camera().empty() || !c.head().empty())
            return bad(c.camera().empty() ? "config.head" : "config.camera",
                       "this daemon replays a recorded sweep: it has no devices to choose");
    } else {
        // The devices: one the daemon has, by URI or alias, else simulated from config.sim.
        const auto choose = [&](const std::string& field, const std::string& asked,
                                const std::vector<std::string>& have,
                                std::string& chosen) -> Status {
            if (asked.size() > 1024 || hasControl(asked))
                return bad(field, "must be a device URI of at most 1024 printable characters");
            if (asked.empty()) {
                if (!have.empty()) chosen = have.front();
                return Ok{};
            }
            for (const std::string& uri : have)
                if (uri == asked) {
                    chosen = uri;
                    return Ok{};
                }
            std::string list;
            for (const std::string& uri : have) list += (list.empty() ? "" : ", ") + uri;
            return bad(field, "'" + asked + "' is not a device of this daemon (" +
                                  (have.empty() ? std::string("it drives the simulated rig only")
                                                : "it has " + list) +
                                  ")");
        };
        if (Status ok = choose("config.camera", c.camera(), limits.cameras, p.camera_uri); !ok)
            return ok.error();
        if (Status ok = choose("config.head", c.head(), limits.heads, p.head_uri); !ok)
            return ok.error();
        if (!p.camera_uri.empty() && !p.head_uri.empty()) {
            if (c.has_sim())
                return bad("config.sim", "this job runs on real devices (camera " + p.camera_uri +
                                             ", head " + p.head_uri +
                                             "): leave sim out, it has nothing to simulate");
        } else if (!c.has_sim()) {
            return bad("config.sim", "is missing: this job's " +
                                         std::string(p.camera_uri.empty() ? "camera" : "head") +
                                         " is simulated (the daemon has no --" +
                                         (p.camera_uri.empty() ? "camera" : "head") +
                                         "), and its settings go here");
        }
        if (p.camera_uri.empty()) {
            if (Status ok = prepareSimLens(c, limits, p); !ok) return ok.error();
        } else if (c.has_sim() && !c.sim().lens().prescription_csv().empty()) {
            return bad("config.sim.lens",
                       "the camera is " + p.camera_uri + ", not simulated: leave the lens out");
        }
        if (c.has_sim() && c.sim().seed() == 0) c.mutable_sim()->set_seed(1);
        if (c.has_sim()) {
            const v1::SimFaults& faults = c.sim().faults();
            if (faults.has_head_stall_at_deg() && !std::isfinite(faults.head_stall_at_deg()))
                return bad("config.sim.faults.head_stall_at_deg", "must be a finite angle");
            if (faults.camera_timeouts() > 1000 || faults.head_hangs() > 1000)
                return bad("config.sim.faults", "at most 1000 injected timeouts");
            if (!p.camera_uri.empty() && faults.camera_timeouts() > 0)
                return bad("config.sim.faults.camera_timeouts",
                           "the camera is " + p.camera_uri +
                               ": faults are injected only into "
                               "simulated devices");
            if (!p.head_uri.empty() && (faults.head_hangs() > 0 || faults.has_head_stall_at_deg()))
                return bad("config.sim.faults", "the head is " + p.head_uri +
                                                    ": faults are injected only into simulated "
                                                    "devices");
        }
    }
    if (!std::isfinite(c.pixel_pitch_um()) || c.pixel_pitch_um() < 0.0 ||
        c.pixel_pitch_um() > 1000.0)
        return bad("config.pixel_pitch_um",
                   "must be 0 (unknown) or a pixel pitch up to 1000 um (got " +
                       num(c.pixel_pitch_um()) + ")");
    if (c.lens_description().size() > 255 || hasControl(c.lens_description()))
        return bad("config.lens_description", "must be at most 255 printable characters");
    if (!c.raw_format().empty() && !hdr::parseRawFormat(c.raw_format()))
        return bad("config.raw_format",
                   "must be empty (the camera's), mono, bayer-rggb, bayer-bggr, bayer-grbg or "
                   "bayer-gbrg");

    // Angles.
    if (Status ok =
            inRange("config.from_deg", c.from_deg(), limits.head_min_deg, limits.head_max_deg);
        !ok)
        return ok.error();
    if (Status ok = inRange("config.to_deg", c.to_deg(), limits.head_min_deg, limits.head_max_deg);
        !ok)
        return ok.error();
    if (c.to_deg() < c.from_deg())
        return bad("config.to_deg",
                   "must be >= from_deg (" + num(c.from_deg()) + "; got " + num(c.to_deg()) + ")");
    if (!std::isfinite(c.step_deg()) || !(c.step_deg() > 0.0))
        return bad("config.step_deg",
                   "must be a finite number > 0 (got " + num(c.step_deg()) + ")");
    const double frames = std::floor((c.to_deg() - c.from_deg()) / c.step_deg() + 1e-9) + 1.0;
    if (frames > static_cast<double>(limits.max_frames))
        return bad("config.step_deg", num(c.step_deg()) + " deg over " + num(c.from_deg()) + ".." +
                                          num(c.to_deg()) + " makes " + num(frames) +
                                          " frames, more than " +
                                          std::to_string(limits.max_frames));
    p.angles_deg = sweepAngles(c.from_deg(), c.to_deg(), c.step_deg());
    if (limits.replay) {
        const auto& frames = limits.replay->frames;
        for (const double angle : p.angles_deg) {
            const bool recorded = std::any_of(frames.begin(), frames.end(), [&](const auto& f) {
                return std::abs(f.angle_deg - angle) <= 1e-6;
            });
            if (!recorded) {
                std::string have;
                for (size_t i = 0; i < frames.size() && i < 8; ++i)
                    have += (i ? ", " : "") + num(frames[i].angle_deg);
                return bad("config.step_deg", "the recorded sweep has no frame at " + num(angle) +
                                                  " deg (it has " + have +
                                                  (frames.size() > 8 ? ", ..." : "") + ")");
            }
        }
    }

    // The bracket and the sensor.
    // None: the job plans its bracket from probes at the first angle (drivers/auto_bracket.h).
    if (c.exposure_times_s_size() > limits.max_exposures)
        return bad("config.exposure_times_s", "has " + std::to_string(c.exposure_times_s_size()) +
                                                  " times, more than " +
                                                  std::to_string(limits.max_exposures));
    for (int i = 0; i < c.exposure_times_s_size(); ++i) {
        if (Status ok =
                inRange("config.exposure_times_s[" + std::to_string(i) + "]", c.exposure_times_s(i),
                        limits.min_exposure_s, limits.max_exposure_s);
            !ok)
            return ok.error();
        p.exposure_times_s.push_back(c.exposure_times_s(i));
    }
    if (c.gain() == 0.0) c.set_gain(1.0);
    if (Status ok = inRange("config.gain", c.gain(), limits.min_gain, limits.max_gain); !ok)
        return ok.error();
    const int64_t default_width = limits.replay ? limits.replay->header.capture.width_px : 640;
    const int64_t default_height = limits.replay ? limits.replay->header.capture.height_px : 427;
    // A real camera's size is what it delivers: 0 stays 0 until the job has opened it.
    const bool real_camera = !limits.replay && !p.camera_uri.empty();
    if (c.width_px() == 0 && !real_camera) c.set_width_px(static_cast<uint32_t>(default_width));
    if (c.height_px() == 0 && !real_camera) c.set_height_px(static_cast<uint32_t>(default_height));
    if (limits.replay && (c.width_px() != default_width || c.height_px() != default_height))
        return bad("config.width_px",
                   "the recorded sweep's frames are " + std::to_string(default_width) + " x " +
                       std::to_string(default_height) + " (got " + std::to_string(c.width_px()) +
                       " x " + std::to_string(c.height_px()) + ")");
    if (c.width_px() > hdr::kSweepMaxSide || c.height_px() > hdr::kSweepMaxSide)
        return bad(c.width_px() > hdr::kSweepMaxSide ? "config.width_px" : "config.height_px",
                   "must be 1.." + std::to_string(hdr::kSweepMaxSide));
    if (static_cast<int64_t>(c.width_px()) * c.height_px() > limits.max_pixels)
        return bad("config.width_px", std::to_string(c.width_px()) + " x " +
                                          std::to_string(c.height_px()) + " is more than " +
                                          std::to_string(limits.max_pixels) + " pixels");
    if (Status ok = inRange("config.preview_stops", c.preview_stops(), -64.0, 64.0); !ok)
        return ok.error();
    // A real camera's size is known once the job opens it; the job checks it then.
    if (c.width_px() > 0 && c.height_px() > 0)
        if (Status ok = checkMemoryBudget(c.width_px(), c.height_px(), c.exposure_times_s_size(),
                                          !limits.replay && p.camera_uri.empty(), limits,
                                          "config.width_px");
            !ok)
            return ok.error();
    if (c.fit() && p.angles_deg.size() < 2)
        return bad("config.fit", "a model needs a sweep of at least two angles");

    // Where it goes.
    auto dir = resolveOutputDir(c.output_dir(), output_root, "config.output_dir");
    if (!dir) return dir.error();
    p.output_dir = *dir;
    std::error_code ec;
    const bool has_manifest = fs::exists(fs::path(p.output_dir) / hdr::kSweepManifestFile, ec);
    if (has_manifest && !c.resume_existing())
        return bad("config.output_dir", "'" + p.output_dir +
                                            "' already holds a sweep: choose another directory, "
                                            "or set resume_existing to append to it");
    if (!has_manifest && fs::exists(p.output_dir, ec) && !fs::is_empty(p.output_dir, ec))
        p.warnings.push_back(p.output_dir + " exists and is not empty");

    // Rig time: the move to the first angle, then per frame a step and the bracket.
    double bracket_s = 0.0;
    for (const double t : p.exposure_times_s) bracket_s += t + limits.readout_s;
    const auto move = [&](double d) {
        return drivers::SimHead::moveDuration_s(std::abs(d), limits.head_speed_deg_s,
                                                limits.head_acceleration_deg_s2) +
               limits.head_settle_s;
    };
    p.rig_time_s = move(p.angles_deg.front()) + bracket_s * p.angles_deg.size();
    for (size_t i = 1; i < p.angles_deg.size(); ++i)
        p.rig_time_s += move(p.angles_deg[i] - p.angles_deg[i - 1]);
    if (p.exposure_times_s.empty())
        p.warnings.push_back(
            "the bracket is planned from probes of the light when the job reaches the first "
            "angle: the rig time counts head moves only, and each frame adds the planned "
            "bracket's exposures (at most 30 s)");
    return p;
}

}  // namespace flarelab::daemon
