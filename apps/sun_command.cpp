#include "apps/sun_command.h"

#include <cstdio>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <ostream>
#include <string>

#include "predict/sun.h"
#include "predict/utc_time.h"

namespace flarelab::apps {
namespace {

struct SunState {
    predict::SunSite site;
    std::string time;
    std::optional<double> delta_t_s;
    bool json = false;
};

// The flag that sets the field a library error names (its message begins with the field).
std::string flagOf(const std::string& message) {
    static const struct {
        const char* field;
        const char* flag;
    } kFields[] = {
        {"latitude", "--lat"},      {"longitude", "--lon"},           {"elevation", "--elevation"},
        {"pressure", "--pressure"}, {"temperature", "--temperature"}, {"delta T", "--delta-t"},
        {"time", "--time"}};
    for (const auto& f : kFields)
        if (message.rfind(f.field, 0) == 0) return f.flag;
    return "";
}

std::string fixed(double value, int decimals) {
    char buffer[64];
    std::snprintf(buffer, sizeof buffer, "%.*f", decimals, value);
    return buffer;
}

int run(const SunState& s, std::ostream& out, std::ostream& err) {
    const auto usage = [&err](const Error& e) {
        const std::string flag = flagOf(e.message);
        err << "flarelab: sun: " << (flag.empty() ? "" : flag + ": ") << e.message << "\n";
        return 2;
    };
    auto instant = predict::parseIso8601(s.time);
    if (!instant) return usage(instant.error());
    predict::SunTimeScale scale;
    scale.delta_t_s = s.delta_t_s;
    auto sun = predict::sunPosition(s.site, *instant, scale);
    if (!sun) {
        if (sun.error().code == ErrorCode::InvalidArgument) return usage(sun.error());
        err << "flarelab: sun: " << sun.error().message << "\n";
        return 1;
    }
    const std::string utc = predict::formatIso8601(*instant);
    if (s.json) {
        nlohmann::json j;
        j["time_utc"] = utc;
        j["latitude_deg"] = s.site.latitude_deg;
        j["longitude_deg"] = s.site.longitude_deg;
        j["elevation_m"] = s.site.elevation_m;
        j["pressure_mbar"] = s.site.pressure_mbar;
        j["temperature_c"] = s.site.temperature_c;
        j["delta_t_s"] = sun->delta_t_s;
        j["delta_t_estimated"] = !s.delta_t_s.has_value();
        j["zenith_deg"] = sun->zenith_deg;
        j["azimuth_deg"] = sun->azimuth_deg;
        j["elevation_deg"] = sun->elevation_deg;
        j["refraction_deg"] = sun->refraction_deg;
        j["hour_angle_deg"] = sun->hour_angle_deg;
        j["declination_deg"] = sun->declination_deg;
        j["right_ascension_deg"] = sun->right_ascension_deg;
        j["distance_au"] = sun->distance_au;
        out << j.dump(2) << "\n";
        return 0;
    }
    out << "sun at " << utc << ", latitude " << fixed(s.site.latitude_deg, 6) << " deg, longitude "
        << fixed(s.site.longitude_deg, 6) << " deg, " << fixed(s.site.elevation_m, 2)
        << " m (NREL SPA, delta T " << fixed(sun->delta_t_s, 1) << " s"
        << (s.delta_t_s ? "" : ", estimated") << ")\n"
        << "  zenith       " << fixed(sun->zenith_deg, 5) << " deg\n"
        << "  azimuth      " << fixed(sun->azimuth_deg, 5) << " deg (eastward from north)\n"
        << "  elevation    " << fixed(sun->elevation_deg, 5) << " deg ("
        << (sun->elevation_deg < 0.0 ? "below the horizon, " : "") << "refraction "
        << fixed(sun->refraction_deg, 5) << " deg)\n"
        << "  hour angle   " << fixed(sun->hour_angle_deg, 5) << " deg\n"
        << "  declination  " << fixed(sun->declination_deg, 5) << " deg\n";
    return 0;
}

}  // namespace

void addSunCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto s = std::make_shared<SunState>();
    CLI::App* cmd = app.add_subcommand(
        "sun", "the sun's topocentric zenith and azimuth at a site and a UTC instant (NREL SPA)");
    cmd->add_option("--lat", s->site.latitude_deg, "latitude, deg, north positive [-90, 90]")
        ->required();
    cmd->add_option("--lon", s->site.longitude_deg, "longitude, deg, east positive [-180, 180]")
        ->required();
    cmd->add_option("--elevation", s->site.elevation_m, "elevation above sea level, m")->required();
    cmd->add_option("--time", s->time, "ISO 8601 with offset: 2003-10-17T12:30:30-07:00 or ...Z")
        ->required();
    cmd->add_option("--pressure", s->site.pressure_mbar,
                    "mean air pressure for the refraction, mbar (0: none)")
        ->capture_default_str();
    cmd->add_option("--temperature", s->site.temperature_c,
                    "mean air temperature for the refraction, C")
        ->capture_default_str();
    cmd->add_option("--delta-t", s->delta_t_s,
                    "TT - UT1, s (default: estimated from the year, Espenak & Meeus)");
    cmd->add_flag("--json", s->json, "as a JSON object (zenith_deg, azimuth_deg, ...)");
    cmd->callback([s, &out, &err, &exit_code] { exit_code = run(*s, out, err); });
}

}  // namespace flarelab::apps
