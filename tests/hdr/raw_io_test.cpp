#include "hdr/raw_io.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "tests/test_files.h"

namespace flarelab::hdr {
namespace {

using flarelab::testing::readText;

RawFrame sample() {
    RawFrame f;
    f.width = 5;
    f.height = 3;
    f.format = RawFormat::BayerGRBG;
    f.bit_depth = 12;
    for (int i = 0; i < 15; ++i) f.samples.push_back(static_cast<uint16_t>(i * 273));
    f.exposure_s = 0.25;
    f.gain = 1.7;
    f.black_level_dn = 256;
    f.white_level_dn = 4000;
    f.read_noise_dn = 2.25;
    f.electrons_per_dn = 0.8125;
    f.angle_deg = -1.4;
    f.timestamp_ns = 1234567890123;
    f.timestamp_marks = TimestampMark::ExposureEnd;
    f.host_timestamp_ns = 1764625473123456789;
    f.sequence = 42;
    f.camera = "sim camera, serial 0";
    return f;
}

std::string tempPath(const std::string& name) {
    const auto dir = std::filesystem::temp_directory_path() / "flarelab_raw_io_test";
    std::filesystem::create_directories(dir);
    return (dir / name).string();
}

Result<RawFrame> parse(const std::string& text) {
    return readRawFromMemory(std::span(reinterpret_cast<const uint8_t*>(text.data()), text.size()),
                             "t.pgm");
}

TEST(RawIo, RoundTripsEveryFieldExactly) {
    const std::string path = tempPath("round.pgm");
    const RawFrame f = sample();
    ASSERT_TRUE(writeRaw(path, f));
    const auto back = readRaw(path);
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(*back, f);
    // A plain PGM: magic, then a 16-bit MAXVAL of 4095 for 12 bits.
    const std::string text = readText(path);
    EXPECT_EQ(text.substr(0, 3), "P5\n");
    EXPECT_NE(text.find("\n5 3\n4095\n"), std::string::npos);
}

TEST(RawIo, RefusesBrokenHeadersNamingTheKey) {
    const std::string good = [] {
        const std::string path = tempPath("good.pgm");
        EXPECT_TRUE(writeRaw(path, sample()));
        return readText(path);
    }();
    ASSERT_TRUE(parse(good));
    const auto replaced = [&](const std::string& from, const std::string& to) {
        std::string t = good;
        const size_t at = t.find(from);
        EXPECT_NE(at, std::string::npos) << from;
        return t.replace(at, from.size(), to);
    };
    const auto message = [&](const std::string& text) {
        const auto r = parse(text);
        EXPECT_FALSE(r);
        return r ? std::string() : r.error().message;
    };
    EXPECT_NE(message(replaced("# gain 1.7\n", "")).find("\"gain\" is missing"), std::string::npos);
    EXPECT_NE(message(replaced("# gain 1.7\n", "# gain 1.7\n# gain 2\n")).find("twice"),
              std::string::npos);
    EXPECT_NE(message(replaced("# gain 1.7\n", "# gain nan\n")).find("gain"), std::string::npos);
    EXPECT_NE(message(replaced("# gain 1.7\n", "# gain -1\n")).find("gain"), std::string::npos);
    EXPECT_NE(message(replaced("# gain 1.7\n", "# colour red\n")).find("unknown header key"),
              std::string::npos);
    EXPECT_NE(message(replaced("flarelab-raw 2", "flarelab-raw 3")).find("not a flarelab raw"),
              std::string::npos);
    EXPECT_NE(message(replaced("# timestamp_marks exposure-end", "# timestamp_marks sometime"))
                  .find("timestamp_marks"),
              std::string::npos);
    EXPECT_NE(message(replaced("# host_timestamp_ns 1764625473123456789\n", ""))
                  .find("\"host_timestamp_ns\" is missing"),
              std::string::npos);
    EXPECT_NE(message(replaced("\n4095\n", "\n65535\n")).find("MAXVAL"), std::string::npos);
    EXPECT_NE(message(replaced("\n5 3\n", "\n5 4\n")).find("bytes of samples"), std::string::npos);
    EXPECT_NE(message(replaced("\n5 3\n", "\n0 3\n")).find("limits"), std::string::npos);
    EXPECT_NE(message(replaced("# format bayer-grbg", "# format bayer-xyzw")).find("format"),
              std::string::npos);
    EXPECT_NE(message(replaced("# black_level_dn 256", "# black_level_dn 4001")).find("black"),
              std::string::npos);
    EXPECT_NE(message(good.substr(0, good.size() - 1)).find("bytes of samples"), std::string::npos);
    std::string high = good;
    high[high.size() - 2] = static_cast<char>(0xff);  // last sample 0xff.. > 4095
    EXPECT_NE(message(high).find("above MAXVAL"), std::string::npos);
    EXPECT_FALSE(parse(""));
    EXPECT_EQ(readRaw(tempPath("missing.pgm")).error().code, ErrorCode::NotFound);
}

TEST(RawIo, ReadsVersion1FilesWithoutTheTimestampKeys) {
    const std::string path = tempPath("v2.pgm");
    ASSERT_TRUE(writeRaw(path, sample()));
    std::string text = readText(path);
    for (const std::string line :
         {"# timestamp_marks exposure-end\n", "# host_timestamp_ns 1764625473123456789\n"})
        text.erase(text.find(line), line.size());
    text.replace(text.find("flarelab-raw 2"), 14, "flarelab-raw 1");
    const auto v1 = parse(text);
    ASSERT_TRUE(v1) << v1.error().message;
    RawFrame expected = sample();
    expected.timestamp_marks = TimestampMark::Unknown;
    expected.host_timestamp_ns = 0;
    EXPECT_EQ(*v1, expected);
    // Version 1 knows no such keys.
    text.insert(text.find("# camera"), "# host_timestamp_ns 5\n");
    EXPECT_NE(parse(text).error().message.find("unknown header key"), std::string::npos);
}

TEST(RawIo, RefusesToWriteFramesThatBreakTheRulesAndKeepsTheOldFile) {
    const std::string path = tempPath("keep.pgm");
    ASSERT_TRUE(writeRaw(path, sample()));
    RawFrame bad = sample();
    bad.samples[3] = 5000;  // above 2^12 - 1
    EXPECT_FALSE(writeRaw(path, bad));
    bad = sample();
    bad.camera = "two\nlines";
    EXPECT_FALSE(writeRaw(path, bad));
    bad = sample();
    bad.exposure_s = 0.0;
    EXPECT_FALSE(writeRaw(path, bad));
    bad = sample();
    bad.samples.pop_back();
    EXPECT_FALSE(writeRaw(path, bad));
    EXPECT_EQ(*readRaw(path), sample());
    EXPECT_FALSE(writeRaw("/nonexistent-dir/x.pgm", sample()));
}

}  // namespace
}  // namespace flarelab::hdr
