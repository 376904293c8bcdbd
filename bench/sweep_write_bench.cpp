// What a sweep of many frames costs the disk (README, "The daemon: measured"):
//
//   sweep_write_bench [--dir DIR] [--brackets N] FRAMES...
//
// For each count in FRAMES, writes a sweep of that many 1 x 1 frames (the smallest a frame can
// be, so that what is measured is the sweep's bookkeeping, not its pixels) with SweepWriter into
// a fresh directory under DIR (default: the system's temporary directory), each frame with a
// bracket of N exposures (default 3) and its statistics, as the daemon writes them. Then reads
// the sweep's frame list back (readSweepManifest) and resumes it: a second writer appends one
// more frame. Prints one Markdown row per count: bytes handed to write(2) while writing (from
// /proc/self/io, "wchar": every file, the frames' EXRs included), that per frame, the wall time
// of the writes, of the read and of the resume, and the size of the files that list the frames.
// Only hdr/sweep.h's public API is used, so the same file measures any version of the writer.
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "hdr/sweep.h"

namespace {

namespace fs = std::filesystem;
using namespace flarelab;
using Clock = std::chrono::steady_clock;

double since(Clock::time_point t) {
    return std::chrono::duration<double>(Clock::now() - t).count();
}

// Bytes this process has passed to write(2) and friends so far.
int64_t bytesWritten() {
    std::ifstream in("/proc/self/io");
    std::string key;
    int64_t value = 0;
    while (in >> key >> value)
        if (key == "wchar:") return value;
    return -1;
}

hdr::SweepHeader header(int64_t frames, int brackets) {
    hdr::SweepHeader h;
    h.software_version = "sweep_write_bench";
    h.lens.description = "bench lens";
    h.camera.description = "bench camera";
    h.capture.from_deg = 0.0;
    h.capture.step_deg = 0.001;
    h.capture.to_deg = static_cast<double>(frames) * 0.001;
    for (int k = 0; k < brackets; ++k) h.capture.exposure_times_s.push_back(0.01 * (1 << k));
    h.capture.gain = 1.0;
    h.capture.width_px = 1;
    h.capture.height_px = 1;
    return h;
}

hdr::SweepFrame frame(const hdr::SweepHeader& h, int64_t index) {
    hdr::SweepFrame f;
    f.angle_deg = std::round(static_cast<double>(index) * h.capture.step_deg * 1e9) / 1e9;
    f.exposure_times_s = h.capture.exposure_times_s;
    f.merge_method = "weighted-mean (hat weights, 3 exposures)";
    for (const double t : f.exposure_times_s) f.brackets.push_back({t, 1, 0});
    return f;
}

int64_t listingBytes(const std::string& dir) {
    int64_t total = 0;
    std::error_code ec;
    for (const auto& entry : fs::directory_iterator(dir, ec)) {
        const std::string name = entry.path().filename().string();
        if (name.size() > 4 && name.substr(name.size() - 4) == ".exr") continue;
        if (entry.is_regular_file(ec)) total += static_cast<int64_t>(entry.file_size(ec));
    }
    return total;
}

int run(const std::string& root, int64_t frames, int brackets) {
    const std::string dir = root + "/sweep-" + std::to_string(frames);
    std::error_code ec;
    fs::remove_all(dir, ec);
    const hdr::SweepHeader h = header(frames + 1, brackets);
    ImageRGB image(1, 1);
    image.pixels = {1.0f, 2.0f, 3.0f};

    const int64_t bytes_before = bytesWritten();
    const auto start = Clock::now();
    {
        auto writer = hdr::SweepWriter::create(dir, h);
        if (!writer) {
            std::fprintf(stderr, "%s\n", writer.error().message.c_str());
            return 1;
        }
        for (int64_t i = 0; i < frames; ++i)
            if (auto added = writer->addFrame(image, frame(h, i)); !added) {
                std::fprintf(stderr, "frame %lld: %s\n", static_cast<long long>(i),
                             added.error().message.c_str());
                return 1;
            }
    }
    const double write_s = since(start);
    const int64_t bytes = bytesWritten() - bytes_before;

    const auto read_start = Clock::now();
    auto listed = hdr::readSweepManifest(dir);
    const double read_s = since(read_start);
    if (!listed || static_cast<int64_t>(listed->frames.size()) != frames) {
        std::fprintf(stderr, "read back: %s\n",
                     listed ? "wrong frame count" : listed.error().message.c_str());
        return 1;
    }
    const auto resume_start = Clock::now();
    {
        hdr::SweepWriteOptions resume;
        resume.resume = true;
        auto writer = hdr::SweepWriter::create(dir, h, resume);
        if (!writer || !writer->addFrame(image, frame(h, frames))) {
            std::fprintf(stderr, "resume failed%s\n",
                         writer ? "" : (": " + writer.error().message).c_str());
            return 1;
        }
    }
    const double resume_s = since(resume_start);
    std::printf("| %lld | %d | %lld | %.0f | %.2f | %.3f | %.3f | %lld |\n",
                static_cast<long long>(frames), brackets, static_cast<long long>(bytes),
                static_cast<double>(bytes) / static_cast<double>(frames), write_s, read_s, resume_s,
                static_cast<long long>(listingBytes(dir)));
    std::fflush(stdout);
    fs::remove_all(dir, ec);
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    std::string root = fs::temp_directory_path().string();
    int brackets = 3;
    std::vector<int64_t> counts;
    for (int i = 1; i < argc; ++i) {
        const std::string arg = argv[i];
        if (arg == "--dir" && i + 1 < argc) {
            root = argv[++i];
        } else if (arg == "--brackets" && i + 1 < argc) {
            brackets = std::atoi(argv[++i]);
        } else {
            counts.push_back(std::atoll(arg.c_str()));
        }
    }
    if (counts.empty() || brackets < 1 || brackets > 16) {
        std::fprintf(stderr, "usage: sweep_write_bench [--dir DIR] [--brackets 1..16] FRAMES...\n");
        return 2;
    }
    std::printf(
        "| frames | brackets | bytes written | per frame | write s | read s | resume s | "
        "listing bytes |\n|---|---|---|---|---|---|---|---|\n");
    for (const int64_t n : counts)
        if (int failed = run(root, n, brackets); failed) return failed;
    return 0;
}
