#include "apps/rig_commands.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <memory>
#include <nlohmann/json.hpp>
#include <ostream>
#include <sstream>
#include <string>
#include <vector>

#include "drivers/rig.h"
#include "hdr/merge.h"
#include "hdr/raw_io.h"
#include "render/preview.h"

namespace flarelab::apps {
namespace {

using nlohmann::json;

struct DevicesState {
    bool json = false;
};

struct HeadState {
    std::string uri;
    std::string action;
    double angle_deg = std::nan("");
    double speed_deg_s = 0.0;
    double timeout_s = 120.0;
    bool json = false;
};

struct CameraState {
    std::string uri;
    double exposure_s = 0.0;
    double gain = 0.0;  // 0: leave as it is
    double timeout_s = 0.0;
    std::string output;
    std::string png;
    double png_stops = 0.0;
    bool json = false;
};

const char* markName(hdr::TimestampMark mark) {
    switch (mark) {
        case hdr::TimestampMark::ExposureStart:
            return "exposure-start";
        case hdr::TimestampMark::ExposureEnd:
            return "exposure-end";
        case hdr::TimestampMark::FrameArrival:
            return "frame-arrival";
        case hdr::TimestampMark::Unknown:
            break;
    }
    return "unknown";
}

const char* responseName(drivers::CameraResponse response) {
    switch (response) {
        case drivers::CameraResponse::Linear:
            return "linear";
        case drivers::CameraResponse::NonLinear:
            return "not linear";
        case drivers::CameraResponse::Unknown:
            break;
    }
    return "unknown";
}

// The registries for devices by hand: simulated devices in real time, as hardware runs.
Result<drivers::RigRegistries> registries() {
    drivers::RigOptions options;
    options.sim_clock = std::make_shared<drivers::SimClock>(drivers::SimTime::RealTime);
    return drivers::makeRigRegistries(options);
}

int runDevices(const DevicesState& s, std::ostream& out, std::ostream& err) {
    auto r = registries();
    if (!r) {
        err << "flarelab: " << r.error().message << "\n";
        return 1;
    }
    const std::vector<drivers::BackendStatus> backends = drivers::backendStatus();
    const std::vector<drivers::DeviceListing> devices = drivers::listDevices(*r);
    if (s.json) {
        json doc = {{"backends", json::array()}, {"devices", json::array()}};
        for (const drivers::BackendStatus& b : backends)
            doc["backends"].push_back({{"scheme", b.scheme},
                                       {"kind", b.kind},
                                       {"description", b.description},
                                       {"built", b.built},
                                       {"missing", b.missing}});
        for (const drivers::DeviceListing& d : devices)
            doc["devices"].push_back({{"uri", d.uri},
                                      {"kind", d.kind},
                                      {"backend", d.backend},
                                      {"model", d.model},
                                      {"serial", d.serial},
                                      {"details", d.details}});
        out << doc.dump(2) << "\n";
        return 0;
    }
    out << "backends:\n";
    for (const drivers::BackendStatus& b : backends)
        out << "  " << std::left << std::setw(7) << b.kind << std::setw(10) << b.scheme
            << b.description << (b.built ? "" : " (not in this build: needs " + b.missing + ")")
            << "\n";
    for (const char* kind : {"camera", "head", "serial-port"}) {
        out << kind << (std::string(kind) == "serial-port" ? "s" : "s") << ":\n";
        bool any = false;
        for (const drivers::DeviceListing& d : devices) {
            if (d.kind != kind) continue;
            any = true;
            out << "  " << d.uri;
            if (!d.model.empty() || !d.serial.empty())
                out << "  (" << d.model << (d.serial.empty() ? "" : ", serial " + d.serial) << ")";
            out << "\n";
            for (const std::string& line : d.details) out << "      " << line << "\n";
        }
        if (!any) out << "  none found\n";
    }
    return 0;
}

int runHead(const HeadState& s, std::ostream& out, std::ostream& err) {
    if (s.action != "home" && s.action != "move" && s.action != "position" && s.action != "stop") {
        err << "flarelab: rig head: ACTION must be home, move, position or stop, not '" << s.action
            << "'\n";
        return 2;
    }
    if (s.action == "move" && !std::isfinite(s.angle_deg)) {
        err << "flarelab: rig head " << s.uri << " move: give the angle in degrees\n";
        return 2;
    }
    if (s.action != "move" && std::isfinite(s.angle_deg)) {
        err << "flarelab: rig head " << s.action << " takes no angle\n";
        return 2;
    }
    auto r = registries();
    if (!r) {
        err << "flarelab: " << r.error().message << "\n";
        return 1;
    }
    auto opened = r->heads.open(s.uri);
    if (!opened) {
        err << "flarelab: head '" << s.uri << "': " << opened.error().message << "\n";
        return 1;
    }
    drivers::Head& head = **opened;
    const auto fail = [&](const Error& e) {
        err << "flarelab: " << head.identity().describe() << ": " << e.message << "\n";
        return 1;
    };
    if (s.speed_deg_s > 0.0)
        if (Status ok = head.setSpeed(s.speed_deg_s); !ok) return fail(ok.error());
    Result<double> at = 0.0;
    if (s.action == "home") {
        if (Status ok = head.home(s.timeout_s); !ok) return fail(ok.error());
        at = head.position();
    } else if (s.action == "move") {
        at = head.moveTo(s.angle_deg, s.timeout_s);
    } else if (s.action == "stop") {
        if (Status ok = head.stop(); !ok) return fail(ok.error());
        at = head.position();
    } else {
        at = head.position();
    }
    if (!at) {
        // A stage that is not homed does not know where it is: stopping it still succeeded.
        if (s.action == "stop") {
            out << "stopped; position unknown (" << at.error().message << ")\n";
            return 0;
        }
        return fail(at.error());
    }
    const drivers::HeadLimits limits = head.limits();
    if (s.json) {
        out << json{{"uri", s.uri},
                    {"model", head.identity().model},
                    {"serial", head.identity().serial},
                    {"action", s.action},
                    {"position_deg", *at},
                    {"min_deg", limits.min_deg},
                    {"max_deg", limits.max_deg},
                    {"speed_deg_s", head.speed_deg_s()}}
                   .dump(2)
            << "\n";
        return 0;
    }
    out << head.identity().describe() << ": " << s.action << " done, at " << std::setprecision(10)
        << *at << " deg (range " << limits.min_deg << " .. " << limits.max_deg << " deg, speed "
        << head.speed_deg_s() << " deg/s)\n";
    return 0;
}

int runCamera(const CameraState& s, std::ostream& out, std::ostream& err) {
    if (!(s.exposure_s > 0.0) || !std::isfinite(s.exposure_s)) {
        err << "flarelab: rig camera: --exposure must be a positive number of seconds\n";
        return 2;
    }
    auto r = registries();
    if (!r) {
        err << "flarelab: " << r.error().message << "\n";
        return 1;
    }
    auto opened = r->cameras.open(s.uri);
    if (!opened) {
        err << "flarelab: camera '" << s.uri << "': " << opened.error().message << "\n";
        return 1;
    }
    drivers::Camera& camera = **opened;
    const auto fail = [&](const Error& e) {
        err << "flarelab: " << camera.identity().describe() << ": " << e.message << "\n";
        return 1;
    };
    if (s.gain > 0.0)
        if (Status ok = camera.setGain(s.gain); !ok) return fail(ok.error());
    if (Status ok = camera.setExposure(s.exposure_s); !ok) return fail(ok.error());
    const double timeout_s = s.timeout_s > 0.0 ? s.timeout_s : 2.0 * s.exposure_s + 5.0;
    auto frame = camera.capture(timeout_s);
    if (!frame) return fail(frame.error());
    if (Status ok = hdr::writeRaw(s.output, *frame); !ok) return fail(ok.error());
    const auto counts = hdr::countExposure(*frame);
    if (!counts) return fail(counts.error());
    double sum = 0.0;
    uint16_t lo = 65535, hi = 0;
    for (const uint16_t v : frame->samples) {
        sum += v;
        lo = std::min(lo, v);
        hi = std::max(hi, v);
    }
    const double mean = frame->samples.empty() ? 0.0 : sum / frame->samples.size();
    if (!s.png.empty()) {
        const hdr::RawFrame* one = &*frame;
        auto merged = hdr::mergeBrackets(std::span(one, 1));
        if (!merged) return fail(merged.error());
        auto image = hdr::toImage(*merged);
        if (!image) return fail(image.error());
        render::ToneMapOptions tone;
        tone.exposure_stops = s.png_stops;
        if (Status ok = render::writePng(*image, s.png, tone); !ok) return fail(ok.error());
    }
    const drivers::CameraCapabilities caps = camera.capabilities();
    if (s.json) {
        json doc = {{"uri", s.uri},
                    {"model", camera.identity().model},
                    {"serial", camera.identity().serial},
                    {"output", s.output},
                    {"width", frame->width},
                    {"height", frame->height},
                    {"bit_depth", frame->bit_depth},
                    {"requested_exposure_s", s.exposure_s},
                    {"exposure_s", frame->exposure_s},
                    {"gain", frame->gain},
                    {"mean_dn", mean},
                    {"min_dn", lo},
                    {"max_dn", hi},
                    {"saturated", counts->saturated},
                    {"dark", counts->dark},
                    {"timestamp_ns", frame->timestamp_ns},
                    {"timestamp_marks", markName(frame->timestamp_marks)},
                    {"host_timestamp_ns", frame->host_timestamp_ns},
                    {"sequence", frame->sequence},
                    {"response", responseName(caps.response)}};
        json stats = json::object();
        for (const auto& [name, value] : camera.statistics()) stats[name] = value;
        doc["statistics"] = stats;
        out << doc.dump(2) << "\n";
        return 0;
    }
    out << camera.identity().describe() << ": " << frame->width << "x" << frame->height << ", "
        << frame->bit_depth << " bits, exposure " << frame->exposure_s << " s (asked "
        << s.exposure_s << " s), gain " << frame->gain << "\n"
        << "  DN mean " << std::fixed << std::setprecision(1) << mean << ", min " << lo << ", max "
        << hi << "; " << counts->saturated << " saturated, " << counts->dark << " dark of "
        << frame->samples.size() << " samples\n"
        << "  timestamp " << frame->timestamp_ns << " ns (" << markName(frame->timestamp_marks)
        << "), sequence " << frame->sequence << "; response " << responseName(caps.response)
        << (caps.response_note.empty() ? "" : " (" + caps.response_note + ")") << "\n"
        << "  -> " << s.output << (s.png.empty() ? "" : ", " + s.png) << "\n";
    return 0;
}

}  // namespace

void addRigDeviceCommands(CLI::App* rig, std::ostream& out, std::ostream& err, int& exit_code) {
    auto d = std::make_shared<DevicesState>();
    CLI::App* devices = rig->add_subcommand(
        "devices", "every camera, head and serial port the backends of this build see");
    devices->add_flag("--json", d->json, "as JSON: backends and devices");
    devices->callback([d, &out, &err, &exit_code] { exit_code = runDevices(*d, out, err); });

    auto h = std::make_shared<HeadState>();
    CLI::App* head = rig->add_subcommand("head", "drive one head by hand");
    head->add_option("URI", h->uri, "head URI or alias (zaber:/dev/ttyUSB0?axis=1, apt:..., sim:)")
        ->required();
    head->add_option("ACTION", h->action, "home, move, position or stop")->required();
    head->add_option("DEG", h->angle_deg, "target of move (deg)");
    head->add_option("--speed", h->speed_deg_s, "speed for this command (deg/s)");
    head->add_option("--timeout", h->timeout_s, "seconds to wait for home or move")
        ->check(CLI::PositiveNumber)
        ->capture_default_str();
    head->add_flag("--json", h->json, "as JSON");
    head->callback([h, &out, &err, &exit_code] { exit_code = runHead(*h, out, err); });

    auto c = std::make_shared<CameraState>();
    CLI::App* camera = rig->add_subcommand("camera", "take one raw frame with one camera by hand");
    camera->add_option("URI", c->uri, "camera URI or alias (aravis:ID, v4l2:/dev/video0, ...)")
        ->required();
    camera->add_option("--exposure", c->exposure_s, "exposure time (s)")->required();
    camera->add_option("--gain", c->gain, "linear gain (default: leave it)");
    camera->add_option("--timeout", c->timeout_s, "seconds to wait (default: 2 x exposure + 5)");
    camera->add_option("-o,--output", c->output, "the raw frame (PGM with metadata)")->required();
    camera->add_option("--png", c->png, "also a tone-mapped PNG of it");
    camera->add_option("--png-stops", c->png_stops, "exposure of the PNG in stops")
        ->capture_default_str();
    camera->add_flag("--json", c->json, "as JSON");
    camera->callback([c, &out, &err, &exit_code] { exit_code = runCamera(*c, out, err); });
}

}  // namespace flarelab::apps
