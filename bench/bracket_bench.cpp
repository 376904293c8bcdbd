#include "bench/bracket_bench.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iomanip>
#include <memory>
#include <sstream>

#include "drivers/sim_camera.h"
#include "drivers/sim_head.h"
#include "optics/prescription.h"

namespace flarelab::bench {
namespace {

namespace fs = std::filesystem;

constexpr double kTimeout_s = 600.0;

std::string num(double x, int digits = 3) {
    std::ostringstream out;
    out << std::setprecision(digits) << x;
    return out.str();
}

std::string times(const std::vector<double>& t) {
    std::string s;
    for (const double x : t) s += (s.empty() ? "" : "/") + num(x);
    return s;
}

// The simulated rig of one case.
struct Rig {
    std::shared_ptr<drivers::SimHead> head;
    std::unique_ptr<drivers::SimCamera> camera;
};

Result<Rig> makeRig(const optics::Lens& lens, const BracketBenchOptions& o, uint64_t seed) {
    auto clock = std::make_shared<drivers::SimClock>(drivers::SimTime::Fast);
    drivers::SimHeadOptions head_options;
    head_options.seed = seed;
    auto head = drivers::SimHead::make(head_options, clock);
    if (!head) return head.error();
    Rig rig;
    rig.head = std::move(*head);
    drivers::SimCameraOptions camera_options;
    camera_options.width_px = o.width;
    camera_options.height_px = o.height;
    camera_options.seed = seed;
    camera_options.cache_angles = 2;
    if (o.min_exposure_s > 0.0) camera_options.min_exposure_s = o.min_exposure_s;
    auto camera = drivers::SimCamera::make(lens, camera_options, rig.head);
    if (!camera) return camera.error();
    rig.camera = std::move(*camera);
    if (Status ok = rig.head->home(kTimeout_s); !ok) return ok.error();
    return rig;
}

Result<hdr::RawFrame> shoot(drivers::SimCamera& camera, double exposure_s) {
    if (Status ok = camera.setExposure(exposure_s); !ok) return ok.error();
    return camera.capture(exposure_s + kTimeout_s);
}

// Scores a bracket (its shortest and longest exposure) at the head's angle against the truth.
Status score(drivers::SimCamera& camera,
             double angle_deg,
             const std::vector<double>& bracket,
             BracketScore& s) {
    auto truth = camera.meanRate_e_s(angle_deg);
    if (!truth) return truth.error();
    auto shortest = shoot(camera, bracket.front());
    if (!shortest) return shortest.error();
    auto longest = shoot(camera, bracket.back());
    if (!longest) return longest.error();
    const double range = shortest->white_level_dn - shortest->black_level_dn;
    const double saturated_at = shortest->white_level_dn - 0.01 * range;
    const size_t core =
        static_cast<size_t>(std::max_element(truth->begin(), truth->end()) - truth->begin());
    if (shortest->samples[core] >= saturated_at) {
        ++s.core_clipped;
        if (s.angles == 0) s.first_core_clipped = true;
    }
    int64_t saturated = 0;
    for (const uint16_t v : shortest->samples) saturated += v >= saturated_at ? 1 : 0;
    s.saturated_fraction =
        std::max(s.saturated_fraction, static_cast<double>(saturated) / shortest->samples.size());
    // The floor: the scene's 5th percentile of electron rate, dark current included.
    const drivers::CameraCapabilities caps = camera.capabilities();
    std::vector<double> rate(truth->begin(), truth->end());
    const auto k = rate.size() / 20;
    std::nth_element(rate.begin(), rate.begin() + static_cast<std::ptrdiff_t>(k), rate.end());
    const double dark_e_s = drivers::SimCameraOptions{}.dark_current_e_s;
    const double signal_e = (rate[k] + dark_e_s) * bracket.back();
    const double electrons_per_dn = longest->electrons_per_dn;
    const double noise_e = std::sqrt(signal_e + caps.read_noise_e * caps.read_noise_e +
                                     electrons_per_dn * electrons_per_dn / 12.0);
    const double snr = signal_e / noise_e;
    if (s.angles == 0) s.first_floor_snr = snr;
    s.floor_snr = s.angles == 0 ? snr : std::min(s.floor_snr, snr);
    ++s.angles;
    s.total_s = 0.0;
    for (const double t : bracket) s.total_s += t;
    return Ok{};
}

}  // namespace

Result<std::vector<BracketBenchRow>> runBracketBench(const BracketBenchOptions& o,
                                                     std::ostream& log) {
    if (o.width < 32 || o.height < 32 || o.width > 8192 || o.height > 8192)
        return makeError(ErrorCode::InvalidArgument, "bench bracket: width and height: 32..8192");
    if (o.first_angles_deg.empty() || o.seeds.empty() || o.sweep_offsets_deg.empty() ||
        o.fixed_s.empty())
        return makeError(ErrorCode::InvalidArgument,
                         "bench bracket: give first angles, sweep offsets, seeds and fixed "
                         "brackets");
    if (!(o.min_exposure_s >= 0.0 && o.min_exposure_s < 1.0))
        return makeError(ErrorCode::InvalidArgument,
                         "bench bracket: --min-exposure must lie in [0, 1) s");
    if (!(o.f_number >= 0.0 && std::isfinite(o.f_number)))
        return makeError(ErrorCode::InvalidArgument, "bench bracket: --f-number must be >= 0");
    std::vector<std::string> files = o.lens_files;
    if (files.empty()) {
        std::error_code ec;
        for (const auto& entry : fs::directory_iterator(o.lens_dir, ec))
            if (entry.path().extension() == ".csv") files.push_back(entry.path().string());
        if (ec)
            return makeError(ErrorCode::NotFound,
                             "bench bracket: " + o.lens_dir + ": " + ec.message());
        std::sort(files.begin(), files.end());
        if (files.empty())
            return makeError(ErrorCode::NotFound, "bench bracket: no lens files in " + o.lens_dir);
    }
    std::vector<double> fixed = o.fixed_s;
    std::sort(fixed.begin(), fixed.end());

    std::vector<BracketBenchRow> rows;
    for (const std::string& file : files) {
        auto prescription = optics::loadPrescription(file);
        if (!prescription) return prescription.error();
        optics::CameraDescription description;
        description.f_number = o.f_number;
        auto lens = optics::Lens::make(*prescription, description);
        if (!lens) return lens.error().withContext(file);
        for (const double first : o.first_angles_deg)
            for (const uint64_t seed : o.seeds) {
                log << "bench bracket: " << fs::path(file).stem().string() << " from " << first
                    << " deg, seed " << seed << "\n";
                auto rig = makeRig(*lens, o, seed);
                if (!rig) return rig.error().withContext(file);
                if (auto at = rig->head->moveTo(first, kTimeout_s); !at) return at.error();
                auto plan = drivers::planBrackets(*rig->camera, o.plan);
                if (!plan) return plan.error().withContext(file);
                BracketBenchRow row;
                row.lens = fs::path(file).stem().string();
                row.f_number = lens->camera().f_number;
                row.first_angle_deg = first;
                row.seed = seed;
                row.plan_s = plan->exposure_times_s;
                row.plan_core_unclipped = plan->core_unclipped;
                row.plan_floor_reached = plan->floor_reached;
                row.probes = plan->probes;
                row.reasons = plan->reasons;
                for (const double offset : o.sweep_offsets_deg) {
                    const double angle = first + offset;
                    auto at = rig->head->moveTo(angle, kTimeout_s);
                    if (!at) return at.error();
                    const double seen = rig->head->trueAngle_deg();
                    if (Status ok = score(*rig->camera, seen, row.plan_s, row.automatic); !ok)
                        return ok.error().withContext(file);
                    if (Status ok = score(*rig->camera, seen, fixed, row.fixed); !ok)
                        return ok.error().withContext(file);
                }
                rows.push_back(std::move(row));
            }
    }
    return rows;
}

void printBracketBench(const std::vector<BracketBenchRow>& rows,
                       const BracketBenchOptions& o,
                       std::ostream& out) {
    const std::string fixed = times(o.fixed_s);
    out << "| lens | f/ | from (deg) | seed | auto bracket (s) | probes | core clipped (auto / "
        << fixed << ") | saturated in the shortest (auto / " << fixed
        << ") | floor SNR in the longest (auto / " << fixed << ") | exposure (s, auto / " << fixed
        << ") |\n";
    out << "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n";
    int auto_clipped = 0, fixed_clipped = 0, auto_missed = 0, fixed_missed = 0;
    int auto_first_clipped = 0, fixed_first_clipped = 0, auto_first_missed = 0,
        fixed_first_missed = 0;
    double auto_time = 0.0, fixed_time = 0.0;
    for (const BracketBenchRow& r : rows) {
        const auto pct = [](double f) { return num(100.0 * f, 3) + " %"; };
        out << "| " << r.lens << " | " << num(r.f_number) << " | " << r.first_angle_deg << " | "
            << r.seed << " | " << times(r.plan_s) << " | " << r.probes << " | "
            << r.automatic.core_clipped << "/" << r.automatic.angles << " / "
            << r.fixed.core_clipped << "/" << r.fixed.angles << " | "
            << pct(r.automatic.saturated_fraction) << " / " << pct(r.fixed.saturated_fraction)
            << " | " << num(r.automatic.first_floor_snr) << " / " << num(r.fixed.first_floor_snr)
            << " | " << num(r.automatic.floor_snr) << " / " << num(r.fixed.floor_snr) << " | "
            << num(r.automatic.total_s) << " / " << num(r.fixed.total_s) << " |\n";
        auto_clipped += r.automatic.core_clipped > 0 ? 1 : 0;
        fixed_clipped += r.fixed.core_clipped > 0 ? 1 : 0;
        auto_missed += r.automatic.floor_snr < o.plan.floor_snr ? 1 : 0;
        fixed_missed += r.fixed.floor_snr < o.plan.floor_snr ? 1 : 0;
        auto_first_clipped += r.automatic.first_core_clipped ? 1 : 0;
        fixed_first_clipped += r.fixed.first_core_clipped ? 1 : 0;
        auto_first_missed += r.automatic.first_floor_snr < o.plan.floor_snr ? 1 : 0;
        fixed_first_missed += r.fixed.first_floor_snr < o.plan.floor_snr ? 1 : 0;
        auto_time += r.automatic.total_s;
        fixed_time += r.fixed.total_s;
    }
    const auto n = static_cast<double>(std::max<size_t>(1, rows.size()));
    out << "\n"
        << rows.size() << " cases. At the first angle: core clipped: auto " << auto_first_clipped
        << ", fixed " << fixed_first_clipped << "; floor below SNR " << num(o.plan.floor_snr)
        << ": auto " << auto_first_missed << ", fixed " << fixed_first_missed
        << ". At some angle of the sweep: core clipped: auto " << auto_clipped << ", fixed "
        << fixed_clipped << "; floor below SNR " << num(o.plan.floor_snr) << ": auto "
        << auto_missed << ", fixed " << fixed_missed << ". Mean exposure per bracket: auto "
        << num(auto_time / n) << " s, fixed " << num(fixed_time / n) << " s.\n";
}

nlohmann::json bracketBenchJson(const std::vector<BracketBenchRow>& rows) {
    const auto score = [](const BracketScore& s) {
        return nlohmann::json{{"core_clipped_angles", s.core_clipped},
                              {"first_core_clipped", s.first_core_clipped},
                              {"first_floor_snr", s.first_floor_snr},
                              {"angles", s.angles},
                              {"saturated_fraction", s.saturated_fraction},
                              {"floor_snr", s.floor_snr},
                              {"exposure_s", s.total_s}};
    };
    nlohmann::json doc = nlohmann::json::array();
    for (const BracketBenchRow& r : rows)
        doc.push_back({{"lens", r.lens},
                       {"f_number", r.f_number},
                       {"first_angle_deg", r.first_angle_deg},
                       {"seed", r.seed},
                       {"plan_s", r.plan_s},
                       {"plan_core_unclipped", r.plan_core_unclipped},
                       {"plan_floor_reached", r.plan_floor_reached},
                       {"probes", r.probes},
                       {"auto", score(r.automatic)},
                       {"fixed", score(r.fixed)},
                       {"reasons", r.reasons}});
    return doc;
}

}  // namespace flarelab::bench
