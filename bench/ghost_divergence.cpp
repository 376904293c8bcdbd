// ghost_divergence: how far the paraxial ghost model strays from real rays.
//
//   ghost_divergence [--json FILE] [--csv FILE] [LENS...]
//
// For every two-reflection ghost that enumerateGhosts keeps with its default options, and for a
// ladder of light angles (phi = 0, 550 nm), compares the first-order ghost (paraxialGhost: the
// centre moves as tan(theta), the radius is fixed) with the ghost that real rays draw
// (exactGhost). Centres differ in units of the sensor half-diagonal, the unit of the project's
// ghost-centre tolerances; radii differ relative to the exact radius. Without LENS arguments it
// reads every data/lenses/*.csv of the source tree.
//
// Prints a Markdown summary per lens and angle (median, 90th percentile and maximum) and the
// acceptance check that every ghost agrees to 0.5 % of the half-diagonal up to 1 degree. --csv
// writes one row per lens x ghost x angle for plotting, --json the summary. Exit status 0 when
// every lens could be read, whatever the divergences are: this tool measures, the reader judges.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <nlohmann/json.hpp>
#include <optional>
#include <span>
#include <sstream>
#include <string>
#include <vector>

#include "common/units.h"
#include "optics/ghosts.h"
#include "optics/lens.h"
#include "optics/paraxial.h"
#include "optics/prescription.h"

namespace flarelab::bench {
namespace {

using Json = nlohmann::ordered_json;
using namespace flarelab::optics;

constexpr double kThetas_deg[] = {0.0, 0.25, 0.5,  1.0,  2.0,  3.0, 5.0,
                                  7.5, 10.0, 15.0, 20.0, 25.0, 30.0};
constexpr double kWavelength_nm = kLambdaGreen_nm;
constexpr double kAcceptanceTheta_deg = 1.0;
constexpr double kAcceptanceCentre_pct = 0.5;

// One ghost at one angle. The divergences are set only when both models gave an answer.
struct Sample {
    GhostPath path;
    double theta_deg = 0.0;
    std::optional<double> paraxial_centre_mm, exact_centre_mm;
    std::optional<double> paraxial_radius_mm, exact_radius_mm;
    int rim_points = 0;
    std::optional<double> centre_pct;  // % of the sensor half-diagonal
    std::optional<double> radius_pct;  // % of the exact radius
    // Why a ghost may diverge, from the path's transfer (A B; C D) to the stop, all at the first
    // vertex and over the front lens's clear semi-aperture: the radius of the beam the stop
    // admits (above 1, something else cuts the beam, so the stop's image is not what the sensor
    // shows), and the height of the paraxial ray that crosses the stop's centre, |B / A| tan
    // theta (large, and real rays pass the lens where its aberrations are large).
    double to_stop_a = 0.0;
    double stop_beam_over_front = 0.0;
    double chief_height_over_front = 0.0;
    bool exact_centre_on_sensor = false;
    // n in centre divergence ~ theta^n, from this angle and the neighbouring one on the ladder
    // (the smaller, or the larger for the smallest non-zero angle). About 3 is the third-order
    // aberration a first-order model leaves out; about 1 at small angles would mean the two
    // models disagree to first order, which is a bug in one of them.
    std::optional<double> exponent;
};

// Fills Sample::exponent for the ladder of one ghost (samples in kThetas_deg order).
void fillExponents(std::span<Sample> ladder) {
    for (size_t k = 0; k < ladder.size(); ++k) {
        if (ladder[k].theta_deg == 0.0 || !ladder[k].centre_pct) continue;
        const size_t other = k > 0 && ladder[k - 1].theta_deg > 0.0 ? k - 1 : k + 1;
        if (other >= ladder.size() || !ladder[other].centre_pct) continue;
        const double a = *ladder[k].centre_pct, b = *ladder[other].centre_pct;
        if (!(a > 0.0 && b > 0.0)) continue;
        ladder[k].exponent =
            std::log(a / b) / std::log(std::tan(degToRad(ladder[k].theta_deg)) /
                                       std::tan(degToRad(ladder[other].theta_deg)));
    }
}

struct LensReport {
    std::string file;
    std::string stem;
    std::string name;
    double half_diagonal_mm = 0.0;
    int ghosts = 0;
    std::vector<Sample> samples;  // ghost-major, angles in kThetas_deg order
};

struct Stats {
    int count = 0;
    double median = 0.0, p90 = 0.0, max = 0.0;
    GhostPath worst;
};

// Percentiles interpolate linearly between order statistics (as numpy's default does), so the
// median of an even count is the mean of the middle two.
double percentile(const std::vector<double>& sorted, double q) {
    if (sorted.size() == 1) return sorted.front();
    const double rank = q * static_cast<double>(sorted.size() - 1);
    const size_t lo = static_cast<size_t>(std::floor(rank));
    const size_t hi = std::min(lo + 1, sorted.size() - 1);
    return sorted[lo] + (rank - static_cast<double>(lo)) * (sorted[hi] - sorted[lo]);
}

template <typename Field>
Stats summarize(const std::vector<const Sample*>& samples, Field field) {
    Stats stats;
    std::vector<double> values;
    for (const Sample* s : samples) {
        const std::optional<double> v = field(*s);
        if (!v) continue;
        if (values.empty() || *v > stats.max) {
            stats.max = *v;
            stats.worst = s->path;
        }
        values.push_back(*v);
    }
    stats.count = static_cast<int>(values.size());
    if (values.empty()) return stats;
    std::sort(values.begin(), values.end());
    stats.median = percentile(values, 0.5);
    stats.p90 = percentile(values, 0.9);
    return stats;
}

std::optional<LensReport> measureLens(const std::string& file) {
    auto prescription = loadPrescription(file);
    if (!prescription) {
        std::cerr << "ghost_divergence: " << prescription.error().message << "\n";
        return std::nullopt;
    }
    auto lens = Lens::make(*prescription, CameraDescription{});
    if (!lens) {
        std::cerr << "ghost_divergence: " << lens.error().message << "\n";
        return std::nullopt;
    }
    const auto enumeration = enumerateGhosts(*lens);
    if (!enumeration) {
        std::cerr << "ghost_divergence: " << file << ": " << enumeration.error().message << "\n";
        return std::nullopt;
    }
    LensReport report;
    report.file = file;
    report.stem = std::filesystem::path(file).stem().string();
    report.name = lens->name();
    report.half_diagonal_mm = lens->sensorHalfDiagonal_mm();
    report.ghosts = static_cast<int>(enumeration->ghosts.size());
    const double stop_mm = lens->surfaces()[lens->stopIndex()].semi_aperture_mm;
    const double front_mm = lens->surfaces().front().semi_aperture_mm;
    const double half_width_mm = 0.5 * lens->camera().sensor_width_mm;
    for (const GhostPath& path : enumeration->ghosts) {
        const std::optional<ParaxialGhost> paraxial = paraxialGhost(*lens, path, kWavelength_nm);
        const Matrix2 to_stop = pathMatrices(*lens, path, kWavelength_nm).to_stop;
        const double to_stop_a = to_stop(0, 0);
        for (const double theta_deg : kThetas_deg) {
            Sample s;
            s.path = path;
            s.theta_deg = theta_deg;
            s.to_stop_a = to_stop_a;
            s.stop_beam_over_front = stop_mm / std::abs(to_stop_a) / front_mm;
            s.chief_height_over_front =
                std::abs(to_stop(0, 1) / to_stop_a) * std::tan(degToRad(theta_deg)) / front_mm;
            if (paraxial) {
                s.paraxial_centre_mm = paraxial->centre_per_tan_mm * std::tan(degToRad(theta_deg));
                s.paraxial_radius_mm = paraxial->radius_mm;
            }
            const std::optional<ExactGhost> exact =
                exactGhost(*lens, path, LightDirectionDeg{theta_deg, 0.0}, kWavelength_nm);
            if (exact) {
                s.exact_centre_mm = exact->centre_mm.x();
                s.exact_centre_on_sensor = std::abs(exact->centre_mm.x()) <= half_width_mm;
                s.rim_points = exact->rim_points;
                if (exact->rim_points > 0) s.exact_radius_mm = exact->radius_mm;
                // With phi = 0 the paraxial centre lies on the x axis; an exact centre off it
                // (there should be none) would count in full.
                if (paraxial)
                    s.centre_pct = 100.0 *
                                   std::hypot(*s.paraxial_centre_mm - exact->centre_mm.x(),
                                              exact->centre_mm.y()) /
                                   report.half_diagonal_mm;
            }
            if (s.paraxial_radius_mm && s.exact_radius_mm && *s.exact_radius_mm > 0.0)
                s.radius_pct = 100.0 * std::abs(*s.paraxial_radius_mm - *s.exact_radius_mm) /
                               *s.exact_radius_mm;
            report.samples.push_back(s);
        }
        fillExponents(std::span<Sample>(report.samples).last(std::size(kThetas_deg)));
    }
    return report;
}

std::vector<const Sample*> samplesAt(const LensReport& report, double theta_deg) {
    std::vector<const Sample*> out;
    for (const Sample& s : report.samples)
        if (s.theta_deg == theta_deg) out.push_back(&s);
    return out;
}

// Three significant digits whatever the magnitude: divergences span 1e-12 % to 100 %.
std::string number(double v) {
    char text[32];
    std::snprintf(text, sizeof text, "%.3g", v);
    return text;
}

std::string statsCells(const Stats& s) {
    if (s.count == 0) return "- | - | - | -";
    return number(s.median) + " | " + number(s.p90) + " | " + number(s.max) + " | " +
           pathLabel(s.worst);
}

Json statsJson(const Stats& s) {
    if (s.count == 0) return Json();
    return Json{{"count", s.count},
                {"median", s.median},
                {"p90", s.p90},
                {"max", s.max},
                {"worst_ghost", pathLabel(s.worst)}};
}

// Ghosts at small angles that miss the acceptance tolerance, or that cannot be compared.
struct Acceptance {
    struct Entry {
        std::string lens;
        const Sample* sample = nullptr;
    };
    std::vector<Entry> over;
    std::vector<Entry> untraced;
    int compared = 0;
};

Acceptance checkAcceptance(const std::vector<LensReport>& reports) {
    Acceptance a;
    for (const LensReport& r : reports) {
        for (const Sample& s : r.samples) {
            if (s.theta_deg > kAcceptanceTheta_deg) continue;
            if (!s.centre_pct) {
                a.untraced.push_back({r.stem, &s});
                continue;
            }
            ++a.compared;
            if (*s.centre_pct > kAcceptanceCentre_pct) a.over.push_back({r.stem, &s});
        }
    }
    return a;
}

std::string markdown(const std::vector<LensReport>& reports, const Acceptance& acceptance) {
    std::ostringstream out;
    out << "## Paraxial vs exact ghosts (" << kWavelength_nm << " nm, phi = 0)\n\n";
    out << "Centre: |paraxial - exact| in % of the sensor half-diagonal. Radius: |paraxial - "
           "exact| in % of the exact radius. Median, 90th percentile and maximum over the ghosts "
           "both models could trace; `traced` counts them among the ghosts enumerateGhosts "
           "keeps.\n\n";
    out << "| lens | theta (deg) | traced | centre median % | centre p90 % | centre max % | "
           "worst | radius median % | radius p90 % | radius max % | worst |\n";
    out << "| --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | --- |\n";
    for (const LensReport& r : reports) {
        for (const double theta_deg : kThetas_deg) {
            const std::vector<const Sample*> at = samplesAt(r, theta_deg);
            const Stats centre = summarize(at, [](const Sample& s) { return s.centre_pct; });
            const Stats radius = summarize(at, [](const Sample& s) { return s.radius_pct; });
            out << "| " << r.stem << " | " << theta_deg << " | " << centre.count << "/" << r.ghosts
                << " | " << statsCells(centre) << " | " << statsCells(radius) << " |\n";
        }
    }
    out << "\n## Acceptance: centres within " << kAcceptanceCentre_pct
        << " % of the half-diagonal for theta <= " << kAcceptanceTheta_deg << " deg\n\n";
    const bool pass = acceptance.over.empty() && acceptance.untraced.empty();
    out << (pass ? "PASS" : "FAIL") << ": " << acceptance.compared
        << " ghost-angle pairs compared, " << acceptance.over.size() << " over the tolerance, "
        << acceptance.untraced.size() << " not traced by one of the models.\n";
    if (!acceptance.over.empty()) {
        int third_order = 0, flipped = 0;
        for (const auto& e : acceptance.over) {
            const Sample& s = *e.sample;
            if (s.exponent && *s.exponent >= 2.5 && *s.exponent <= 3.5) ++third_order;
            if (*s.paraxial_centre_mm * *s.exact_centre_mm < 0.0) ++flipped;
        }
        out << "\nOver the tolerance: " << third_order
            << " grow as theta^n with n in [2.5, 3.5] (third-order aberration, which a "
               "first-order model leaves out); "
            << flipped
            << " have the exact centre on the other side of the axis from the paraxial one (the "
               "real ray through the stop's centre is far from the paraxial one); the others "
               "grow with another power.\n";
    }
    const auto rows = [&out](const std::vector<Acceptance::Entry>& list) {
        const auto optional = [](const std::optional<double>& v) {
            return v ? number(*v) : std::string("-");
        };
        for (const auto& e : list) {
            const Sample& s = *e.sample;
            out << "| " << e.lens << " | " << pathLabel(s.path) << " | " << s.theta_deg << " | "
                << (s.centre_pct ? number(*s.centre_pct) : std::string("not traced")) << " | "
                << optional(s.paraxial_centre_mm) << " | " << optional(s.exact_centre_mm) << " | "
                << optional(s.exponent) << " | " << number(s.to_stop_a) << " | "
                << number(s.chief_height_over_front) << " | " << number(s.stop_beam_over_front)
                << " | " << s.rim_points << " |\n";
        }
    };
    if (!acceptance.over.empty() || !acceptance.untraced.empty()) {
        out << "\nn: exponent of theta in the divergence. A: of the path's transfer to the stop. "
               "Chief: height of the paraxial ray through the stop's centre at the first vertex, "
               "beam: radius of the beam the stop admits there, both over the front lens's clear "
               "semi-aperture. Rim: rim rays exactGhost found by bisection (of 32; 0 when the "
               "centre ray itself is vignetted).\n\n";
        out << "| lens | ghost | theta (deg) | centre divergence % | paraxial centre mm | "
               "exact centre mm | n | A | chief | beam | rim |\n";
        out << "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n";
        rows(acceptance.over);
        rows(acceptance.untraced);
    }
    return out.str();
}

Json summaryJson(const std::vector<LensReport>& reports, const Acceptance& acceptance) {
    Json doc;
    doc["wavelength_nm"] = kWavelength_nm;
    doc["phi_deg"] = 0.0;
    doc["centre_unit"] = "percent of the sensor half-diagonal";
    doc["radius_unit"] = "percent of the exact radius";
    Json lenses = Json::array();
    for (const LensReport& r : reports) {
        Json angles = Json::array();
        for (const double theta_deg : kThetas_deg) {
            const std::vector<const Sample*> at = samplesAt(r, theta_deg);
            angles.push_back(
                {{"theta_deg", theta_deg},
                 {"ghosts", r.ghosts},
                 {"centre_pct",
                  statsJson(summarize(at, [](const Sample& s) { return s.centre_pct; }))},
                 {"radius_pct",
                  statsJson(summarize(at, [](const Sample& s) { return s.radius_pct; }))}});
        }
        lenses.push_back({{"file", r.file},
                          {"name", r.name},
                          {"sensor_half_diagonal_mm", r.half_diagonal_mm},
                          {"ghosts", r.ghosts},
                          {"angles", angles}});
    }
    doc["lenses"] = lenses;
    const auto entries = [](const std::vector<Acceptance::Entry>& list) {
        Json out = Json::array();
        for (const auto& e : list) {
            const Sample& s = *e.sample;
            out.push_back({{"lens", e.lens},
                           {"ghost", pathLabel(s.path)},
                           {"theta_deg", s.theta_deg},
                           {"centre_pct", s.centre_pct ? Json(*s.centre_pct) : Json()},
                           {"to_stop_a", s.to_stop_a},
                           {"exponent", s.exponent ? Json(*s.exponent) : Json()},
                           {"chief_height_over_front", s.chief_height_over_front},
                           {"stop_beam_over_front", s.stop_beam_over_front},
                           {"exact_centre_on_sensor", s.exact_centre_on_sensor}});
        }
        return out;
    };
    doc["acceptance"] = {{"theta_max_deg", kAcceptanceTheta_deg},
                         {"tolerance_pct", kAcceptanceCentre_pct},
                         {"pass", acceptance.over.empty() && acceptance.untraced.empty()},
                         {"compared", acceptance.compared},
                         {"over", entries(acceptance.over)},
                         {"untraced", entries(acceptance.untraced)}};
    return doc;
}

std::string csv(const std::vector<LensReport>& reports) {
    std::ostringstream out;
    out << std::setprecision(10);
    out << "lens,ghost,first,second,theta_deg,paraxial_centre_mm,exact_centre_mm,"
           "centre_divergence_pct,paraxial_radius_mm,exact_radius_mm,radius_divergence_pct,"
           "rim_points,to_stop_a,stop_beam_over_front,chief_height_over_front\n";
    const auto cell = [&out](const std::optional<double>& v) {
        out << ',';
        if (v) out << *v;
    };
    for (const LensReport& r : reports) {
        for (const Sample& s : r.samples) {
            out << r.stem << ',' << pathLabel(s.path) << ',' << s.path.first + 1 << ','
                << s.path.second + 1 << ',' << s.theta_deg;
            cell(s.paraxial_centre_mm);
            cell(s.exact_centre_mm);
            cell(s.centre_pct);
            cell(s.paraxial_radius_mm);
            cell(s.exact_radius_mm);
            cell(s.radius_pct);
            out << ',' << s.rim_points << ',' << s.to_stop_a << ',' << s.stop_beam_over_front << ','
                << s.chief_height_over_front << '\n';
        }
    }
    return out.str();
}

// Written to a temporary name and renamed, so a reader never sees half a file.
bool writeFile(const std::string& path, const std::string& text) {
    const std::string temporary = path + ".tmp";
    {
        std::ofstream out(temporary, std::ios::binary);
        out << text;
        if (!out.flush()) {
            std::cerr << "ghost_divergence: cannot write " << temporary << "\n";
            return false;
        }
    }
    std::error_code error;
    std::filesystem::rename(temporary, path, error);
    if (error) {
        std::cerr << "ghost_divergence: cannot rename " << temporary << " to " << path << ": "
                  << error.message() << "\n";
        return false;
    }
    return true;
}

std::vector<std::string> shippedLenses() {
    std::vector<std::string> files;
    const std::filesystem::path dir = std::filesystem::path(FLARELAB_SOURCE_DIR) / "data/lenses";
    std::error_code error;
    for (const auto& entry : std::filesystem::directory_iterator(dir, error))
        if (entry.path().extension() == ".csv") files.push_back(entry.path().string());
    std::sort(files.begin(), files.end());
    return files;
}

int run(int argc, char** argv) {
    std::string json_path, csv_path;
    std::vector<std::string> files;
    for (int i = 1; i < argc; ++i) {
        const std::string arg = argv[i];
        if (arg == "--json" || arg == "--csv") {
            if (i + 1 >= argc) {
                std::cerr << "ghost_divergence: " << arg << " needs a file name\n";
                return 2;
            }
            (arg == "--json" ? json_path : csv_path) = argv[++i];
        } else if (arg == "-h" || arg == "--help") {
            std::cout << "usage: ghost_divergence [--json FILE] [--csv FILE] [LENS.csv...]\n";
            return 0;
        } else if (arg.starts_with("-")) {
            std::cerr << "ghost_divergence: unknown option " << arg << "\n";
            return 2;
        } else {
            files.push_back(arg);
        }
    }
    if (files.empty()) files = shippedLenses();
    if (files.empty()) {
        std::cerr << "ghost_divergence: no lens files in " << FLARELAB_SOURCE_DIR
                  << "/data/lenses\n";
        return 1;
    }
    std::vector<LensReport> reports;
    for (const std::string& file : files) {
        auto report = measureLens(file);
        if (!report) return 1;
        reports.push_back(std::move(*report));
    }
    const Acceptance acceptance = checkAcceptance(reports);
    std::cout << markdown(reports, acceptance);
    if (!csv_path.empty() && !writeFile(csv_path, csv(reports))) return 1;
    if (!json_path.empty() &&
        !writeFile(json_path, summaryJson(reports, acceptance).dump(2) + "\n"))
        return 1;
    return 0;
}

}  // namespace
}  // namespace flarelab::bench

int main(int argc, char** argv) {
    try {
        return flarelab::bench::run(argc, argv);
    } catch (const std::exception& e) {
        std::cerr << "ghost_divergence: " << e.what() << "\n";
        return 1;
    }
}
