#include "apps/calibrate_command.h"

#include <cmath>
#include <iomanip>
#include <memory>
#include <ostream>
#include <sstream>
#include <string>
#include <vector>

#include "apps/capture_command.h"
#include "drivers/calibration.h"
#include "drivers/calibration_measure.h"
#include "drivers/rig.h"
#include "drivers/sim_camera.h"

namespace flarelab::apps {
namespace {

struct CalibrateState {
    std::string camera;
    std::string head;
    std::string exposures;  // "0.01,0.02,..." or empty: planned by probes
    int pairs = 1;
    double gain = 0.0;  // 0: as the camera is
    std::string dark_frames_from;
    double dark_exposure_s = 4.0;
    double budget_s = 300.0;
    bool yes = false;
    std::string output;
};

std::string num(double x, int digits = 4) {
    std::ostringstream out;
    out << std::setprecision(digits) << x;
    return out.str();
}

Result<std::vector<double>> parseExposures(const std::string& text) {
    auto parsed = parseExposureTimes(text, "--exposures");
    if (!parsed) return parsed.error();
    const std::vector<double>& times = *parsed;
    if (times.size() < 3)
        return makeError(ErrorCode::InvalidArgument,
                         "--exposures: give at least 3 exposure times (a series from dim to "
                         "clipped)");
    return parsed;
}

const char* formatName(hdr::RawFormat format) {
    switch (format) {
        case hdr::RawFormat::Mono:
            return "mono";
        case hdr::RawFormat::BayerRGGB:
            return "Bayer RGGB";
        case hdr::RawFormat::BayerBGGR:
            return "Bayer BGGR";
        case hdr::RawFormat::BayerGRBG:
            return "Bayer GRBG";
        case hdr::RawFormat::BayerGBRG:
            return "Bayer GBRG";
    }
    return "?";
}

// Waits for the operator's Enter, unless --yes. False when the input ended (no operator).
bool ask(const CalibrateState& s, std::istream& in, std::ostream& out, const std::string& what) {
    out << what << (s.yes ? " (--yes: going on)" : "; press Enter when done") << "\n" << std::flush;
    if (s.yes) return true;
    std::string line;
    return static_cast<bool>(std::getline(in, line));
}

void report(const drivers::CameraCalibration& c, std::ostream& out) {
    out << "camera: " << drivers::calibrationCameraName(c) << ", " << c.width_px << "x"
        << c.height_px << " " << formatName(c.format) << ", " << c.bit_depth << " bits, gain "
        << num(c.gain) << "\n";
    out << "black level: " << num(c.black_level_dn, 6) << " DN\n";
    if (c.read_noise_dn > 0.0 || c.electrons_per_dn > 0.0) {
        out << "read noise: " << num(c.read_noise_dn) << " DN";
        if (c.electrons_per_dn > 0.0) out << " = " << num(c.read_noise_e) << " e-";
        out << (c.linear ? "" : " (in linearized 16-bit DN)") << "\n";
    } else {
        out << "read noise: not measured\n";
    }
    if (c.electrons_per_dn > 0.0)
        out << "conversion gain: " << num(c.electrons_per_dn) << " e-/DN"
            << (c.linear ? "" : " (in linearized 16-bit DN)") << "\n";
    else
        out << "conversion gain: not measured\n";
    out << "saturation: " << num(c.saturation_dn, 6) << " DN\n";
    if (c.linear) {
        out << "response: linear (linearity error " << num(100.0 * c.linearity_error, 3) << " %)\n";
    } else {
        out << "response: not linear (linearity error " << num(100.0 * c.linearity_error, 3)
            << " %); its curve was recovered and fits the samples to "
            << num(c.response_curve->rms_error_stops, 3)
            << " stops RMS: frames are linearized before merging\n";
    }
    out << "hot pixels: " << c.hot_pixels.size() << "\n";
    out << "how it was measured:\n";
    for (const std::string& note : c.notes) out << "  " << note << "\n";
}

int run(const CalibrateState& s, std::istream& in, std::ostream& out, std::ostream& err) {
    const auto fail = [&](const std::string& what) {
        err << "flarelab: calibrate: " << what << "\n";
        return 1;
    };
    if (s.pairs < 1 || s.pairs > 64) return fail("--pairs must lie in 1..64");
    if (!(s.dark_exposure_s > 0.0) || !(s.budget_s > 0.0))
        return fail("--dark-exposure and --budget must be positive");
    std::vector<double> exposures;
    if (!s.exposures.empty()) {
        auto parsed = parseExposures(s.exposures);
        if (!parsed) return fail(parsed.error().message);
        exposures = std::move(*parsed);
    }

    // The simulated devices run on simulated time: a calibration takes minutes of exposures.
    drivers::RigOptions rig_options;
    rig_options.sim_clock = std::make_shared<drivers::SimClock>(drivers::SimTime::Fast);
    auto registries = drivers::makeRigRegistries(rig_options);
    if (!registries) return fail(registries.error().message);
    std::shared_ptr<drivers::Camera> camera;
    std::shared_ptr<drivers::Head> head;
    if (!s.head.empty()) {
        auto rig = drivers::openRig(*registries, s.camera, s.head, rig_options);
        if (!rig) return fail(rig.error().message);
        camera = rig->camera;
        head = rig->head;
        // A head that does not know where it is is homed; otherwise it is not moved.
        if (auto at = head->position(); !at) {
            out << "homing the head (it does not know its position)\n";
            if (Status homed = head->home(600.0); !homed) return fail(homed.error().message);
        }
    } else {
        auto opened = registries->cameras.open(s.camera);
        if (!opened) return fail("camera '" + s.camera + "': " + opened.error().message);
        camera = std::shared_ptr<drivers::Camera>(std::move(*opened));
    }
    if (s.gain > 0.0)
        if (Status ok = camera->setGain(s.gain); !ok) return fail(ok.error().message);
    const drivers::DeviceIdentity identity = camera->identity();
    const drivers::CameraCapabilities caps = camera->capabilities();
    out << "calibrating " << identity.describe() << " (" << caps.width_px << "x" << caps.height_px
        << ", " << caps.bit_depth << " bits, exposures " << num(caps.min_exposure_s) << " to "
        << num(caps.max_exposure_s) << " s, gain " << num(camera->gain()) << ")\n";
    if (caps.response == drivers::CameraResponse::NonLinear)
        out << "the camera says its response is not linear"
            << (caps.response_note.empty() ? "" : " (" + caps.response_note + ")")
            << ": its curve will be recovered\n";

    drivers::CalibrationCapture capture;
    capture.frames_per_exposure = 2 * s.pairs;
    capture.long_dark_exposure_s = s.dark_exposure_s;
    capture.budget_s = s.budget_s;

    // 1. Dark frames.
    drivers::DarkFrames dark;
    auto* sim = dynamic_cast<drivers::SimCamera*>(camera.get());
    if (!s.dark_frames_from.empty()) {
        auto other = registries->cameras.open(s.dark_frames_from);
        if (!other)
            return fail("--dark-frames-from '" + s.dark_frames_from +
                        "': " + other.error().message);
        const drivers::DeviceIdentity other_id = (*other)->identity();
        if (other_id.model != identity.model || other_id.serial != identity.serial)
            return fail("--dark-frames-from '" + s.dark_frames_from + "' is " +
                        other_id.describe() + ", not the camera being calibrated, " +
                        identity.describe());
        if (Status ok = (*other)->setGain(camera->gain()); !ok) return fail(ok.error().message);
        out << "dark frames: from " << s.dark_frames_from << "\n";
        auto frames = drivers::captureDarkFrames(**other, capture);
        if (!frames) return fail(frames.error().message);
        dark = std::move(*frames);
    } else {
        if (sim != nullptr && s.yes) {
            sim->setLensCapped(true);
            out << "dark frames: the simulated camera's lens is capped\n";
        } else if (!ask(s, in, out,
                        "dark frames: cap the lens and shade the camera from stray light")) {
            return fail(
                "no answer from the operator (input ended); pass --yes to go on "
                "without asking");
        }
        auto frames = drivers::captureDarkFrames(*camera, capture);
        if (sim != nullptr) sim->setLensCapped(false);
        if (!frames) return fail(frames.error().message);
        dark = std::move(*frames);
    }
    auto measured_dark = drivers::measureDark(dark);
    if (!measured_dark) return fail(measured_dark.error().message);
    out << "dark frames: black level " << num(measured_dark->black_level_dn, 6) << " DN, "
        << measured_dark->hot_pixels.size() << " hot pixels\n";

    // 2. The exposure series.
    if (!(sim != nullptr && s.yes) &&
        !ask(s, in, out,
             "exposure series: uncap the lens and point the camera at a steady light (a scene "
             "with bright and dark parts that does not change; no flicker)"))
        return fail(
            "no answer from the operator (input ended); pass --yes to go on without "
            "asking");
    if (exposures.empty()) {
        auto planned =
            drivers::planSeriesExposures(*camera, measured_dark->black_level_dn, capture);
        if (!planned) return fail(planned.error().message);
        exposures = std::move(*planned);
    }
    out << "exposure series: " << exposures.size() << " exposures from " << num(exposures.front())
        << " to " << num(exposures.back()) << " s, " << capture.frames_per_exposure
        << " frames each\n";
    auto series = drivers::captureSeries(*camera, exposures, capture);
    if (!series) return fail(series.error().message);

    // 3. Measure, report, write.
    auto calibration = drivers::buildCalibration(identity, dark, *series);
    if (!calibration) return fail(calibration.error().message);
    report(*calibration, out);
    if (Status ok = drivers::writeCalibration(s.output, *calibration); !ok)
        return fail(ok.error().message);
    out << "wrote " << s.output << "\n";
    return 0;
}

}  // namespace

void addCalibrateCommand(
    CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code, std::istream& in) {
    auto s = std::make_shared<CalibrateState>();
    CLI::App* cmd = app.add_subcommand(
        "calibrate",
        "measure a camera (dark frames, linearity, saturation, noise, response curve) and write "
        "its calibration file");
    cmd->add_option("--camera", s->camera,
                    "the camera's URI (sim:?lens=FILE, aravis:ID, v4l2:/dev/videoN, ...)")
        ->required();
    cmd->add_option("--head", s->head,
                    "the head the camera sits on, if any (homed when it does not know its "
                    "position, not moved otherwise)");
    cmd->add_option("--exposures", s->exposures,
                    "the exposure series in seconds, comma separated, from dim to clipped "
                    "(default: planned by probes of the scene)");
    cmd->add_option("--pairs", s->pairs, "frame pairs per exposure (photon transfer)")
        ->capture_default_str();
    cmd->add_option("--gain", s->gain, "the gain to calibrate at (default: as the camera is)");
    cmd->add_option("--dark-frames-from", s->dark_frames_from,
                    "take the dark frames from this URI (the same camera, capped) without "
                    "asking");
    cmd->add_option("--dark-exposure", s->dark_exposure_s,
                    "exposure of the long dark frames that find hot pixels, s (the longest a "
                    "capture will use)")
        ->capture_default_str();
    cmd->add_option("--budget", s->budget_s, "most exposure time a planned series may take, s")
        ->capture_default_str();
    cmd->add_flag("-y,--yes", s->yes,
                  "do not ask the operator (a simulated camera caps its own lens)");
    cmd->add_option("-o,--output", s->output, "the calibration file to write (camera.cal.json)")
        ->required();
    cmd->callback([s, &in, &out, &err, &exit_code] { exit_code = run(*s, in, out, err); });
}

}  // namespace flarelab::apps
