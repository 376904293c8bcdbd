#include "apps/fit_command.h"

#include <openssl/evp.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <vector>

#include "apps/camera_flags.h"
#include "drivers/sim_truth.h"
#include "fit/sweep_fit.h"
#include "hdr/sweep.h"

namespace flarelab::apps {
namespace {

struct FitState {
    std::string sweep;
    std::string output;
    std::string lens_file;
    std::string sensor;
    std::string optimizer = "ceres";
    // The library's defaults, so that the command fits what fitSweep fits.
    int iterations = fit::FrameFitOptions{}.max_iterations;
    int passes = fit::FrameFitOptions{}.passes;
    int samples = fit::CostOptions{}.max_samples;
    int distance_iterations = fit::CostOptions{}.distance.iterations;
    int degree = -1;
    bool quiet = false;
};

struct ScoreState {
    std::string model;
    std::string lens_file;
    std::vector<double> angles;
    int halfway = 16;
    int random = 4;
    int fit_angles = 16;
    uint64_t seed = 1;
    bool json = false;
};

bool parseSensor(const std::string& text, std::array<double, 2>& out) {
    const auto x = text.find('x');
    if (x == std::string::npos) return false;
    try {
        size_t used = 0;
        out[0] = std::stod(text.substr(0, x), &used);
        if (used != x) return false;
        out[1] = std::stod(text.substr(x + 1), &used);
        if (used != text.size() - x - 1) return false;
    } catch (...) {
        return false;
    }
    return out[0] > 0.0 && out[1] > 0.0 && std::isfinite(out[0]) && std::isfinite(out[1]);
}

int runFit(const FitState& s, std::ostream& out, std::ostream& err) {
    auto sweep = hdr::readSweep(s.sweep);
    if (!sweep) {
        err << "flarelab: fit: " << sweep.error().message << "\n";
        return 1;
    }
    if (const std::string w =
            hdr::clippingWarning(hdr::clippedFrames(*sweep), sweep->frames.size());
        !w.empty())
        err << "flarelab: fit: warning: " << w << "\n";
    std::array<double, 2> sensor{};
    bool have_sensor = false;
    if (!s.sensor.empty()) {
        if (!parseSensor(s.sensor, sensor)) {
            err << "flarelab: fit: --sensor-mm must be WxH in mm, both > 0 (got \"" << s.sensor
                << "\")\n";
            return 2;
        }
        have_sensor = true;
    }
    std::optional<optics::Lens> lens;
    std::string sha;
    if (!s.lens_file.empty()) {
        lens = loadLens(s.lens_file, CameraFlags{}, err);
        if (!lens) return 1;
        auto digest = sha256Hex(s.lens_file);
        if (!digest) {
            err << "flarelab: fit: " << digest.error().message << "\n";
            return 1;
        }
        sha = *digest;
        if (!have_sensor) {
            sensor = {lens->camera().sensor_width_mm, lens->camera().sensor_height_mm};
            have_sensor = true;
        }
    }
    auto size = fit::sweepSensorSize(*sweep, have_sensor ? &sensor : nullptr);
    if (!size) {
        err << "flarelab: fit: " << size.error().message << "\n";
        return 2;
    }
    fit::SweepFitOptions options;
    if (s.optimizer == "ceres") {
        options.frame.optimizer = fit::Optimizer::Ceres;
    } else if (s.optimizer == "gradient-descent") {
        options.frame.optimizer = fit::Optimizer::GradientDescent;
    } else {
        err << "flarelab: fit: --optimizer must be ceres or gradient-descent\n";
        return 2;
    }
    options.frame.max_iterations = s.iterations;
    options.frame.passes = s.passes;
    options.frame.cost.max_samples = s.samples;
    options.frame.cost.distance.iterations = s.distance_iterations;
    options.poly.fixed_degree = s.degree;
    if (Status ok = fit::checkSweepFitOptions(options); !ok) {
        err << "flarelab: fit: " << ok.error().message << "\n";
        return 2;
    }
    const auto progress = [&](const fit::SweepFitProgress& p) {
        if (s.quiet) return;
        err << "\rfit: frame " << p.frames_done << "/" << p.frames_total << "  " << std::fixed
            << std::setprecision(2) << p.angle_deg << " deg  " << p.live_ghosts << " ghosts   "
            << std::defaultfloat << std::flush;
    };
    fit::SweepFitResult result;
    auto model = fit::fitSweep(*sweep, (*size)[0], (*size)[1], options, progress, &result);
    if (!s.quiet) err << "\n";
    if (!model) {
        err << "flarelab: fit: " << model.error().message << "\n";
        return 1;
    }
    if (lens) {
        model->lens.prescription_file = s.lens_file;
        model->lens.prescription_sha256 = sha;
        if (!model->lens.f_number && lens->camera().f_number > 0.0)
            model->lens.f_number = lens->camera().f_number;
    }
    if (Status written = fit::writeModel(s.output, *model); !written) {
        err << "flarelab: fit: " << written.error().message << "\n";
        return 1;
    }
    out << "fit: " << model->ghosts.size() << " ghosts from " << sweep->frames.size() << " frames ("
        << result.frames_fitted << " frame fits, " << result.evaluations << " cost evaluations) in "
        << std::fixed << std::setprecision(1) << result.time_ms / 1000.0 << " s -> " << s.output
        << "\n";
    return 0;
}

void printSummary(const char* name, const fit::ScoreSummary& s, std::ostream& out) {
    out << name << ": " << s.count << " angles, relative L2 median " << std::fixed
        << std::setprecision(4) << s.median << ", worst " << s.worst << " at "
        << std::setprecision(3) << s.worst_angle_deg << " deg, median PSNR " << std::setprecision(1)
        << s.median_psnr_db << " dB\n"
        << std::defaultfloat;
}

nlohmann::json summaryJson(const fit::ScoreSummary& s) {
    return {{"count", s.count},
            {"median", s.median},
            {"worst", s.worst},
            {"worst_angle_deg", s.worst_angle_deg},
            {"median_psnr_db", s.median_psnr_db}};
}

int runScore(const ScoreState& s, std::ostream& out, std::ostream& err) {
    auto model = fit::readModel(s.model);
    if (!model) {
        err << "flarelab: score: " << model.error().message << "\n";
        return 1;
    }
    auto lens = loadLens(s.lens_file, CameraFlags{}, err);
    if (!lens) return 1;
    if (!model->lens.prescription_sha256.empty()) {
        auto digest = sha256Hex(s.lens_file);
        if (!digest) {
            err << "flarelab: score: " << digest.error().message << "\n";
            return 1;
        }
        if (*digest != model->lens.prescription_sha256) {
            err << "flarelab: score: " << s.lens_file << " is not the lens the model was fitted "
                << "with (" << model->lens.prescription_file << ", sha256 "
                << model->lens.prescription_sha256 << ")\n";
            return 2;
        }
    }
    fit::ScoreOptions options;
    options.angles_deg = s.angles;
    options.halfway_angles = s.halfway;
    options.random_angles = s.random;
    options.fit_angles = s.fit_angles;
    options.seed = s.seed;
    auto truth =
        drivers::simulatedGhostTruth(*lens, model->capture.width_px, model->capture.height_px);
    if (!truth) {
        err << "flarelab: score: " << truth.error().message << "\n";
        return 1;
    }
    auto report = fit::scoreModel(*model, *truth, options, [&](int done, int total) {
        if (!s.json) err << "\rscore: " << done << "/" << total << std::flush;
    });
    if (!s.json) err << "\n";
    if (!report) {
        err << "flarelab: score: " << report.error().message << "\n";
        return 1;
    }
    if (s.json) {
        nlohmann::json j;
        j["model"] = s.model;
        j["heldout_rel_l2"] = summaryJson(report->heldout_rel_l2);
        j["fit_rel_l2"] = summaryJson(report->fit_rel_l2);
        nlohmann::json angles = nlohmann::json::array();
        for (const auto& a : report->angles)
            angles.push_back({{"angle_deg", a.angle_deg},
                              {"held_out", a.held_out},
                              {"rel_l2", a.rel_l2},
                              {"psnr_db", a.psnr_db}});
        j["angles"] = angles;
        out << j.dump(2) << "\n";
        return 0;
    }
    out << "score: " << s.model << " against " << s.lens_file << " (simulated, ghosts only, "
        << "light neighbourhood masked)\n";
    out << "  angle_deg  kind      rel_L2   PSNR_dB\n";
    for (const auto& a : report->angles)
        out << "  " << std::setw(9) << std::fixed << std::setprecision(3) << a.angle_deg << "  "
            << (a.held_out ? "held-out" : "fitted  ") << "  " << std::setw(7)
            << std::setprecision(4) << a.rel_l2 << "  " << std::setw(7) << std::setprecision(1)
            << a.psnr_db << "\n"
            << std::defaultfloat;
    printSummary("fitted angles", report->fit_rel_l2, out);
    printSummary("held-out angles", report->heldout_rel_l2, out);
    return 0;
}

}  // namespace

Result<std::string> sha256Hex(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return makeError(ErrorCode::NotFound, path + ": cannot open it to hash");
    std::unique_ptr<EVP_MD_CTX, decltype(&EVP_MD_CTX_free)> ctx(EVP_MD_CTX_new(), EVP_MD_CTX_free);
    if (!ctx || EVP_DigestInit_ex(ctx.get(), EVP_sha256(), nullptr) != 1)
        return makeError(ErrorCode::Internal, "sha256: OpenSSL refused to start a digest");
    std::vector<char> buffer(1 << 16);
    while (in) {
        in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
        const std::streamsize got = in.gcount();
        if (got > 0 && EVP_DigestUpdate(ctx.get(), buffer.data(), static_cast<size_t>(got)) != 1)
            return makeError(ErrorCode::Internal, "sha256: OpenSSL refused the data");
    }
    if (in.bad()) return makeError(ErrorCode::IoError, path + ": read failed while hashing");
    unsigned char digest[EVP_MAX_MD_SIZE];
    unsigned int length = 0;
    if (EVP_DigestFinal_ex(ctx.get(), digest, &length) != 1)
        return makeError(ErrorCode::Internal, "sha256: OpenSSL refused to finish the digest");
    std::ostringstream hex;
    for (unsigned int i = 0; i < length; ++i)
        hex << std::hex << std::setw(2) << std::setfill('0') << static_cast<int>(digest[i]);
    return hex.str();
}

void addFitCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto fs = std::make_shared<FitState>();
    CLI::App* fit = app.add_subcommand("fit", "fit every ghost of a sweep and write a model file");
    fit->add_option("SWEEP", fs->sweep, "sweep directory")->required();
    fit->add_option("-o,--output", fs->output, "model file to write")->required();
    fit->add_option("--lens", fs->lens_file,
                    "the lens prescription, recorded in the model (gives the sensor size)");
    fit->add_option("--sensor-mm", fs->sensor, "sensor size WxH in mm (when nothing else says)");
    fit->add_option("--optimizer", fs->optimizer, "ceres or gradient-descent")
        ->capture_default_str();
    fit->add_option("--iterations", fs->iterations, "optimizer iterations per ghost and pass")
        ->capture_default_str();
    fit->add_option("--passes", fs->passes, "passes over a frame's ghosts")->capture_default_str();
    fit->add_option("--samples", fs->samples, "crop samples per side (the fit's resolution)")
        ->capture_default_str();
    fit->add_option("--distance-iterations", fs->distance_iterations,
                    "Newton steps of the Bezier distance")
        ->capture_default_str();
    fit->add_option("--degree", fs->degree,
                    "fixed polynomial degree of every parameter (-1: chosen by cross-validation)")
        ->capture_default_str();
    fit->add_flag("--quiet", fs->quiet, "no progress on stderr");
    fit->callback([fs, &out, &err, &exit_code] { exit_code = runFit(*fs, out, err); });

    auto ss = std::make_shared<ScoreState>();
    CLI::App* score = app.add_subcommand(
        "score",
        "score a model against the simulator's noiseless ghosts at fitted and held-out angles");
    score->add_option("MODEL", ss->model, "model file")->required();
    score->add_option("--lens", ss->lens_file, "the lens prescription the sweep was simulated with")
        ->required();
    score->add_option("--angles", ss->angles, "held-out angles to score (deg), comma separated")
        ->delimiter(',');
    score->add_option("--halfway", ss->halfway, "half-way angles scored when --angles is not given")
        ->capture_default_str();
    score->add_option("--random", ss->random, "random angles scored when --angles is not given")
        ->capture_default_str();
    score->add_option("--fitted", ss->fit_angles, "captured angles scored")->capture_default_str();
    score->add_option("--seed", ss->seed, "seed of the random angles")->capture_default_str();
    score->add_flag("--json", ss->json, "print the scores as JSON");
    score->callback([ss, &out, &err, &exit_code] { exit_code = runScore(*ss, out, err); });
}

}  // namespace flarelab::apps
