// ============================================================================
//  flarelab fit: TrackLinkOptions, TrackLinkStats, trackLinkCost, linkTracks
// ============================================================================
//
// Global linking of a sweep's track fragments (issue 20, item 3). The passes of fitSweepFrames
// follow ghosts frame to frame; where a ghost fades into the noise for a few frames, hides
// behind another or its detection fails, its track ends and a new one starts a few frames
// later. Each fragment is then compressed on its own, and the model cross-fades between the two
// over a capture step at their ends. Here every fragment's end is weighed against every other
// fragment's start over the whole sweep at once, and the links are the minimum-cost assignment
// between ends and starts (the Hungarian method), with "no link" at the gate's cost, so a chain
// of fragments of one ghost becomes one track and two different ghosts are never joined just
// because one of them ended near the other.
//
// The cost of a link A -> B (B starting after A ends, or at most max_overlap_frames before):
// each side is extrapolated across the gap by a least-squares line in the angle through its
// `history` samples nearest the gap, and compared with the other side's first sample there; in
// both directions, the larger of the two is the cost. A comparison is the largest of
//   |centre difference| / (position_radii * size)   the centre, in ghost sizes (ghostSize)
//   |ln size ratio| / ln(size_ratio)                 the size
//   |ln energy ratio| / ln(energy_ratio)             the light it puts in the frame (a rough
//                                                    estimate from shape and shading)
// so a cost below 1 means every feature agrees within its tolerance. Fragments that start from
// a lens's ghost paths (GhostTrack::path >= 0) keep their identity and take no part.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "common/result.h"

namespace flarelab::fit {

struct GhostTrack;  // fit/sweep_fit.h
struct TrackSample;

struct TrackLinkOptions {
    // Off by default: measured on five lenses (docs/track-linking.md), joining fragments as they
    // were fitted lowers the track count but not the model's error (the Heliar fitted at every
    // frame: 103 tracks to 78, held out 0.084 to 0.096); `flarelab fit --link` turns it on.
    bool enabled = false;
    int max_gap_frames = 3;       // fitted frames between A's last and B's first, >= 0
    int max_overlap_frames = 3;   // frames both may hold (a track followed back over another), >= 0
    int history = 6;              // samples each side's extrapolation uses, >= 1
    double position_radii = 0.6;  // > 0
    double size_ratio = 1.5;      // > 1
    double energy_ratio = 4.0;    // > 1
    double gate = 1.0;            // links costing more are not made, > 0
};

Status checkTrackLinkOptions(const TrackLinkOptions& options);

struct TrackLinkStats {
    int64_t fragments = 0;   // tracks that took part
    int64_t candidates = 0;  // pairs within the gap and overlap limits
    int64_t links = 0;       // links made
};

// The cost of linking `from` to `to` (see above), or nullopt when `to` does not start after
// `from` within the limits (`frame_angles_deg`: the fitted frames' angles, ascending).
std::optional<double> trackLinkCost(const GhostTrack& from,
                                    const GhostTrack& to,
                                    std::span<const double> frame_angles_deg,
                                    const TrackLinkOptions& options);

// Adds `from`'s samples to `into`; where both hold a frame (the same angle) the sample of lower
// cost stays. `from` is left empty, `into` unsorted. How pieces of one ghost become one track,
// here and for the pieces of one ghost path (fit/sweep_fit.cpp).
void mergeTrackSamples(std::vector<TrackSample>& into, std::vector<TrackSample>& from);

// The tracks with every chain of linked fragments joined into one (the earliest fragment's id;
// where two fragments hold the same frame the sample of lower cost stays), by id. Tracks with a
// path, and all of them when linking is off, pass unchanged.
std::vector<GhostTrack> linkTracks(std::vector<GhostTrack> tracks,
                                   std::span<const double> frame_angles_deg,
                                   const TrackLinkOptions& options,
                                   TrackLinkStats* stats = nullptr);

}  // namespace flarelab::fit
