#include "predict/scene.h"

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <initializer_list>
#include <limits>
#include <map>
#include <new>
#include <nlohmann/json.hpp>
#include <utility>

#include "common/utf8.h"
#include "predict/detail/json_document.h"
#include "predict/gltf_import.h"

namespace flarelab::predict {
namespace {

using nlohmann::json;

constexpr std::string_view kFormatName = "flarelab-scene";
constexpr size_t kMaxNameCharacters = 64;
constexpr int64_t kMaxSidePx = 32768;
constexpr double kMinStep_s = 0.001;
constexpr double kMaxStep_s = 86400.0;
// A scene is four levels deep (cameras[0].position_m); anything far deeper is refused while it is
// read, before a deep document costs memory or recursion in nlohmann's destructor.
constexpr size_t kMaxDepth = 16;
constexpr double kInf = std::numeric_limits<double>::infinity();

// ---------------------------------------------------------------------------------------------
// Text for messages.

using detail::controlAt;
using detail::indexed;
using detail::number;

std::string quotedText(std::string_view text) {
    return detail::quotedText(text, kMaxNameCharacters);
}

bool isContinuationByte(unsigned char c) { return (c & 0xC0) == 0x80; }

size_t characterCount(std::string_view text) {
    size_t count = 0;
    for (const char c : text) count += isContinuationByte(static_cast<unsigned char>(c)) ? 0 : 1;
    return count;
}

std::string typeOf(const json& value) { return detail::typeOf(value, false); }

std::string join(const std::string& path, std::string_view key) {
    return path.empty() ? std::string(key) : path + "." + std::string(key);
}

// ---------------------------------------------------------------------------------------------
// Reading values (the document is built by detail::JsonDocumentBuilder).

Error failAt(const std::string& scene, const std::string& path, const std::string& what) {
    return makeError(ErrorCode::ParseError,
                     scene + ": " + (path.empty() ? "" : path + ": ") + what);
}

// The range a number must lie in. Every number must be finite in any case.
struct Bound {
    double low = -kInf;
    double high = kInf;
    bool low_open = false;  // (low, high] rather than [low, high]

    bool admits(double x) const { return (low_open ? x > low : x >= low) && x <= high; }
    std::string describe() const {
        if (high == kInf) return std::string(low_open ? "> " : ">= ") + number(low);
        return "in [" + number(low) + ", " + number(high) + "]";
    }
};
constexpr Bound kFinite{};
constexpr Bound kPositive{0.0, kInf, true};
constexpr Bound kNonNegative{0.0, kInf, false};
constexpr Bound between(double low, double high) { return Bound{low, high, false}; }

Result<double> readNumber(const json& value,
                          const std::string& scene,
                          const std::string& path,
                          Bound bound) {
    if (!value.is_number()) return failAt(scene, path, "must be a number, got " + typeOf(value));
    const double x = value.get<double>();
    if (!std::isfinite(x)) return failAt(scene, path, "must be a finite number");
    if (!bound.admits(x))
        return failAt(scene, path, "must be " + bound.describe() + ", got " + number(x));
    return x;
}

// JSON has one kind of number: 1920.0 and 1.92e3 are integers too (as drivers/calibration.cpp
// reads them), where they are exact.
Result<int64_t> readInteger(const json& value,
                            const std::string& scene,
                            const std::string& path,
                            int64_t low,
                            int64_t high) {
    const std::string range = std::to_string(low) + ".." + std::to_string(high);
    if (!value.is_number()) return failAt(scene, path, "must be an integer, got " + typeOf(value));
    int64_t n = 0;
    if (value.is_number_unsigned()) {
        const uint64_t u = value.get<uint64_t>();
        if (u > static_cast<uint64_t>(std::numeric_limits<int64_t>::max()))
            return failAt(scene, path, "must be in " + range + ", got " + std::to_string(u));
        n = static_cast<int64_t>(u);
    } else if (value.is_number_integer()) {
        n = value.get<int64_t>();
    } else {
        const double x = value.get<double>();
        if (!(std::isfinite(x) && x == std::floor(x) && std::abs(x) < 9.007199254740992e15))
            return failAt(scene, path, "must be an integer, got " + number(x));
        n = static_cast<int64_t>(x);
    }
    if (n < low || n > high)
        return failAt(scene, path, "must be in " + range + ", got " + std::to_string(n));
    return n;
}

Result<std::string> readString(const json& value,
                               const std::string& scene,
                               const std::string& path) {
    if (!value.is_string()) return failAt(scene, path, "must be a string, got " + typeOf(value));
    std::string text = value.get<std::string>();
    // nlohmann checks this already; kept so the rule does not hang on a library's behaviour.
    if (!validUtf8(text)) return failAt(scene, path, "is not valid UTF-8");
    return text;
}

Result<std::array<double, 3>> readTriple(const json& value,
                                         const std::string& scene,
                                         const std::string& path,
                                         const char* shape,
                                         Bound bound) {
    if (!value.is_array())
        return failAt(
            scene, path,
            std::string("must be an array of 3 numbers ") + shape + ", got " + typeOf(value));
    if (value.size() != 3)
        return failAt(scene, path,
                      std::string("must be an array of 3 numbers ") + shape + ", got " +
                          std::to_string(value.size()) + " elements");
    std::array<double, 3> triple{};
    for (size_t k = 0; k < 3; ++k) {
        auto x = readNumber(value[k], scene, indexed(path, k), bound);
        if (!x) return x.error();
        triple[k] = *x;
    }
    return triple;
}

// One JSON object of the scene: its field path for messages, and the keys it may hold. The keys
// are checked when it is opened, so a misspelt key is named as unknown rather than reported as a
// missing field (or, for an optional one, silently replaced by its default).
class Fields {
public:
    static Result<Fields> open(const json& value,
                               const std::string& scene,
                               std::string path,
                               std::initializer_list<std::string_view> known) {
        if (!value.is_object())
            return failAt(scene, path, "must be an object, got " + typeOf(value));
        for (const auto& [key, unused] : value.items()) {
            bool found = false;
            for (const std::string_view k : known) found = found || k == key;
            if (!found) {
                std::string list;
                for (const std::string_view k : known)
                    list += (list.empty() ? "" : ", ") + std::string(k);
                return failAt(
                    scene, path,
                    "unknown field " + quotedText(key) + " (the fields here: " + list + ")");
            }
        }
        return Fields(value, scene, std::move(path));
    }

    const std::string& path() const { return path_; }
    std::string pathOf(std::string_view key) const { return join(path_, key); }
    bool has(const char* key) const { return find(key) != nullptr; }
    const json* find(const char* key) const {
        const auto it = object_->find(key);
        return it == object_->end() ? nullptr : &*it;
    }

    Error fail(const std::string& what) const { return failAt(scene_, path_, what); }
    Error fail(std::string_view key, const std::string& what) const {
        return failAt(scene_, pathOf(key), what);
    }
    Error missing(std::string_view key, const std::string& why = "") const {
        return fail(key, "missing" + (why.empty() ? "" : "; " + why));
    }

    Result<double> number(const char* key, Bound bound = kFinite) const {
        const json* value = find(key);
        if (!value) return missing(key);
        return readNumber(*value, scene_, pathOf(key), bound);
    }
    Result<std::optional<double>> optionalNumber(const char* key, Bound bound = kFinite) const {
        const json* value = find(key);
        if (!value) return std::optional<double>();
        auto x = readNumber(*value, scene_, pathOf(key), bound);
        if (!x) return x.error();
        return std::optional<double>(*x);
    }
    Result<std::optional<int64_t>> optionalInteger(const char* key,
                                                   int64_t low,
                                                   int64_t high) const {
        const json* value = find(key);
        if (!value) return std::optional<int64_t>();
        auto n = readInteger(*value, scene_, pathOf(key), low, high);
        if (!n) return n.error();
        return std::optional<int64_t>(*n);
    }
    Result<std::string> string(const char* key) const {
        const json* value = find(key);
        if (!value) return missing(key);
        return readString(*value, scene_, pathOf(key));
    }
    Result<Vec3> point(const char* key) const {
        const json* value = find(key);
        if (!value) return missing(key);
        return readTriple(*value, scene_, pathOf(key), "[x, y, z]", kFinite);
    }
    // A light's colour: factors >= 0, [1, 1, 1] when absent.
    Result<std::array<double, 3>> colour(const char* key) const {
        const json* value = find(key);
        if (!value) return std::array<double, 3>{1.0, 1.0, 1.0};
        auto rgb = readTriple(*value, scene_, pathOf(key), "[r, g, b]", kNonNegative);
        if (!rgb) return rgb.error();
        if ((*rgb)[0] == 0.0 && (*rgb)[1] == 0.0 && (*rgb)[2] == 0.0)
            return fail(key,
                        "is [0, 0, 0]: a light of no colour draws nothing, which is almost surely "
                        "a mistake (leave the light out instead)");
        return *rgb;
    }
    Result<Fields> object(const char* key, std::initializer_list<std::string_view> known) const {
        const json* value = find(key);
        if (!value) return missing(key);
        return open(*value, scene_, pathOf(key), known);
    }
    // An array of at most `most` elements; an empty one when absent and not `required`.
    Result<const json*> array(const char* key, size_t most, bool required) const {
        static const json kEmpty = json::array();
        const json* value = find(key);
        if (!value) {
            if (required) return missing(key);
            return &kEmpty;
        }
        if (!value->is_array()) return fail(key, "must be an array, got " + typeOf(*value));
        if (value->size() > most)
            return fail(key, "has " + std::to_string(value->size()) + " elements; at most " +
                                 std::to_string(most) + " are allowed");
        return value;
    }

    const std::string& scene() const { return scene_; }

private:
    Fields(const json& object, const std::string& scene, std::string path)
        : object_(&object), scene_(scene), path_(std::move(path)) {}

    const json* object_;
    const std::string& scene_;
    std::string path_;
};

// A camera's or light's name: 1..64 characters, none a control character.
Result<std::string> readName(const Fields& fields) {
    auto name = fields.string("name");
    if (!name) return name.error();
    const size_t characters = characterCount(*name);
    if (characters == 0) return fields.fail("name", "must not be empty");
    if (characters > kMaxNameCharacters)
        return fields.fail("name", quotedText(*name) + " is " + std::to_string(characters) +
                                       " characters long; a name has 1 to " +
                                       std::to_string(kMaxNameCharacters));
    for (size_t i = 0; i < name->size(); ++i)
        if (controlAt(*name, i))
            return fields.fail("name", quotedText(*name) + " holds a control character");
    return name;
}

// Names must be unique within their list, so that reports and switching plans name one thing.
// `seen` maps each name so far to the path of its owner.
Status checkUnique(const std::string& scene,
                   const std::string& path,
                   const std::string& name,
                   std::map<std::string, std::string>& seen) {
    const auto [it, inserted] = seen.emplace(name, path);
    if (!inserted)
        return failAt(scene, join(path, "name"),
                      quotedText(name) + " is also the name of " + it->second);
    return Ok{};
}

// Exactly one of the intensities; intensity_cd only where `point` (a light with a position).
Result<LightIntensity> readIntensity(const Fields& fields, bool point, const char* why_no_cd) {
    LightIntensity intensity;
    auto cd = fields.optionalNumber("intensity_cd", kPositive);
    if (!cd) return cd.error();
    auto lux = fields.optionalNumber("illuminance_lux", kPositive);
    if (!lux) return lux.error();
    auto relative = fields.optionalNumber("relative", kNonNegative);
    if (!relative) return relative.error();
    if (*cd && !point) return fields.fail("intensity_cd", why_no_cd);
    std::string given;
    int count = 0;
    for (const auto& [key, value] : {std::pair<const char*, bool>{"intensity_cd", cd->has_value()},
                                     {"illuminance_lux", lux->has_value()},
                                     {"relative", relative->has_value()}})
        if (value) {
            given += (count == 0 ? "" : " and ") + std::string(key);
            ++count;
        }
    const char* choices =
        point ? "intensity_cd, illuminance_lux or relative" : "illuminance_lux or relative";
    if (count == 0) return fields.fail(std::string("no intensity: give one of ") + choices);
    if (count > 1)
        return fields.fail(given + " are given together; give exactly one of " + choices);
    intensity.intensity_cd = *cd;
    intensity.illuminance_lux = *lux;
    intensity.relative = *relative;
    return intensity;
}

const char* photometricField(const LightIntensity& intensity) {
    if (intensity.intensity_cd) return "intensity_cd";
    if (intensity.illuminance_lux) return "illuminance_lux";
    return nullptr;
}

// ---------------------------------------------------------------------------------------------
// The parts of a scene.

// A file named by the scene (`key`): not empty, no control character, joined to `base_dir`
// unless absolute.
Result<std::string> readPath(const Fields& f, const char* key, const std::string& base_dir) {
    auto text = f.string(key);
    if (!text) return text.error();
    if (text->empty()) return f.fail(key, "must not be empty");
    for (size_t i = 0; i < text->size(); ++i)
        if (controlAt(*text, i))
            return f.fail(key, quotedText(*text) + " holds a control character");
    const std::filesystem::path path(*text);
    return path.is_absolute() || base_dir.empty()
               ? *text
               : (std::filesystem::path(base_dir) / path).string();
}

Result<SceneCamera> readExposure(const Fields& f, SceneCamera camera);

Result<SceneCamera> readCamera(const json& value,
                               const std::string& scene,
                               const std::string& path,
                               const std::string& base_dir) {
    auto opened =
        Fields::open(value, scene, path,
                     {"name", "model", "gltf_camera", "position_m", "pan_deg", "tilt_deg",
                      "roll_deg", "look_at_m", "exposure_s", "f_number", "gain", "width_px",
                      "height_px", "scene_min_dn", "scene_max_dn", "scene_log_average_dn",
                      "rig_illuminance_lux"});
    if (!opened) return opened.error();
    const Fields& f = *opened;
    SceneCamera camera;

    auto name = readName(f);
    if (!name) return name.error();
    camera.name = std::move(*name);

    auto model = readPath(f, "model", base_dir);
    if (!model) return model.error();
    camera.model_path = std::move(*model);

    // Aimed one way or the other, never by default: a camera that silently looks north at the
    // horizon gives a plausible but wrong prediction.
    if (f.has("gltf_camera")) {
        for (const char* key : {"position_m", "pan_deg", "tilt_deg", "roll_deg", "look_at_m"})
            if (f.has(key))
                return f.fail(key, "not with gltf_camera: the glTF file gives the camera's pose");
        auto node = f.string("gltf_camera");
        if (!node) return node.error();
        if (node->empty()) return f.fail("gltf_camera", "must not be empty");
        camera.gltf_camera = std::move(*node);
        return readExposure(f, std::move(camera));
    }
    auto position = f.point("position_m");
    if (!position) return position.error();
    if (f.has("look_at_m")) {
        for (const char* key : {"pan_deg", "tilt_deg", "roll_deg"})
            if (f.has(key))
                return f.fail(key, std::string("not with look_at_m: aim the camera with look_at_m "
                                               "or with pan_deg and tilt_deg") +
                                       (std::string_view(key) == "roll_deg"
                                            ? " (a camera aimed by look_at_m has no roll)"
                                            : ""));
        auto target = f.point("look_at_m");
        if (!target) return target.error();
        auto pose = poseLookingAt(*position, *target);
        if (!pose) {
            std::string what = pose.error().message;
            if (what.rfind("look-at: ", 0) == 0) what.erase(0, 9);
            return f.fail("look_at_m", what);
        }
        camera.pose = *pose;
    } else {
        for (const char* key : {"pan_deg", "tilt_deg"})
            if (!f.has(key))
                return f.missing(key, "aim the camera with pan_deg and tilt_deg, or look_at_m");
        auto pan = f.number("pan_deg");
        if (!pan) return pan.error();
        auto tilt = f.number("tilt_deg", between(-90.0, 90.0));
        if (!tilt) return tilt.error();
        auto roll = f.optionalNumber("roll_deg");
        if (!roll) return roll.error();
        camera.pose.position_m = *position;
        camera.pose.pan_deg = *pan;
        camera.pose.tilt_deg = *tilt;
        camera.pose.roll_deg = roll->value_or(0.0);
    }
    return readExposure(f, std::move(camera));
}

// The rest of a camera after its pose: exposure, size, the scene's range, the rig's light.
Result<SceneCamera> readExposure(const Fields& f, SceneCamera camera) {
    auto exposure = f.number("exposure_s", kPositive);
    if (!exposure) return exposure.error();
    camera.exposure_s = *exposure;
    auto f_number = f.optionalNumber("f_number", kPositive);
    if (!f_number) return f_number.error();
    camera.f_number = *f_number;
    auto gain = f.optionalNumber("gain", kPositive);
    if (!gain) return gain.error();
    camera.gain = gain->value_or(1.0);

    auto width = f.optionalInteger("width_px", 1, kMaxSidePx);
    if (!width) return width.error();
    auto height = f.optionalInteger("height_px", 1, kMaxSidePx);
    if (!height) return height.error();
    if (width->has_value() != height->has_value())
        return f.missing(*width ? "height_px" : "width_px",
                         "width_px and height_px come together (neither: the model's capture "
                         "size)");
    camera.width_px = *width;
    camera.height_px = *height;

    auto min_dn = f.optionalNumber("scene_min_dn", kNonNegative);
    if (!min_dn) return min_dn.error();
    auto max_dn = f.optionalNumber("scene_max_dn", kPositive);
    if (!max_dn) return max_dn.error();
    if (min_dn->has_value() != max_dn->has_value())
        return f.missing(*min_dn ? "scene_max_dn" : "scene_min_dn",
                         "scene_min_dn and scene_max_dn come together");
    if (*min_dn && **min_dn > **max_dn)
        return f.fail("scene_min_dn",
                      number(**min_dn) + " is above scene_max_dn (" + number(**max_dn) + ")");
    camera.scene_min_dn = *min_dn;
    camera.scene_max_dn = *max_dn;
    auto log_average = f.optionalNumber("scene_log_average_dn", kPositive);
    if (!log_average) return log_average.error();
    camera.scene_log_average_dn = *log_average;

    auto rig = f.optionalNumber("rig_illuminance_lux", kPositive);
    if (!rig) return rig.error();
    camera.rig_illuminance_lux = *rig;
    return camera;
}

Result<SceneLight> readLight(const json& value, const std::string& scene, const std::string& path) {
    auto opened = Fields::open(value, scene, path,
                               {"name", "position_m", "direction", "intensity_cd",
                                "illuminance_lux", "relative", "colour"});
    if (!opened) return opened.error();
    const Fields& f = *opened;
    SceneLight light;

    auto name = readName(f);
    if (!name) return name.error();
    light.name = std::move(*name);

    const bool point = f.has("position_m");
    if (point == f.has("direction"))
        return f.fail(point ? "position_m and direction are both given; give exactly one"
                            : "no place: give position_m (a point light) or direction (a light "
                              "at infinity)");
    if (point) {
        auto position = f.point("position_m");
        if (!position) return position.error();
        light.position_m = *position;
    } else {
        auto direction = f.object("direction", {"azimuth_deg", "elevation_deg"});
        if (!direction) return direction.error();
        auto azimuth = direction->number("azimuth_deg");
        if (!azimuth) return azimuth.error();
        auto elevation = direction->number("elevation_deg", between(-90.0, 90.0));
        if (!elevation) return elevation.error();
        light.direction = directionFromAzimuthElevation(*azimuth, *elevation);
    }

    auto intensity = readIntensity(f, point,
                                   "only for a light with position_m (a light at infinity has no "
                                   "distance to fall off over); give illuminance_lux or relative");
    if (!intensity) return intensity.error();
    light.intensity = *intensity;
    auto colour = f.colour("colour");
    if (!colour) return colour.error();
    light.colour = *colour;
    return light;
}

Result<UtcInstant> readInstant(const json& value,
                               const std::string& scene,
                               const std::string& path) {
    auto text = readString(value, scene, path);
    if (!text) return text.error();
    auto instant = parseIso8601(*text);
    if (!instant) return failAt(scene, path, instant.error().message);
    // The sun's position is known for these years only; a frame outside could not be drawn.
    const int year = calendarYear(*instant);
    if (year < kSunFirstYear || year > kSunLastYear)
        return failAt(scene, path,
                      "year " + std::to_string(year) + " is outside the years the sun's position " +
                          "covers (" + std::to_string(kSunFirstYear) + ".." +
                          std::to_string(kSunLastYear) + ")");
    return *instant;
}

Result<SceneSun> readSun(const Fields& root) {
    auto opened = root.object(
        "sun", {"latitude_deg", "longitude_deg", "elevation_m", "pressure_mbar", "temperature_c",
                "from", "to", "step_s", "intensity_cd", "illuminance_lux", "relative", "colour"});
    if (!opened) return opened.error();
    const Fields& f = *opened;
    SceneSun sun;

    for (const auto& [key, target] :
         {std::pair<const char*, double*>{"latitude_deg", &sun.site.latitude_deg},
          {"longitude_deg", &sun.site.longitude_deg},
          {"elevation_m", &sun.site.elevation_m}}) {
        auto x = f.number(key);
        if (!x) return x.error();
        *target = *x;
    }
    for (const auto& [key, target] :
         {std::pair<const char*, double*>{"pressure_mbar", &sun.site.pressure_mbar},
          {"temperature_c", &sun.site.temperature_c}}) {
        auto x = f.optionalNumber(key);
        if (!x) return x.error();
        if (*x) *target = **x;
    }
    if (Status site = checkSunSite(sun.site); !site) return f.fail(site.error().message);

    const json* from_value = f.find("from");
    if (!from_value) return f.missing("from");
    auto from = readInstant(*from_value, f.scene(), f.pathOf("from"));
    if (!from) return from.error();
    const json* to_value = f.find("to");
    if (!to_value) return f.missing("to");
    auto to = readInstant(*to_value, f.scene(), f.pathOf("to"));
    if (!to) return to.error();
    if (*to < *from)
        return f.fail("to", formatIso8601(*to) + " is before from (" + formatIso8601(*from) + ")");
    auto step_s = f.number("step_s", between(kMinStep_s, kMaxStep_s));
    if (!step_s) return step_s.error();
    sun.from = *from;
    sun.to = *to;
    sun.step = std::chrono::microseconds(std::llround(*step_s * 1e6));
    const int64_t steps = (*to - *from) / sun.step + 1;
    if (steps > kSceneMaxSteps)
        return f.fail("step_s", "the span from " + formatIso8601(*from) + " to " +
                                    formatIso8601(*to) + " takes " + std::to_string(steps) +
                                    " steps of " + number(*step_s) + " s; at most " +
                                    std::to_string(kSceneMaxSteps) + " are allowed");

    auto intensity = readIntensity(f, false,
                                   "the sun is at infinity (no distance to fall off over): give "
                                   "illuminance_lux or relative");
    if (!intensity) return intensity.error();
    sun.intensity = *intensity;
    auto colour = f.colour("colour");
    if (!colour) return colour.error();
    sun.colour = *colour;
    return sun;
}

Result<SceneSwitching> readSwitching(const Fields& root, const Scene& scene) {
    auto opened = root.object("switching", {"figure", "threshold", "min_dwell_s"});
    if (!opened) return opened.error();
    const Fields& f = *opened;
    if (!scene.sun)
        return f.fail(
            "needs a sun: switching plans a cut over the sun's timeline, and a scene "
            "without one does not change with time");
    SceneSwitching switching;
    auto figure = f.string("figure");
    if (!figure) return figure.error();
    if (*figure == "contrast-loss") {
        switching.figure = SwitchFigure::ContrastLoss;
    } else if (*figure == "flare-mean") {
        switching.figure = SwitchFigure::FlareMean;
    } else if (*figure == "flare-peak") {
        switching.figure = SwitchFigure::FlarePeak;
    } else if (*figure == "glare") {
        switching.figure = SwitchFigure::GlareIndicator;
    } else {
        return f.fail("figure", quotedText(*figure) +
                                    " is not a figure; use \"contrast-loss\", \"flare-mean\", "
                                    "\"flare-peak\" or \"glare\"");
    }
    const bool contrast = switching.figure == SwitchFigure::ContrastLoss;
    // A contrast loss is a fraction of the ideal contrast; the flare figures are DN.
    auto threshold = f.number("threshold", contrast ? between(0.0, 1.0) : kNonNegative);
    if (!threshold) return threshold.error();
    switching.threshold = *threshold;
    auto dwell = f.optionalNumber("min_dwell_s", kNonNegative);
    if (!dwell) return dwell.error();
    switching.min_dwell_s = dwell->value_or(0.0);
    if (contrast)
        for (size_t i = 0; i < scene.cameras.size(); ++i)
            if (!scene.cameras[i].scene_min_dn)
                return failAt(f.scene(), indexed("cameras", i),
                              "camera " + quotedText(scene.cameras[i].name) +
                                  " has no scene_min_dn and scene_max_dn, which switching by "
                                  "contrast-loss needs (the contrast ratio, eq. 9.3)");
    if (switching.figure == SwitchFigure::GlareIndicator)
        for (size_t i = 0; i < scene.cameras.size(); ++i)
            if (!scene.cameras[i].scene_log_average_dn)
                return failAt(f.scene(), indexed("cameras", i),
                              "camera " + quotedText(scene.cameras[i].name) +
                                  " has no scene_log_average_dn, which switching by glare needs "
                                  "(the glare indicator's reference)");
    return switching;
}

Result<Scene> readScene(const json& document,
                        const std::string& name,
                        const std::string& base_dir) {
    if (!document.is_object())
        return failAt(name, "", "must be a JSON object, got " + typeOf(document));
    // The format and version first: a file of another kind, or a later version with fields this
    // reader does not know, is named as such rather than by its first unknown field.
    const auto format = document.find("format");
    if (format == document.end())
        return failAt(name, "format", "missing; a scene file has \"format\": \"flarelab-scene\"");
    auto format_name = readString(*format, name, "format");
    if (!format_name) return format_name.error();
    if (*format_name != kFormatName)
        return failAt(name, "format",
                      "must be \"flarelab-scene\", got " + quotedText(*format_name));
    const auto version = document.find("version");
    if (version == document.end()) return failAt(name, "version", "missing");
    if (!version->is_number())
        return failAt(name, "version", "must be an integer, got " + typeOf(*version));
    const double version_number = version->get<double>();
    if (version_number != std::floor(version_number))
        return failAt(name, "version", "must be an integer, got " + number(version_number));
    if (version_number != kSceneFormatVersion)
        return makeError(ErrorCode::Unsupported, name + ": version: " + number(version_number) +
                                                     "; this reader knows version " +
                                                     std::to_string(kSceneFormatVersion));

    auto opened = Fields::open(document, name, "",
                               {"format", "version", "out_of_range", "gltf", "cameras", "lights",
                                "sun", "switching", "frames"});
    if (!opened) return opened.error();
    const Fields& root = *opened;
    Scene scene;

    if (root.has("out_of_range")) {
        auto policy = root.string("out_of_range");
        if (!policy) return policy.error();
        if (*policy == "refuse") {
            scene.out_of_range = RangePolicy::Refuse;
        } else if (*policy == "clamp") {
            scene.out_of_range = RangePolicy::Clamp;
        } else {
            return root.fail("out_of_range",
                             quotedText(*policy) + " is not a policy; use \"refuse\" or \"clamp\"");
        }
    }

    if (root.has("gltf")) {
        auto gltf = root.object("gltf", {"file", "lights"});
        if (!gltf) return gltf.error();
        auto file = readPath(*gltf, "file", base_dir);
        if (!file) return file.error();
        bool lights = true;
        if (const json* value = gltf->find("lights")) {
            if (!value->is_boolean())
                return gltf->fail("lights", "must be true or false, got " + typeOf(*value));
            lights = value->get<bool>();
        }
        scene.gltf = SceneGltf{std::move(*file), lights};
    }

    auto cameras = root.array("cameras", kSceneMaxCameras, true);
    if (!cameras) return cameras.error();
    if ((*cameras)->empty()) return root.fail("cameras", "is empty; a scene needs a camera");
    std::map<std::string, std::string> camera_names;
    for (size_t i = 0; i < (*cameras)->size(); ++i) {
        const std::string path = indexed("cameras", i);
        auto camera = readCamera((**cameras)[i], name, path, base_dir);
        if (!camera) return camera.error();
        if (Status unique = checkUnique(name, path, camera->name, camera_names); !unique)
            return unique.error();
        if (!camera->gltf_camera.empty() && !scene.gltf)
            return failAt(name, join(path, "gltf_camera"),
                          "needs the scene's \"gltf\" file to take the camera from");
        scene.cameras.push_back(std::move(*camera));
    }

    auto lights = root.array("lights", kSceneMaxLights, false);
    if (!lights) return lights.error();
    std::map<std::string, std::string> light_names;
    for (size_t i = 0; i < (*lights)->size(); ++i) {
        const std::string path = indexed("lights", i);
        auto light = readLight((**lights)[i], name, path);
        if (!light) return light.error();
        if (Status unique = checkUnique(name, path, light->name, light_names); !unique)
            return unique.error();
        scene.lights.push_back(std::move(*light));
    }

    if (root.has("sun")) {
        auto sun = readSun(root);
        if (!sun) return sun.error();
        scene.sun = std::move(*sun);
    }
    if (scene.lights.empty() && !scene.sun && !(scene.gltf && scene.gltf->lights))
        return root.fail("lights", "the scene has no light and no sun, so nothing can flare");

    // Found now rather than when the first frame is drawn: lightRatio would refuse the pair.
    const auto photometric = [&](const LightIntensity& intensity,
                                 const std::string& what) -> Status {
        const char* field = photometricField(intensity);
        if (!field) return Ok{};
        for (size_t i = 0; i < scene.cameras.size(); ++i)
            if (!scene.cameras[i].rig_illuminance_lux)
                return failAt(name, join(indexed("cameras", i), "rig_illuminance_lux"),
                              "missing; " + what + " gives " + field +
                                  ", and a photometric intensity is compared with the rig "
                                  "light's illuminance at the lens");
        return Ok{};
    };
    for (size_t i = 0; i < scene.lights.size(); ++i)
        if (Status ok =
                photometric(scene.lights[i].intensity,
                            indexed("lights", i) + " (" + quotedText(scene.lights[i].name) + ")");
            !ok)
            return ok.error();
    if (scene.sun)
        if (Status ok = photometric(scene.sun->intensity, "the sun"); !ok) return ok.error();

    if (root.has("switching")) {
        auto switching = readSwitching(root, scene);
        if (!switching) return switching.error();
        scene.switching = *switching;
    }

    if (root.has("frames")) {
        auto frames = root.array("frames", kSceneMaxFrames, true);
        if (!frames) return frames.error();
        if (!scene.sun)
            return root.fail("frames",
                             "needs a sun: without one the scene does not change with time, and "
                             "one frame per camera is drawn");
        for (size_t i = 0; i < (*frames)->size(); ++i) {
            const std::string path = indexed("frames", i);
            auto instant = readInstant((**frames)[i], name, path);
            if (!instant) return instant.error();
            if (*instant < scene.sun->from || *instant > scene.sun->to)
                return failAt(name, path,
                              formatIso8601(*instant) + " is outside the sun's span, " +
                                  formatIso8601(scene.sun->from) + " to " +
                                  formatIso8601(scene.sun->to));
            scene.frames.push_back(*instant);
        }
    }
    return scene;
}

}  // namespace

Result<Scene> parseScene(std::string_view json_text,
                         const std::string& name,
                         const std::string& base_dir) {
    try {
        detail::JsonDocumentBuilder builder(kMaxDepth, "; a scene is at most 4");
        json::sax_parse(json_text.data(), json_text.data() + json_text.size(), &builder);
        if (!builder.error.empty()) return failAt(name, builder.error_path, builder.error);
        return readScene(builder.document, name, base_dir);
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::ParseError, name + ": too large to parse");
    } catch (const std::exception& e) {
        // The readers check every type before they convert: this is a bug, not bad input.
        return makeError(ErrorCode::Internal, name + ": " + e.what());
    }
}

namespace {

// The scene's glTF file read into it (loadScene's contract).
Status applyGltf(Scene& scene, const std::string& name) {
    const std::string& file = scene.gltf->path;
    auto venue = importGltf(file);
    if (!venue) return venue.error().withContext(name + ": gltf.file");
    for (const std::string& note : venue->notes) scene.notes.push_back(file + ": " + note);
    for (size_t i = 0; i < scene.cameras.size(); ++i) {
        SceneCamera& camera = scene.cameras[i];
        if (camera.gltf_camera.empty()) continue;
        const GltfCamera* found = nullptr;
        int matches = 0;
        std::string known;
        for (const GltfCamera& c : venue->cameras) {
            known += (known.empty() ? "" : ", ") + quotedText(c.name);
            if (c.name == camera.gltf_camera) {
                found = &c;
                ++matches;
            }
        }
        const std::string field = join(indexed("cameras", i), "gltf_camera");
        if (matches == 0)
            return failAt(name, field,
                          "no camera " + quotedText(camera.gltf_camera) + " in " + file +
                              (known.empty() ? " (it has no camera)" : " (it has " + known + ")"));
        if (matches > 1)
            return failAt(name, field,
                          std::to_string(matches) + " cameras of " + file + " are named " +
                              quotedText(camera.gltf_camera) + "; name them apart");
        camera.pose = found->pose;
    }
    if (!scene.gltf->lights) return Ok{};
    if (scene.lights.size() + venue->lights.size() > kSceneMaxLights)
        return failAt(name, "gltf.file",
                      file + " has " + std::to_string(venue->lights.size()) +
                          " lights; with the scene's that is more than " +
                          std::to_string(kSceneMaxLights));
    for (const GltfLight& l : venue->lights) {
        SceneLight light;
        light.name = l.name;
        bool taken = true;
        for (int n = 1; taken; ++n) {
            taken = false;
            for (const SceneLight& other : scene.lights) taken = taken || other.name == light.name;
            if (taken)
                light.name = l.name + " (glTF" + (n > 1 ? " " + std::to_string(n) : "") + ")";
        }
        light.colour = l.colour;
        if (l.direction) {
            light.direction = l.direction;
            light.intensity.illuminance_lux = l.intensity;
        } else {
            light.position_m = l.position_m;
            light.intensity.intensity_cd = l.intensity;
        }
        if (l.range_m)
            scene.notes.push_back(file + ": light " + quotedText(l.name) +
                                  ": its range is not modelled (the inverse-square law holds "
                                  "at any distance)");
        scene.lights.push_back(std::move(light));
    }
    if (!venue->lights.empty())
        for (size_t i = 0; i < scene.cameras.size(); ++i)
            if (!scene.cameras[i].rig_illuminance_lux)
                return failAt(name, join(indexed("cameras", i), "rig_illuminance_lux"),
                              "missing; the lights of " + file +
                                  " are photometric (candela, lux), compared with the rig "
                                  "light's illuminance at the lens");
    if (scene.lights.empty() && !scene.sun)
        return failAt(
            name, "lights",
            "the scene has no light and no sun, and " + file + " adds none, so nothing can flare");
    return Ok{};
}

}  // namespace

Result<Scene> loadScene(const std::string& path) {
    auto text = detail::readSmallFile(path, kSceneMaxFileBytes, "a scene file");
    if (!text) return text.error();
    std::string base_dir = std::filesystem::path(path).parent_path().string();
    if (base_dir.empty()) base_dir = ".";
    auto scene = parseScene(*text, path, base_dir);
    if (!scene || !scene->gltf) return scene;
    if (Status applied = applyGltf(*scene, path); !applied) return applied.error();
    return scene;
}

Result<double> lightRatio(const LightIntensity& intensity,
                          const SceneCamera& camera,
                          double distance_m,
                          const std::string& what) {
    const auto invalid = [&](const std::string& message) -> Error {
        return makeError(ErrorCode::InvalidArgument, what + ": " + message);
    };
    const int given = int{intensity.intensity_cd.has_value()} +
                      int{intensity.illuminance_lux.has_value()} +
                      int{intensity.relative.has_value()};
    if (given != 1)
        return invalid("a light has exactly one intensity; this one has " + std::to_string(given));
    if (intensity.relative) {
        const double relative = *intensity.relative;
        if (!(std::isfinite(relative) && relative >= 0.0))
            return invalid("relative must be >= 0, got " + number(relative));
        return relative;
    }
    if (!camera.rig_illuminance_lux)
        return invalid("a photometric intensity needs the camera's rig_illuminance_lux (camera " +
                       quotedText(camera.name) + " has none)");
    const double rig_lux = *camera.rig_illuminance_lux;
    if (!(std::isfinite(rig_lux) && rig_lux > 0.0))
        return invalid("the camera's rig_illuminance_lux must be > 0, got " + number(rig_lux));
    double lux = 0.0;
    if (intensity.illuminance_lux) {
        lux = *intensity.illuminance_lux;
        if (!(std::isfinite(lux) && lux > 0.0))
            return invalid("illuminance_lux must be > 0, got " + number(lux));
    } else {
        const double cd = *intensity.intensity_cd;
        if (!(std::isfinite(cd) && cd > 0.0))
            return invalid("intensity_cd must be > 0, got " + number(cd));
        if (!(std::isfinite(distance_m) && distance_m >= 1e-3))
            return invalid("the light is " + number(distance_m) +
                           " m from the camera; a point light must be at least 1 mm away");
        // The inverse-square law: illuminance at the lens, facing the light.
        lux = cd / (distance_m * distance_m);
    }
    const double ratio = lux / rig_lux;
    if (!std::isfinite(ratio))
        return invalid("the light ratio " + number(lux) + " lux / " + number(rig_lux) +
                       " lux is not finite");
    return ratio;
}

}  // namespace flarelab::predict
