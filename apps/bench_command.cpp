#include "apps/bench_command.h"

#include <fstream>
#include <memory>
#include <ostream>
#include <string>

#include "bench/bracket_bench.h"
#include "bench/fit_bench.h"
#include "bench/merge_bench.h"
#include "bench/oracle_bench.h"
#include "bench/playback_bench.h"
#include "bench/predict_bench.h"
#include "bench/render_bench.h"
#include "bench/response_bench.h"

namespace flarelab::apps {
namespace {

// Writes `text` and a newline to `path` when a path is given; false (said on `err`) when that
// fails.
template <typename Text>
bool writeJsonFile(const std::string& path, const Text& text, std::ostream& err) {
    if (path.empty()) return true;
    std::ofstream file(path);
    file << text << "\n";
    if (!file) {
        err << "flarelab: cannot write " << path << "\n";
        return false;
    }
    return true;
}

}  // namespace

void addBenchCommands(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    CLI::App* bench = app.add_subcommand("bench", "measure speed and accuracy");
    bench->require_subcommand(1);
    auto options = std::make_shared<bench::RenderBenchOptions>();
    auto json_path = std::make_shared<std::string>();
    auto lights = std::make_shared<int>(0);
    CLI::App* render = bench->add_subcommand(
        "render", "the tiled renderer against the reference rasterizer (paper Tables 2-7)");
    render->add_option("--lens", options->lens_files,
                       "lens files (default: the paper's five in --lens-dir)");
    render->add_option("--lens-dir", options->lens_dir, "where the paper's lenses are")
        ->capture_default_str();
    render->add_option("--lights", *lights, "only this many lights (default: 1 and 2)")
        ->check(CLI::Range(1, 64));
    render->add_flag("--quick", options->quick,
                     "smoke test: two small lenses at 640x360, grid 64, one run (under a minute)");
    render->add_option("--repeat", options->repeat, "runs per figure; the best is kept")
        ->check(CLI::Range(1, 100))
        ->capture_default_str();
    render->add_option("--width", options->width, "image width")->check(CLI::Range(1, 16384));
    render->add_option("--height", options->height, "image height")->check(CLI::Range(1, 16384));
    render->add_option("--grid", options->base_grid, "base ray-grid size")
        ->check(CLI::Range(2, 2048))
        ->capture_default_str();
    render
        ->add_option("--max-grid", options->max_grid,
                     "the most rays a side of a smooth ghost's grid (0: eq. 13's size, no cap)")
        ->check(CLI::Range(0, 2048))
        ->capture_default_str();
    render
        ->add_option("--truth-grid", options->truth_grid,
                     "base ray-grid size of the truth the PSNR columns measure against (0: "
                     "--grid's)")
        ->check(CLI::Range(0, 2048))
        ->capture_default_str();
    render->add_flag("!--no-lenses", options->lenses, "skip the per-lens tables (Tables 2-7)");
    render->add_flag("!--no-trade", options->trade, "skip the grid-size x merge trade table");
    render->add_flag("!--no-scaling", options->scaling, "skip the lights and image-size tables");
    render->add_flag("!--no-cull", options->cull, "skip the ghost-culling table");
    render->add_flag("!--no-centre-edges", options->centre_edges,
                     "skip the table of interior edges drawn by pixel centre");
    render
        ->add_option("--truth-samples", options->truth_samples,
                     "also PSNR against N x N point samples per pixel (0: not)")
        ->check(CLI::Range(0, 64));
    render->add_option("--json", *json_path, "also write the results as JSON here");
    render->callback([options, json_path, lights, &out, &err, &exit_code] {
        if (*lights > 0) options->light_counts = {*lights};
        auto doc = bench::runRenderBench(*options, out, err);
        if (!doc) {
            err << "flarelab: " << doc.error().message << "\n";
            exit_code = 1;
            return;
        }
        exit_code = writeJsonFile(*json_path, doc->dump(2), err) ? 0 : 1;
    });

    auto merge_options = std::make_shared<bench::MergeBenchOptions>();
    auto merge_json_path = std::make_shared<std::string>();
    CLI::App* merge = bench->add_subcommand(
        "merge", "the HDR bracket merge against OpenCV's MergeDebevec and MergeRobertson");
    merge->add_flag("--quick", merge_options->quick,
                    "smoke test: 1200x800, at most two runs (seconds)");
    merge->add_option("--repeat", merge_options->repeat, "runs per figure; the best is kept")
        ->check(CLI::Range(1, 100))
        ->capture_default_str();
    merge->add_option("--width", merge_options->width, "image width, pixels")
        ->check(CLI::Range(8, 32768))
        ->capture_default_str();
    merge->add_option("--height", merge_options->height, "image height, pixels")
        ->check(CLI::Range(8, 32768))
        ->capture_default_str();
    merge->add_option("--bit-depth", merge_options->bit_depth, "bits of the simulated converter")
        ->check(CLI::Range(10, 16))
        ->capture_default_str();
    merge
        ->add_option("--exposure-s", merge_options->exposure_times_s,
                     "the bracket's exposure times, seconds")
        ->capture_default_str();
    merge->add_option("--seed", merge_options->seed, "noise seed")->capture_default_str();
    merge->add_flag("!--no-opencv", merge_options->opencv, "skip OpenCV's merges");
    merge->add_option("--json", *merge_json_path, "also write the results as JSON here");
    merge->callback([merge_options, merge_json_path, &out, &err, &exit_code] {
        auto doc = bench::runMergeBench(*merge_options, out, err);
        if (!doc) {
            err << "flarelab: " << doc.error().message << "\n";
            exit_code = 1;
            return;
        }
        exit_code = writeJsonFile(*merge_json_path, doc->dump(2), err) ? 0 : 1;
    });

    auto fit_options = std::make_shared<bench::FitBenchOptions>();
    auto fit_json_path = std::make_shared<std::string>();
    CLI::App* fit = bench->add_subcommand(
        "fit",
        "the fitting backend: Ceres against the thesis's gradient descent, and the "
        "speed/accuracy trade of its knobs, scored against the simulator");
    fit->add_option("--sweep", fit_options->sweeps,
                    "a simulated sweep (repeat: the first is the main one, the others the angular "
                    "step rows)")
        ->required();
    fit->add_option("--lens", fit_options->lens_file, "the lens the sweeps were simulated with")
        ->required();
    fit->add_option("--optimizer-frames", fit_options->optimizer_frames,
                    "frames of the optimizer table")
        ->capture_default_str();
    fit->add_flag("!--no-trade", fit_options->trade, "skip the trade table");
    fit->add_flag("!--no-frames", fit_options->frames, "skip the per-frame table");
    fit->add_flag("--quick", fit_options->quick, "fewer settings and angles (a smoke test)");
    std::string knob_help = "trade rows of this knob only (repeat; the baseline always runs):";
    for (const std::string& knob : bench::tradeKnobs())
        knob_help += (knob_help.back() == ':' ? " " : ", ") +
                     (knob.find(' ') == std::string::npos ? knob : "'" + knob + "'");
    fit->add_option("--knob", fit_options->knobs, knob_help);
    fit->add_option("--json", *fit_json_path, "also write the results as JSON here");
    fit->callback([fit_options, fit_json_path, &out, &err, &exit_code] {
        auto report = bench::runFitBench(*fit_options, err);
        if (!report) {
            err << "flarelab: bench fit: " << report.error().message << "\n";
            exit_code = 1;
            return;
        }
        bench::printFitBench(*report, out);
        exit_code = writeJsonFile(*fit_json_path, bench::fitBenchJson(*report), err) ? 0 : 1;
    });

    auto oracle_options = std::make_shared<bench::OracleBenchOptions>();
    auto oracle_json_path = std::make_shared<std::string>();
    CLI::App* oracle = bench->add_subcommand(
        "oracle",
        "the ghost model's capacity floor: each ghost path of a lens rendered alone, detected and "
        "fitted as one ghost, against its image");
    oracle->add_option("--lens", oracle_options->lens_files, "lens files (repeat)")->required();
    oracle->add_option("--angle", oracle_options->angles_deg, "light angles in deg (repeat)")
        ->capture_default_str();
    oracle->add_option("--width", oracle_options->width, "frame width")->capture_default_str();
    oracle->add_option("--height", oracle_options->height, "frame height")->capture_default_str();
    oracle
        ->add_option("--min-share", oracle_options->min_share,
                     "paths with less of an angle's ghost light are not fitted")
        ->capture_default_str();
    oracle->add_option("--images", oracle_options->images,
                       "write each path's image beside its fitted ghost (PNG) into this directory");
    oracle->add_flag("--colour", oracle_options->colour,
                     "the truth in colour (a Bayer capture's), each ghost fitted in three "
                     "channels with one shape; default: the monochrome camera's green");
    oracle->add_option("--json", *oracle_json_path, "also write the results as JSON here");
    oracle->callback([oracle_options, oracle_json_path, &out, &err, &exit_code] {
        auto report = bench::runOracleBench(*oracle_options, err);
        if (!report) {
            err << "flarelab: " << report.error().message << "\n";
            exit_code = 1;
            return;
        }
        bench::printOracleBench(*report, out);
        exit_code = writeJsonFile(*oracle_json_path, bench::oracleBenchJson(*report), err) ? 0 : 1;
    });

    auto response_options = std::make_shared<bench::ResponseBenchOptions>();
    auto response_json_path = std::make_shared<std::string>();
    CLI::App* response = bench->add_subcommand(
        "response",
        "camera response recovery (flarelab calibrate) against OpenCV's CalibrateDebevec and "
        "CalibrateRobertson, on the simulated camera with a known curve");
    response
        ->add_option("--curve", response_options->curves,
                     "curves to recover: linear, gamma:G, log:A (repeat)")
        ->capture_default_str();
    response->add_option("--seed", response_options->seeds, "noise seeds (repeat)")
        ->capture_default_str();
    response->add_option("--lens", response_options->lens_file,
                         "the simulated camera's lens (default: "
                         "data/lenses/heliar-tronnier.csv)");
    response->add_option("--angle-deg", response_options->angle_deg, "the light's angle")
        ->capture_default_str();
    response->add_option("--width", response_options->width, "frame width")
        ->check(CLI::Range(int64_t{32}, int64_t{8192}))
        ->capture_default_str();
    response->add_option("--height", response_options->height, "frame height")
        ->check(CLI::Range(int64_t{32}, int64_t{8192}))
        ->capture_default_str();
    response->add_option("--stops", response_options->stops, "stops below the clip level scored")
        ->capture_default_str();
    response->add_flag("!--no-opencv", response_options->opencv, "skip OpenCV's calibrations");
    response->add_option("--json", *response_json_path, "also write the results as JSON here");
    response->callback([response_options, response_json_path, &out, &err, &exit_code] {
        auto rows = bench::runResponseBench(*response_options, err);
        if (!rows) {
            err << "flarelab: " << rows.error().message << "\n";
            exit_code = 1;
            return;
        }
        bench::printResponseBench(*rows, out);
        exit_code = writeJsonFile(*response_json_path, bench::responseBenchJson(*rows).dump(2), err)
                        ? 0
                        : 1;
    });

    auto bracket_options = std::make_shared<bench::BracketBenchOptions>();
    auto bracket_json_path = std::make_shared<std::string>();
    auto bracket_fixed = std::make_shared<std::vector<double>>(bracket_options->fixed_s);
    CLI::App* bracket = bench->add_subcommand(
        "bracket",
        "auto-bracketing against fixed brackets on the simulated rig, every lens, scored along "
        "the sweep against the simulator's truth");
    bracket->add_option("--lens", bracket_options->lens_files,
                        "lens files (repeat; default: every *.csv in --lens-dir)");
    bracket->add_option("--lens-dir", bracket_options->lens_dir, "where the lenses are")
        ->capture_default_str();
    bracket->add_option("--f-number", bracket_options->f_number,
                        "working f-number of every lens (default: each file's)");
    bracket
        ->add_option("--from", bracket_options->first_angles_deg,
                     "first angles of the sweeps, deg (repeat)")
        ->capture_default_str();
    bracket
        ->add_option("--offset", bracket_options->sweep_offsets_deg,
                     "angles after the first where the plan is scored, deg (repeat)")
        ->capture_default_str();
    bracket->add_option("--seed", bracket_options->seeds, "noise seeds (repeat)")
        ->capture_default_str();
    bracket->add_option("--width", bracket_options->width, "frame width")
        ->check(CLI::Range(int64_t{32}, int64_t{8192}))
        ->capture_default_str();
    bracket->add_option("--height", bracket_options->height, "frame height")
        ->check(CLI::Range(int64_t{32}, int64_t{8192}))
        ->capture_default_str();
    bracket->add_option("--min-exposure", bracket_options->min_exposure_s,
                        "the simulated camera's shortest exposure, s (default: its own, 1e-9)");
    bracket
        ->add_option("--floor-headroom", bracket_options->plan.floor_headroom,
                     "aim at a floor this many times dimmer than the first angle's")
        ->capture_default_str();
    bracket->add_option("--fixed", *bracket_fixed, "the fixed bracket compared with, s")
        ->delimiter(',')
        ->capture_default_str();
    bracket
        ->add_option("--core-level", bracket_options->plan.core_level,
                     "the core's peak in the shortest exposure, of the range")
        ->capture_default_str();
    bracket
        ->add_option("--floor-snr", bracket_options->plan.floor_snr,
                     "the floor's signal-to-noise ratio in the longest exposure")
        ->capture_default_str();
    bracket
        ->add_option("--floor-percentile", bracket_options->plan.floor_percentile,
                     "the scene's dark level, as a fraction of the pixels")
        ->capture_default_str();
    bracket
        ->add_option("--max-ratio", bracket_options->plan.max_ratio,
                     "most ratio between neighbouring exposures")
        ->capture_default_str();
    bracket
        ->add_option("--budget", bracket_options->plan.budget_s,
                     "most exposure time of one bracket, s")
        ->capture_default_str();
    bracket->add_option("--json", *bracket_json_path, "also write the results as JSON here");
    bracket->callback([bracket_options, bracket_fixed, bracket_json_path, &out, &err, &exit_code] {
        bracket_options->fixed_s = *bracket_fixed;
        auto rows = bench::runBracketBench(*bracket_options, err);
        if (!rows) {
            err << "flarelab: " << rows.error().message << "\n";
            exit_code = 1;
            return;
        }
        bench::printBracketBench(*rows, *bracket_options, out);
        exit_code =
            writeJsonFile(*bracket_json_path, bench::bracketBenchJson(*rows).dump(2), err) ? 0 : 1;
    });
    auto playback_options = std::make_shared<bench::PlaybackBenchOptions>();
    auto playback_json_path = std::make_shared<std::string>();
    CLI::App* playback = bench->add_subcommand("playback",
                                               "a model file drawn frame after frame (flarelab "
                                               "model render's fast path) against the exact "
                                               "evaluation: frame time and error");
    playback->add_option("MODEL", playback_options->model_path, "flare model file")->required();
    playback->add_option("--width", playback_options->width, "image width")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}))
        ->capture_default_str();
    playback->add_option("--height", playback_options->height, "image height")
        ->check(CLI::Range(int64_t{1}, int64_t{32768}))
        ->capture_default_str();
    playback->add_option("--angle", playback_options->angle_deg,
                         "head angle (deg); default: the valid range's angle with the most ghosts");
    playback->add_option("--roll", playback_options->roll_deg,
                         "roll (deg); default: the capture's");
    playback->add_option("--frames", playback_options->frames, "timed frames after the first")
        ->check(CLI::Range(1, 10000))
        ->capture_default_str();
    playback
        ->add_option("--smooth-tolerance", playback_options->smooth_tolerance,
                     "largest error of an interpolated block at its check points, as a fraction "
                     "of the ghost's peak")
        ->check(CLI::Range(1e-9, 0.1))
        ->capture_default_str();
    playback->add_flag("!--ghost-tolerance", playback_options->frame_tolerance,
                       "the smooth tolerance a fraction of each ghost's own peak (as the fit "
                       "and score draw) instead of the frame's brightest ghost's (as model "
                       "render draws)");
    playback
        ->add_option("--dense-tile", playback_options->dense_tile_px,
                     "the fast frames' dense tiles (px; a divisor of --coarse-tile)")
        ->check(CLI::Range(1, 256))
        ->capture_default_str();
    playback
        ->add_option("--coarse-tile", playback_options->coarse_tile_px,
                     "the fast frames' coarse tiles (px, at most 4096)")
        ->check(CLI::Range(1, 4096))
        ->capture_default_str();
    playback
        ->add_option("--exact-seeds", playback_options->exact_seeds,
                     "Newton seeds per segment of the exact frame's distance")
        ->check(CLI::Range(1, 64))
        ->capture_default_str();
    playback
        ->add_option("--exact-iterations", playback_options->exact_iterations,
                     "Newton steps per seed of the exact frame's distance")
        ->check(CLI::Range(0, 64))
        ->capture_default_str();
    playback
        ->add_option("--log-scale", playback_options->log_scale,
                     "log_rel_l2's tone mapping, as score's (a fraction of the peak)")
        ->check(CLI::Range(1e-12, 1.0))
        ->capture_default_str();
    playback->add_flag("!--no-exact", playback_options->exact,
                       "skip the exact frame (and the error figures)");
    playback->add_option("--json", *playback_json_path, "also write the results as JSON here");
    playback->callback([playback_options, playback_json_path, &out, &err, &exit_code] {
        auto result = bench::runPlaybackBench(*playback_options, err);
        if (!result) {
            err << "flarelab: bench playback: " << result.error().message << "\n";
            exit_code = 1;
            return;
        }
        bench::printPlaybackBench(*result, out);
        exit_code =
            writeJsonFile(*playback_json_path, bench::playbackBenchJson(*result).dump(2), err) ? 0
                                                                                               : 1;
    });

    auto predict_options = std::make_shared<bench::PredictBenchOptions>();
    auto predict_json_path = std::make_shared<std::string>();
    CLI::App* predict = bench->add_subcommand(
        "predict",
        "the planner's figure table against drawing each constellation, the prediction against "
        "the simulator (--lens) and a broadcast's timeline and switching plan");
    predict->add_option("MODEL", predict_options->model_path, "flare model file")->required();
    predict->add_option("--lens", predict_options->lens_path,
                        "the model's lens prescription: also score against the simulator");
    predict
        ->add_option("--constellations", predict_options->constellations,
                     "random constellations drawn")
        ->check(CLI::Range(1, 100000))
        ->capture_default_str();
    predict->add_option("--seed", predict_options->seed, "of the random constellations")
        ->capture_default_str();
    predict->add_option("--cameras", predict_options->cameras, "cameras of the broadcast")
        ->check(CLI::Range(1, 64))
        ->capture_default_str();
    predict->add_option("--hours", predict_options->hours, "length of the broadcast")
        ->check(CLI::Range(0.001, 48.0))
        ->capture_default_str();
    predict->add_option("--step-s", predict_options->step_s, "timeline step, s")
        ->check(CLI::Range(0.001, 3600.0))
        ->capture_default_str();
    predict->add_option("--repeat", predict_options->repeat, "timed runs of the broadcast")
        ->check(CLI::Range(1, 100))
        ->capture_default_str();
    predict->add_flag("!--no-trade", predict_options->trade, "only the default table");
    predict->add_option("--json", *predict_json_path, "also write the results as JSON here");
    predict->callback([predict_options, predict_json_path, &out, &err, &exit_code] {
        auto result = bench::runPredictBench(*predict_options, err);
        if (!result) {
            err << "flarelab: bench predict: " << result.error().message << "\n";
            exit_code = 1;
            return;
        }
        bench::printPredictBench(*result, out);
        exit_code = writeJsonFile(*predict_json_path, bench::predictBenchJson(*result).dump(2), err)
                        ? 0
                        : 1;
    });
}

}  // namespace flarelab::apps
