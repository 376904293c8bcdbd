#include "apps/capture_command.h"

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <iomanip>
#include <memory>
#include <ostream>
#include <sstream>
#include <string>
#include <vector>

#include "apps/camera_flags.h"
#include "apps/fit_command.h"
#include "drivers/auto_bracket.h"
#include "drivers/calibration.h"
#include "drivers/lens_settings.h"
#include "drivers/rig.h"
#include "hdr/digest.h"
#include "hdr/merge.h"
#include "hdr/raw_io.h"
#include "hdr/sweep.h"
#include "render/preview.h"

namespace flarelab::apps {
namespace {

struct CaptureState {
    bool sim = false;
    std::string camera_uri;  // empty: "sim:" with --sim
    std::string head_uri;
    std::string format;     // the camera's raw format (hdr::parseRawFormat); empty: its default
    double pixel_um = 0.0;  // the sensor's pixel pitch, for cameras other than the simulated one
    std::string lens_file;
    CameraFlags camera;
    double from_deg = 0.0;
    double to_deg = 30.0;
    double step_deg = 0.2;
    std::string brackets = "auto";
    std::string calibration_file;
    int64_t width = 640;
    int64_t height = 427;
    bool fast = false;
    uint64_t seed = 1;
    bool keep_raw = false;
    bool resume = false;
    std::string previews;  // directory for PNG previews, empty for none
    double preview_stops = 0.0;
    std::string output;
};

std::string seconds(double s) {
    std::ostringstream o;
    o << std::fixed << std::setprecision(s < 10 ? 1 : 0) << s << " s";
    return o.str();
}

// One line of progress: a bar, frames done, elapsed time and the estimate of what is left.
void progress(std::ostream& err, bool terminal, size_t done, size_t total, double elapsed_s) {
    constexpr int kWidth = 30;
    const int filled = static_cast<int>(kWidth * done / std::max<size_t>(total, 1));
    const double eta = done > 0 ? elapsed_s / done * (total - done) : 0.0;
    err << (terminal ? "\r" : "") << "capture: [" << std::string(filled, '#')
        << std::string(kWidth - filled, ' ') << "] " << done << "/" << total << " frames, "
        << seconds(elapsed_s) << " elapsed, ETA " << seconds(eta) << (terminal ? "" : "\n")
        << std::flush;
}

std::string bracketText(const std::vector<double>& times) {
    std::ostringstream o;
    for (size_t k = 0; k < times.size(); ++k) o << (k ? "," : "") << times[k];
    return o.str();
}

// Whether the simulated camera wears the --lens file's lens: a sim: URI may name its own.
bool sameLens(const optics::Lens& a, const optics::Lens& b) {
    if (a.name() != b.name() || a.surfaces().size() != b.surfaces().size()) return false;
    for (size_t i = 0; i < a.surfaces().size(); ++i) {
        const optics::LensSurface& x = a.surfaces()[i];
        const optics::LensSurface& y = b.surfaces()[i];
        if (x.z_mm != y.z_mm || x.curvature != y.curvature || x.ior_d != y.ior_d ||
            x.abbe != y.abbe)
            return false;
    }
    return true;
}

int run(const CaptureState& s, std::ostream& out, std::ostream& err) {
    const std::string camera_uri = !s.camera_uri.empty() ? s.camera_uri : s.sim ? "sim:" : "";
    const std::string head_uri = !s.head_uri.empty() ? s.head_uri : s.sim ? "sim:" : "";
    if (camera_uri.empty() || head_uri.empty()) {
        err << "flarelab: capture needs a rig: --camera URI and --head URI (see `flarelab rig "
               "devices`), or --sim for the simulated rig\n";
        return 1;
    }
    const bool auto_brackets = s.brackets == "auto";
    std::vector<double> times;
    if (!auto_brackets) {
        auto given = parseBrackets(s.brackets);
        if (!given) {
            err << "flarelab: " << given.error().message << "\n";
            return 1;
        }
        times = std::move(*given);
    }
    std::optional<drivers::CameraCalibration> calibration;
    if (!s.calibration_file.empty()) {
        auto read = drivers::readCalibration(s.calibration_file);
        if (!read) {
            err << "flarelab: --calibration: " << read.error().message << "\n";
            return 1;
        }
        calibration = std::move(*read);
    }
    if (!(s.step_deg > 0.0) || !std::isfinite(s.from_deg) || !std::isfinite(s.to_deg) ||
        s.to_deg < s.from_deg) {
        err << "flarelab: capture needs --from <= --to and --step > 0\n";
        return 1;
    }
    if (!(s.pixel_um >= 0.0) || !std::isfinite(s.pixel_um)) {
        err << "flarelab: --pixel-um must be a positive number of micrometres\n";
        return 1;
    }
    const double span = s.to_deg - s.from_deg;
    const size_t frames = static_cast<size_t>(std::floor(span / s.step_deg + 1e-9)) + 1;
    if (frames > 100000) {
        err << "flarelab: capture: " << frames << " frames is more than 100000\n";
        return 1;
    }
    std::optional<optics::Lens> lens;
    if (!s.lens_file.empty()) {
        lens = loadLens(s.lens_file, s.camera, err);
        if (!lens) return 1;
    }

    drivers::RigOptions rig_options;
    rig_options.sim_clock = std::make_shared<drivers::SimClock>(
        s.fast ? drivers::SimTime::Fast : drivers::SimTime::RealTime);
    rig_options.sim_head.seed = s.seed;
    rig_options.sim_camera.width_px = s.width;
    rig_options.sim_camera.height_px = s.height;
    rig_options.sim_camera.seed = s.seed;
    rig_options.sim_lens = lens;
    auto registries = drivers::makeRigRegistries(rig_options);
    if (!registries) {
        err << "flarelab: " << registries.error().message << "\n";
        return 1;
    }
    auto rig = drivers::openRig(*registries, camera_uri, head_uri, rig_options);
    if (!rig) {
        err << "flarelab: " << rig.error().message << "\n";
        return 1;
    }
    drivers::Camera& camera = *rig->camera;
    drivers::Head& head = *rig->head;
    if (!s.format.empty()) {
        const std::optional<hdr::RawFormat> format = hdr::parseRawFormat(s.format);
        if (!format) {
            err << "flarelab: capture: --format " << s.format
                << " is not mono, bayer-rggb, bayer-bggr, bayer-grbg or bayer-gbrg\n";
            return 1;
        }
        if (Status ok = camera.setFormat(*format); !ok) {
            err << "flarelab: capture: --format " << s.format << ": " << ok.error().message << "\n";
            return 1;
        }
    }
    const drivers::CameraCapabilities caps = camera.capabilities();
    for (const std::string& note : camera.notes()) err << "flarelab: note: " << note << "\n";
    // A camera known not to be linear is merged only through its response curve.
    if (Status ok = drivers::checkCalibrationFor(camera, calibration ? &*calibration : nullptr);
        !ok) {
        err << "flarelab: " << ok.error().message << "\n";
        return 1;
    }
    constexpr double kTimeout_s = 600.0;
    if (Status homed = head.home(kTimeout_s); !homed) {
        err << "flarelab: " << homed.error().message << "\n";
        return 1;
    }
    // The bracket: given, the one a resumed sweep was taken with, or planned from probes at the
    // first angle.
    if (auto_brackets) {
        std::optional<std::vector<double>> resumed;
        if (s.resume)
            if (auto existing = hdr::readSweepManifest(s.output))
                resumed = existing->header.capture.exposure_times_s;
        if (resumed) {
            times = *resumed;
        } else {
            if (auto at = head.moveTo(s.from_deg, kTimeout_s); !at) {
                err << "flarelab: " << at.error().message << "\n";
                return 1;
            }
            drivers::BracketPlanOptions plan_options;
            plan_options.calibration = calibration ? &*calibration : nullptr;
            auto plan = drivers::planBrackets(camera, plan_options);
            if (!plan) {
                err << "flarelab: planning the bracket: " << plan.error().message << "\n";
                return 1;
            }
            for (const std::string& reason : plan->reasons)
                err << "flarelab: bracket: " << reason << "\n";
            if (!plan->core_unclipped || !plan->floor_reached)
                err << "flarelab: warning: the planned bracket "
                    << (!plan->core_unclipped ? "clips the light's core" : "")
                    << (!plan->core_unclipped && !plan->floor_reached ? " and " : "")
                    << (!plan->floor_reached ? "does not reach the ghosts' noise floor" : "")
                    << " (the lines above say why)\n";
            times = plan->exposure_times_s;
        }
    }

    hdr::SweepHeader header;
    header.software_version = rig->sim_camera
                                  ? "flarelab capture (simulated rig)"
                                  : "flarelab capture (" + camera_uri + ", " + head_uri + ")";
    const optics::Lens* sim_lens = rig->sim_camera ? &rig->sim_camera->lens() : nullptr;
    // The lens and its camera settings, so that a score simulates the same lens again: the
    // simulated camera's own, or the one --lens says a real camera wears.
    const optics::Lens* described = sim_lens ? sim_lens : lens ? &*lens : nullptr;
    if (described) header.lens = drivers::describeLens(*described);
    if (!sim_lens) {
        // A real camera's sensor is what its pixel pitch says, not the --sensor-mm default.
        header.lens.sensor_width_mm.reset();
        header.lens.sensor_height_mm.reset();
    }
    if (lens && (!sim_lens || sameLens(*sim_lens, *lens))) {
        auto digest = hdr::sha256File(s.lens_file);
        if (!digest) {
            err << "flarelab: " << digest.error().message << "\n";
            return 1;
        }
        header.lens.prescription_file = s.lens_file;
        header.lens.prescription_sha256 = *digest;
    }
    header.camera.description = camera.identity().model;
    header.camera.serial = camera.identity().serial;
    header.camera.bit_depth = caps.bit_depth;
    header.camera.raw_format = camera.format();
    header.camera.light_power_dn_s = camera.lightPowerDnPerS();
    // The sensor's geometry, so that a fit maps pixels to sensor mm: the simulated camera's own;
    // for other cameras what --pixel-um says.
    if (s.pixel_um > 0.0)
        header.camera.pixel_pitch_um = s.pixel_um;
    else if (sim_lens)
        header.camera.pixel_pitch_um =
            1000.0 * sim_lens->camera().sensor_width_mm / static_cast<double>(caps.width_px);
    header.capture.from_deg = s.from_deg;
    header.capture.to_deg = s.to_deg;
    header.capture.step_deg = s.step_deg;
    header.capture.exposure_times_s = times;
    header.capture.gain = camera.gain();
    header.capture.width_px = caps.width_px;
    header.capture.height_px = caps.height_px;
    hdr::SweepWriteOptions write_options;
    write_options.resume = s.resume;
    auto writer = hdr::SweepWriter::create(s.output, header, write_options);
    if (!writer) {
        err << "flarelab: " << writer.error().message << "\n";
        return 1;
    }
    const bool terminal = ::isatty(STDERR_FILENO) != 0;
    const auto start = std::chrono::steady_clock::now();
    const auto elapsed = [&] {
        return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    };
    size_t written = 0, skipped = 0;
    const double last_angle = writer->sweep().frames.empty()
                                  ? -std::numeric_limits<double>::infinity()
                                  : writer->sweep().frames.back().angle_deg;
    for (size_t i = 0; i < frames; ++i) {
        // from + i step, rounded to a nanodegree so that 0 + 2 x 0.2 is 0.4 and not
        // 0.4000000000000001 in the manifest.
        const double angle = std::min(
            s.to_deg, std::round((s.from_deg + static_cast<double>(i) * s.step_deg) * 1e9) / 1e9);
        if (angle <= last_angle) {  // resumed: already on disk
            ++skipped;
            continue;
        }
        const auto at = head.moveTo(angle, kTimeout_s);
        if (!at) {
            err << "\nflarelab: " << at.error().message << "\n";
            return 1;
        }
        std::vector<hdr::RawFrame> bracket;
        hdr::SweepFrame frame;
        for (size_t k = 0; k < times.size(); ++k) {
            const double t = times[k];
            auto captured = [&]() -> Result<hdr::RawFrame> {
                if (Status set = camera.setExposure(t); !set) return set.error();
                return camera.capture(kTimeout_s);
            }();
            if (!captured) {
                err << "\nflarelab: frame " << i << " at " << angle << " deg, exposure " << t
                    << " s: " << captured.error().message << "\n";
                return 1;
            }
            if (s.keep_raw) {
                std::ostringstream name;
                name << "raw/frame_" << std::setw(5) << std::setfill('0') << i << "_" << k
                     << ".pgm";
                std::filesystem::create_directories(s.output + "/raw");
                if (Status ok = hdr::writeRaw(s.output + "/" + name.str(), *captured); !ok) {
                    err << "\nflarelab: " << ok.error().message << "\n";
                    return 1;
                }
                frame.raw_files.push_back(name.str());
            }
            // Kept as the camera gave it (above); merged through its calibration.
            if (calibration) {
                auto calibrated = drivers::applyCalibration(*captured, *calibration);
                if (!calibrated) {
                    err << "\nflarelab: frame " << i << " at " << angle << " deg, exposure " << t
                        << " s: " << calibrated.error().message << "\n";
                    return 1;
                }
                *captured = std::move(*calibrated);
            }
            // Which of its samples the merge can use: recorded per exposure in the manifest.
            const auto counts = hdr::countExposure(*captured);
            if (!counts) {
                err << "\nflarelab: frame " << i << " at " << angle << " deg, exposure " << t
                    << " s: " << counts.error().message << "\n";
                return 1;
            }
            frame.brackets.push_back({t, static_cast<uint64_t>(counts->usable),
                                      static_cast<uint64_t>(counts->saturated)});
            bracket.push_back(std::move(*captured));
        }
        auto merged = hdr::mergeBrackets(bracket);
        if (!merged) {
            err << "\nflarelab: frame " << i << ": " << merged.error().message << "\n";
            return 1;
        }
        auto image = hdr::toImage(*merged);
        auto bounds = hdr::lowerBounds(*merged);
        if (!image || !bounds) {
            err << "\nflarelab: frame " << i << ": "
                << (!image ? image.error().message : bounds.error().message) << "\n";
            return 1;
        }
        // Where the head reported it stood, to a nanodegree (its arithmetic may add an ulp).
        frame.angle_deg = std::round(*at * 1e9) / 1e9;
        // The manifest lists the bracket in the order it was taken, with its raw files.
        frame.exposure_times_s = times;
        frame.merge_method = merged->method;
        auto added = writer->addFrame(*image, frame, {}, *bounds);
        if (!added) {
            err << "\nflarelab: frame " << i << ": " << added.error().message << "\n";
            return 1;
        }
        if (!s.previews.empty()) {
            std::filesystem::create_directories(s.previews);
            render::ToneMapOptions tone;
            tone.exposure_stops = s.preview_stops;
            const std::string png =
                s.previews + "/" + std::filesystem::path(added->exr_file).stem().string() + ".png";
            if (Status ok = render::writePng(*image, png, tone); !ok) {
                err << "\nflarelab: " << ok.error().message << "\n";
                return 1;
            }
        }
        ++written;
        if (terminal || written % std::max<size_t>(1, frames / 10) == 0 || i + 1 == frames)
            progress(err, terminal, i + 1, frames, elapsed());
    }
    if (terminal) err << "\n";
    // The frame log compacted into the manifest and removed: the finished sweep is its manifest
    // and frames (hdr/sweep.h). When that fails the log still lists every frame.
    if (Status ok = writer->finish(); !ok) {
        err << "flarelab: " << ok.error().message << "\n";
        return 1;
    }
    const hdr::ClippedFrames clipped = hdr::clippedFrames(writer->sweep());
    if (const std::string w = hdr::clippingWarning(clipped, writer->sweep().frames.size());
        !w.empty())
        err << "flarelab: warning: " << w << "\n";
    out << "capture: " << written << " frames"
        << (skipped ? " (" + std::to_string(skipped) + " already there)" : "") << " of "
        << (header.lens.description.empty() ? camera_uri : header.lens.description) << ", "
        << s.from_deg << " to " << s.to_deg << " deg in steps of " << s.step_deg << ", brackets "
        << bracketText(times) << (auto_brackets ? " s (planned), " : " s, ") << caps.width_px << "x"
        << caps.height_px << ", " << seconds(elapsed()) << (s.fast ? " (fast)" : "") << " -> "
        << s.output << "\n";
    return 0;
}

}  // namespace

Result<std::vector<double>> parseExposureTimes(const std::string& text, const std::string& flag) {
    std::vector<double> times;
    std::stringstream in(text);
    std::string part;
    while (std::getline(in, part, ',')) {
        size_t used = 0;
        double t = 0.0;
        try {
            t = std::stod(part, &used);
        } catch (const std::exception&) {
            used = 0;
        }
        if (used == 0 || used != part.size() || !(t > 0.0) || !std::isfinite(t))
            return makeError(ErrorCode::InvalidArgument,
                             flag + ": '" + part + "' is not a positive exposure time in seconds");
        times.push_back(t);
    }
    return times;
}

Result<std::vector<double>> parseBrackets(const std::string& text) {
    auto times = parseExposureTimes(text, "--brackets");
    if (!times) return times.error();
    if (times->empty())
        return makeError(ErrorCode::InvalidArgument, "--brackets: give at least one exposure time");
    return times;
}

void addCaptureCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto state = std::make_shared<CaptureState>();
    CLI::App* cmd = app.add_subcommand("capture", "take a sweep of bracketed frames on a rig");
    cmd->add_flag("--sim", state->sim,
                  "use the simulated rig: --camera sim: --head sim: unless they say otherwise");
    cmd->add_option("--camera", state->camera_uri,
                    "camera URI or alias (sim:, aravis:ID, v4l2:/dev/videoN, libcamera:NAME)");
    cmd->add_option("--head", state->head_uri,
                    "head URI or alias (sim:, zaber:/dev/ttyUSB0?axis=1, apt:/dev/ttyUSB0)");
    cmd->add_option("--lens", state->lens_file,
                    "the lens (CSV, format v1): the simulated camera's, or the one a real camera "
                    "wears, for the sweep's description");
    cmd->add_option("--format", state->format,
                    "the camera's raw format: mono, or a Bayer mosaic (bayer-rggb, bayer-bggr, "
                    "bayer-grbg, bayer-gbrg; frames are demosaiced to RGB); default: the camera's. "
                    "The simulated camera has mono (its green channel) and bayer-rggb");
    cmd->add_option("--pixel-um", state->pixel_um,
                    "pixel pitch of a real camera's sensor in micrometres (the fit maps pixels to "
                    "sensor mm with it)");
    cmd->add_option("--from", state->from_deg, "first angle (deg)")->capture_default_str();
    cmd->add_option("--to", state->to_deg, "last angle (deg)")->capture_default_str();
    cmd->add_option("--step", state->step_deg, "angle step (deg)")->capture_default_str();
    cmd->add_option("--brackets", state->brackets,
                    "exposure times in seconds, comma separated, or auto: planned from probes of "
                    "the light at the first angle")
        ->capture_default_str();
    cmd->add_option("--calibration", state->calibration_file,
                    "the camera's calibration (flarelab calibrate): frames are merged through it");
    cmd->add_option("--width", state->width, "frame width of the simulated camera")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}))
        ->capture_default_str();
    cmd->add_option("--height", state->height, "frame height of the simulated camera")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}))
        ->capture_default_str();
    cmd->add_flag("--fast", state->fast, "simulated time: do not wait for exposures and moves");
    cmd->add_option("--seed", state->seed, "noise seed")->capture_default_str();
    cmd->add_flag("--keep-raw", state->keep_raw, "also keep every raw bracket (raw/*.pgm)");
    cmd->add_flag("--resume", state->resume, "continue an interrupted sweep in the directory");
    cmd->add_option("--previews", state->previews, "also write a PNG preview of every frame here");
    cmd->add_option("--preview-stops", state->preview_stops, "exposure of the previews in stops")
        ->capture_default_str();
    cmd->add_option("-o,--output", state->output, "sweep directory")->required();
    addCameraFlags(cmd, state->camera);
    cmd->callback([state, &out, &err, &exit_code] { exit_code = run(*state, out, err); });
}

}  // namespace flarelab::apps
