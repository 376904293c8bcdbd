#include "predict/gltf_import.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <numbers>
#include <random>
#include <string>
#include <vector>

namespace flarelab::predict {
namespace {

using nlohmann::json;

constexpr double kPi = std::numbers::pi;

// A glTF 2.0 document with `nodes`, the scene listing `roots`, and whatever else `extra` adds.
json document(const json& nodes, const json& roots, const json& extra = json::object()) {
    json doc = {{"asset", {{"version", "2.0"}}},
                {"scene", 0},
                {"scenes", json::array({{{"nodes", roots}}})},
                {"nodes", nodes}};
    doc.update(extra);
    return doc;
}

json perspectiveCamera(double yfov = 0.8) {
    return {{"type", "perspective"}, {"perspective", {{"yfov", yfov}, {"znear", 0.1}}}};
}

json withLights(const json& lights) {
    return {{"extensions", {{"KHR_lights_punctual", {{"lights", lights}}}}}};
}

json lightRef(int index) { return {{"KHR_lights_punctual", {{"light", index}}}}; }

Result<GltfImport> importJson(const json& doc) {
    return importGltfFromMemory(doc.dump(), "test.gltf", false);
}

Result<GltfImport> importText(const std::string& text) {
    return importGltfFromMemory(text, "test.gltf", false);
}

void appendU32(std::string& out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out += static_cast<char>((v >> (8 * i)) & 0xFF);
}

// A GLB by hand (glTF 2.0, section 4.4): header, JSON chunk padded with spaces, optional BIN
// chunk padded with zeros.
std::string glb(std::string json_text, std::string bin = {}) {
    while (json_text.size() % 4 != 0) json_text += ' ';
    while (bin.size() % 4 != 0) bin += '\0';
    std::string out = "glTF";
    appendU32(out, 2);
    const size_t length = 12 + 8 + json_text.size() + (bin.empty() ? 0 : 8 + bin.size());
    appendU32(out, static_cast<uint32_t>(length));
    appendU32(out, static_cast<uint32_t>(json_text.size()));
    appendU32(out, 0x4E4F534A);
    out += json_text;
    if (!bin.empty()) {
        appendU32(out, static_cast<uint32_t>(bin.size()));
        appendU32(out, 0x004E4942);
        out += bin;
    }
    return out;
}

bool contains(const std::vector<std::string>& notes, const std::string& part) {
    for (const std::string& note : notes)
        if (note.find(part) != std::string::npos) return true;
    return false;
}

void expectVec(const Vec3& actual, const Vec3& expected, double tolerance) {
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(actual[k], expected[k], tolerance) << "component " << k;
}

// v rotated by the unit quaternion q = (x, y, z, w): v + 2w (q x v) + 2 q x (q x v).
Vec3 rotate(const std::array<double, 4>& q, const Vec3& v) {
    const Vec3 u = {q[0], q[1], q[2]};
    const auto cross = [](const Vec3& a, const Vec3& b) {
        return Vec3{a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                    a[0] * b[1] - a[1] * b[0]};
    };
    const Vec3 t = cross(u, v);
    const Vec3 tt = cross(u, t);
    return {v[0] + 2 * q[3] * t[0] + 2 * tt[0], v[1] + 2 * q[3] * t[1] + 2 * tt[1],
            v[2] + 2 * q[3] * t[2] + 2 * tt[2]};
}

std::array<double, 4> multiply(const std::array<double, 4>& a, const std::array<double, 4>& b) {
    return {a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
            a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
            a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
            a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2]};
}

std::array<double, 4> axisAngle(const Vec3& axis, double angle) {
    const double s = std::sin(angle / 2);
    return {axis[0] * s, axis[1] * s, axis[2] * s, std::cos(angle / 2)};
}

// glTF (x, y, z) in the world: east x, north -z, up y.
Vec3 world(const Vec3& v) { return {v[0], -v[2], v[1]}; }

json quaternionJson(const std::array<double, 4>& q) { return {q[0], q[1], q[2], q[3]}; }

// The column-major matrix of rotation q and translation t, as a node's "matrix".
json matrixJson(const std::array<double, 4>& q, const Vec3& t) {
    const Vec3 x = rotate(q, {1, 0, 0}), y = rotate(q, {0, 1, 0}), z = rotate(q, {0, 0, 1});
    return {x[0], x[1], x[2], 0, y[0], y[1], y[2], 0, z[0], z[1], z[2], 0, t[0], t[1], t[2], 1};
}

// ---------------------------------------------------------------------------------------------

TEST(GltfImport, CameraWithoutRotationLooksNorth) {
    auto imported =
        importJson(document({{{"camera", 0}}}, {0}, {{"cameras", {perspectiveCamera()}}}));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->cameras.size(), 1u);
    const GltfCamera& camera = imported->cameras[0];
    EXPECT_EQ(camera.name, "node 0");
    EXPECT_EQ(camera.type, "perspective");
    EXPECT_DOUBLE_EQ(camera.pose.pan_deg, 0.0);
    EXPECT_DOUBLE_EQ(camera.pose.tilt_deg, 0.0);
    EXPECT_DOUBLE_EQ(camera.pose.roll_deg, 0.0);
    ASSERT_TRUE(camera.yfov_deg);
    EXPECT_NEAR(*camera.yfov_deg, 0.8 * 180 / kPi, 1e-12);
    EXPECT_TRUE(contains(imported->notes, "no lights"));
}

TEST(GltfImport, CameraAtTranslatedRotatedNode) {
    // +90 degrees about glTF's +Y (up) turns -Z (north) to -X (west); a further tilt of 20
    // degrees up about the camera's own +X.
    const auto yaw = axisAngle({0, 1, 0}, kPi / 2);
    const auto pitch = axisAngle({1, 0, 0}, 20 * kPi / 180);
    const json nodes = {{{"name", "gantry cam"},
                         {"camera", 0},
                         {"translation", {1, 2, 3}},
                         {"rotation", quaternionJson(multiply(yaw, pitch))}}};
    json camera = perspectiveCamera(0.5);
    camera["name"] = "camera data";
    auto imported = importJson(document(nodes, {0}, {{"cameras", {camera}}}));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->cameras.size(), 1u);
    const CameraPose& pose = imported->cameras[0].pose;
    EXPECT_EQ(imported->cameras[0].name, "gantry cam");
    expectVec(pose.position_m, {1, -3, 2}, 1e-12);
    EXPECT_NEAR(pose.pan_deg, 270.0, 1e-9);
    EXPECT_NEAR(pose.tilt_deg, 20.0, 1e-9);
    EXPECT_NEAR(pose.roll_deg, 0.0, 1e-9);
}

TEST(GltfImport, CameraRollIsClockwiseSeenFromBehind) {
    // Turning the camera by -30 degrees about its own +Z (its back) is clockwise as seen from
    // behind it: flarelab's roll +30.
    const json nodes = {
        {{"camera", 0}, {"rotation", quaternionJson(axisAngle({0, 0, 1}, -kPi / 6))}}};
    auto imported = importJson(document(nodes, {0}, {{"cameras", {perspectiveCamera()}}}));
    ASSERT_TRUE(imported) << imported.error().message;
    EXPECT_NEAR(imported->cameras[0].pose.roll_deg, 30.0, 1e-9);
    EXPECT_NEAR(imported->cameras[0].pose.pan_deg, 0.0, 1e-9);
}

TEST(GltfImport, OrthographicCameraHasNoFieldOfView) {
    const json camera = {
        {"type", "orthographic"},
        {"orthographic", {{"xmag", 1}, {"ymag", 1}, {"znear", 0.1}, {"zfar", 100}}}};
    auto imported = importJson(document({{{"camera", 0}}}, {0}, {{"cameras", {camera}}}));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->cameras.size(), 1u);
    EXPECT_EQ(imported->cameras[0].type, "orthographic");
    EXPECT_FALSE(imported->cameras[0].yfov_deg);
}

TEST(GltfImport, ComposesNestedTransformsWithScale) {
    // Parent: at x 10, turned +90 degrees about +Y, scaled 2. Child at local (1, 0, 0): the
    // parent's rotation takes +X to -Z, its scale makes that 2 m: glTF (10, 0, -2), 2 m north.
    // Grandchild by matrix: 0.5 m up in the child's frame (scaled 2: 1 m up).
    const json nodes = {{{"name", "truss"},
                         {"translation", {10, 0, 0}},
                         {"rotation", quaternionJson(axisAngle({0, 1, 0}, kPi / 2))},
                         {"scale", {2, 2, 2}},
                         {"children", {1}}},
                        {{"name", "lamp"},
                         {"translation", {1, 0, 0}},
                         {"extensions", lightRef(0)},
                         {"children", {2}}},
                        {{"name", "lamp 2"},
                         {"matrix", {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0.5, 0, 1}},
                         {"extensions", lightRef(0)}}};
    auto imported = importJson(document(
        nodes, {0}, withLights({{{"type", "point"}, {"intensity", 1000}, {"name", "par"}}})));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->lights.size(), 2u);
    EXPECT_EQ(imported->lights[0].name, "lamp");
    ASSERT_TRUE(imported->lights[0].position_m);
    expectVec(*imported->lights[0].position_m, {10, 2, 0}, 1e-12);
    EXPECT_EQ(imported->lights[1].name, "lamp 2");
    ASSERT_TRUE(imported->lights[1].position_m);
    expectVec(*imported->lights[1].position_m, {10, 2, 1}, 1e-12);
    EXPECT_TRUE(contains(imported->notes, "no cameras"));
}

TEST(GltfImport, ReadsPointSpotAndDirectionalLights) {
    const json lights = {
        {{"type", "point"}, {"color", {1, 0.5, 0.25}}, {"intensity", 20000}, {"range", 80}},
        {{"type", "spot"},
         {"name", "follow"},
         {"intensity", 5e5},
         {"spot", {{"innerConeAngle", 0.1}, {"outerConeAngle", 0.3}}}},
        {{"type", "directional"}, {"color", {0.9, 0.9, 1}}, {"intensity", 0.2}}};
    // A directional light turned -90 degrees about +X shines along glTF -Y (down): the light is
    // straight up. One turned +90 degrees about +Y shines along -X (west): the light is east.
    const auto down = axisAngle({1, 0, 0}, -kPi / 2);
    const auto west = axisAngle({0, 1, 0}, kPi / 2);
    const json nodes = {
        {{"translation", {0, 8, 0}}, {"extensions", lightRef(0)}},
        {{"translation", {5, 6, -7}}, {"extensions", lightRef(1)}},
        {{"rotation", quaternionJson(down)}, {"extensions", lightRef(2)}},
        {{"name", "moon"}, {"rotation", quaternionJson(west)}, {"extensions", lightRef(2)}}};
    auto imported = importJson(document(nodes, {0, 1, 2, 3}, withLights(lights)));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->lights.size(), 4u);

    const GltfLight& point = imported->lights[0];
    EXPECT_EQ(point.type, "point");
    ASSERT_TRUE(point.position_m);
    expectVec(*point.position_m, {0, 0, 8}, 0.0);
    EXPECT_FALSE(point.direction);
    EXPECT_EQ(point.colour, (std::array<double, 3>{1, 0.5, 0.25}));
    EXPECT_EQ(point.intensity, 20000);
    ASSERT_TRUE(point.range_m);
    EXPECT_EQ(*point.range_m, 80);

    const GltfLight& spot = imported->lights[1];
    EXPECT_EQ(spot.type, "spot");
    EXPECT_EQ(spot.name, "follow");
    ASSERT_TRUE(spot.position_m);
    expectVec(*spot.position_m, {5, 7, 6}, 0.0);
    EXPECT_EQ(spot.colour, (std::array<double, 3>{1, 1, 1}));
    EXPECT_FALSE(spot.range_m);
    EXPECT_TRUE(contains(imported->notes, "imported as a point light"));

    const GltfLight& sun = imported->lights[2];
    EXPECT_EQ(sun.type, "directional");
    EXPECT_FALSE(sun.position_m);
    ASSERT_TRUE(sun.direction);
    expectVec(*sun.direction, {0, 0, 1}, 1e-15);
    EXPECT_EQ(sun.intensity, 0.2);

    const GltfLight& moon = imported->lights[3];
    EXPECT_EQ(moon.name, "moon");
    ASSERT_TRUE(moon.direction);
    expectVec(*moon.direction, {1, 0, 0}, 1e-15);
    expectVec(*moon.direction, directionFromAzimuthElevation(90, 0), 1e-15);
}

TEST(GltfImport, LightUsedByTwoNodesIsImportedTwice) {
    const json nodes = {{{"translation", {1, 0, 0}}, {"extensions", lightRef(0)}},
                        {{"translation", {2, 0, 0}}, {"extensions", lightRef(0)}}};
    auto imported =
        importJson(document(nodes, {0, 1}, withLights({{{"type", "point"}, {"name", "flood"}}})));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->lights.size(), 2u);
    EXPECT_EQ(imported->lights[0].name, "flood");
    EXPECT_EQ(imported->lights[0].intensity, 1.0);  // KHR_lights_punctual's default
    expectVec(*imported->lights[1].position_m, {2, 0, 0}, 0.0);
}

TEST(GltfImport, FileWithoutLightsOrCamerasIsNotAnError) {
    auto imported = importJson(document({{{"name", "floor"}}}, {0}));
    ASSERT_TRUE(imported) << imported.error().message;
    EXPECT_TRUE(imported->cameras.empty());
    EXPECT_TRUE(imported->lights.empty());
    EXPECT_TRUE(contains(imported->notes, "no cameras"));
    EXPECT_TRUE(contains(imported->notes, "no lights"));

    auto bare = importText(R"({"asset": {"version": "2.0"}})");
    ASSERT_TRUE(bare) << bare.error().message;
    EXPECT_TRUE(bare->cameras.empty());
    EXPECT_EQ(bare->notes.size(), 2u);
}

TEST(GltfImport, UnsupportedLightTypeGoesToNotes) {
    const json nodes = {{{"extensions", lightRef(0)}}, {{"extensions", lightRef(1)}}};
    auto imported = importJson(document(
        nodes, {0, 1}, withLights({{{"type", "area"}, {"name", "softbox"}}, {{"type", "point"}}})));
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->lights.size(), 1u);
    EXPECT_TRUE(contains(imported->notes, "type \"area\""));
    EXPECT_TRUE(contains(imported->notes, "\"softbox\""));
}

TEST(GltfImport, DarkLightsGoToNotes) {
    const json nodes = {{{"extensions", lightRef(0)}}, {{"extensions", lightRef(1)}}};
    auto imported = importJson(document(nodes, {0, 1},
                                        withLights({{{"type", "point"}, {"intensity", 0}},
                                                    {{"type", "point"}, {"color", {0, 0, 0}}}})));
    ASSERT_TRUE(imported) << imported.error().message;
    EXPECT_TRUE(imported->lights.empty());
    EXPECT_TRUE(contains(imported->notes, "intensity 0"));
    EXPECT_TRUE(contains(imported->notes, "colour black"));
}

TEST(GltfImport, UnusedCamerasAndLightsAreNoted) {
    auto imported = importJson(
        document(json::array({json::object()}), {0},
                 {{"cameras", {perspectiveCamera()}},
                  {"extensions", {{"KHR_lights_punctual", {{"lights", {{{"type", "point"}}}}}}}}}));
    ASSERT_TRUE(imported) << imported.error().message;
    EXPECT_TRUE(contains(imported->notes, "cameras[0] is on no node"));
    EXPECT_TRUE(contains(imported->notes, "lights[0] is on no node"));
}

TEST(GltfImport, RefusesLightIndexOutOfRange) {
    const json nodes = {{{"name", "a"}}, {{"extensions", lightRef(3)}}};
    auto imported = importJson(document(nodes, {0, 1}, withLights({{{"type", "point"}}})));
    ASSERT_FALSE(imported);
    EXPECT_EQ(imported.error().code, ErrorCode::ParseError);
    EXPECT_EQ(imported.error().message,
              "test.gltf: nodes[1].extensions.KHR_lights_punctual.light: light index 3 out of "
              "range (1 light)");

    auto no_lights = importJson(document({{{"extensions", lightRef(0)}}}, {0}));
    ASSERT_FALSE(no_lights);
    EXPECT_NE(no_lights.error().message.find("light index 0 out of range (0 lights)"),
              std::string::npos);
}

TEST(GltfImport, RefusesIndicesOfTheWrongType) {
    // tinygltf alone would drop each of these silently.
    for (const json& camera : {json("0"), json(0.0), json(-1), json(4294967296)}) {
        auto imported =
            importJson(document({{{"camera", camera}}}, {0}, {{"cameras", {perspectiveCamera()}}}));
        ASSERT_FALSE(imported) << camera.dump();
        EXPECT_NE(imported.error().message.find("nodes[0].camera"), std::string::npos)
            << imported.error().message;
    }
    auto light =
        importJson(document({{{"extensions", {{"KHR_lights_punctual", {{"light", "0"}}}}}}}, {0},
                            withLights({{{"type", "point"}}})));
    ASSERT_FALSE(light);
    auto translation = importJson(document({{{"translation", {1, 2}}}}, {0}));
    ASSERT_FALSE(translation);
    EXPECT_NE(
        translation.error().message.find("nodes[0].translation: must be an array of 3 numbers"),
        std::string::npos);
    auto colour = importJson(document({{{"extensions", lightRef(0)}}}, {0},
                                      withLights({{{"type", "point"}, {"color", {1, -1, 1}}}})));
    ASSERT_FALSE(colour);
    EXPECT_NE(colour.error().message.find("lights[0].color[1]: must be >= 0"), std::string::npos);
    auto range = importJson(document({{{"extensions", lightRef(0)}}}, {0},
                                     withLights({{{"type", "point"}, {"range", 0}}})));
    ASSERT_FALSE(range);
    auto intensity = importJson(document({{{"extensions", lightRef(0)}}}, {0},
                                         withLights({{{"type", "point"}, {"intensity", -1}}})));
    ASSERT_FALSE(intensity);
}

TEST(GltfImport, RefusesNodeCycles) {
    auto cycle = importJson(document({{{"children", {1}}}, {{"children", {0}}}}, json::array()));
    ASSERT_FALSE(cycle);
    EXPECT_NE(cycle.error().message.find("cycle"), std::string::npos) << cycle.error().message;

    auto self = importJson(document({{{"children", {0}}}}, {0}));
    ASSERT_FALSE(self);
    EXPECT_NE(self.error().message.find("nodes[0].children[0]: the node is its own child"),
              std::string::npos);

    auto two_parents =
        importJson(document({{{"children", {2}}}, {{"children", {2}}}, json::object()}, {0, 1}));
    ASSERT_FALSE(two_parents);
    EXPECT_NE(two_parents.error().message.find("already a child of node 0"), std::string::npos);

    auto child_in_scene = importJson(document({{{"children", {1}}}, json::object()}, {0, 1}));
    ASSERT_FALSE(child_in_scene);
    EXPECT_NE(child_in_scene.error().message.find("scenes[0].nodes[1]"), std::string::npos);

    auto child_range = importJson(document({{{"children", {5}}}}, {0}));
    ASSERT_FALSE(child_range);
    EXPECT_NE(child_range.error().message.find("node index 5 out of range (1 node)"),
              std::string::npos);
}

TEST(GltfImport, RefusesNodesNestedTooDeep) {
    const auto chain = [](int length) {
        json nodes = json::array();
        for (int i = 0; i < length; ++i) {
            json node = {{"translation", {0, 0.5, 0}}};
            if (i + 1 < length)
                node["children"] = {i + 1};
            else
                node["extensions"] = lightRef(0);
            nodes.push_back(node);
        }
        return document(nodes, {0}, withLights({{{"type", "point"}}}));
    };
    auto deepest = importJson(chain(kGltfMaxNodeDepth));
    ASSERT_TRUE(deepest) << deepest.error().message;
    ASSERT_EQ(deepest->lights.size(), 1u);
    EXPECT_NEAR((*deepest->lights[0].position_m)[2], 0.5 * kGltfMaxNodeDepth, 1e-12);

    auto too_deep = importJson(chain(kGltfMaxNodeDepth + 1));
    ASSERT_FALSE(too_deep);
    EXPECT_NE(too_deep.error().message.find("nested more than 64 levels"), std::string::npos)
        << too_deep.error().message;
}

TEST(GltfImport, RefusesBrokenTransforms) {
    auto both = importJson(document({{{"matrix", {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1}},
                                      {"translation", {1, 2, 3}}}},
                                    {0}));
    ASSERT_FALSE(both);
    EXPECT_NE(both.error().message.find("both a matrix and"), std::string::npos);

    auto projective = importJson(
        document({{{"matrix", {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.5, 0, 0, 0, 1}}}}, {0}));
    ASSERT_FALSE(projective);
    EXPECT_NE(projective.error().message.find("nodes[0].matrix: its last row"), std::string::npos);

    auto zero = importJson(document({{{"rotation", {0, 0, 0, 0}}}}, {0}));
    ASSERT_FALSE(zero);
    EXPECT_NE(zero.error().message.find("nodes[0].rotation"), std::string::npos);

    // Finite numbers whose product is not.
    auto overflow = importJson(document(
        {{{"scale", {1e300, 1e300, 1e300}}, {"children", {1}}}, {{"translation", {1e300, 0, 0}}}},
        {0}));
    ASSERT_FALSE(overflow);
    EXPECT_NE(overflow.error().message.find("nodes[1]: its world transform overflows"),
              std::string::npos);
}

TEST(GltfImport, NotesOddCameraTransforms) {
    const json cameras = {perspectiveCamera()};
    auto uneven =
        importJson(document({{{"camera", 0}, {"scale", {1, 2, 1}}}}, {0}, {{"cameras", cameras}}));
    ASSERT_TRUE(uneven) << uneven.error().message;
    ASSERT_EQ(uneven->cameras.size(), 1u);
    EXPECT_TRUE(contains(uneven->notes, "scales unevenly"));
    EXPECT_NEAR(uneven->cameras[0].pose.pan_deg, 0.0, 1e-12);

    auto uniform =
        importJson(document({{{"camera", 0}, {"scale", {3, 3, 3}}}}, {0}, {{"cameras", cameras}}));
    ASSERT_TRUE(uniform);
    EXPECT_FALSE(contains(uniform->notes, "scales unevenly"));

    auto flat =
        importJson(document({{{"camera", 0}, {"scale", {1, 1, 0}}}}, {0}, {{"cameras", cameras}}));
    ASSERT_TRUE(flat) << flat.error().message;
    EXPECT_TRUE(flat->cameras.empty());
    EXPECT_TRUE(contains(flat->notes, "skipped"));

    auto long_quaternion = importJson(
        document({{{"camera", 0}, {"rotation", {0, 0, 0, 2}}}}, {0}, {{"cameras", cameras}}));
    ASSERT_TRUE(long_quaternion);
    EXPECT_TRUE(contains(long_quaternion->notes, "normalised"));
}

TEST(GltfImport, RefusesFieldOfViewOutOfRange) {
    for (const double yfov : {0.0, -0.1, kPi, 4.0}) {
        auto imported =
            importJson(document({{{"camera", 0}}}, {0}, {{"cameras", {perspectiveCamera(yfov)}}}));
        ASSERT_FALSE(imported) << yfov;
        EXPECT_NE(imported.error().message.find("cameras[0].perspective.yfov"), std::string::npos);
    }
}

TEST(GltfImport, RefusesGarbage) {
    const std::vector<std::string> inputs = {
        "",
        "{",
        "[]",
        "null",
        "not json at all",
        std::string("\0\xff\xfe{", 4),
        R"({"asset": {"version": "2.0"}, "nodes": [1, 2]})",
        R"({"asset": {"version": "2.0"}, "asset": {"version": "2.0"}})",
        R"({"nodes": []})",
        std::string(200, '[') + std::string(200, ']'),
        R"({"asset": {"version": "2.0"}, "scene": 0})",
        R"({"asset": {"version": "2.0"}, "nodes": [{"translation": [1e999, 0, 0]}]})",
        R"({"asset": {"version": "2.0"}, "cameras": [{"type": "fisheye"}]})",
        R"({"asset": {"version": "2.0"}, "extensions": {"KHR_lights_punctual": {"lights": 5}}})"};
    for (const std::string& text : inputs) {
        auto imported = importText(text);
        ASSERT_FALSE(imported) << text;
        EXPECT_EQ(imported.error().code, ErrorCode::ParseError) << imported.error().message;
        EXPECT_EQ(imported.error().message.rfind("test.gltf: ", 0), 0u) << imported.error().message;
    }
    auto old = importText(R"({"asset": {"version": "1.0"}})");
    ASSERT_FALSE(old);
    EXPECT_EQ(old.error().code, ErrorCode::Unsupported);

    std::mt19937_64 rng(11);
    for (int i = 0; i < 200; ++i) {
        std::string bytes(static_cast<size_t>(rng() % 64), '\0');
        for (char& c : bytes) c = static_cast<char>(rng());
        for (const bool binary : {false, true}) {
            auto imported = importGltfFromMemory(bytes, "noise", binary);
            ASSERT_FALSE(imported);
            EXPECT_FALSE(imported.error().message.empty());
        }
    }
}

TEST(GltfImport, ReadsGlb) {
    const auto tilt = axisAngle({1, 0, 0}, -kPi / 4);
    const json doc = document(
        {{{"name", "cam"},
          {"camera", 0},
          {"rotation", quaternionJson(tilt)},
          {"translation", {0, 10, 0}}},
         {{"extensions", lightRef(0)}, {"translation", {3, 4, 5}}}},
        {0, 1},
        {{"cameras", {perspectiveCamera()}},
         {"extensions",
          {{"KHR_lights_punctual", {{"lights", {{{"type", "point"}, {"intensity", 7}}}}}}}},
         {"buffers", {{{"byteLength", 4}}}}});
    auto binary =
        importGltfFromMemory(glb(doc.dump(), std::string("\1\2\3\4", 4)), "test.glb", true);
    ASSERT_TRUE(binary) << binary.error().message;
    ASSERT_EQ(binary->cameras.size(), 1u);
    ASSERT_EQ(binary->lights.size(), 1u);
    EXPECT_NEAR(binary->cameras[0].pose.tilt_deg, -45.0, 1e-9);
    expectVec(binary->cameras[0].pose.position_m, {0, 0, 10}, 0.0);
    expectVec(*binary->lights[0].position_m, {3, -5, 4}, 0.0);
    EXPECT_EQ(binary->lights[0].intensity, 7.0);

    // Without a binary chunk, a buffer without a URI has nothing to read.
    auto no_chunk = importGltfFromMemory(glb(doc.dump()), "test.glb", true);
    ASSERT_FALSE(no_chunk);

    json plain = doc;
    plain.erase("buffers");
    auto from_text = importJson(plain);
    auto from_glb = importGltfFromMemory(glb(plain.dump()), "test.glb", true);
    ASSERT_TRUE(from_text) << from_text.error().message;
    ASSERT_TRUE(from_glb) << from_glb.error().message;
    EXPECT_EQ(from_text->cameras[0].pose.pan_deg, from_glb->cameras[0].pose.pan_deg);
    EXPECT_EQ(from_text->cameras[0].pose.tilt_deg, from_glb->cameras[0].pose.tilt_deg);
    EXPECT_EQ(from_text->notes, from_glb->notes);
}

TEST(GltfImport, RefusesBrokenGlb) {
    const std::string good = glb(R"({"asset": {"version": "2.0"}})", "abcd");
    ASSERT_TRUE(importGltfFromMemory(good, "test.glb", true));
    // The binary chunk's length claims its own 8-byte header and more: tinygltf 2.7 alone
    // would read past the end.
    std::string overlong = good;
    overlong[good.size() - 12] = 8;
    EXPECT_FALSE(importGltfFromMemory(overlong, "test.glb", true));
    std::string wrong_length = good;
    wrong_length[8] = static_cast<char>(good.size() + 4);
    EXPECT_FALSE(importGltfFromMemory(wrong_length, "test.glb", true));
    std::string version1 = good;
    version1[4] = 1;
    auto v1 = importGltfFromMemory(version1, "test.glb", true);
    ASSERT_FALSE(v1);
    EXPECT_EQ(v1.error().code, ErrorCode::Unsupported);
    EXPECT_FALSE(importGltfFromMemory(good.substr(0, 19), "test.glb", true));
    EXPECT_FALSE(importGltfFromMemory(good, "test.gltf", false));  // a GLB read as JSON
}

TEST(GltfImport, RefusesBufferUrisOutsideTheFolder) {
    for (const std::string uri : {"../venue.bin", "a/../../b.bin", "%2e%2e/x.bin", "/etc/passwd",
                                  "http://example.com/x.bin", "file:///etc/passwd", "C:/x.bin",
                                  "data:text/plain,abcd", "a\\b.bin"}) {
        const json doc = {{"asset", {{"version", "2.0"}}},
                          {"buffers", {{{"uri", uri}, {"byteLength", 4}}}}};
        auto imported = importJson(doc);
        ASSERT_FALSE(imported) << uri;
        EXPECT_NE(imported.error().message.find("buffers[0].uri"), std::string::npos)
            << imported.error().message;
    }
    // From memory no file at all is read.
    auto relative = importJson({{"asset", {{"version", "2.0"}}},
                                {"buffers", {{{"uri", "venue.bin"}, {"byteLength", 4}}}}});
    ASSERT_FALSE(relative);
    EXPECT_NE(relative.error().message.find("import from memory"), std::string::npos);
    // A base64 data: URI is read.
    auto data = importJson(
        {{"asset", {{"version", "2.0"}}},
         {"buffers",
          {{{"uri", "data:application/octet-stream;base64,AQIDBA=="}, {"byteLength", 4}}}}});
    EXPECT_TRUE(data) << data.error().message;
}

class GltfFiles : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = std::filesystem::path(::testing::TempDir()) /
               ("gltf_import_test_" + std::to_string(::getpid()));
        std::filesystem::remove_all(dir_);
        std::filesystem::create_directories(dir_ / "venue");
    }
    void TearDown() override { std::filesystem::remove_all(dir_); }

    void write(const std::filesystem::path& path, const std::string& bytes) {
        std::ofstream out(path, std::ios::binary);
        out << bytes;
    }

    std::filesystem::path dir_;
};

TEST_F(GltfFiles, ReadsBuffersBesideTheFileButNoImages) {
    const json doc =
        document({{{"extensions", lightRef(0)}, {"translation", {0, 3, 0}}}}, {0},
                 {{"extensions", {{"KHR_lights_punctual", {{"lights", {{{"type", "point"}}}}}}}},
                  {"buffers", {{{"uri", "mesh%20data.bin"}, {"byteLength", 8}}}},
                  {"images", {{{"uri", "../textures/brick.png"}}, {{"uri", "wall.png"}}}}});
    write(dir_ / "venue" / "scene.gltf", doc.dump());
    write(dir_ / "venue" / "mesh data.bin", "12345678");
    write(dir_ / "venue" / "wall.png", "not a png");
    auto imported = importGltf((dir_ / "venue" / "scene.gltf").string());
    ASSERT_TRUE(imported) << imported.error().message;
    ASSERT_EQ(imported->lights.size(), 1u);
    expectVec(*imported->lights[0].position_m, {0, 0, 3}, 0.0);

    std::filesystem::remove(dir_ / "venue" / "mesh data.bin");
    auto missing = importGltf((dir_ / "venue" / "scene.gltf").string());
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_NE(missing.error().message.find("\"mesh data.bin\""), std::string::npos)
        << missing.error().message;

    // A buffer of another size than it says is refused by tinygltf.
    write(dir_ / "venue" / "mesh data.bin", "1234");
    EXPECT_FALSE(importGltf((dir_ / "venue" / "scene.gltf").string()));
}

TEST_F(GltfFiles, ReadsGlbFilesByTheirMagic) {
    const json doc = document({{{"camera", 0}}}, {0}, {{"cameras", {perspectiveCamera()}}});
    write(dir_ / "venue" / "scene.glb", glb(doc.dump()));
    auto imported = importGltf((dir_ / "venue" / "scene.glb").string());
    ASSERT_TRUE(imported) << imported.error().message;
    EXPECT_EQ(imported->cameras.size(), 1u);
}

TEST_F(GltfFiles, RefusesLargeAndMissingFiles) {
    const auto big = dir_ / "venue" / "big.gltf";
    write(big, "{}");
    std::filesystem::resize_file(big, static_cast<uintmax_t>(kGltfMaxBytes) + 1);  // sparse
    auto large = importGltf(big.string());
    ASSERT_FALSE(large);
    EXPECT_EQ(large.error().code, ErrorCode::ParseError);
    EXPECT_NE(large.error().message.find("bytes, more than"), std::string::npos);

    auto missing = importGltf((dir_ / "venue" / "none.gltf").string());
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
}

TEST(GltfImport, ChoosesTheDefaultSceneElseSceneZeroElseRootNodes) {
    const json nodes = {{{"name", "a"}, {"extensions", lightRef(0)}},
                        {{"name", "b"}, {"extensions", lightRef(0)}},
                        {{"name", "c"}, {"extensions", lightRef(0)}, {"children", {3}}},
                        {{"name", "d"}, {"extensions", lightRef(0)}}};
    json doc = document(nodes, {0}, withLights({{{"type", "point"}}}));
    doc["scenes"] = {{{"nodes", {0}}}, {{"nodes", {1, 2}}}};
    doc["scene"] = 1;
    auto chosen = importJson(doc);
    ASSERT_TRUE(chosen) << chosen.error().message;
    ASSERT_EQ(chosen->lights.size(), 3u);
    EXPECT_EQ(chosen->lights[0].name, "b");
    EXPECT_EQ(chosen->lights[2].name, "d");

    doc.erase("scene");
    auto first = importJson(doc);
    ASSERT_TRUE(first);
    ASSERT_EQ(first->lights.size(), 1u);
    EXPECT_EQ(first->lights[0].name, "a");
    EXPECT_TRUE(contains(first->notes, "no default scene"));

    doc.erase("scenes");
    auto roots = importJson(doc);
    ASSERT_TRUE(roots);
    ASSERT_EQ(roots->lights.size(), 4u);  // a, b, c and c's child d
    EXPECT_EQ(roots->lights[3].name, "d");
}

// A camera at random orientations, as TRS and as a matrix, under a random parent: cameraFrame
// of the imported pose has the node's -Z as forward and +Y as up.
TEST(GltfImport, CameraPosesRoundTripThroughCameraFrame) {
    std::mt19937_64 rng(7);
    std::normal_distribution<double> normal;
    std::uniform_real_distribution<double> angle(-kPi, kPi);
    const auto randomRotation = [&] {
        std::array<double, 4> q;
        double norm = 0.0;
        do {
            for (double& c : q) c = normal(rng);
            norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        } while (norm < 1e-3);
        for (double& c : q) c /= norm;
        return q;
    };
    std::vector<std::array<double, 4>> rotations;
    for (int i = 0; i < 2000; ++i) rotations.push_back(randomRotation());
    // Straight up and straight down (about glTF's +X by +-90 degrees), turned about the vertical
    // by any angle and rolled about the axis.
    for (const double pitch : {kPi / 2, -kPi / 2}) {
        for (int i = 0; i < 50; ++i) {
            const auto yaw = axisAngle({0, 1, 0}, i == 0 ? 0.0 : angle(rng));
            const auto roll = axisAngle({0, 0, 1}, i < 2 ? 0.0 : angle(rng));
            rotations.push_back(multiply(multiply(yaw, axisAngle({1, 0, 0}, pitch)), roll));
        }
    }
    // Level, and exactly east, south, west.
    for (int k = 0; k < 4; ++k) rotations.push_back(axisAngle({0, 1, 0}, k * kPi / 2));

    for (size_t i = 0; i < rotations.size(); ++i) {
        const auto& q = rotations[i];
        const bool nested = i % 3 == 1;
        const auto parent = nested ? randomRotation() : std::array<double, 4>{0, 0, 0, 1};
        const Vec3 translation = {normal(rng), normal(rng), normal(rng)};
        json child = {{"camera", 0}};
        if (i % 2 == 0) {
            child["rotation"] = quaternionJson(q);
            child["translation"] = translation;
        } else {
            child["matrix"] = matrixJson(q, translation);
        }
        const json nodes = {{{"rotation", quaternionJson(parent)}, {"children", {1}}}, child};
        auto imported = importJson(document(nodes, {0}, {{"cameras", {perspectiveCamera()}}}));
        ASSERT_TRUE(imported) << imported.error().message;
        ASSERT_EQ(imported->cameras.size(), 1u);
        const CameraPose& pose = imported->cameras[0].pose;
        const auto total = multiply(parent, q);
        const Vec3 forward = world(rotate(total, {0, 0, -1}));
        const Vec3 up = world(rotate(total, {0, 1, 0}));
        const CameraFrame frame = cameraFrame(pose);
        SCOPED_TRACE("rotation " + std::to_string(i));
        expectVec(frame.forward, forward, 1e-9);
        expectVec(frame.up, up, 1e-9);
        expectVec(pose.position_m, world(rotate(parent, translation)), 1e-12);
        EXPECT_GE(pose.pan_deg, 0.0);
        EXPECT_LT(pose.pan_deg, 360.0);
        EXPECT_GE(pose.tilt_deg, -90.0);
        EXPECT_LE(pose.tilt_deg, 90.0);
        EXPECT_GT(pose.roll_deg, -180.0);
        EXPECT_LE(pose.roll_deg, 180.0);
        if (std::abs(forward[2]) == 1.0) {
            EXPECT_EQ(pose.roll_deg, 0.0);
        }
    }
}

}  // namespace
}  // namespace flarelab::predict
