#include "apps/daemon_commands.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <memory>
#include <ostream>
#include <sstream>
#include <string>

#include "apps/camera_flags.h"
#include "apps/capture_command.h"
#include "apps/rig_commands.h"
#include "proto/daemon.grpc.pb.h"

namespace flarelab::apps {
namespace {

namespace fs = std::filesystem;

struct Connection {
    std::string socket;
    std::string address;
    std::string token_file;
    std::string tls_ca;
};

void addConnectionFlags(CLI::App* cmd, Connection& c) {
    cmd->add_option("--socket", c.socket, "the daemon's Unix socket (default: $FLARELAB_SOCKET)");
    cmd->add_option("--address", c.address,
                    "the daemon's TCP address HOST:PORT (default: $FLARELAB_ADDRESS)");
    cmd->add_option("--token-file", c.token_file,
                    "file whose first line is the daemon's token (default: $FLARELAB_TOKEN_FILE)");
    cmd->add_option("--tls-ca", c.tls_ca,
                    "talk TLS to --address, trusting the certificates in this PEM file (the "
                    "daemon's own, when self-signed; default: $FLARELAB_TLS_CA)");
}

std::string env(const char* name) {
    const char* v = std::getenv(name);
    return v ? v : "";
}

class Client {
public:
    // nullptr (and the reason in `err`) when no daemon is named or the token cannot be read.
    static std::unique_ptr<Client> connect(const Connection& c, std::ostream& err) {
        std::string target;
        std::string socket = !c.socket.empty() ? c.socket : env("FLARELAB_SOCKET");
        std::string address = !c.address.empty() ? c.address : env("FLARELAB_ADDRESS");
        if (!c.socket.empty() || (c.address.empty() && !socket.empty()))
            target = "unix:" + fs::absolute(socket).string();
        else if (!address.empty())
            target = address;
        if (target.empty()) {
            err << "flarelab: no daemon named: pass --socket PATH (flarelabd --state-dir DIR "
                   "listens on DIR/flarelabd.sock) or set FLARELAB_SOCKET\n";
            return nullptr;
        }
        auto client = std::unique_ptr<Client>(new Client());
        const std::string token_file =
            !c.token_file.empty() ? c.token_file : env("FLARELAB_TOKEN_FILE");
        if (!token_file.empty()) {
            std::ifstream in(token_file);
            if (!in || !std::getline(in, client->token_) || client->token_.empty()) {
                err << "flarelab: --token-file " << token_file << ": cannot read a token\n";
                return nullptr;
            }
        }
        client->name_ = env("FLARELAB_CLIENT");
        if (client->name_.empty()) {
            char host[256] = {};
            ::gethostname(host, sizeof host - 1);
            const std::string user = env("USER").empty() ? "user" : env("USER");
            client->name_ = user + "@" + host;
        }
        client->target_ = target;
        grpc::ChannelArguments args;
        args.SetMaxReceiveMessageSize(64 << 20);
        std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
        const std::string tls_ca = !c.tls_ca.empty() ? c.tls_ca : env("FLARELAB_TLS_CA");
        if (!tls_ca.empty() && target.rfind("unix:", 0) != 0) {
            std::ifstream in(tls_ca, std::ios::binary);
            std::stringstream pem;
            pem << in.rdbuf();
            if (!in || pem.str().find("-----BEGIN CERTIFICATE-----") == std::string::npos) {
                err << "flarelab: --tls-ca " << tls_ca << ": cannot read a PEM certificate\n";
                return nullptr;
            }
            grpc::SslCredentialsOptions ssl;
            ssl.pem_root_certs = pem.str();
            credentials = grpc::SslCredentials(ssl);
        }
        client->api_ = v1::FlareLab::NewStub(grpc::CreateCustomChannel(target, credentials, args));
        return client;
    }

    // A context with the client's metadata and, for unary calls, a deadline.
    std::unique_ptr<grpc::ClientContext> context(bool unary = true) const {
        auto ctx = std::make_unique<grpc::ClientContext>();
        ctx->AddMetadata("flarelab-client", name_);
        if (!token_.empty()) ctx->AddMetadata("authorization", "Bearer " + token_);
        if (unary) ctx->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
        return ctx;
    }

    v1::FlareLab::Stub& api() { return *api_; }
    const std::string& target() const { return target_; }

    // "flarelab: <what>: <status message>", with a hint when the daemon is not there.
    int fail(const grpc::Status& s, const std::string& what, std::ostream& err) const {
        err << "flarelab: " << what << ": " << s.error_message();
        if (s.error_code() == grpc::StatusCode::UNAVAILABLE)
            err << " (is flarelabd running and listening on " << target_ << "?)";
        err << "\n";
        return 1;
    }

private:
    Client() = default;
    std::string name_, token_, target_;
    std::unique_ptr<v1::FlareLab::Stub> api_;
};

// A message as `--json` prints it: protobuf's JSON mapping with the .proto's field names.
void printJson(const google::protobuf::Message& message, std::ostream& out) {
    std::string json;
    google::protobuf::util::JsonPrintOptions print;
    print.add_whitespace = true;
    print.preserve_proto_field_names = true;
    (void)google::protobuf::util::MessageToJsonString(message, &json, print);
    out << json;
}

std::string duration(double s) {
    std::ostringstream o;
    if (!(s >= 0.0) || !std::isfinite(s)) return "?";
    if (s < 60)
        o << std::fixed << std::setprecision(s < 10 ? 1 : 0) << s << " s";
    else if (s < 3600)
        o << static_cast<int>(s / 60) << " min " << static_cast<int>(std::fmod(s, 60)) << " s";
    else
        o << static_cast<int>(s / 3600) << " h " << static_cast<int>(std::fmod(s, 3600) / 60)
          << " min";
    return o.str();
}

std::string lower(std::string n) {
    for (char& c : n) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return n;
}
std::string stateName(v1::JobState s) { return lower(v1::JobState_Name(s)); }

void printJobLine(const v1::Job& j, std::ostream& out) {
    out << j.id() << "  " << std::left << std::setw(11) << stateName(j.state()) << std::right << " "
        << j.frames_done() << "/" << j.frames_total() << " frames  " << j.output_dir();
    if (!j.reason().empty()) out << "  (" << j.reason() << ")";
    out << "\n";
}

// Follows a job until it ends; a progress bar on a terminal, a line per tenth otherwise.
int watch(Client& client, const std::string& id, std::ostream& out, std::ostream& err) {
    auto ctx = client.context(false);
    v1::WatchJobRequest request;
    request.set_job_id(id);
    auto reader = client.api().WatchJob(ctx.get(), request);
    const bool terminal = ::isatty(STDERR_FILENO) != 0;
    v1::JobEvent event;
    v1::Job last;
    v1::JobState shown_state = v1::JOB_STATE_UNSPECIFIED;
    uint32_t last_tenth = 0;
    bool bar = false;
    while (reader->Read(&event)) {
        last = event.job();
        if (event.kind() == v1::STATE || event.job().state() != shown_state) {
            if (bar) err << "\n";
            bar = false;
            shown_state = event.job().state();
            err << id << ": " << stateName(event.job().state());
            if (event.job().phase() != v1::JOB_PHASE_UNSPECIFIED)
                err << " (" << lower(v1::JobPhase_Name(event.job().phase())) << ")";
            if (!event.job().reason().empty()) err << ": " << event.job().reason();
            err << "\n";
            continue;
        }
        if (event.kind() == v1::WARNING) {
            if (bar) err << "\n";
            bar = false;
            err << id << ": warning: " << event.message() << "\n";
            continue;
        }
        const bool fitting = event.kind() == v1::FIT_PROGRESS;
        if (!fitting && event.kind() != v1::FRAME && !(terminal && event.kind() == v1::EXPOSURE))
            continue;
        const uint32_t total =
            std::max<uint32_t>(1, fitting ? event.fit_frames_total() : event.job().frames_total());
        const uint32_t done = fitting ? event.frame_index() : event.job().frames_done();
        std::ostringstream line;
        constexpr int kWidth = 30;
        const int filled = static_cast<int>(kWidth * std::min(done, total) / total);
        line << (fitting ? "fit     " : "capture ") << "[" << std::string(filled, '#')
             << std::string(kWidth - filled, ' ') << "] " << done << "/" << total
             << (fitting ? " frame fits" : " frames");
        if (!fitting)
            line << ", " << std::fixed << std::setprecision(2) << event.angle_deg() << " deg";
        line << ", " << duration(event.elapsed_s()) << " elapsed, ETA "
             << (event.eta_s() > 0 ? duration(event.eta_s()) : "?");
        if (terminal) {
            err << "\r" << line.str() << "   " << std::flush;
            bar = true;
        } else if (done * 10 / total != last_tenth || done == total) {
            last_tenth = done * 10 / total;
            err << line.str() << "\n";
        }
    }
    if (bar) err << "\n";
    const grpc::Status status = reader->Finish();
    if (!status.ok()) return client.fail(status, "job watch " + id, err);
    if (last.state() == v1::SUCCEEDED) {
        out << id << " succeeded: " << last.frames_done() << " frames in " << last.output_dir();
        if (!last.model_file().empty()) out << ", model " << last.model_file();
        out << "\n";
        return 0;
    }
    out << id << " " << stateName(last.state())
        << (last.reason().empty() ? "" : ": " + last.reason()) << "\n";
    return last.state() == v1::CANCELLED ? 3 : 1;
}

struct StartState {
    Connection connection;
    bool sim = false;
    std::string lens_file;
    CameraFlags camera;
    double from_deg = 0.0, to_deg = 30.0, step_deg = 0.2;
    std::string brackets = "auto";
    int64_t width = 0, height = 0;  // 0: the rig's default (640 x 427 simulated)
    double gain = 1.0;
    bool fast = false;
    uint64_t seed = 1;
    bool keep_raw = false, previews = false, fit = false, watch = false, resume_existing = false;
    double preview_stops = 0.0;
    std::string request_id;
    std::string output;
    std::string camera_uri, head_uri, lens_description;
    std::string raw_format;  // empty: the camera's
    double pixel_um = 0.0;
};

int runStart(const StartState& s, std::ostream& out, std::ostream& err) {
    // "auto": none sent, and the daemon plans the bracket at the first angle.
    auto times = s.brackets == "auto" ? Result<std::vector<double>>(std::vector<double>{})
                                      : parseBrackets(s.brackets);
    if (!times) {
        err << "flarelab: " << times.error().message << "\n";
        return 2;
    }
    if (!s.lens_file.empty() && !s.sim) {
        err << "flarelab: sweep start: --lens is the simulated camera's lens: add --sim, or name "
               "a real camera's lens with --lens-description\n";
        return 2;
    }
    std::string text;
    if (!s.lens_file.empty()) {
        std::ifstream lens(s.lens_file, std::ios::binary);
        if (!lens) {
            err << "flarelab: --lens " << s.lens_file << ": cannot open it\n";
            return 1;
        }
        text.resize(size_t{1} << 20);
        lens.read(text.data(), static_cast<std::streamsize>(text.size()));
        text.resize(static_cast<size_t>(lens.gcount()));
        if (lens.peek() != EOF) {
            err << "flarelab: --lens " << s.lens_file << ": more than 1 MiB, not a lens file\n";
            return 1;
        }
    }
    double sw = 0.0, sh = 0.0;
    if (!parseSensorMm(s.camera.sensor, sw, sh)) {
        err << "flarelab: --sensor-mm '" << s.camera.sensor << "' is not WIDTHxHEIGHT in mm\n";
        return 2;
    }
    v1::StartSweepRequest request;
    request.set_request_id(s.request_id);
    v1::SweepConfig& c = *request.mutable_config();
    if (s.sim) {
        v1::SimSettings& sim = *c.mutable_sim();
        sim.set_fast(s.fast);
        sim.set_seed(s.seed);
    }
    if (s.sim && !s.lens_file.empty()) {
        v1::SimLens& l = *c.mutable_sim()->mutable_lens();
        l.set_prescription_csv(text);
        l.set_name(fs::path(s.lens_file).filename().string());
        l.set_focal_length_mm(s.camera.focal_mm);
        l.set_f_number(s.camera.f_number);
        l.set_sensor_width_mm(sw);
        l.set_sensor_height_mm(sh);
        l.set_aperture_blades(static_cast<uint32_t>(std::max(0, s.camera.blades)));
        l.set_blade_rotation_deg(s.camera.blade_rotation_deg);
        l.set_table_stop(s.camera.table_stop);
        l.set_coat_unspecified(s.camera.coat_unspecified);
    }
    c.set_from_deg(s.from_deg);
    c.set_to_deg(s.to_deg);
    c.set_step_deg(s.step_deg);
    for (const double t : *times) c.add_exposure_times_s(t);
    c.set_gain(s.gain);
    c.set_width_px(static_cast<uint32_t>(s.width));  // 0: the rig's default
    c.set_height_px(static_cast<uint32_t>(s.height));
    // The daemon resolves it against its output root; relative to the caller here.
    c.set_output_dir(fs::absolute(s.output).lexically_normal().string());
    c.set_keep_raw(s.keep_raw);
    c.set_previews(s.previews);
    c.set_preview_stops(s.preview_stops);
    c.set_fit(s.fit);
    c.set_resume_existing(s.resume_existing);
    c.set_camera(s.camera_uri);
    c.set_head(s.head_uri);
    c.set_pixel_pitch_um(s.pixel_um);
    c.set_lens_description(s.lens_description);
    c.set_raw_format(s.raw_format);

    auto client = Client::connect(s.connection, err);
    if (!client) return 2;
    v1::Job job;
    auto ctx = client->context();
    const grpc::Status status = client->api().StartSweep(ctx.get(), request, &job);
    if (!status.ok()) return client->fail(status, "sweep start", err);
    out << job.id() << " " << stateName(job.state()) << ": " << job.frames_total() << " frames"
        << (s.sim ? " of " + c.sim().lens().name() : std::string()) << " -> " << job.output_dir()
        << "\n";
    for (const std::string& w : job.warnings()) err << "flarelab: warning: " << w << "\n";
    if (!s.watch) return 0;
    return watch(*client, job.id(), out, err);
}

struct JobState {
    Connection connection;
    std::string id;
    bool take_control = false;
    bool json = false;
};

int runList(const JobState& s, std::ostream& out, std::ostream& err) {
    auto client = Client::connect(s.connection, err);
    if (!client) return 2;
    v1::ListJobsResponse response;
    auto ctx = client->context();
    const grpc::Status status = client->api().ListJobs(ctx.get(), {}, &response);
    if (!status.ok()) return client->fail(status, "job list", err);
    if (s.json) {
        printJson(response, out);
        return 0;
    }
    if (response.jobs().empty()) out << "no jobs\n";
    for (const v1::Job& j : response.jobs()) printJobLine(j, out);
    return 0;
}

int runControl(const JobState& s, const std::string& what, std::ostream& out, std::ostream& err) {
    auto client = Client::connect(s.connection, err);
    if (!client) return 2;
    v1::JobControlRequest request;
    request.set_job_id(s.id);
    request.set_take_control(s.take_control);
    v1::Job job;
    auto ctx = client->context();
    grpc::Status status;
    if (what == "pause")
        status = client->api().PauseJob(ctx.get(), request, &job);
    else if (what == "resume")
        status = client->api().ResumeJob(ctx.get(), request, &job);
    else
        status = client->api().CancelJob(ctx.get(), request, &job);
    if (!status.ok()) return client->fail(status, "job " + what, err);
    printJobLine(job, out);
    return 0;
}

int runRigStatus(const JobState& s, std::ostream& out, std::ostream& err) {
    auto client = Client::connect(s.connection, err);
    if (!client) return 2;
    v1::RigDescription rig;
    auto ctx = client->context();
    const grpc::Status status = client->api().DescribeRig(ctx.get(), {}, &rig);
    if (!status.ok()) return client->fail(status, "rig status", err);
    if (s.json) {
        printJson(rig, out);
        return 0;
    }
    out << rig.daemon_version() << " (API v" << rig.api_version() << ") at " << client->target()
        << "\n"
        << "rig: " << rig.rig() << "\n"
        << "camera: " << rig.camera().model() << " " << rig.camera().serial() << " ("
        << rig.camera().uri() << "), exposures " << rig.min_exposure_s() << " to "
        << rig.max_exposure_s() << " s, " << rig.bit_depth() << " bits\n"
        << "head: " << rig.head().model() << " " << rig.head().serial() << ", "
        << rig.head_min_deg() << " to " << rig.head_max_deg() << " deg at "
        << rig.head_speed_deg_s() << " deg/s\n";
    for (const auto& [kind, list] :
         {std::pair{"cameras", &rig.cameras()}, std::pair{"heads", &rig.heads()}}) {
        if (list->empty()) continue;
        out << kind << " jobs may name:";
        for (const v1::DeviceDescription& d : *list)
            out << " " << d.uri()
                << (d.model().empty() ? "" : " (" + d.model() + " " + d.serial() + ")");
        out << "\n";
    }
    out << "running: " << (rig.running_job_id().empty() ? "nothing" : rig.running_job_id()) << ", "
        << rig.queued_jobs() << " queued\n"
        << "output root: " << rig.output_root() << "\n";
    return 0;
}

}  // namespace

void addSweepStartCommand(CLI::App& sweep, std::ostream& out, std::ostream& err, int& exit_code) {
    auto s = std::make_shared<StartState>();
    CLI::App* cmd = sweep.add_subcommand("start", "start a sweep as a job of flarelabd");
    addConnectionFlags(cmd, s->connection);
    cmd->add_flag("--sim", s->sim,
                  "simulate what the daemon has no device for (its settings: --lens, --fast, "
                  "--seed)");
    cmd->add_option("--lens", s->lens_file, "the simulated camera's lens (CSV, format v1)");
    cmd->add_option("--camera", s->camera_uri,
                    "one of the daemon's cameras by URI (default: its first; see rig status)");
    cmd->add_option("--head", s->head_uri,
                    "one of the daemon's heads by URI (default: its first; see rig status)");
    cmd->add_option("--pixel-um", s->pixel_um,
                    "a real camera's pixel pitch in micrometres (to fit the sweep)");
    cmd->add_option("--lens-description", s->lens_description,
                    "the lens a real camera wears, for the sweep's description");
    cmd->add_option("--format", s->raw_format,
                    "the camera's raw format: mono, bayer-rggb, bayer-bggr, bayer-grbg, "
                    "bayer-gbrg (default: the camera's)");
    cmd->add_option("--from", s->from_deg, "first angle (deg)")->capture_default_str();
    cmd->add_option("--to", s->to_deg, "last angle (deg)")->capture_default_str();
    cmd->add_option("--step", s->step_deg, "angle step (deg)")->capture_default_str();
    cmd->add_option("--brackets", s->brackets,
                    "exposure times in seconds, comma separated, or auto: planned by the daemon at "
                    "the first angle")
        ->capture_default_str();
    cmd->add_option("--gain", s->gain, "linear gain")->capture_default_str();
    cmd->add_option("--width", s->width, "frame width (default: the rig's, 640 simulated)")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}));
    cmd->add_option("--height", s->height, "frame height (default: the rig's, 427 simulated)")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}));
    cmd->add_flag("--fast", s->fast, "simulated time: do not wait for exposures and moves");
    cmd->add_option("--seed", s->seed, "noise seed")->capture_default_str();
    cmd->add_flag("--keep-raw", s->keep_raw, "also keep every raw bracket (raw/*.pgm)");
    cmd->add_flag("--previews", s->previews, "a PNG preview of every frame (DIR/previews/)");
    cmd->add_option("--preview-stops", s->preview_stops, "exposure of the previews in stops");
    cmd->add_flag("--fit", s->fit, "fit the finished sweep into DIR/model.flm");
    cmd->add_flag("--resume-existing", s->resume_existing,
                  "append to the interrupted sweep already in DIR");
    cmd->add_option("--request-id", s->request_id,
                    "a retried start with the same id does not start a second job");
    cmd->add_flag("--watch", s->watch, "follow the job with a progress bar until it ends");
    cmd->add_option("-o,--output", s->output, "sweep directory (below the daemon's output root)")
        ->required();
    addCameraFlags(cmd, s->camera);
    cmd->callback([s, &out, &err, &exit_code] { exit_code = runStart(*s, out, err); });
}

void addRigCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    CLI::App* rig =
        app.add_subcommand("rig", "the rig: its devices by hand, and the one flarelabd drives");
    rig->require_subcommand(1);
    addRigDeviceCommands(rig, out, err, exit_code);
    auto s = std::make_shared<JobState>();
    CLI::App* status = rig->add_subcommand("status", "the daemon, its devices and its jobs");
    addConnectionFlags(status, s->connection);
    status->add_flag("--json", s->json, "as JSON (flarelab.v1.RigDescription)");
    status->callback([s, &out, &err, &exit_code] { exit_code = runRigStatus(*s, out, err); });
}

void addJobCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    CLI::App* job =
        app.add_subcommand("job", "flarelabd's jobs: list, watch, pause, resume, cancel");
    job->require_subcommand(1);
    auto list = std::make_shared<JobState>();
    CLI::App* list_cmd = job->add_subcommand("list", "every job the daemon knows");
    addConnectionFlags(list_cmd, list->connection);
    list_cmd->add_flag("--json", list->json, "as JSON (flarelab.v1.ListJobsResponse)");
    list_cmd->callback([list, &out, &err, &exit_code] { exit_code = runList(*list, out, err); });

    auto w = std::make_shared<JobState>();
    CLI::App* watch_cmd = job->add_subcommand("watch", "follow a job until it ends");
    addConnectionFlags(watch_cmd, w->connection);
    watch_cmd->add_option("JOB", w->id, "job id (job-000001)")->required();
    watch_cmd->callback([w, &out, &err, &exit_code] {
        auto client = Client::connect(w->connection, err);
        exit_code = client ? watch(*client, w->id, out, err) : 2;
    });
    for (const char* what : {"pause", "resume", "cancel"}) {
        auto c = std::make_shared<JobState>();
        CLI::App* cmd = job->add_subcommand(what, std::string(what) + " a job");
        addConnectionFlags(cmd, c->connection);
        cmd->add_option("JOB", c->id, "job id (job-000001)")->required();
        cmd->add_flag("--take-control", c->take_control,
                      "take control of a job another client started");
        const std::string name = what;
        cmd->callback(
            [c, name, &out, &err, &exit_code] { exit_code = runControl(*c, name, out, err); });
    }
}

}  // namespace flarelab::apps
