#include "hdr/sweep.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <bit>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "tests/test_files.h"

namespace flarelab::hdr {
namespace {

using flarelab::testing::contains;
using flarelab::testing::readText;
using flarelab::testing::TempDir;
using flarelab::testing::writeText;

namespace fs = std::filesystem;

constexpr int64_t kWidth = 8;
constexpr int64_t kHeight = 6;

SweepHeader smallHeader() {
    SweepHeader header;
    header.software_version = "flarelab sweep_test";
    header.lens.description = "test lens 50mm f/2";
    header.lens.serial = "L-1";
    header.lens.focal_length_mm = 50.0;
    header.lens.f_number = 2.0;
    header.camera.description = "test camera";
    header.camera.bit_depth = 12;
    header.camera.pixel_pitch_um = 3.45;
    header.capture.from_deg = -0.4;
    header.capture.to_deg = 0.6;
    header.capture.step_deg = 0.2;
    header.capture.roll_deg = 10.0;
    header.capture.exposure_times_s = {0.001, 0.01, 0.1};
    header.capture.gain = 2.0;
    header.capture.width_px = kWidth;
    header.capture.height_px = kHeight;
    return header;
}

// Seeded pixels in [0, 100).
ImageRGB testImage(uint64_t seed, int64_t width = kWidth, int64_t height = kHeight) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<float> value(0.0f, 100.0f);
    ImageRGB image(width, height);
    for (float& v : image.pixels) v = value(rng);
    return image;
}

SweepFrame frameAt(const SweepHeader& header, int index) {
    SweepFrame frame;
    frame.angle_deg = header.capture.from_deg + index * header.capture.step_deg;
    frame.exposure_times_s = header.capture.exposure_times_s;
    frame.merge_method = "debevec-malik";
    return frame;
}

// Writes `count` frames with seeds 0, 1, ...; the writer stays open for more.
SweepWriter writeSweep(const std::string& directory, int count, SweepWriteOptions options = {}) {
    const SweepHeader header = smallHeader();
    auto writer = SweepWriter::create(directory, header, options);
    EXPECT_TRUE(writer) << writer.error().message;
    for (int i = 0; i < count; ++i) {
        auto frame = writer->addFrame(testImage(i), frameAt(header, i));
        EXPECT_TRUE(frame) << frame.error().message;
    }
    return std::move(*writer);
}

// A valid manifest with frames a.exr at 0.1 deg and b.exr at 0.3 deg, for editing by hand.
std::string validManifest() {
    Sweep sweep;
    sweep.header = smallHeader();
    sweep.header.created_utc = "2026-11-29T07:00:00Z";
    SweepFrame a = frameAt(sweep.header, 0), b = frameAt(sweep.header, 1);
    a.angle_deg = 0.1;
    a.exr_file = "a.exr";
    a.raw_files = {"raw/a0.raw", "raw/a1.raw", "raw/a2.raw"};
    b.angle_deg = 0.3;
    b.exr_file = "b.exr";
    sweep.frames = {a, b};
    auto json = formatSweepManifest(sweep);
    EXPECT_TRUE(json) << json.error().message;
    return *json;
}

std::string replaced(std::string text, const std::string& from, const std::string& to) {
    const size_t at = text.find(from);
    EXPECT_NE(at, std::string::npos) << from;
    if (at != std::string::npos) text.replace(at, from.size(), to);
    return text;
}

// ---------------------------------------------------------------------------------------------

TEST(SweepWriter, RoundTripsASmallSweepWithRawBrackets) {
    TempDir dir;
    const SweepHeader header = smallHeader();
    auto writer = SweepWriter::create(dir.path(), header);
    ASSERT_TRUE(writer) << writer.error().message;
    fs::create_directories(dir.file("raw"));
    std::vector<ImageRGB> images;
    for (int i = 0; i < 4; ++i) {
        SweepFrame frame = frameAt(header, i);
        for (int b = 0; b < 3; ++b) {
            const std::string raw = "raw/f" + std::to_string(i) + "_b" + std::to_string(b) + ".raw";
            writeText(dir.file(raw), "raw bytes");
            frame.raw_files.push_back(raw);
            frame.brackets.push_back({frame.exposure_times_s[b], 40u + b, 8u - b});
        }
        images.push_back(testImage(i));
        auto added = writer->addFrame(images.back(), frame);
        ASSERT_TRUE(added) << added.error().message;
        EXPECT_EQ(added->exr_file, sweepFrameFileName(i, frame.angle_deg));
        // The manifest lists exactly the frames written so far.
        auto listed = readSweepManifest(dir.path());
        ASSERT_TRUE(listed) << listed.error().message;
        EXPECT_EQ(listed->frames.size(), static_cast<size_t>(i + 1));
    }

    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_TRUE(sweep->warnings.empty()) << sweep->warnings.front();
    EXPECT_EQ(sweep->header, writer->sweep().header);
    EXPECT_EQ(sweep->frames, writer->sweep().frames);
    EXPECT_EQ(sweep->header.lens, header.lens);
    EXPECT_EQ(sweep->header.capture, header.capture);
    EXPECT_FALSE(sweep->header.created_utc.empty());
    for (size_t i = 0; i < images.size(); ++i) {
        auto frame = loadFrame(*sweep, i);
        ASSERT_TRUE(frame) << frame.error().message;
        EXPECT_EQ(frame->image.pixels, images[i].pixels);
        EXPECT_EQ(frame->meta.angle_deg, sweep->frames[i].angle_deg);
        EXPECT_EQ(frame->meta.lens, header.lens.description);
    }
}

TEST(SweepWriter, FramesCarryOpenExrStandardAttributes) {
    TempDir dir;
    const SweepHeader header = smallHeader();  // f/2
    auto writer = SweepWriter::create(dir.path(), header);
    ASSERT_TRUE(writer) << writer.error().message;
    ASSERT_TRUE(writer->addFrame(testImage(0), frameAt(header, 0)));
    ExrStandardAttributes standard;
    standard.cap_date = "2026:11:29 08:04:02";
    standard.utc_offset_s = -3600.0;
    standard.aperture = 2.8;  // the caller's word wins over the header's
    ASSERT_TRUE(writer->addFrame(testImage(1), frameAt(header, 1), standard));
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    auto first = loadFrame(*sweep, 0);
    auto second = loadFrame(*sweep, 1);
    ASSERT_TRUE(first && second);
    // Known without the caller: the lens's f-number, and 1 s (a merged frame is DN per second).
    EXPECT_EQ(first->meta.standard.aperture, 2.0);
    EXPECT_EQ(first->meta.standard.exp_time_s, 1.0);
    EXPECT_TRUE(first->meta.standard.cap_date.empty());
    EXPECT_EQ(second->meta.standard.cap_date, "2026:11:29 08:04:02");
    EXPECT_EQ(second->meta.standard.utc_offset_s, -3600.0);
    EXPECT_EQ(second->meta.standard.aperture, static_cast<double>(2.8f));
    EXPECT_EQ(second->meta.standard.exp_time_s, 1.0);
}

TEST(SweepWriter, WritesAnEmptyButValidSweepOnCreate) {
    TempDir dir;
    auto writer = SweepWriter::create(dir.file("new/sweep"), smallHeader());
    ASSERT_TRUE(writer) << writer.error().message;
    auto sweep = readSweep(dir.file("new/sweep"));
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_TRUE(sweep->frames.empty());
}

// The frames a sweep lists, as readSweepManifest reads them.
std::vector<SweepFrame> listedFrames(const std::string& directory) {
    auto listed = readSweepManifest(directory);
    EXPECT_TRUE(listed) << listed.error().message;
    return listed ? listed->frames : std::vector<SweepFrame>{};
}

TEST(SweepWriter, CrashBetweenFrameAndItsRecordLeavesThePreviousFrames) {
    // Forked, so that the child writes into this test's directory.
    GTEST_FLAG_SET(death_test_style, "fast");
    TempDir dir;
    writeSweep(dir.path(), 2);
    const std::vector<SweepFrame> before = listedFrames(dir.path());
    ASSERT_EQ(before.size(), 2u);
    EXPECT_EXIT(
        {
            SweepWriteOptions options;
            options.resume = true;
            options.after_frame_written = [] { std::_Exit(7); };
            auto writer = SweepWriter::create(dir.path(), smallHeader(), options);
            if (writer) (void)writer->addFrame(testImage(2), frameAt(smallHeader(), 2));
            std::_Exit(0);
        },
        ::testing::ExitedWithCode(7), "");
    EXPECT_EQ(listedFrames(dir.path()), before);

    // The previous frames read, with the orphaned frame as a warning.
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 2u);
    const std::string orphan = sweepFrameFileName(2, frameAt(smallHeader(), 2).angle_deg);
    ASSERT_EQ(sweep->warnings.size(), 1u);
    EXPECT_TRUE(contains(sweep->warnings[0], orphan)) << sweep->warnings[0];

    ReadSweepOptions strict;
    strict.extra_exr_files_are_errors = true;
    auto refused = readSweep(dir.path(), strict);
    ASSERT_FALSE(refused);
    EXPECT_TRUE(contains(refused.error().message, orphan)) << refused.error().message;

    // Resuming does not overwrite the orphan silently; once it is set aside, the frame goes in.
    SweepWriteOptions resume;
    resume.resume = true;
    auto writer = SweepWriter::create(dir.path(), smallHeader(), resume);
    ASSERT_TRUE(writer) << writer.error().message;
    auto again = writer->addFrame(testImage(2), frameAt(smallHeader(), 2));
    ASSERT_FALSE(again);
    EXPECT_TRUE(contains(again.error().message, "already exists")) << again.error().message;
    EXPECT_EQ(listedFrames(dir.path()), before);
    TempDir aside;
    auto moved = writer->setAsideUnlisted(aside.file("recovered"));
    ASSERT_TRUE(moved) << moved.error().message;
    EXPECT_EQ(*moved, std::vector<std::string>{orphan});
    EXPECT_TRUE(fs::exists(aside.file("recovered/" + orphan)));
    again = writer->addFrame(testImage(2), frameAt(smallHeader(), 2));
    ASSERT_TRUE(again) << again.error().message;
    auto three = readSweep(dir.path());
    ASSERT_TRUE(three) << three.error().message;
    EXPECT_EQ(three->frames.size(), 3u);
}

TEST(SweepWriter, CrashWhileCompactingKeepsTheOldManifestAndTheLog) {
    // Forked, so that the child writes into this test's directory.
    GTEST_FLAG_SET(death_test_style, "fast");
    TempDir dir;
    writeSweep(dir.path(), 1);  // the manifest lists none, the log one frame
    const std::string before = readText(dir.file(kSweepManifestFile));
    EXPECT_EXIT(
        {
            SweepWriteOptions options;
            options.resume = true;  // which compacts
            options.before_manifest_replaced = [] { std::_Exit(7); };
            (void)SweepWriter::create(dir.path(), smallHeader(), options);
            std::_Exit(0);
        },
        ::testing::ExitedWithCode(7), "");
    EXPECT_EQ(readText(dir.file(kSweepManifestFile)), before);
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 1u);
    // The unrenamed manifest is reported.
    ASSERT_EQ(sweep->warnings.size(), 1u);
    EXPECT_TRUE(contains(sweep->warnings[0], "manifest.json.tmp-"));
    EXPECT_TRUE(contains(sweep->warnings[0], "temporary file"));
}

TEST(SweepWriter, RefusesToOverwriteAnotherSweep) {
    TempDir dir;
    writeSweep(dir.path(), 1);
    auto second = SweepWriter::create(dir.path(), smallHeader());
    ASSERT_FALSE(second);
    EXPECT_TRUE(contains(second.error().message, "already holds a sweep"));

    // Resuming with other settings is refused, naming what differs.
    SweepHeader other = smallHeader();
    other.capture.step_deg = 0.1;
    SweepWriteOptions resume;
    resume.resume = true;
    second = SweepWriter::create(dir.path(), other, resume);
    ASSERT_FALSE(second);
    EXPECT_TRUE(contains(second.error().message, "capture")) << second.error().message;

    // A directory of loose EXR files is not a place for a new sweep either.
    TempDir loose;
    ASSERT_TRUE(writeExr(loose.file("old.exr"), testImage(0), {}));
    second = SweepWriter::create(loose.path(), smallHeader());
    ASSERT_FALSE(second);
    EXPECT_TRUE(contains(second.error().message, "old.exr"));
}

TEST(SweepWriter, OneWriterPerDirectory) {
    TempDir dir;
    SweepWriter first = writeSweep(dir.path(), 1);
    SweepWriteOptions resume;
    resume.resume = true;
    auto second = SweepWriter::create(dir.path(), smallHeader(), resume);
    ASSERT_FALSE(second);
    EXPECT_TRUE(contains(second.error().message, "another sweep writer"));
}

TEST(SweepWriter, RefusesBadFramesWithoutTouchingTheSweep) {
    TempDir dir;
    SweepWriter writer = writeSweep(dir.path(), 2);
    const std::string before = readText(dir.file(kSweepManifestFile));
    const SweepHeader header = smallHeader();

    auto repeat = writer.addFrame(testImage(9), frameAt(header, 1));
    ASSERT_FALSE(repeat);
    EXPECT_TRUE(contains(repeat.error().message, "frames[2].angle_deg")) << repeat.error().message;

    auto wrong_size = writer.addFrame(testImage(9, kWidth + 1, kHeight), frameAt(header, 2));
    ASSERT_FALSE(wrong_size);
    EXPECT_TRUE(contains(wrong_size.error().message, "capture.width_px"));

    SweepFrame outside = frameAt(header, 2);
    outside.exr_file = "../escape.exr";
    auto escaped = writer.addFrame(testImage(9), outside);
    ASSERT_FALSE(escaped);
    EXPECT_TRUE(contains(escaped.error().message, "frames[2].exr_file"));

    TempDir elsewhere;
    fs::create_directory_symlink(elsewhere.path(), dir.file("linked"));
    SweepFrame through_link = frameAt(header, 2);
    through_link.exr_file = "linked/x.exr";
    auto linked = writer.addFrame(testImage(9), through_link);
    ASSERT_FALSE(linked);
    EXPECT_TRUE(contains(linked.error().message, "outside the sweep directory"));
    EXPECT_TRUE(fs::is_empty(elsewhere.path()));
    fs::remove(dir.file("linked"));

    SweepFrame missing_raw = frameAt(header, 2);
    missing_raw.raw_files = {"r0.raw", "r1.raw", "r2.raw"};
    auto no_raw = writer.addFrame(testImage(9), missing_raw);
    ASSERT_FALSE(no_raw);
    EXPECT_EQ(no_raw.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(contains(no_raw.error().message, "frames[2].raw_files[0]"));

    SweepFrame nan_angle = frameAt(header, 2);
    nan_angle.angle_deg = std::numeric_limits<double>::quiet_NaN();
    ASSERT_FALSE(writer.addFrame(testImage(9), nan_angle));

    EXPECT_EQ(readText(dir.file(kSweepManifestFile)), before);
    EXPECT_EQ(writer.sweep().frames.size(), 2u);
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_TRUE(sweep->warnings.empty());
}

TEST(SweepWriter, RefusesABadHeader) {
    TempDir dir;
    SweepHeader header = smallHeader();
    header.capture.width_px = 0;
    auto writer = SweepWriter::create(dir.path(), header);
    ASSERT_FALSE(writer);
    EXPECT_EQ(writer.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(contains(writer.error().message, "capture.width_px"));
    header = smallHeader();
    header.capture.exposure_times_s = {0.1, -1.0};
    writer = SweepWriter::create(dir.path(), header);
    ASSERT_FALSE(writer);
    EXPECT_TRUE(contains(writer.error().message, "capture.exposure_times_s[1]"));
    EXPECT_FALSE(fs::exists(dir.file(kSweepManifestFile)));
}

// ---------------------------------------------------------------------------------------------

TEST(ReadSweep, MissingFrameIsNotFoundNamingFileAndField) {
    TempDir dir;
    const Sweep written = writeSweep(dir.path(), 3).sweep();
    fs::remove(dir.file(written.frames[1].exr_file));
    auto sweep = readSweep(dir.path());
    ASSERT_FALSE(sweep);
    EXPECT_EQ(sweep.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(contains(sweep.error().message, "frames[1].exr_file"));
    EXPECT_TRUE(contains(sweep.error().message, written.frames[1].exr_file));
    // The manifest alone is still fine.
    EXPECT_TRUE(readSweepManifest(dir.path()));
}

TEST(ReadSweep, ExtraFrameIsAWarningOrAnErrorWhenAsked) {
    TempDir dir;
    writeSweep(dir.path(), 2);
    ASSERT_TRUE(writeExr(dir.file("stray.exr"), testImage(5), {}));
    writeText(dir.file("notes.txt"), "lab notes");
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    ASSERT_EQ(sweep->warnings.size(), 2u);
    EXPECT_TRUE(contains(sweep->warnings[0], "notes.txt"));
    EXPECT_TRUE(contains(sweep->warnings[1], "stray.exr"));
    ReadSweepOptions strict;
    strict.extra_exr_files_are_errors = true;
    auto refused = readSweep(dir.path(), strict);
    ASSERT_FALSE(refused);
    EXPECT_TRUE(contains(refused.error().message, "stray.exr"));
}

TEST(ReadSweep, FrameOfAnotherSizeIsRefused) {
    TempDir dir;
    const Sweep written = writeSweep(dir.path(), 2).sweep();
    const std::string path = dir.file(written.frames[1].exr_file);
    auto original = readExr(path);
    ASSERT_TRUE(original);
    ASSERT_TRUE(writeExr(path, testImage(1, kWidth, kHeight + 2), original->meta));
    auto sweep = readSweep(dir.path());
    ASSERT_FALSE(sweep);
    EXPECT_TRUE(contains(sweep.error().message, "frames[1].exr_file"));
    // Refused from the header, before the pixels are read.
    EXPECT_TRUE(contains(sweep.error().message, "declares a 8x8 image, but 8x6 was expected"))
        << sweep.error().message;
}

TEST(ReadSweep, NanPixelOnDiskIsRefused) {
    TempDir dir;
    const SweepHeader header = smallHeader();
    SweepWriteOptions options;
    options.exr.compression = ExrCompression::None;  // pixels stored as plain float32
    auto writer = SweepWriter::create(dir.path(), header, options);
    ASSERT_TRUE(writer);
    ImageRGB image = testImage(3);
    constexpr float kSentinel = 12345.678f;
    image.at(2, 3)[1] = kSentinel;
    ASSERT_TRUE(writer->addFrame(testImage(2), frameAt(header, 0)));
    auto frame = writer->addFrame(image, frameAt(header, 1));
    ASSERT_TRUE(frame) << frame.error().message;

    // Put a NaN where the sentinel is, as a faulty writer might.
    const std::string path = dir.file(frame->exr_file);
    std::string bytes = readText(path);
    char pattern[4];
    std::memcpy(pattern, &kSentinel, 4);
    const size_t at = bytes.find(std::string(pattern, 4));
    ASSERT_NE(at, std::string::npos);
    ASSERT_EQ(bytes.find(std::string(pattern, 4), at + 1), std::string::npos);
    const float nan = std::numeric_limits<float>::quiet_NaN();
    std::memcpy(bytes.data() + at, &nan, 4);
    writeText(path, bytes);

    auto sweep = readSweep(dir.path());
    ASSERT_FALSE(sweep);
    EXPECT_EQ(sweep.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(sweep.error().message, "frames[1].exr_file"));
    EXPECT_TRUE(contains(sweep.error().message, frame->exr_file));
    EXPECT_TRUE(contains(sweep.error().message, "(2, 3)")) << sweep.error().message;
    auto manifest_only = readSweepManifest(dir.path());
    ASSERT_TRUE(manifest_only);
    EXPECT_TRUE(loadFrame(*manifest_only, 0));
    EXPECT_FALSE(loadFrame(*manifest_only, 1));
}

TEST(ReadSweep, AttributesThatDisagreeWithTheManifestAreRefused) {
    struct Case {
        const char* what;
        void (*edit)(ExrMetadata&);
    };
    const Case cases[] = {
        {"flarelab.angle_deg", [](ExrMetadata& m) { *m.angle_deg += 1e-9; }},
        {"flarelab.angle_deg", [](ExrMetadata& m) { m.angle_deg.reset(); }},
        {"flarelab.exposure_times_s", [](ExrMetadata& m) { m.exposure_times_s.pop_back(); }},
        {"flarelab.roll_deg", [](ExrMetadata& m) { m.roll_deg = 0.0; }},
        {"flarelab.gain", [](ExrMetadata& m) { m.gain.reset(); }},
        {"flarelab.lens", [](ExrMetadata& m) { m.lens = "another lens"; }},
        {"flarelab.camera", [](ExrMetadata& m) { m.camera.clear(); }},
        {"flarelab.merge_method", [](ExrMetadata& m) { m.merge_method = "max"; }},
    };
    for (const Case& c : cases) {
        TempDir dir;
        const Sweep written = writeSweep(dir.path(), 2).sweep();
        const std::string path = dir.file(written.frames[0].exr_file);
        auto frame = readExr(path);
        ASSERT_TRUE(frame);
        c.edit(frame->meta);
        ASSERT_TRUE(writeExr(path, frame->image, frame->meta));
        auto sweep = readSweep(dir.path());
        ASSERT_FALSE(sweep) << c.what;
        EXPECT_TRUE(contains(sweep.error().message, c.what)) << sweep.error().message;
        EXPECT_TRUE(contains(sweep.error().message, "frames[0].exr_file"));
    }
}

TEST(ReadSweep, LinkOutOfTheDirectoryIsRefused) {
    TempDir dir, elsewhere;
    const Sweep written = writeSweep(dir.path(), 1).sweep();
    const std::string frame = dir.file(written.frames[0].exr_file);
    fs::rename(frame, elsewhere.file("moved.exr"));
    fs::create_symlink(elsewhere.file("moved.exr"), frame);
    auto sweep = readSweep(dir.path());
    ASSERT_FALSE(sweep);
    EXPECT_TRUE(contains(sweep.error().message, "outside the sweep directory"));
}

TEST(ReadSweep, MissingManifestIsNotFound) {
    TempDir dir;
    auto sweep = readSweep(dir.path());
    ASSERT_FALSE(sweep);
    EXPECT_EQ(sweep.error().code, ErrorCode::NotFound);
    EXPECT_TRUE(contains(sweep.error().message, "manifest.json"));
}

// ---------------------------------------------------------------------------------------------

TEST(ParseSweepManifest, AcceptsWhatFormatWrites) {
    auto sweep = parseSweepManifest(validManifest(), "m.json");
    ASSERT_TRUE(sweep) << sweep.error().message;
    ASSERT_EQ(sweep->frames.size(), 2u);
    EXPECT_EQ(sweep->frames[0].raw_files[2], "raw/a2.raw");
    EXPECT_EQ(sweep->header.created_utc, "2026-11-29T07:00:00Z");
    EXPECT_EQ(sweep->header.camera.bit_depth, 12);
    auto again = formatSweepManifest(*sweep);
    ASSERT_TRUE(again);
    EXPECT_EQ(*again, validManifest());
}

TEST(ParseSweepManifest, AcceptsCamelCaseNamesAndQuotedIntegers) {
    const std::string json =
        replaced(replaced(validManifest(), "\"angle_deg\":0.1", "\"angleDeg\":0.1"),
                 "\"format_version\": 5", "\"formatVersion\": \"5\"");
    auto sweep = parseSweepManifest(json);
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames[0].angle_deg, 0.1);
}

TEST(ParseSweepManifest, UnknownVersionIsUnsupported) {
    // A later version with a field this reader does not know: the version is what is wrong.
    const std::string json = replaced(validManifest(), "\"format_version\": 5",
                                      "\"format_version\": 6, \"new_field\": true");
    auto sweep = parseSweepManifest(json, "m.json");
    ASSERT_FALSE(sweep);
    EXPECT_EQ(sweep.error().code, ErrorCode::Unsupported);
    EXPECT_TRUE(contains(sweep.error().message, "m.json: format_version: 6"))
        << sweep.error().message;
    auto missing = parseSweepManifest(replaced(validManifest(), "\"format_version\": 5,", ""));
    ASSERT_FALSE(missing);
    EXPECT_TRUE(contains(missing.error().message, "format_version: missing"));
}

// The camera settings of a simulated capture, as drivers::describeLens records them.
SweepHeader withSimulatedLens(SweepHeader header) {
    header.lens.aperture_blades = 6;
    header.lens.blade_rotation_deg = 15.0;
    header.lens.stop_semi_aperture_mm = 4.3759765625;
    header.lens.coat_unspecified_surfaces = true;
    header.lens.sensor_width_mm = 36.0;
    header.lens.sensor_height_mm = 24.0;
    header.lens.prescription_file = "data/lenses/test lens.csv";
    header.lens.prescription_sha256 = std::string(32, 'a') + std::string(32, '7');
    return header;
}

TEST(ParseSweepManifest, Version3LensSettingsRoundTrip) {
    Sweep sweep;
    sweep.header = withSimulatedLens(smallHeader());
    sweep.frames = {frameAt(sweep.header, 0)};
    sweep.frames[0].exr_file = "a.exr";
    auto json = formatSweepManifest(sweep);
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_TRUE(contains(*json, "\"format_version\": 5")) << *json;
    EXPECT_TRUE(contains(*json, "\"aperture_blades\": 6")) << *json;
    EXPECT_TRUE(contains(*json, "\"coat_unspecified_surfaces\": true")) << *json;
    auto read = parseSweepManifest(*json, "m.json");
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->header, sweep.header);
    EXPECT_EQ(read->header.lens.stop_semi_aperture_mm, 4.3759765625);

    // A circular stop and bare surfaces are recorded settings too, not absent ones.
    sweep.header.lens.aperture_blades = 0;
    sweep.header.lens.coat_unspecified_surfaces = false;
    json = formatSweepManifest(sweep);
    ASSERT_TRUE(json) << json.error().message;
    read = parseSweepManifest(*json);
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->header.lens.aperture_blades, 0);
    EXPECT_EQ(read->header.lens.coat_unspecified_surfaces, false);

    // Without them, the fields are left out of the text and read back absent.
    const std::string bare = validManifest();
    EXPECT_FALSE(contains(bare, "aperture_blades")) << bare;
    EXPECT_FALSE(contains(bare, "prescription_file")) << bare;
}

TEST(ParseSweepManifest, AVersion2ManifestStillReadsWithoutTheSettings) {
    const std::string v2 =
        replaced(validManifest(), "\"format_version\": 5", "\"format_version\": 2");
    auto sweep = parseSweepManifest(v2, "m.json");
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->header.format_version, 2);
    EXPECT_EQ(sweep->header.lens.f_number, 2.0);
    EXPECT_FALSE(sweep->header.lens.aperture_blades);
    EXPECT_FALSE(sweep->header.lens.sensor_width_mm);
    // Version 3's fields belong to version 3: an older manifest holding one is refused by name.
    auto mixed = parseSweepManifest(
        replaced(v2, "\"f_number\": 2", "\"f_number\": 2, \"aperture_blades\": 6"), "m.json");
    ASSERT_FALSE(mixed);
    EXPECT_EQ(mixed.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(mixed.error().message,
                         "m.json: lens.aperture_blades: is a field of format version 3, not of "
                         "version 2"))
        << mixed.error().message;
    Sweep old = *sweep;
    old.header.lens.sensor_width_mm = 36.0;
    auto written = formatSweepManifest(old);
    ASSERT_FALSE(written);
    EXPECT_EQ(written.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(contains(written.error().message, "lens.sensor_width_mm"))
        << written.error().message;
}

TEST(ParseSweepManifest, TheCamerasRawFormatRoundTripsAndIsVersion4s) {
    Sweep sweep;
    sweep.header = smallHeader();
    sweep.header.camera.raw_format = RawFormat::BayerGRBG;
    sweep.frames = {frameAt(sweep.header, 0)};
    sweep.frames[0].exr_file = "a.exr";
    auto json = formatSweepManifest(sweep);
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_TRUE(contains(*json, "\"raw_format\": \"bayer-grbg\"")) << *json;
    auto read = parseSweepManifest(*json, "m.json");
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->header.camera.raw_format, RawFormat::BayerGRBG);
    EXPECT_EQ(read->header, sweep.header);
    // Not recorded: absent from the text and read back absent.
    EXPECT_FALSE(contains(validManifest(), "raw_format"));
    EXPECT_FALSE(parseSweepManifest(validManifest())->header.camera.raw_format);

    // A name that is no raw format, and the field in a version 3 manifest, are refused by name.
    auto bad = parseSweepManifest(replaced(*json, "bayer-grbg", "bayer-rgbg"), "m.json");
    ASSERT_FALSE(bad);
    EXPECT_EQ(bad.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(bad.error().message,
                         "m.json: camera.raw_format: 'bayer-rgbg' is not mono, bayer-rggb"))
        << bad.error().message;
    auto older = parseSweepManifest(
        replaced(*json, "\"format_version\": 5", "\"format_version\": 3"), "m.json");
    ASSERT_FALSE(older);
    EXPECT_TRUE(contains(older.error().message,
                         "camera.raw_format: is a field of format version 4, not of version 3"))
        << older.error().message;
}

TEST(ParseSweepManifest, TheLightsPowerRoundTripsAndIsVersion5s) {
    Sweep sweep;
    sweep.header = smallHeader();
    sweep.header.camera.light_power_dn_s = 3.25e9;
    sweep.frames = {frameAt(sweep.header, 0)};
    sweep.frames[0].exr_file = "a.exr";
    auto json = formatSweepManifest(sweep);
    ASSERT_TRUE(json) << json.error().message;
    EXPECT_TRUE(contains(*json, "\"light_power_dn_s\": 3250000000")) << *json;
    auto read = parseSweepManifest(*json, "m.json");
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->header, sweep.header);
    EXPECT_FALSE(contains(validManifest(), "light_power"));
    EXPECT_FALSE(parseSweepManifest(validManifest())->header.camera.light_power_dn_s);
    for (const char* bad : {"0", "-1"}) {
        auto refused = parseSweepManifest(replaced(*json, "\"light_power_dn_s\": 3250000000",
                                                   std::string("\"light_power_dn_s\": ") + bad),
                                          "m.json");
        ASSERT_FALSE(refused) << bad;
        EXPECT_TRUE(contains(refused.error().message, "m.json: camera.light_power_dn_s: "))
            << refused.error().message;
    }
    auto older = parseSweepManifest(
        replaced(*json, "\"format_version\": 5", "\"format_version\": 4"), "m.json");
    ASSERT_FALSE(older);
    EXPECT_TRUE(contains(older.error().message,
                         "camera.light_power_dn_s: is a field of format version 5, not of "
                         "version 4"))
        << older.error().message;
}

TEST(ParseSweepManifest, BrokenLensSettingsAreRefusedByField) {
    Sweep sweep;
    sweep.header = withSimulatedLens(smallHeader());
    auto json = formatSweepManifest(sweep);
    ASSERT_TRUE(json) << json.error().message;
    const std::pair<std::pair<const char*, const char*>, const char*> cases[] = {
        {{"\"aperture_blades\": 6", "\"aperture_blades\": 2"},
         "lens.aperture_blades: 2 is neither"},
        {{"\"aperture_blades\": 6", "\"aperture_blades\": 65"}, "lens.aperture_blades: 65"},
        {{"\"aperture_blades\": 6", "\"aperture_blades\": 4294967295"},
         "lens.aperture_blades: 4294967295"},
        {{"\"aperture_blades\": 6", "\"aperture_blades\": -6"}, "aperture_blades"},
        {{"\"blade_rotation_deg\": 15", "\"blade_rotation_deg\": \"NaN\""},
         "lens.blade_rotation_deg"},
        {{"\"stop_semi_aperture_mm\": 4.3759765625", "\"stop_semi_aperture_mm\": 0"},
         "lens.stop_semi_aperture_mm: 0 is not a finite number > 0"},
        {{"\"sensor_width_mm\": 36", "\"sensor_width_mm\": -36"}, "lens.sensor_width_mm"},
        {{"\"sensor_height_mm\": 24", "\"sensor_height_mm\": \"Infinity\""},
         "lens.sensor_height_mm"},
        {{"\"prescription_sha256\": \"aaaa", "\"prescription_sha256\": \"AAaa"},
         "lens.prescription_sha256"},
        {{"\"coat_unspecified_surfaces\": true", "\"coat_unspecified_surfaces\": 2"},
         "coat_unspecified_surfaces"},
    };
    for (const auto& [edit, field] : cases) {
        auto read = parseSweepManifest(replaced(*json, edit.first, edit.second), "m.json");
        ASSERT_FALSE(read) << edit.second;
        EXPECT_EQ(read.error().code, ErrorCode::ParseError);
        EXPECT_TRUE(contains(read.error().message, field)) << read.error().message;
    }
    // The writer refuses them the same way.
    sweep.header.lens.aperture_blades = 1;
    auto refused = formatSweepManifest(sweep);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(contains(refused.error().message, "lens.aperture_blades: 1 is neither"));
}

TEST(ParseSweepManifest, MalformedJsonIsAParseError) {
    const std::string json = validManifest();
    for (const std::string& broken :
         {json.substr(0, json.size() / 2), std::string(""), std::string("[1, 2]"),
          std::string("{\"format_version\": 1,}"), std::string("\xff\xfe")}) {
        auto sweep = parseSweepManifest(broken, "m.json");
        ASSERT_FALSE(sweep) << broken;
        EXPECT_EQ(sweep.error().code, ErrorCode::ParseError);
        EXPECT_EQ(sweep.error().message.rfind("m.json: ", 0), 0u) << sweep.error().message;
    }
}

TEST(ParseSweepManifest, UnknownFieldIsRefusedByName) {
    const std::string json = replaced(validManifest(), "\"angle_deg\":0.3", "\"angle_degs\":0.3");
    auto sweep = parseSweepManifest(json, "m.json");
    ASSERT_FALSE(sweep);
    EXPECT_EQ(sweep.error().code, ErrorCode::ParseError);
    EXPECT_TRUE(contains(sweep.error().message, "angle_degs")) << sweep.error().message;
}

TEST(ParseSweepManifest, PathsOutsideTheDirectoryAreRefused) {
    const std::pair<const char*, const char*> cases[] = {
        {"\"a.exr\"", "\"../a.exr\""},
        {"\"a.exr\"", "\"/tmp/a.exr\""},
        {"\"a.exr\"", "\"sub/../../a.exr\""},
        {"\"a.exr\"", "\"./a.exr\""},
        {"\"a.exr\"", "\"sub//a.exr\""},
        {"\"a.exr\"", "\"sub\\\\a.exr\""},
        {"\"a.exr\"", "\"\""},
        {"\"a.exr\"", "\"a.png\""},
        {"\"a.exr\"", "\"a\\u0001.exr\""},
        {"\"raw/a1.raw\"", "\"../raw/a1.raw\""},
        {"\"raw/a1.raw\"", "\"raw/\""},
        {"\"a.exr\"", "\"manifest.json\""},
    };
    for (const auto& [from, to] : cases) {
        auto sweep = parseSweepManifest(replaced(validManifest(), from, to), "m.json");
        ASSERT_FALSE(sweep) << to;
        EXPECT_EQ(sweep.error().code, ErrorCode::ParseError);
        EXPECT_TRUE(contains(sweep.error().message, "m.json: frames[0].")) << sweep.error().message;
    }
    auto twice = parseSweepManifest(replaced(validManifest(), "\"b.exr\"", "\"a.exr\""));
    ASSERT_FALSE(twice);
    EXPECT_TRUE(contains(twice.error().message, "frames[1].exr_file: 'a.exr' is named twice"));
}

TEST(ParseSweepManifest, DuplicateOrDecreasingAnglesAreRefused) {
    auto duplicate = parseSweepManifest(
        replaced(validManifest(), "\"angle_deg\":0.3", "\"angle_deg\":0.1"), "m.json");
    ASSERT_FALSE(duplicate);
    EXPECT_TRUE(contains(duplicate.error().message, "frames[1].angle_deg: 0.1 repeats"))
        << duplicate.error().message;
    auto decreasing =
        parseSweepManifest(replaced(validManifest(), "\"angle_deg\":0.3", "\"angle_deg\":-0.3"));
    ASSERT_FALSE(decreasing);
    EXPECT_TRUE(contains(decreasing.error().message, "is below frames[0].angle_deg"));
    auto outside =
        parseSweepManifest(replaced(validManifest(), "\"angle_deg\":0.3", "\"angle_deg\":0.7"));
    ASSERT_FALSE(outside);
    EXPECT_TRUE(contains(outside.error().message, "outside capture.from_deg"));
}

TEST(ParseSweepManifest, BrokenNumbersAreRefusedByField) {
    const std::pair<std::pair<const char*, const char*>, const char*> cases[] = {
        {{"\"angle_deg\":0.3", "\"angle_deg\":\"NaN\""}, "frames[1].angle_deg"},
        {{"\"step_deg\": 0.2", "\"step_deg\": 0"}, "capture.step_deg"},
        {{"\"gain\": 2", "\"gain\": \"-Infinity\""}, "capture.gain"},
        {{"\"width_px\": 8", "\"width_px\": 40000"}, "capture.width_px"},
        {{"\"bit_depth\": 12", "\"bit_depth\": 4294967295"}, "camera.bit_depth"},
        {{"\"to_deg\": 0.6", "\"to_deg\": -1"}, "capture.to_deg"},
        {{"\"raw/a0.raw\",", ""}, "frames[0].raw_files"},
        {{"\"width_px\": 8", "\"width_px\": -8"}, "width_px"},
        {{"\"created\": \"2026-11-29T07:00:00Z\"", "\"created\": \"yesterday\""}, "created"},
    };
    for (const auto& [edit, field] : cases) {
        auto sweep = parseSweepManifest(replaced(validManifest(), edit.first, edit.second));
        ASSERT_FALSE(sweep) << edit.second;
        EXPECT_TRUE(contains(sweep.error().message, field)) << sweep.error().message;
    }
}

TEST(ClippedFrames, CountsFramesWhoseShortestExposureClipsAndNamesTheWorst) {
    Sweep s;
    s.header.capture.width_px = 100;
    s.header.capture.height_px = 10;  // 1000 samples
    const auto with = [&](double angle, uint64_t clipped_short, uint64_t clipped_long) {
        SweepFrame f;
        f.angle_deg = angle;
        f.exposure_times_s = {4.0, 0.25};  // the shortest need not come first
        f.brackets = {{4.0, 0, clipped_long}, {0.25, 0, clipped_short}};
        s.frames.push_back(f);
    };
    with(0.0, 5, 900);  // the light's core: 0.5 %, however much the long exposure clips
    EXPECT_EQ(clippedFrames(s).frames, 0u);
    EXPECT_EQ(clippingWarning(clippedFrames(s), s.frames.size()), "");
    with(0.2, 300, 1000);
    with(0.4, 20, 1000);
    SweepFrame bare;  // a frame without statistics is not looked at
    bare.angle_deg = 0.6;
    s.frames.push_back(bare);
    const ClippedFrames c = clippedFrames(s);
    EXPECT_EQ(c.frames, 2u);
    EXPECT_EQ(c.with_stats, 3u);
    EXPECT_DOUBLE_EQ(c.worst_fraction, 0.3);
    EXPECT_DOUBLE_EQ(c.worst_angle_deg, 0.2);
    EXPECT_DOUBLE_EQ(c.shortest_exposure_s, 0.25);
    const std::string w = clippingWarning(c, s.frames.size());
    EXPECT_TRUE(contains(w, "2 of 4 frames")) << w;
    EXPECT_TRUE(contains(w, "worst 30.0% at 0.2 deg, 0.25 s")) << w;
    EXPECT_TRUE(contains(w, "shorter --brackets")) << w;
    EXPECT_EQ(clippedFrames(s, 0.5).frames, 0u);
    s.header.capture.width_px = 0;  // no size: nothing can be said
    EXPECT_EQ(clippedFrames(s).frames, 0u);
}

TEST(FormatSweepManifest, RefusesWhatParseWouldRefuse) {
    Sweep sweep;
    sweep.header = smallHeader();
    sweep.frames = {frameAt(sweep.header, 0)};
    sweep.frames[0].exr_file = "a.exr";
    ASSERT_TRUE(formatSweepManifest(sweep));
    sweep.frames[0].merge_method = std::string("a\0b", 3);
    auto json = formatSweepManifest(sweep);
    ASSERT_FALSE(json);
    EXPECT_EQ(json.error().code, ErrorCode::InvalidArgument);
    EXPECT_TRUE(contains(json.error().message, "frames[0].merge_method"));
}

}  // namespace
}  // namespace flarelab::hdr
