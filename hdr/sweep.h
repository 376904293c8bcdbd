// ============================================================================
//  flarelab hdr: SweepLens, SweepCamera, SweepCapture, SweepHeader, SweepBracketStats,
//                SweepFrame, Sweep, ReadSweepOptions, SweepWriteOptions, SweepWriter,
//                parseSweepManifest, formatSweepManifest, readSweepManifest, readSweep,
//                loadFrame, sweepFrameFileName, SweepFrameLog, parseSweepFrameLog,
//                formatSweepFrameLogRecord
// ============================================================================
//
// Sweeps on disk (DESIGN.md, "Formats"): a directory holding `manifest.json` and one HDR frame
// (OpenEXR, hdr/exr.h) per head angle, optionally with the raw brackets each frame was merged
// from. The manifest is the message flarelab.v1.SweepManifest (proto/sweep.proto) in the protobuf
// JSON mapping; this module turns it into the plain structs below and back, and validates it.
//
// Format versions. Version 1 lists every frame in manifest.json, which its writer rewrote whole
// after every frame: bytes written grew with the square of the frame count (a sweep of 10000
// frames wrote some 26 GB; README, "The daemon: measured"). Version 2, which version 3 extends,
// has the same manifest fields and adds an append-only frame log beside it, `frames.log`: a frame
// is listed by appending one record to the log; the manifest is rewritten with every frame
// ("compacted") only when the log has grown as long as the manifest, on resume, and when the
// writer finishes, after which the log is removed. Bytes written thus stay within a small
// multiple of the final manifest. The frames of a version 2 sweep are the manifest's, followed by
// the log's records. Version 3, which SweepWriter writes, keeps version 2's files and adds to
// `lens` the camera settings a simulated capture depends on (aperture blades and their rotation,
// the stop semi-aperture used, the coating of unspecified surfaces, the sensor size) and the
// prescription's file name and SHA-256, so that a score re-simulates exactly the capture.
// Version 4, which SweepWriter writes, adds the camera's raw format (`camera.raw_format`: mono or
// a Bayer pattern), so that a score knows whether the frames are monochrome or colour. Version 5
// adds the power of the rig light's own image (`camera.light_power_dn_s`), which a model carries
// on to its lab figures (predict/lab_figures.h). Every
// version is read; older sweeps are upgraded when resumed, their new fields left absent (nobody
// recorded them for the frames already taken).
//
// The frame log: the 21 bytes "flarelab frame log 1\n", then records, each a 4-byte little-endian
// payload length (1..kSweepMaxLogRecordBytes), the payload's CRC-32 (4 bytes, little-endian) and
// the payload, a flarelab.v1.FrameLogRecord (the frame's index and its manifest entry) in the
// protobuf binary encoding. A record that is cut short, fails its checksum or declares an
// impossible length ends the log: it is what a crash in the middle of an append leaves, it is
// ignored (Sweep::warnings says so, naming the byte offset) and the next writer cuts it off. A
// record whose index lies below the manifest's frame count must equal that frame (a crash between
// compaction and the log's truncation leaves such records); one beyond the next index is a gap,
// refused.
//
// Rules of the format (every version). A manifest breaking any of them is refused with an Error
// naming the manifest file and the field ("frames[3].angle_deg"):
//   - format_version is 1 to 5 (another version: Unsupported). Fields the reader does not know
//     are refused (ParseError), not skipped: a writer that adds a field raises the version, so a
//     misspelt field cannot silently lose data; so are version 3's lens fields and version 4's
//     camera.raw_format or version 5's camera.light_power_dn_s in an older manifest. Field names may be written as in the .proto
//     ("angle_deg", as the writer does) or in lowerCamelCase ("angleDeg"), as protobuf JSON
//     allows.
//   - camera.raw_format is one of mono, bayer-rggb, bayer-bggr, bayer-grbg, bayer-gbrg;
//     camera.light_power_dn_s > 0.
//   - every number is finite; exposure times, gain, focal length, f-number, pixel pitch, stop
//     semi-aperture and sensor width and height > 0; lens.aperture_blades 0 (a circle) or
//     3..kSweepMaxApertureBlades; lens.prescription_sha256 empty or 64 lowercase hex digits;
//     capture.from_deg <= capture.to_deg; capture.step_deg > 0; capture.width_px and height_px
//     1..32768; camera.bit_depth 1..32; strings hold no NUL (EXR attributes cannot).
//   - frame angles strictly increase and lie in [from_deg, to_deg] (give or take
//     kSweepAngleSlackDeg); they need not sit on the step grid.
//   - a frame's raw_files and brackets are empty or have one entry per exposure time; brackets[i]
//     .exposure_s equals exposure_times_s[i].
//   - file names (exr_file, raw_files) are relative paths inside the sweep directory: '/'
//     separated, no empty, "." or ".." component, no backslash or control character, at most 255
//     bytes per component; exr_file ends in ".exr"; no file is named twice, nor manifest.json.
// readSweep further checks every file (see there). Besides its frames a sweep directory may hold
// its products, which are not part of the manifest and not looked at: the folder `previews/`
// (PNG previews of the frames) and the fitted model `model.flm` with its description
// `model.txt` (isSweepProduct), and the writer's lock file `sweep.lock`. Other extra files in
// the directory that the manifest does not list are warnings (Sweep::warnings), not errors,
// unless ReadSweepOptions::extra_exr_files_are_errors: an interrupted writer leaves exactly such
// a file (its last frame, written but not yet listed), and the sweep up to it is still good.
//
// Every file of a sweep is opened without following a symbolic link and without waiting (a FIFO
// or a device in place of a manifest, log or frame is refused, never read), and its size is
// checked against a limit before it is read; a frame's EXR must declare the manifest's frame size
// before its pixels are allocated.
//
// SweepWriter keeps the sweep true at every instant and on disk in the right order: a frame's
// EXR (and its raw files, written by the caller) is flushed and its name flushed into its
// directory before the record that lists it is appended and flushed; a new directory's name is
// flushed into its parent. Every fsync is checked, and a failed one closes the writer for good
// (PostgreSQL's lesson, common/durable_io.h): the frames listed before it stay listed.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/image.h"
#include "common/result.h"
#include "hdr/exr.h"
#include "hdr/raw_frame.h"

namespace flarelab::hdr {

inline constexpr int kSweepFormatVersion = 5;        // what SweepWriter writes
inline constexpr int kSweepOldestFormatVersion = 1;  // the oldest version still read
inline constexpr char kSweepManifestFile[] = "manifest.json";
inline constexpr char kSweepFrameLogFile[] = "frames.log";
inline constexpr char kSweepLockFile[] = "sweep.lock";
// Largest manifest.json, and largest frames.log, read. A compacted manifest takes some 300 bytes
// per frame of a 3-exposure bracket and under 1.6 KB for 16 exposures with raw files kept, so the
// daemon's largest sweep (100000 frames) stays well within it.
inline constexpr int64_t kSweepMaxManifestBytes = int64_t{512} << 20;
inline constexpr int64_t kSweepMaxLogRecordBytes = int64_t{1} << 20;
inline constexpr int64_t kSweepMaxSide = int64_t{1} << 15;  // frame width and height, pixels
// How far a frame's angle may lie outside [from_deg, to_deg]: the writer computes angles as
// from_deg + i * step_deg, which may round past to_deg.
inline constexpr double kSweepAngleSlackDeg = 1e-6;
// The most aperture blades a lens may record: what optics::CameraDescription accepts.
inline constexpr int kSweepMaxApertureBlades = 64;

// The lens, and from version 3 the camera settings it was simulated with, precisely enough to
// simulate it again (drivers/lens_settings.h). A setting nobody recorded is absent: a sweep begun
// by an older version keeps them absent when it is resumed.
struct SweepLens {
    std::string description;  // also the frames' EXR attribute flarelab.lens
    std::string serial;
    std::optional<double> focal_length_mm;
    std::optional<double> f_number;
    // Version 3.
    std::optional<int> aperture_blades;  // 0: a circular stop; else 3..kSweepMaxApertureBlades
    std::optional<double> blade_rotation_deg;
    std::optional<double> stop_semi_aperture_mm;    // what the lens used: the table's or scaled
    std::optional<bool> coat_unspecified_surfaces;  // given the default coating, or left bare
    std::optional<double> sensor_width_mm;          // the sensor area the frames show
    std::optional<double> sensor_height_mm;
    std::string prescription_file;    // as given to the program; empty when none
    std::string prescription_sha256;  // of the file's bytes, 64 lowercase hex digits, or empty
    bool operator==(const SweepLens&) const = default;
};

struct SweepCamera {
    std::string description;  // also the frames' EXR attribute flarelab.camera
    std::string serial;
    std::optional<double> pixel_pitch_um;
    std::optional<int> bit_depth;
    // Version 4: what the sensor delivers, one channel or a colour mosaic (then the EXR frames
    // are demosaiced RGB); absent when not recorded.
    std::optional<RawFormat> raw_format;
    // Version 5: the rig light's own image, summed over the sensor, DN/s at unity gain; absent
    // when not known.
    std::optional<double> light_power_dn_s;
    bool operator==(const SweepCamera&) const = default;
};

// What the rig was asked to do.
struct SweepCapture {
    double from_deg = 0.0;
    double to_deg = 0.0;
    double step_deg = 0.2;
    double roll_deg = 0.0;                 // the light's roll, fixed for the sweep
    std::vector<double> exposure_times_s;  // the planned bracket; empty when not bracketed
    std::optional<double> gain;            // linear
    int64_t width_px = 0;                  // every frame's size
    int64_t height_px = 0;
    bool operator==(const SweepCapture&) const = default;
};

struct SweepHeader {
    int format_version = kSweepFormatVersion;
    std::string software_version;
    // When the sweep started, RFC 3339 ("2026-11-29T07:04:02Z"); empty when the manifest does not
    // say. SweepWriter::create fills in the current time when it is empty.
    std::string created_utc;
    SweepLens lens;
    SweepCamera camera;
    SweepCapture capture;
    bool operator==(const SweepHeader&) const = default;
};

// How one exposure of the bracket contributed to the merged frame.
struct SweepBracketStats {
    double exposure_s = 0.0;
    uint64_t samples_used = 0;
    uint64_t samples_clipped = 0;
    bool operator==(const SweepBracketStats&) const = default;
};

struct SweepFrame {
    double angle_deg = 0.0;
    std::string exr_file;                  // relative to the sweep directory
    std::vector<double> exposure_times_s;  // the bracket merged into this frame
    std::vector<std::string> raw_files;    // relative; none or one per exposure time
    std::string merge_method;
    std::vector<SweepBracketStats> brackets;  // none or one per exposure time
    bool operator==(const SweepFrame&) const = default;
};

struct Sweep {
    std::string directory;  // as given to the reader or writer; empty for parseSweepManifest
    SweepHeader header;
    std::vector<SweepFrame> frames;  // angles strictly increasing
    // What the reader found odd but not wrong (files the manifest does not list, a torn record at
    // the end of the frame log), one line each, naming the file. Not part of the manifest.
    std::vector<std::string> warnings;
    bool operator==(const Sweep&) const = default;
};

struct ReadSweepOptions {
    // An EXR file in the directory that the manifest does not list is an error instead of a
    // warning. Off by default: an interrupted writer leaves one (see the top of this file).
    bool extra_exr_files_are_errors = false;
    ExrReadOptions exr;  // limits for reading each frame
};

// Parses and validates manifest text (the rules at the top of this file; no file is looked at).
// `name` stands for the manifest in error messages. ParseError for malformed JSON, unknown fields
// and broken rules, Unsupported for another format_version.
Result<Sweep> parseSweepManifest(std::string_view json, const std::string& name = "<memory>");

// The manifest text of `sweep` (header and frames; directory and warnings are not part of it), as
// the writer stores it: protobuf JSON with the .proto's field names, indented. InvalidArgument,
// naming the field, when `sweep` breaks a rule, so whatever this returns parses back to `sweep`.
Result<std::string> formatSweepManifest(const Sweep& sweep);

// Reads and validates the sweep's frame list: `directory`/manifest.json and, from version 2 on, its
// frames.log: cheap, for listing a sweep. NotFound when there is no manifest, IoError when it or
// the log cannot be read, is not a regular file or exceeds kSweepMaxManifestBytes, else as
// parseSweepManifest and parseSweepFrameLog. Frame files are not looked at; `warnings` names a
// torn record at the end of the log, if any.
Result<Sweep> readSweepManifest(const std::string& directory);

// A frame log (see the top of this file), parsed.
struct SweepFrameLog {
    struct Record {
        uint64_t index = 0;
        SweepFrame frame;
    };
    std::vector<Record> records;  // in file order
    int64_t valid_bytes = 0;      // the magic and the whole records
    // What follows them (a record cut short by a crash): ignored, and why; 0 and empty if none.
    int64_t torn_bytes = 0;
    std::string torn;
};
inline constexpr std::string_view kSweepFrameLogMagic = "flarelab frame log 1\n";
// Parses the bytes of a frame log; `name` stands for the file in messages. An empty text is an
// empty log. ParseError for another file (wrong magic) or a whole record whose payload is not a
// FrameLogRecord; a bad record at the end is torn, not an error. Frames are not validated here
// (readSweepManifest does that against the manifest).
Result<SweepFrameLog> parseSweepFrameLog(std::string_view bytes, const std::string& name);
// One record of a frame log, as SweepWriter appends it.
std::string formatSweepFrameLogRecord(uint64_t index, const SweepFrame& frame);

// Reads and validates a whole sweep: the manifest as readSweepManifest, then every file it lists
// (one frame in memory at a time). Refused, with the manifest field and the file named:
//   - a missing file (NotFound), one that is not a regular file, or one that resolves (through
//     symbolic links) to a place outside the directory;
//   - a frame that readExr refuses (unreadable, corrupt, NaN or infinite pixels), whose size is not
//     capture.width_px x capture.height_px, or whose flarelab attributes disagree with the
//     manifest: angle_deg must equal the frame's angle, roll_deg the capture's roll, gain the
//     capture's gain, exposure_times_s, lens, camera and merge_method the manifest's, each
//     exactly (an attribute absent on one side must be absent or empty on the other; the angle
//     and roll must be present). flarelab.software_version and flarelab.extra.* are not compared.
//   - raw files are checked for existence and type only; their contents belong to hdr/raw_io.h.
// Then every file under the directory that the manifest does not list (temporary files of an
// interrupted write included) becomes a warning, or for an EXR file an error when
// options.extra_exr_files_are_errors.
Result<Sweep> readSweep(const std::string& directory, const ReadSweepOptions& options = {});

// Reads frame `index` (< sweep.frames.size(), else a bug) of a sweep from readSweep or
// readSweepManifest and checks it against the manifest as readSweep does. An EXR whose header
// declares another size than the capture's is refused before its pixels are allocated.
Result<ExrImage> loadFrame(const Sweep& sweep, size_t index, const ExrReadOptions& options = {});

// Whether `relative` (a '/'-separated path inside a sweep directory) is one of the sweep's
// products named at the top of this file: under previews/, or model.flm or model.txt.
bool isSweepProduct(std::string_view relative);
inline constexpr char kSweepPreviewsDir[] = "previews";
inline constexpr char kSweepModelFile[] = "model.flm";
inline constexpr char kSweepModelText[] = "model.txt";

// The file name SweepWriter gives frame `index` at `angle_deg`: "frame_00012_+2.4000deg.exr".
// The index keeps names unique and sorted whatever the angles.
std::string sweepFrameFileName(size_t index, double angle_deg);

// Frames whose shortest exposure saturated more than a fraction of the samples (from the frames'
// bracket statistics; frames without them are not looked at). There the merged radiance is only a
// lower bound: a fit takes the clipped light for flat background, so the capture should be taken
// again with shorter exposures. The light's own core saturates every exposure but covers far
// less than the default fraction.
struct ClippedFrames {
    double fraction = 0.0;  // the fraction looked for
    size_t frames = 0;      // frames over it
    size_t with_stats = 0;  // frames that have bracket statistics
    double worst_fraction = 0.0;
    double worst_angle_deg = 0.0;
    double shortest_exposure_s = 0.0;  // of the worst frame
};
inline constexpr double kClippedFraction = 0.01;
ClippedFrames clippedFrames(const Sweep& sweep, double fraction = kClippedFraction);
// One line for users, naming the frames, the worst and the remedy; empty when no frame is over.
std::string clippingWarning(const ClippedFrames& clipped, size_t total_frames);

struct SweepWriteOptions {
    ExrWriteOptions exr;
    // Append to the sweep already in the directory, whose lens, camera and capture settings must
    // equal the new header's (its software_version and created_utc are kept). A sweep of version 1
    // or 2 records none of version 3's lens fields, one of version 1 to 3 no camera.raw_format, one of
    // version 1 to 4 no camera.light_power_dn_s:
    // those are not compared and stay absent. Without
    // it a directory that holds a manifest or any EXR file is refused.
    bool resume = false;
    // The frame log is compacted into the manifest once it holds this many records and as many as
    // the manifest lists (so that compactions grow geometrically and bytes stay linear).
    size_t compact_after_frames = 256;
    // Test seams, to simulate a crash: called after a frame's EXR is in place and before its
    // record is appended to the frame log, and after a new manifest is on disk under its
    // temporary name and before it is renamed over the old one (a compaction).
    std::function<void()> after_frame_written;
    std::function<void()> before_manifest_replaced;
};

// Writes a sweep frame by frame. One writer per directory: the writer holds an exclusive lock
// (flock) on the directory and on its lock file `sweep.lock`, and a second writer is refused.
class SweepWriter {
public:
    // Creates `directory` (and its parents, each flushed into its parent) if needed, checks
    // `header` against the rules and writes a manifest with no frames (or, with options.resume,
    // takes the lock, reads the existing sweep, checks its header and compacts it: an older sweep
    // becomes version 4, a torn record at the end of the log is cut off). InvalidArgument naming
    // the field for a bad header, a resumed sweep whose header differs (naming the first field
    // that does), when the directory already holds a sweep or EXR files (without resume), another
    // writer, or a lock file that is not a regular file; IoError when the system refuses.
    static Result<SweepWriter> create(const std::string& directory,
                                      SweepHeader header,
                                      SweepWriteOptions options = {});

    SweepWriter(SweepWriter&&) noexcept;
    SweepWriter& operator=(SweepWriter&&) noexcept;
    ~SweepWriter();

    // Writes `image` as the next frame and lists it. `frame.exr_file` empty means
    // sweepFrameFileName(frames so far, angle); its raw_files must already be on disk, flushed.
    // Refused, with nothing changed on disk: a frame that breaks a rule (an angle not above the
    // last one, an image not capture.width_px x capture.height_px, ...), a raw file that is
    // missing or not a regular file, and an exr_file that already exists, whatever it holds (a
    // frame is never silently overwritten; after a crash, the unlisted frame the crash left must
    // be moved away: setAsideUnlisted). When the frame cannot be written or listed (a full disk),
    // the new EXR is removed again and the sweep stays as it was; when a flush to disk fails, the
    // writer is broken (broken() says why) and refuses every further frame. Returns the frame as
    // listed.
    //
    // The EXR carries OpenEXR's standard attributes `standard` (hdr/exr.h: capDate and utcOffset
    // where the caller knows when the bracket was taken, exrCaptureTime), and where it leaves
    // them unset, aperture (lens.f_number, when known) and expTime 1 s (a merged frame holds DN
    // per second at unity gain: what a 1 s exposure would read), and the channels that are only
    // lower bounds (`lower_bound`, hdr/merge.h lowerBounds) when given.
    Result<SweepFrame> addFrame(const ImageRGB& image,
                                SweepFrame frame,
                                const ExrStandardAttributes& standard = {},
                                std::span<const uint8_t> lower_bound = {});

    // Compacts the frame log into the manifest and removes the log: the finished sweep is its
    // manifest and frames. The writer takes no frames after it. IoError when it cannot (the log
    // then still lists the frames), and for a broken writer.
    Status finish();

    // Moves every file under the directory that the sweep does not list (and that is not its
    // manifest, log, lock file or one of its products) to the directory `to`, keeping relative
    // paths: what an interrupted writer leaves (the frame it wrote but did not list, temporary
    // files). Across file systems a file is copied, flushed and then unlinked; nothing in `to` is
    // ever overwritten, and `to` may not lie inside the sweep (compared by device and inode, not
    // by path). Returns the relative paths moved. Call it on a resumed sweep before addFrame.
    Result<std::vector<std::string>> setAsideUnlisted(const std::string& to);

    // The sweep as written so far (the manifest and the frame log on disk say the same).
    const Sweep& sweep() const { return sweep_; }
    // Why the writer refuses to write (a flush to disk failed); empty while it works.
    const std::string& broken() const;

private:
    struct State;
    SweepWriter(Sweep sweep, SweepWriteOptions options, std::unique_ptr<State> state);
    Status compact(bool remove_log);
    Error breakWith(const std::string& why);

    Sweep sweep_;
    SweepWriteOptions options_;
    std::unique_ptr<State> state_;
};

}  // namespace flarelab::hdr
