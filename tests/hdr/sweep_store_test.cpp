// Sweeps on disk under faults: the frame log of version 2 on (linear bytes, torn records), older
// versions resumed, the order of writes and flushes, a failed flush or a full disk, files set
// aside on resume, and hostile files (FIFOs, links, devices, oversized declarations) in place of
// every file a reader opens.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <future>
#include <iterator>
#include <mutex>
#include <random>
#include <string>
#include <vector>

#include "common/durable_io.h"
#include "hdr/exr.h"
#include "hdr/sweep.h"
#include "tests/test_files.h"
#include "tests/test_paths.h"

namespace flarelab::hdr {
namespace {

using flarelab::testing::contains;
using flarelab::testing::readText;
using flarelab::testing::TempDir;
using flarelab::testing::writeText;

namespace fs = std::filesystem;

SweepHeader header(double to_deg = 100.0) {
    SweepHeader h;
    h.software_version = "sweep_store_test";
    h.lens.description = "test lens";
    h.camera.description = "test camera";
    h.capture.from_deg = 0.0;
    h.capture.to_deg = to_deg;
    h.capture.step_deg = 0.1;
    h.capture.exposure_times_s = {0.01, 0.1, 1.0};
    h.capture.gain = 1.0;
    h.capture.width_px = 4;
    h.capture.height_px = 3;
    return h;
}

ImageRGB image(uint64_t seed, int64_t width = 4, int64_t height = 3) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<float> value(0.0f, 10.0f);
    ImageRGB out(width, height);
    for (float& v : out.pixels) v = value(rng);
    return out;
}

SweepFrame frame(int index) {
    SweepFrame f;
    f.angle_deg = 0.1 * index;
    f.exposure_times_s = {0.01, 0.1, 1.0};
    f.merge_method = "test merge";
    for (const double t : f.exposure_times_s) f.brackets.push_back({t, 12, 0});
    return f;
}

SweepWriter writeFrames(const std::string& dir, int count, SweepWriteOptions options = {}) {
    auto writer = SweepWriter::create(dir, header(), options);
    EXPECT_TRUE(writer) << writer.error().message;
    for (int i = 0; i < count; ++i) {
        auto added = writer->addFrame(image(i), frame(i));
        EXPECT_TRUE(added) << added.error().message;
    }
    return std::move(*writer);
}

// Bytes this process has handed to write(2) so far.
int64_t bytesWritten() {
    std::ifstream in("/proc/self/io");
    std::string key;
    int64_t value = 0;
    while (in >> key >> value)
        if (key == "wchar:") return value;
    return -1;
}

// Runs `read` on a thread and waits at most 20 s for it. A read that blocks on a FIFO is freed by
// opening the FIFO for writing, and reported as a failure instead of a hung test.
template <typename Read>
auto bounded(Read read, const std::vector<std::string>& fifos) {
    auto future = std::async(std::launch::async, read);
    if (future.wait_for(std::chrono::seconds(20)) != std::future_status::ready) {
        ADD_FAILURE() << "the reader blocked";
        for (const std::string& fifo : fifos) ::close(::open(fifo.c_str(), O_WRONLY | O_NONBLOCK));
    }
    return future.get();
}

// ---------------------------------------------------------------------------------------------

TEST(SweepWriter, BytesWrittenGrowLinearlyWithTheFrameCount) {
    // Version 1 rewrote its manifest after every frame: 4x the frames wrote 16x the bytes.
    const auto written = [](int frames) {
        TempDir dir;
        const int64_t before = bytesWritten();
        SweepWriter writer = writeFrames(dir.file("s"), frames);
        EXPECT_TRUE(writer.finish());
        return bytesWritten() - before;
    };
    const int64_t small = written(32), large = written(128);
    ASSERT_GT(small, 0);
    EXPECT_LT(static_cast<double>(large) / static_cast<double>(small), 6.0)
        << small << " bytes for 32 frames, " << large << " for 128";
}

TEST(SweepWriter, TheFinishedSweepIsItsManifestAlone) {
    TempDir dir;
    SweepWriteOptions options;
    options.compact_after_frames = 4;
    SweepWriter writer = writeFrames(dir.path(), 11, options);
    // Compacted on the way: the manifest lists some frames, the log the rest.
    auto listed = readSweepManifest(dir.path());
    ASSERT_TRUE(listed) << listed.error().message;
    EXPECT_EQ(listed->frames, writer.sweep().frames);
    EXPECT_TRUE(fs::exists(dir.file(kSweepFrameLogFile)));
    ASSERT_TRUE(writer.finish());
    EXPECT_FALSE(fs::exists(dir.file(kSweepFrameLogFile)));
    auto manifest = parseSweepManifest(readText(dir.file(kSweepManifestFile)));
    ASSERT_TRUE(manifest) << manifest.error().message;
    EXPECT_EQ(manifest->header.format_version, kSweepFormatVersion);
    EXPECT_EQ(manifest->frames, writer.sweep().frames);
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_TRUE(sweep->warnings.empty()) << sweep->warnings.front();
    EXPECT_FALSE(writer.addFrame(image(11), frame(11)));
}

TEST(FrameLog, ATornRecordAtTheEndIsIgnoredAndCutOffByTheNextWriter) {
    TempDir dir;
    writeFrames(dir.path(), 3);
    const std::string log = dir.file(kSweepFrameLogFile);
    const std::string whole = readText(log);
    // What a crash in the middle of the fourth append leaves: its record cut short.
    const std::string fourth = formatSweepFrameLogRecord(3, frame(3));
    for (const size_t cut : {size_t{3}, size_t{8}, fourth.size() - 1}) {
        writeText(log, whole + fourth.substr(0, cut));
        auto listed = readSweepManifest(dir.path());
        ASSERT_TRUE(listed) << listed.error().message;
        EXPECT_EQ(listed->frames.size(), 3u);
        ASSERT_EQ(listed->warnings.size(), 1u);
        EXPECT_TRUE(contains(listed->warnings[0], "from byte " + std::to_string(whole.size())))
            << listed->warnings[0];
    }
    // A checksum that fails, and a length no record has, end the log the same way; the length
    // is never allocated.
    std::string flipped = fourth;
    flipped.back() ^= 0x40;
    std::string huge = fourth;
    huge[0] = huge[1] = huge[2] = huge[3] = '\xff';
    for (const std::string& bad : {flipped, huge}) {
        writeText(log, whole + bad);
        auto listed = readSweepManifest(dir.path());
        ASSERT_TRUE(listed) << listed.error().message;
        EXPECT_EQ(listed->frames.size(), 3u);
        EXPECT_EQ(listed->warnings.size(), 1u);
    }
    // The next writer cuts it off before appending, so the new frame is reachable.
    SweepWriteOptions resume;
    resume.resume = true;
    auto writer = SweepWriter::create(dir.path(), header(), resume);
    ASSERT_TRUE(writer) << writer.error().message;
    ASSERT_TRUE(writer->addFrame(image(3), frame(3)));
    auto sweep = readSweep(dir.path());
    ASSERT_TRUE(sweep) << sweep.error().message;
    EXPECT_EQ(sweep->frames.size(), 4u);
    EXPECT_TRUE(sweep->warnings.empty()) << sweep->warnings.front();
}

TEST(FrameLog, RecordsTheManifestHoldsAreSkippedButGapsAndDisagreementsRefused) {
    TempDir dir;
    SweepWriter writer = writeFrames(dir.path(), 2);
    ASSERT_TRUE(writer.finish());  // the manifest lists frames 0 and 1
    const std::string log = dir.file(kSweepFrameLogFile);
    const std::string magic(kSweepFrameLogMagic);
    // A crash between a compaction and the log's truncation: the log repeats listed frames.
    writeText(log, magic + formatSweepFrameLogRecord(0, writer.sweep().frames[0]) +
                       formatSweepFrameLogRecord(1, writer.sweep().frames[1]));
    auto repeated = readSweepManifest(dir.path());
    ASSERT_TRUE(repeated) << repeated.error().message;
    EXPECT_EQ(repeated->frames.size(), 2u);
    SweepFrame other = writer.sweep().frames[1];
    other.merge_method = "something else";
    writeText(log, magic + formatSweepFrameLogRecord(1, other));
    auto differs = readSweepManifest(dir.path());
    ASSERT_FALSE(differs);
    EXPECT_TRUE(contains(differs.error().message, "frames.log: record 0 (frame 1)"))
        << differs.error().message;
    SweepFrame later = frame(3);
    later.exr_file = "later.exr";
    writeText(log, magic + formatSweepFrameLogRecord(3, later));
    auto gap = readSweepManifest(dir.path());
    ASSERT_FALSE(gap);
    EXPECT_TRUE(contains(gap.error().message, "gap")) << gap.error().message;
    writeText(log, "not a frame log at all");
    auto foreign = readSweepManifest(dir.path());
    ASSERT_FALSE(foreign);
    EXPECT_EQ(foreign.error().code, ErrorCode::ParseError);
}

TEST(ReadSweep, VersionOneSweepsStillReadAndAreUpgradedWhenResumed) {
    for (const char* recorded : {"heliar-raw", "nikon-hdr"}) {
        auto sweep = readSweep(testing::sourcePath(std::string("tests/data/sweeps/") + recorded));
        ASSERT_TRUE(sweep) << sweep.error().message;
        EXPECT_EQ(sweep->header.format_version, 1);
        EXPECT_FALSE(sweep->frames.empty());
    }
    // A version 1 sweep as its writer left it: every frame in the manifest, no log.
    TempDir dir;
    Sweep old = writeFrames(dir.path(), 3).sweep();
    old.header.format_version = 1;
    old.directory.clear();
    auto v1 = formatSweepManifest(old);
    ASSERT_TRUE(v1) << v1.error().message;
    writeText(dir.file(kSweepManifestFile), *v1);
    fs::remove(dir.file(kSweepFrameLogFile));
    auto read = readSweep(dir.path());
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(read->frames.size(), 3u);
    SweepWriteOptions resume;
    resume.resume = true;
    auto resumed = SweepWriter::create(dir.path(), header(), resume);
    ASSERT_TRUE(resumed) << resumed.error().message;
    ASSERT_TRUE(resumed->addFrame(image(3), frame(3)));
    auto manifest = parseSweepManifest(readText(dir.file(kSweepManifestFile)));
    ASSERT_TRUE(manifest) << manifest.error().message;
    EXPECT_EQ(manifest->header.format_version, kSweepFormatVersion);
    auto upgraded = readSweep(dir.path());
    ASSERT_TRUE(upgraded) << upgraded.error().message;
    EXPECT_EQ(upgraded->frames.size(), 4u);
}

// The camera settings a version 3 sweep records for a simulated lens (drivers::describeLens).
SweepHeader withLensSettings(SweepHeader h, int blades = 6) {
    h.lens.f_number = 4.5;
    h.lens.focal_length_mm = 50.0;
    h.lens.aperture_blades = blades;
    h.lens.blade_rotation_deg = 15.0;
    h.lens.stop_semi_aperture_mm = 3.25;
    h.lens.coat_unspecified_surfaces = false;
    h.lens.sensor_width_mm = 36.0;
    h.lens.sensor_height_mm = 24.0;
    return h;
}

// A sweep begun by an older version (here 2, its frame log holding frames) is resumed by a writer
// whose camera records the settings: the frames already taken were not recorded with them, so
// they stay absent, and the sweep becomes version 4 when compacted.
TEST(SweepWriter, AnOlderSweepResumesWithTheSettingsItNeverRecordedLeftAbsent) {
    TempDir dir;
    SweepHeader old_header = header();
    old_header.lens.f_number = 4.5;
    old_header.lens.focal_length_mm = 50.0;
    writeFrames(dir.path(), 3);
    // What version 2 left: its manifest (no frames yet compacted) and a log with the frames.
    Sweep old;
    old.header = old_header;
    old.header.format_version = 2;
    old.header.created_utc = "2026-11-29T07:00:00Z";
    auto v2 = formatSweepManifest(old);
    ASSERT_TRUE(v2) << v2.error().message;
    writeText(dir.file(kSweepManifestFile), *v2);
    auto listed = readSweepManifest(dir.path());
    ASSERT_TRUE(listed) << listed.error().message;
    EXPECT_EQ(listed->header.format_version, 2);
    EXPECT_EQ(listed->frames.size(), 3u);

    SweepWriteOptions resume;
    resume.resume = true;
    {
        SweepHeader now = withLensSettings(old_header);
        now.camera.raw_format = RawFormat::BayerRGGB;  // version 4's, not recorded before either
        auto resumed = SweepWriter::create(dir.path(), now, resume);
        ASSERT_TRUE(resumed) << resumed.error().message;
        EXPECT_EQ(resumed->sweep().header.format_version, kSweepFormatVersion);
        EXPECT_EQ(resumed->sweep().header.lens, old_header.lens);
        EXPECT_FALSE(resumed->sweep().header.camera.raw_format);
        ASSERT_TRUE(resumed->addFrame(image(3), frame(3)));
        ASSERT_TRUE(resumed->finish());
    }
    auto manifest = parseSweepManifest(readText(dir.file(kSweepManifestFile)));
    ASSERT_TRUE(manifest) << manifest.error().message;
    EXPECT_EQ(manifest->header.format_version, kSweepFormatVersion);
    EXPECT_EQ(manifest->header.lens, old_header.lens);
    EXPECT_FALSE(manifest->header.camera.raw_format);
    EXPECT_FALSE(manifest->header.lens.aperture_blades);
    EXPECT_FALSE(manifest->header.lens.sensor_width_mm);
    EXPECT_EQ(manifest->header.created_utc, "2026-11-29T07:00:00Z");
    EXPECT_EQ(manifest->frames.size(), 4u);

    // Now version 4, it records no settings: a writer that has some is another capture.
    auto again = SweepWriter::create(dir.path(), withLensSettings(old_header), resume);
    ASSERT_FALSE(again);
    EXPECT_TRUE(contains(again.error().message, "lens.aperture_blades: absent, the new sweep's 6"))
        << again.error().message;
    // What older versions recorded is still compared.
    SweepHeader other = old_header;
    other.lens.f_number = 8.0;
    EXPECT_FALSE(SweepWriter::create(dir.path(), other, resume));
}

// A version 3 sweep taken with six blades is not continued with another aperture: the frames
// would mix two captures, and a score would re-simulate only one of them.
TEST(SweepWriter, AResumeWithOtherBladesIsRefusedAsAnotherCapture) {
    TempDir dir;
    const SweepHeader six = withLensSettings(header(), 6);
    {
        auto writer = SweepWriter::create(dir.path(), six);
        ASSERT_TRUE(writer) << writer.error().message;
        ASSERT_TRUE(writer->addFrame(image(0), frame(0)));
    }
    SweepWriteOptions resume;
    resume.resume = true;
    for (const int blades : {0, 5}) {
        auto refused = SweepWriter::create(dir.path(), withLensSettings(header(), blades), resume);
        ASSERT_FALSE(refused) << blades;
        EXPECT_EQ(refused.error().code, ErrorCode::InvalidArgument);
        EXPECT_TRUE(contains(refused.error().message,
                             "lens.aperture_blades: 6, the new sweep's " + std::to_string(blades)))
            << refused.error().message;
        EXPECT_TRUE(contains(refused.error().message, "cannot resume")) << refused.error().message;
    }
    SweepHeader rotated = six;
    rotated.lens.blade_rotation_deg = 0.0;
    auto refused = SweepWriter::create(dir.path(), rotated, resume);
    ASSERT_FALSE(refused);
    EXPECT_TRUE(contains(refused.error().message, "lens.blade_rotation_deg: 15, the new sweep's 0"))
        << refused.error().message;
    // Nothing was touched: the same settings resume.
    auto same = SweepWriter::create(dir.path(), six, resume);
    ASSERT_TRUE(same) << same.error().message;
    EXPECT_EQ(same->sweep().header.lens, six.lens);
    EXPECT_EQ(same->sweep().frames.size(), 1u);
}

TEST(SweepWriter, FramesReachTheDiskBeforeTheRecordThatListsThem) {
    TempDir dir;
    std::mutex mutex;
    std::vector<std::string> flushed;  // every fsync, in order
    ScopedFileFaults faults({.write = {}, .fsync = [&](const std::string& path) {
                                 std::lock_guard lock(mutex);
                                 flushed.push_back(path);
                                 return 0;
                             }});
    const std::string sweep_dir = dir.file("new/deeper/sweep");
    SweepWriter writer = writeFrames(sweep_dir, 0);
    // Every new directory's name was flushed into its parent.
    for (const std::string& parent : {dir.path(), dir.file("new"), dir.file("new/deeper")})
        EXPECT_NE(std::find(flushed.begin(), flushed.end(), parent), flushed.end()) << parent;
    flushed.clear();
    ASSERT_TRUE(writer.addFrame(image(0), frame(0)));
    const std::string exr = sweep_dir + "/" + sweepFrameFileName(0, 0.0);
    const auto at = [&](const std::function<bool(const std::string&)>& match) {
        return std::find_if(flushed.begin(), flushed.end(), match) - flushed.begin();
    };
    const auto exr_file = at([&](const std::string& p) { return p.rfind(exr + ".tmp-", 0) == 0; });
    const auto exr_name = at([&](const std::string& p) { return p == sweep_dir; });
    const auto record = at([&](const std::string& p) { return contains(p, kSweepFrameLogFile); });
    ASSERT_LT(record, static_cast<long>(flushed.size())) << "the record was not flushed";
    EXPECT_LT(exr_file, exr_name);
    EXPECT_LT(exr_name, record);
}

TEST(SweepWriter, AFailedFlushClosesTheWriterForGoodAndKeepsTheFramesBefore) {
    for (const std::string& failing : {std::string(kSweepFrameLogFile), std::string(".exr.tmp-")}) {
        TempDir dir;
        SweepWriter writer = writeFrames(dir.path(), 3);
        int calls = 0;
        {
            ScopedFileFaults faults({.write = {}, .fsync = [&](const std::string& path) {
                                         if (!contains(path, failing)) return 0;
                                         ++calls;
                                         return EIO;
                                     }});
            auto failed = writer.addFrame(image(3), frame(3));
            ASSERT_FALSE(failed);
            EXPECT_TRUE(contains(failed.error().message, "fsync")) << failed.error().message;
            EXPECT_TRUE(contains(failed.error().message, "never retried"));
        }
        EXPECT_EQ(calls, 1) << "a failed fsync was tried again";
        EXPECT_FALSE(writer.broken().empty());
        // Nothing more, though the disk is well again.
        auto refused = writer.addFrame(image(4), frame(4));
        ASSERT_FALSE(refused);
        EXPECT_TRUE(contains(refused.error().message, "closed"));
        EXPECT_FALSE(writer.finish());
        auto sweep = readSweep(dir.path());
        ASSERT_TRUE(sweep) << sweep.error().message;
        ASSERT_GE(sweep->frames.size(), 3u);
        for (int i = 0; i < 3; ++i) EXPECT_EQ(sweep->frames[i], writer.sweep().frames[i]);
    }
}

TEST(SweepWriter, AFullDiskLeavesTheSweepAsItWasAndTheWriterGoesOnOnceThereIsRoom) {
    for (const std::string& failing : {std::string(kSweepFrameLogFile), std::string(".exr.tmp-")}) {
        TempDir dir;
        SweepWriter writer = writeFrames(dir.path(), 2);
        {
            ScopedFileFaults full(
                {.write =
                     [&](const std::string& path) { return contains(path, failing) ? ENOSPC : 0; },
                 .fsync = {}});
            auto failed = writer.addFrame(image(2), frame(2));
            ASSERT_FALSE(failed);
            EXPECT_TRUE(contains(failed.error().message, "No space left"))
                << failed.error().message;
        }
        EXPECT_TRUE(writer.broken().empty());
        auto sweep = readSweep(dir.path(), {.extra_exr_files_are_errors = true, .exr = {}});
        ASSERT_TRUE(sweep) << sweep.error().message;
        EXPECT_EQ(sweep->frames.size(), 2u);
        ASSERT_TRUE(writer.addFrame(image(2), frame(2)));
        EXPECT_EQ(readSweepManifest(dir.path())->frames.size(), 3u);
    }
}

TEST(SweepWriter, SetAsideMovesAcrossFileSystemsAndNeverOverwrites) {
    TempDir dir;
    writeFrames(dir.path(), 2);
    const std::string orphan = sweepFrameFileName(2, 0.2);
    writeText(dir.file(orphan), "the frame a crash left");
    fs::create_directories(dir.file("raw"));
    writeText(dir.file("raw/frame_00002_0.pgm"), "its raw bracket");
    SweepWriteOptions resume;
    resume.resume = true;
    auto writer = SweepWriter::create(dir.path(), header(), resume);
    ASSERT_TRUE(writer) << writer.error().message;

    // Not into the sweep itself, however the path is spelt.
    fs::create_directory_symlink(dir.path(), dir.path() + "-link");
    const std::string inside = dir.path() + "-link/recovered";
    auto refused = writer->setAsideUnlisted(inside);
    ASSERT_FALSE(refused);
    EXPECT_TRUE(contains(refused.error().message, "inside the sweep")) << refused.error().message;
    fs::remove(dir.path() + "-link");

    // A file of the same name already set aside is not overwritten.
    TempDir aside;
    writeText(aside.file(orphan), "set aside before");
    auto collided = writer->setAsideUnlisted(aside.path());
    ASSERT_FALSE(collided);
    EXPECT_EQ(readText(aside.file(orphan)), "set aside before");
    EXPECT_EQ(readText(dir.file(orphan)), "the frame a crash left");

    // Another file system (tmpfs) when there is one: copied, flushed, then unlinked.
    const fs::path shm = "/dev/shm";
    TempDir elsewhere(fs::exists(shm) ? shm : fs::temp_directory_path());
    auto moved = writer->setAsideUnlisted(elsewhere.file("job/1"));
    ASSERT_TRUE(moved) << moved.error().message;
    EXPECT_EQ(*moved, (std::vector<std::string>{orphan, "raw/frame_00002_0.pgm"}));
    EXPECT_EQ(readText(elsewhere.file("job/1/" + orphan)), "the frame a crash left");
    EXPECT_EQ(readText(elsewhere.file("job/1/raw/frame_00002_0.pgm")), "its raw bracket");
    EXPECT_FALSE(fs::exists(dir.file(orphan)));
    ASSERT_TRUE(writer->addFrame(image(2), frame(2)));
}

// A FIFO, a link to a good file and a device that never ends (/dev/zero), each in place of `file`.
struct Hostile {
    const char* kind;
    std::function<void(const std::string& file, const std::string& good_copy)> make;
};
std::vector<Hostile> hostiles() {
    std::vector<Hostile> out = {
        {"FIFO",
         [](const std::string& f, const std::string&) { ASSERT_EQ(::mkfifo(f.c_str(), 0644), 0); }},
        {"symbolic link",
         [](const std::string& f, const std::string& good) { fs::create_symlink(good, f); }},
    };
    if (::geteuid() == 0)  // mknod needs CAP_MKNOD
        out.push_back({"character device", [](const std::string& f, const std::string&) {
                           ASSERT_EQ(::mknod(f.c_str(), S_IFCHR | 0644, makedev(1, 5)), 0);
                       }});
    return out;
}

TEST(HostileFiles, EveryFileOfASweepThatIsNotARegularFileIsRefusedWithoutBlocking) {
    TempDir dir;
    const std::string sweep_dir = dir.file("sweep");
    {
        SweepWriter writer = writeFrames(sweep_dir, 2);  // a manifest, a log, two frames
        fs::create_directories(sweep_dir + "/raw");
        for (int b = 0; b < 3; ++b)
            writeText(sweep_dir + "/raw/r" + std::to_string(b) + ".pgm", "raw");
        SweepFrame with_raw = frame(2);
        with_raw.raw_files = {"raw/r0.pgm", "raw/r1.pgm", "raw/r2.pgm"};
        ASSERT_TRUE(writer.addFrame(image(2), with_raw));
    }
    const std::vector<std::string> files = {kSweepManifestFile, kSweepFrameLogFile,
                                            sweepFrameFileName(1, 0.1), "raw/r1.pgm"};
    for (const Hostile& hostile : hostiles())
        for (const std::string& name : files) {
            SCOPED_TRACE(std::string(hostile.kind) + " as " + name);
            const std::string path = sweep_dir + "/" + name;
            const std::string good = dir.file("good-copy");
            fs::copy_file(path, good, fs::copy_options::overwrite_existing);
            fs::remove(path);
            hostile.make(path, good);
            auto read = bounded([&] { return readSweep(sweep_dir); }, {path});
            ASSERT_FALSE(read);
            EXPECT_TRUE(contains(read.error().message, path) ||
                        contains(read.error().message, name))
                << read.error().message;
            fs::remove(path);
            fs::rename(good, path);
            ASSERT_TRUE(readSweep(sweep_dir)) << "restored";
        }
    // The lock file too: a writer refuses the directory rather than open what stands there.
    for (const Hostile& hostile : hostiles()) {
        SCOPED_TRACE(std::string(hostile.kind) + " as the lock file");
        const std::string lock = sweep_dir + "/" + kSweepLockFile;
        fs::remove(lock);
        writeText(dir.file("target"), "");
        hostile.make(lock, dir.file("target"));
        SweepWriteOptions resume;
        resume.resume = true;
        auto writer =
            bounded([&] { return SweepWriter::create(sweep_dir, header(), resume); }, {lock});
        ASSERT_FALSE(writer);
        EXPECT_TRUE(contains(writer.error().message, kSweepLockFile)) << writer.error().message;
        fs::remove(lock);
    }
}

TEST(HostileFiles, OversizedDeclarationsAreRefusedBeforeAnythingIsAllocated) {
    TempDir dir;
    writeFrames(dir.path(), 2);
    // A frame whose header declares far more than the manifest's 4 x 3 pixels.
    const std::string frame_path = dir.file(sweepFrameFileName(1, 0.1));
    ImageRGB large(1024, 1024);
    ExrMetadata meta;
    meta.angle_deg = 0.1;
    ASSERT_TRUE(writeExr(frame_path, large, meta));
    auto sweep = readSweep(dir.path());
    ASSERT_FALSE(sweep);
    EXPECT_TRUE(contains(sweep.error().message, "declares a 1024x1024 image, but 4x3"))
        << sweep.error().message;
    ASSERT_TRUE(writeExr(frame_path, image(1), {}));
    // A manifest and a log larger than any sweep's (sparse: no disk is used).
    for (const std::string name : {kSweepManifestFile, kSweepFrameLogFile}) {
        const std::string path = dir.file(name);
        const std::string kept = readText(path);
        ASSERT_EQ(::truncate(path.c_str(), kSweepMaxManifestBytes + 1), 0);
        auto listed = readSweepManifest(dir.path());
        ASSERT_FALSE(listed) << name;
        EXPECT_TRUE(contains(listed.error().message, "more than the limit"))
            << listed.error().message;
        writeText(path, kept);
    }
}

TEST(SweepFormat, TheDaemonsLargestSweepFitsTheReadLimits) {
    // 100000 frames (the daemon's most) of 16 exposures (its most), raw files kept, as the
    // compacted manifest and the log hold them.
    SweepHeader h = header(1e4);
    h.capture.exposure_times_s.assign(16, 0.0);
    for (int k = 0; k < 16; ++k) h.capture.exposure_times_s[k] = 1e-5 * (k + 1) * 3.7;
    Sweep sweep;
    sweep.header = h;
    for (int i = 0; i < 100; ++i) {
        SweepFrame f;
        f.angle_deg = 99.99 + 1e-9 * i;
        f.exr_file = sweepFrameFileName(99900 + i, f.angle_deg);
        f.exposure_times_s = h.capture.exposure_times_s;
        f.merge_method = "granados-optimal (16 exposures, gain 16, black 4095)";
        for (int k = 0; k < 16; ++k) {
            f.raw_files.push_back("raw/frame_" + std::to_string(99900 + i) + "_" +
                                  std::to_string(k) + ".pgm");
            f.brackets.push_back({f.exposure_times_s[k], 4294967295u, 4294967295u});
        }
        EXPECT_LT(formatSweepFrameLogRecord(99900 + i, f).size(), kSweepMaxLogRecordBytes);
        sweep.frames.push_back(std::move(f));
    }
    auto json = formatSweepManifest(sweep);
    ASSERT_TRUE(json) << json.error().message;
    const double per_frame = static_cast<double>(json->size()) / 100.0;
    EXPECT_LT(per_frame * 100000.0, 0.5 * static_cast<double>(kSweepMaxManifestBytes))
        << per_frame << " bytes per frame";
}

}  // namespace
}  // namespace flarelab::hdr
