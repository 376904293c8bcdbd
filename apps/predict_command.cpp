#include "apps/predict_command.h"

#include <memory>
#include <ostream>
#include <string>
#include <vector>

#include "predict/prediction.h"

namespace flarelab::apps {
namespace {

struct PredictState {
    std::string scene_path;
    std::string out_dir;
    bool json = false;
    double table_theta_step_deg = 0.0;
    double table_phi_step_deg = 10.0;
    int64_t table_width = 240;
    double exposure_stops = 0.0;
    double black_spot_deg = predict::LabFigureOptions{}.black_spot_deg;
    std::vector<double> lab_heights = predict::FigureTableOptions{}.field_points;
};

int run(const PredictState& s, std::ostream& out, std::ostream& err) {
    predict::PredictOptions options;
    options.table.theta_step_deg = s.table_theta_step_deg;
    options.table.phi_step_deg = s.table_phi_step_deg;
    options.table.width = s.table_width;
    options.exposure_stops = s.exposure_stops;
    options.lab.black_spot_deg = s.black_spot_deg;
    options.table.field_points = s.lab_heights;
    options.on_note = [&err](const std::string& note) {
        err << "flarelab: predict: note: " << note << "\n";
    };
    auto predicted = predict::predictScene(s.scene_path, s.out_dir, options);
    if (!predicted) {
        const Error& e = predicted.error();
        err << "flarelab: predict: " << e.message << "\n";
        return e.code == ErrorCode::ParseError || e.code == ErrorCode::InvalidArgument ? 2 : 1;
    }
    out << (s.json ? predicted->report_json : predicted->summary);
    return 0;
}

}  // namespace

void addPredictCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto s = std::make_shared<PredictState>();
    CLI::App* cmd = app.add_subcommand(
        "predict",
        "flare figures, a sun timeline with a camera switching plan, frames and a report for a "
        "scene file (docs/predict.md)");
    cmd->add_option("SCENE", s->scene_path, "scene file (JSON, flarelab-scene version 1)")
        ->required();
    cmd->add_option("-o,--output", s->out_dir, "report folder (created)")->required();
    cmd->add_flag("--json", s->json, "print report.json instead of the summary");
    cmd->add_option("--table-theta-step", s->table_theta_step_deg,
                    "figure table's theta step, deg (0: the capture's, at most 0.5)")
        ->check(CLI::Range(0.0, 10.0))
        ->capture_default_str();
    cmd->add_option("--table-phi-step", s->table_phi_step_deg,
                    "figure table's roll step, deg (divides 360)")
        ->check(CLI::Range(0.5, 90.0))
        ->capture_default_str();
    cmd->add_option("--table-width", s->table_width, "figure table's drawing width, px")
        ->check(CLI::Range(int64_t{8}, int64_t{4096}))
        ->capture_default_str();
    cmd->add_option("--exposure-stops", s->exposure_stops,
                    "frames' PNG exposure, stops above the camera's white (scene_max_dn)")
        ->capture_default_str();
    cmd->add_option("--black-spot-deg", s->black_spot_deg,
                    "angular diameter of the black spot (veiling glare index) and of the chart's "
                    "centre patch (image flare), deg")
        ->check(CLI::Range(0.001, 20.0))
        ->capture_default_str();
    cmd->add_option("--lab-heights", s->lab_heights,
                    "image heights (of the half-diagonal, along the diagonal) of the off-axis "
                    "black spots and chart patches, at most 8")
        ->delimiter(',')
        ->check(CLI::Range(0.001, 1.0))
        ->capture_default_str();
    cmd->callback([s, &out, &err, &exit_code] { exit_code = run(*s, out, err); });
}

}  // namespace flarelab::apps
