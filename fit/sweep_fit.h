// ============================================================================
//  flarelab fit: SweepFitOptions, TrackSample, GhostTrack, SweepFitProgress, SweepFitResult,
//                FrameSource, fitSweepFrames, buildModel, modelLens, fitSweep
// ============================================================================
//
// A whole sweep fitted with no human input (chapters 7.3 and 10.3 of the thesis, automated):
//   1. Start: detect ghosts in a few frames spread over the sweep and start where the most are
//      found apart (at small angles the ghosts are concentric and merge into one blob). The
//      brightest light those frames show sets a floor under what counts as the light (a
//      hundredth of it): where the light is out of view, the brightest blob is a ghost.
//   2. Forward from the start to the last frame, then backward from the start to the first (the
//      reverse pass): in each frame, predict every live track's parameters by a low-order least
//      squares polynomial through its last `history` fitted frames (§7.3), match the predictions
//      to the frame's detections, start new tracks from unmatched detections that no live ghost
//      explains, fit all of them together (fitFrame, the predictions as priors), and end tracks
//      whose ghost has faded into the noise, is less than a tenth in view, collapsed to a speck,
//      ran off (brighter than anything in the frame), fell below min_energy_fraction of the
//      frame's ghost light, or went unmatched for max_missed frames. The sky is the lowest
//      background of the probed frames; light above it everywhere in a frame is a ghost larger
//      than the frame (a veil), followed like the others.
//      With the lens's ghost paths as seeds (SweepFitOptions::path_seeds), tracks start from the
//      seeds instead of from detections (a veil too is a path), one per path, and a path's
//      outline is its shape's prior.
//   3. Tracks born after the start are also followed back from where they were born, at most
//      max_extension_frames (a ghost that separates from another was there before it was
//      detected); the other ghosts stored there are held fixed. Optionally (SweepFitOptions::
//      link) the fragments of one ghost (a track that ended and another that started a few
//      frames later, where the ghost faded, hid or went undetected) are then linked over the
//      whole sweep at once, as the minimum-cost assignment of fragments' ends to starts
//      (fit/track_link.h).
//   4. Compression (buildModel): each parameter of each track as a Chebyshev series of the angle
//      (polyfit.h), its degree chosen by cross-validation unless fixed (a fixed degree above a
//      track's frames less one is capped there), frames more than four
//      robust sigmas off the first fit down-weighted; intensities as logs floored at a
//      thousandth of the track's brightest; each parameter's bounds the range its frames
//      spanned, widened by a quarter (evaluation clamps to them). Tracks with fewer than
//      min_track_frames frames are noise and are not modelled.
//   5. Shading refit (fitSweep): the compressed shading series fitted to the frames' pixels, the
//      shapes held (fit/shading_refit.h; per-frame shading is too loosely determined to be
//      compressed parameter by parameter); then, with ShadingRefitOptions::shape_passes, every
//      series of each ghost, its shape's too, fitted to the same pixels.
// Only one frame is held in memory at a time, whatever the sweep's length.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "common/result.h"
#include "fit/detect.h"
#include "fit/frame.h"
#include "fit/frame_fit.h"
#include "fit/model_file.h"
#include "fit/polyfit.h"
#include "fit/shading_refit.h"
#include "fit/track_link.h"
#include "hdr/sweep.h"

namespace flarelab::fit {

// A ghost path of the lens's prescription at a head angle, where the optics core puts its ghost
// (`fit --lens FILE --paths`, drivers/path_seeds.h): an outline around what its rays light.
struct PathSeed {
    int64_t path = 0;  // the path's identity: the same number at every angle
    render::GhostShapeParams shape;
};
// The seeds at a head angle; called from two threads at once (the passes run side by side).
using PathSeeder = std::function<Result<std::vector<PathSeed>>(double angle_deg)>;

struct SweepFitOptions {
    DetectOptions detect;
    FrameFitOptions frame;
    PolyFitOptions poly;
    int history = 6;            // fitted frames a prediction uses, >= 1
    int prediction_degree = 2;  // of the prediction polynomial, 0..3 (capped by the history)
    double match_radius = 0.6;  // a detection matches a prediction within this many ghost radii
    // A detection starts no new track when a ghost lies within this (centre distance plus radius
    // difference over the radius): overlapping ghosts of similar place and size are distinct.
    double duplicate_radius = 0.12;
    int max_missed = 3;        // frames a track may go undetected before it ends, >= 0
    int min_track_frames = 5;  // shorter tracks are not modelled (capped by the sweep length)
    // Keep each parameter's per-frame values in the model (ModelParameter::sample_values), for a
    // report to show the series against its data; a model about 3 to 5 times larger.
    bool keep_samples = false;
    // -1: chosen automatically, by probing start_probes frames, which also set the sky and the
    // light's floor (step 1 above); a frame given here skips the probes, and with them both.
    int start_frame = -1;
    int start_probes = 9;  // frames detected to choose the start, >= 1
    // The start is the probe nearest the sweep's middle among those showing at least this share
    // of the most candidates any probe shows, (0, 1]; 1: the most (the one nearest the middle
    // of those). A start near one end leaves one pass to run alone for most of the sweep.
    double start_min_share = 1.0;
    int max_ghosts = 64;  // live tracks at most, >= 1
    // A ghost whose light in a frame is below this fraction of all the ghosts' light there ends:
    // it changes no figure a user measures, and the model stays small. 0 keeps every ghost.
    double min_energy_fraction = 0.003;
    // Full detection (overlapping circles included) in the start frame and every this many
    // frames, and wherever no track is live; in between only the sky and the light are measured
    // and the tracks' predictions carry the fit. >= 1.
    int detect_every = 5;
    // A track born away from the start is followed back at most this many frames, >= 0.
    int max_extension_frames = 3;
    // Step 3b, when enabled (off by default): fragments of one ghost linked over the whole
    // sweep (track_link.h); not the tracks of path seeds, which keep their path's identity.
    TrackLinkOptions link;
    // Step 5 (fitSweep): the compressed shading series refitted to the frames.
    ShadingRefitOptions shading;
    // fitSweep fits every this many frames of the sweep (the first, then every k-th), >= 1: a
    // sparse fit, whose left-out frames the score holds out (`fit --every K`, `score --sweep`).
    // The model's capture step is the sweep's times k.
    int frame_stride = 1;
    // fitSweep keeps the frames it has read in memory, up to this many bytes (the ones used
    // longest ago are let go first), so that the passes, the tracks followed back and the
    // shading refit decode each frame once: a 640 x 427 frame takes 3.3 MB. 0 reads every time.
    int64_t frame_cache_bytes = int64_t{1} << 30;
    // When set, tracks start only from these (one per path, where its ghost is in view and lit
    // above the noise, its shading read off the frame) instead of from detections, ghosts of two
    // paths are never ended as duplicates of each other, and the pieces of one path become one
    // track. Empty: the tracks come from detections alone (a lens with no prescription).
    PathSeeder path_seeds;
    // In frames detected in full, detect again in what the fitted ghosts leave (the frame less
    // their model) and start tracks from what no ghost stands for (processFrame). Off by default.
    bool residual_detection = false;
    // When set and it becomes true, the fit stops before its next frame with an Unsupported
    // error "sweep fit: cancelled" (a daemon's job being cancelled or the daemon stopping).
    const std::atomic<bool>* cancel = nullptr;
};

struct TrackSample {
    double angle_deg = 0.0;
    GhostState state;
    double cost = 0.0;  // the ghost's final cost in that frame
};

struct GhostTrack {
    int64_t id = 0;
    int64_t path = -1;                 // the PathSeed::path it was started from, -1 without seeds
    std::vector<TrackSample> samples;  // ascending angle, one per frame
};

struct SweepFitProgress {
    int64_t frames_done = 0;
    int64_t frames_total = 0;  // frames fitted, including reverse passes (may grow)
    double angle_deg = 0.0;
    int live_ghosts = 0;
};

// Where a sweep fit's time went, wall clock, ms. The forward and backward passes run side by
// side, and their load, detect and fit times are summed over both, so the stages may add up to
// more than the whole (track_ms is what the whole leaves, 0 when nothing is left).
struct SweepFitStages {
    double load_ms = 0.0;    // frames read from disk and mapped (the tracking passes)
    double detect_ms = 0.0;  // detectGhosts, start probes included
    // Frames loaded and detected ahead of each pass on another thread (FrameSource::prefetch),
    // while the pass fits the frame before; load_ms and detect_ms then hold what the pass
    // itself still waited for.
    double ahead_ms = 0.0;
    double fit_ms = 0.0;       // fitFrame in the forward and backward passes
    double extend_ms = 0.0;    // fitFrame following tracks born away from the start back
    double seed_ms = 0.0;      // SweepFitOptions::path_seeds and reading the seeds off the frames
    double link_ms = 0.0;      // linking the tracks' fragments (track_link.h)
    double track_ms = 0.0;     // the rest of the passes: prediction, matching, track ends
    double compress_ms = 0.0;  // buildModel: the Chebyshev series (fitSweep only)
    double shading_ms = 0.0;   // refitShading less its shape passes, frame loads included
    double shape_ms = 0.0;     // refitShading's shape passes (fitSweep only)
    double total_ms = 0.0;     // the whole call
};

struct SweepFitResult {
    std::vector<GhostTrack> tracks;  // by id
    int start_frame = 0;
    // The sky every ghost sits on, per channel (the lowest background of the probed frames).
    std::array<double, 3> sky{};
    // The detection options the frames were detected with: SweepFitOptions::detect with
    // min_light_peak raised to a hundredth of the brightest light the probed frames show, so
    // that where the light is out of view a small bright ghost is not taken for it (and left
    // out). The shading refit detects with the same.
    DetectOptions detect;
    // The disc around the light the detection left out of each frame processed, by increasing
    // angle (radius 0 where no light was found); buildModel records it (ModelCapture).
    std::vector<ModelLightDisc> light_discs;
    int64_t frame_count = 0;       // frames in the sweep (caps min_track_frames in buildModel)
    int64_t frames_fitted = 0;     // fitFrame calls
    int64_t fragments_linked = 0;  // links made between track fragments (track_link.h)
    int64_t evaluations = 0;
    double time_ms = 0.0;  // steps 1 to 3
    SweepFitStages stages;
    // The shape refit (ShadingRefitOptions::shape_passes; fitSweep only): ghosts whose shapes it
    // refitted, and those it left as compressed for an outline mostly outside their frames.
    int shape_refitted = 0;
    int shape_unobserved = 0;
};

// Where frames come from: their count, angles (strictly increasing) and loader.
struct FrameSource {
    std::vector<double> angles_deg;
    std::function<Result<FitFrame>(size_t)> load;
    // Optional: detectGhosts of frame `index` (as `load` gave it) with these options, which the
    // source may remember (fitSweep's does, with its frames); empty: detected every time.
    std::function<Result<FrameDetection>(size_t index, const FitFrame&, const DetectOptions&)>
        detect;
    // Optional: frame `index` read and detected with these options into the source's memory, so
    // that the load and detect of it that follow return at once (fitSweep's source keeps its
    // frames and their detections); errors are left for the load to report. The fitter calls it
    // from another thread, never at the same time as load, detect or another prefetch.
    std::function<void(size_t index, const DetectOptions&)> prefetch;
};

Status checkSweepFitOptions(const SweepFitOptions& options);

// Steps 1 to 3. A progress callback (may be empty) is called after every fitted frame.
Result<SweepFitResult> fitSweepFrames(
    const FrameSource& frames,
    const SweepFitOptions& options,
    const std::function<void(const SweepFitProgress&)>& progress = {});

// Step 4: the model of the tracks, with `model`'s metadata (lens, capture, valid range) kept and
// its ghosts replaced. InvalidArgument when the metadata does not validate.
Result<FlareModel> buildModel(const SweepFitResult& result,
                              FlareModel model,
                              const SweepFitOptions& options);

// The model's lens from the sweep's: description, f-number, focal length, the camera settings
// and prescription a version 3 manifest records (absent ones stay absent), and the sensor size
// the fit maps pixels with.
ModelLens modelLens(const hdr::SweepLens& lens, double sensor_width_mm, double sensor_height_mm);

// All of it (steps 1 to 5) for a sweep on disk: frames loaded one at a time, the metadata from the
// manifest (lens with its camera settings, capture, sensor size, camera), the valid range the
// sweep's angles. The sensor size is sweepSensorSize's: the manifest's when it records one (a
// given one must agree), else the one given, else from the pixel pitch (both <= 0: none given).
// InvalidArgument for a sweep whose frames (every frame_stride-th) do not span two angles (a model
// needs at least two).
Result<FlareModel> fitSweep(const hdr::Sweep& sweep,
                            double sensor_width_mm,
                            double sensor_height_mm,
                            const SweepFitOptions& options,
                            const std::function<void(const SweepFitProgress&)>& progress = {},
                            SweepFitResult* result = nullptr);

}  // namespace flarelab::fit
