#include "drivers/calibration.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <sstream>

namespace flarelab::drivers {
namespace {

namespace fs = std::filesystem;

// A calibration with every field set, the curve a gamma 2 curve on 12 bits.
CameraCalibration sample(bool linear) {
    CameraCalibration c;
    c.camera_model = "Acme GigE 1234";
    c.camera_serial = "SN-0042";
    c.width_px = 8;
    c.height_px = 6;
    c.format = hdr::RawFormat::BayerRGGB;
    c.bit_depth = 12;
    c.gain = 2.0;
    c.created_utc = "2026-11-29T07:04:02Z";
    c.software_version = "flarelab calibrate";
    c.black_level_dn = 64.25;
    c.saturation_dn = 4000.0;
    c.linear = linear;
    c.linearity_error = linear ? 0.004 : 0.8;
    c.read_noise_dn = 1.5;
    c.read_noise_e = 3.0;
    c.electrons_per_dn = 2.0;
    if (!linear) {
        ResponseCurve r;
        r.method = "test curve";
        r.rms_error_stops = 0.01;
        for (double z = 100.0; z <= 4000.0; z += 100.0) {
            r.dn.push_back(z);
            const double u = (z - c.black_level_dn) / (4000.0 - c.black_level_dn);
            r.relative_exposure.push_back(u * u);
        }
        c.response_curve = r;
    }
    c.hot_pixels = {3, 17, 40};
    c.notes = {"measured on the bench", "ünïcode is fine"};
    return c;
}

std::string temporaryDirectory() {
    const fs::path dir =
        fs::temp_directory_path() / ("flarelab_calibration_test_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    return dir.string();
}

TEST(CalibrationFile, RoundTripsEveryField) {
    for (const bool linear : {true, false}) {
        const CameraCalibration c = sample(linear);
        const std::string path = temporaryDirectory() + "/camera.cal.json";
        ASSERT_TRUE(writeCalibration(path, c));
        auto read = readCalibration(path);
        ASSERT_TRUE(read) << read.error().message;
        EXPECT_EQ(*read, c);
        // No temporary file is left beside it.
        int files = 0;
        for ([[maybe_unused]] const auto& entry :
             fs::directory_iterator(fs::path(path).parent_path()))
            ++files;
        EXPECT_EQ(files, 1);
        fs::remove_all(fs::path(path).parent_path());
    }
}

TEST(CalibrationFile, HotPixelsReadInAnyOrder) {
    const CameraCalibration c = sample(true);
    auto doc = nlohmann::json::parse(*formatCalibration(c));
    doc["hot_pixels"] = {{0, 5}, {1, 2}, {3, 0}};  // (x, y): indices 40, 17, 3
    auto read = parseCalibration(doc.dump(), "cal.json");
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->hot_pixels, (std::vector<int64_t>{3, 17, 40}));
}

TEST(CalibrationFile, RefusesBadFilesNamingTheField) {
    struct Case {
        std::function<void(nlohmann::json&)> edit;
        std::string field;
        ErrorCode code = ErrorCode::ParseError;
    };
    using J = nlohmann::json;
    const std::vector<Case> cases = {
        {[](J& d) { d.erase("black_level_dn"); }, "black_level_dn: is missing"},
        {[](J& d) { d["blacklevel"] = 3; }, "blacklevel: is not a field"},
        {[](J& d) { d["format_version"] = 2; }, "format_version: 2", ErrorCode::Unsupported},
        {[](J& d) { d["format"] = "something else"; }, "format:", ErrorCode::Unsupported},
        {[](J& d) { d["noise"]["read_noise_dn"] = -1; }, "noise.read_noise_dn"},
        {[](J& d) { d["noise"]["electrons_per_dn"] = "4"; },
         "noise.electrons_per_dn: is not a number"},
        {[](J& d) { d["camera"]["bit_depth"] = 20; }, "camera.bit_depth"},
        {[](J& d) { d["camera"]["format"] = "rgb"; }, "camera.format"},
        {[](J& d) { d["camera"]["width_px"] = 0; }, "camera.width_px"},
        {[](J& d) { d["camera"]["gain"] = 0; }, "camera.gain"},
        {[](J& d) { d["saturation_dn"] = 5000; }, "saturation_dn"},
        {[](J& d) { d["black_level_dn"] = 4001; }, "black_level_dn"},
        {[](J& d) { d["linear"] = true; }, "response_curve: is present but linear is true"},
        {[](J& d) { d.erase("response_curve"); }, "response_curve: is missing"},
        {[](J& d) { d["response_curve"]["dn"][3] = 150; }, "response_curve.dn[3]"},
        {[](J& d) { d["response_curve"]["relative_exposure"][5] = 0.0; },
         "response_curve.relative_exposure[5]"},
        {[](J& d) { d["response_curve"]["relative_exposure"].erase(0); }, "response_curve: dn has"},
        {[](J& d) { d["response_curve"]["dn"][0] = 10; }, "response_curve.dn[0]"},
        {[](J& d) {
             d["hot_pixels"][1] = {8, 0};
         },
         "hot_pixels[1]"},
        {[](J& d) {
             d["hot_pixels"][2] = {3, 0};
         },
         "hot_pixels[2]: [3, 0] is listed twice"},
        {[](J& d) { d["hot_pixels"][0] = 7; }, "hot_pixels[0]: is not a pair"},
        {[](J& d) { d["notes"][0] = std::string("a\0b", 3); }, "notes[0]: holds a NUL"},
    };
    const std::string good = *formatCalibration(sample(false));
    ASSERT_TRUE(parseCalibration(good, "cal.json"));
    for (const Case& c : cases) {
        J doc = J::parse(good);
        c.edit(doc);
        auto read = parseCalibration(doc.dump(), "cal.json");
        ASSERT_FALSE(read) << c.field;
        EXPECT_EQ(read.error().code, c.code) << read.error().message;
        EXPECT_NE(read.error().message.find("cal.json: " + c.field), std::string::npos)
            << c.field << " -> " << read.error().message;
    }
    std::string bad_utf8 = good;
    bad_utf8.replace(bad_utf8.find("Acme GigE 1234"), 14, "\xff");
    for (const std::string& broken :
         {std::string(""), std::string("{"), std::string("[1, 2]"), std::string("{\"format\": 3}"),
          good.substr(0, 100), bad_utf8}) {
        auto read = parseCalibration(broken, "cal.json");
        ASSERT_FALSE(read) << broken;
        EXPECT_NE(read.error().message.find("cal.json"), std::string::npos);
    }
}

// The fuzz corpus's seeds: those named bad-* are refused, the others read.
TEST(CalibrationFile, FuzzSeedsReadAsTheirNamesSay) {
    int seeds = 0;
    for (const auto& entry :
         fs::directory_iterator(std::string(FLARELAB_SOURCE_DIR) + "/fuzz/corpus/calibration")) {
        const std::string name = entry.path().filename().string();
        auto read = readCalibration(entry.path().string());
        EXPECT_EQ(read.has_value(), name.rfind("bad-", 0) != 0)
            << name << ": " << (read ? "read" : read.error().message);
        ++seeds;
    }
    EXPECT_GE(seeds, 10);
}

TEST(CalibrationFile, AFailedWriteLeavesTheOldFile) {
    const std::string dir = temporaryDirectory();
    const std::string path = dir + "/camera.cal.json";
    ASSERT_TRUE(writeCalibration(path, sample(true)));
    CameraCalibration bad = sample(true);
    bad.saturation_dn = -1.0;
    Status written = writeCalibration(path, bad);
    ASSERT_FALSE(written);
    EXPECT_NE(written.error().message.find("saturation_dn"), std::string::npos);
    auto read = readCalibration(path);
    ASSERT_TRUE(read);
    EXPECT_EQ(*read, sample(true));
    EXPECT_FALSE(writeCalibration(dir + "/no/such/dir/camera.cal.json", sample(true)));
    EXPECT_EQ(readCalibration(dir + "/missing.json").error().code, ErrorCode::NotFound);
    fs::remove_all(dir);
}

hdr::RawFrame frameFor(const CameraCalibration& c, uint16_t value) {
    hdr::RawFrame f;
    f.width = c.width_px;
    f.height = c.height_px;
    f.format = c.format;
    f.bit_depth = c.bit_depth;
    f.gain = c.gain;
    f.exposure_s = 1.0;
    f.camera = calibrationCameraName(c);
    f.samples.assign(static_cast<size_t>(f.width * f.height), value);
    return f;
}

TEST(ApplyCalibration, RefusesFramesOfAnotherCameraOrSetting) {
    const CameraCalibration c = sample(true);
    const std::vector<std::pair<std::function<void(hdr::RawFrame&)>, std::string>> cases = {
        {[](hdr::RawFrame& f) { f.camera = "Acme GigE 1234 SN-0043"; }, "camera"},
        {[](hdr::RawFrame& f) {
             f.width = 6;
             f.height = 8;
         },
         "size is 6x8"},
        {[](hdr::RawFrame& f) { f.format = hdr::RawFormat::Mono; }, "format is mono"},
        {[](hdr::RawFrame& f) { f.bit_depth = 16; }, "bit depth is 16"},
        {[](hdr::RawFrame& f) { f.samples.pop_back(); }, "samples"},
        {[](hdr::RawFrame& f) { f.gain = std::nan(""); }, "gain"},
    };
    for (const auto& [edit, what] : cases) {
        hdr::RawFrame f = frameFor(c, 100);
        edit(f);
        auto out = applyCalibration(f, c);
        ASSERT_FALSE(out) << what;
        EXPECT_NE(out.error().message.find(what), std::string::npos) << out.error().message;
    }
}

TEST(ApplyCalibration, SetsLevelsAndScalesNoiseToTheFramesGain) {
    CameraCalibration c = sample(true);
    c.hot_pixels.clear();
    hdr::RawFrame f = frameFor(c, 500);
    f.gain = 4.0;  // twice the calibration's
    auto out = applyCalibration(f, c);
    ASSERT_TRUE(out) << out.error().message;
    EXPECT_EQ(out->samples, f.samples);
    EXPECT_EQ(out->black_level_dn, 64.25);
    EXPECT_EQ(out->white_level_dn, 4000.0);
    EXPECT_DOUBLE_EQ(out->electrons_per_dn, 1.0);  // 2 e-/DN at gain 2 is 1 at gain 4
    EXPECT_DOUBLE_EQ(out->read_noise_dn, 3.0);     // 3 e- over 1 e-/DN
    EXPECT_EQ(out->bit_depth, 12);
}

TEST(ApplyCalibration, RepairsHotPixelsFromNeighboursOfTheirColour) {
    // Mono: the median of the 8 neighbours. A hot neighbour is left out.
    CameraCalibration mono = sample(true);
    mono.format = hdr::RawFormat::Mono;
    mono.hot_pixels = {2 * 8 + 3, 2 * 8 + 4};  // (3, 2) and (4, 2), side by side
    hdr::RawFrame f = frameFor(mono, 0);
    for (int64_t i = 0; i < f.width * f.height; ++i) f.samples[static_cast<size_t>(i)] = 100 + i;
    f.samples[2 * 8 + 3] = f.samples[2 * 8 + 4] = 4095;
    auto out = applyCalibration(f, mono);
    ASSERT_TRUE(out);
    // Neighbours of (3, 2) other than (4, 2): rows 1 and 3 at x 2..4 and (2, 2).
    std::vector<int> around = {100 + 10, 100 + 11, 100 + 12, 100 + 18,
                               100 + 26, 100 + 27, 100 + 28};
    std::sort(around.begin(), around.end());
    EXPECT_EQ(out->samples[2 * 8 + 3], around[3]);
    for (size_t i = 0; i < f.samples.size(); ++i) {
        if (i != 2 * 8 + 3 && i != 2 * 8 + 4) {
            EXPECT_EQ(out->samples[i], f.samples[i]);
        }
    }

    // Bayer RGGB: a red pixel takes red neighbours only (distance 2), a green one greens.
    CameraCalibration bayer = sample(true);
    bayer.hot_pixels = {2 * 8 + 2, 3 * 8 + 2};  // (2, 2) red, (2, 3) green
    hdr::RawFrame b = frameFor(bayer, 0);
    for (int64_t y = 0; y < b.height; ++y)
        for (int64_t x = 0; x < b.width; ++x) {
            const bool red = x % 2 == 0 && y % 2 == 0, blue = x % 2 == 1 && y % 2 == 1;
            b.samples[static_cast<size_t>(y * 8 + x)] = red ? 1000 : blue ? 3000 : 2000;
        }
    b.samples[2 * 8 + 2] = b.samples[3 * 8 + 2] = 4095;
    auto repaired = applyCalibration(b, bayer);
    ASSERT_TRUE(repaired);
    EXPECT_EQ(repaired->samples[2 * 8 + 2], 1000);
    EXPECT_EQ(repaired->samples[3 * 8 + 2], 2000);
}

TEST(ApplyCalibration, LinearizesThroughTheResponseCurve) {
    CameraCalibration c = sample(false);  // X = u^2 with u the fraction of the range
    c.hot_pixels.clear();
    for (const uint16_t z : {uint16_t{0}, uint16_t{64}, uint16_t{1000}, uint16_t{2032},
                             uint16_t{3900}, uint16_t{4000}, uint16_t{4095}}) {
        hdr::RawFrame f = frameFor(c, z);
        auto out = applyCalibration(f, c);
        ASSERT_TRUE(out) << out.error().message;
        const double u = std::clamp((z - c.black_level_dn) / (4000.0 - c.black_level_dn), 0.0, 1.0);
        // Between knots 100 DN apart the file's linear interpolation of u^2 is off by at most
        // (100 / range)^2 / 4 of the top.
        EXPECT_NEAR(out->samples[0], 65535.0 * u * u, 65535.0 * 2e-4 + 1.0) << z;
        EXPECT_EQ(out->bit_depth, 16);
        EXPECT_EQ(out->black_level_dn, 0.0);
        EXPECT_EQ(out->white_level_dn, 65535.0);
    }
}

TEST(CheckMergeable, RefusesANonLinearCameraUntilItsCurveIsGiven) {
    CameraCapabilities caps;
    caps.width_px = 8;
    caps.height_px = 6;
    caps.response = CameraResponse::NonLinear;
    caps.response_note = "test pattern grows with the logarithm of the exposure";
    Status refused = checkMergeable(caps, nullptr);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().code, ErrorCode::Unsupported);
    EXPECT_NE(refused.error().message.find("flarelab calibrate"), std::string::npos);
    EXPECT_NE(refused.error().message.find("logarithm"), std::string::npos);
    const CameraCalibration linear = sample(true);
    EXPECT_FALSE(checkMergeable(caps, &linear));
    const CameraCalibration curved = sample(false);
    EXPECT_TRUE(checkMergeable(caps, &curved));

    caps.response = CameraResponse::Linear;
    EXPECT_TRUE(checkMergeable(caps, nullptr));
    EXPECT_TRUE(checkMergeable(caps, &linear));
    caps.response = CameraResponse::Unknown;
    EXPECT_TRUE(checkMergeable(caps, nullptr));
    caps.width_px = 16;
    EXPECT_FALSE(checkMergeable(caps, &linear));  // a calibration of another frame size
}

}  // namespace
}  // namespace flarelab::drivers
