// A small flare model for the prediction's tests: one disc ghost (radius 3 mm, inner 4, border 2,
// soft inside, sharp outside) that moves away from the image centre on the far side of the light
// as the light's angle grows (centre x = -1.5 mm per degree), the way a real ghost does. Fitted at
// every 0.5 deg from 0 to 10 deg on a 36 x 24 mm sensor of 72 x 48 pixels, f/8, roll 0.
#pragma once

#include <gtest/gtest.h>

#include "fit/model_file.h"
#include "fit/sweep_fit.h"
#include "render/ghost_shape.h"

namespace flarelab::predict::testing {

// keep_samples: the model keeps the per-frame values (SweepFitOptions::keep_samples).
inline fit::FlareModel movingDiscModel(int ghosts = 1, bool keep_samples = false) {
    fit::FlareModel shell;
    shell.software_version = "flarelab test";
    shell.lens.description = "moving disc";
    shell.lens.f_number = 8.0;
    shell.lens.focal_length_mm = 50.0;
    shell.lens.sensor_width_mm = 36.0;
    shell.lens.sensor_height_mm = 24.0;
    shell.capture.from_deg = shell.valid_from_deg = 0.0;
    shell.capture.to_deg = shell.valid_to_deg = 10.0;
    shell.capture.step_deg = 0.5;
    shell.capture.width_px = 72;
    shell.capture.height_px = 48;
    shell.capture.camera = "test camera";
    fit::SweepFitResult tracks;
    tracks.frame_count = 21;
    for (int g = 0; g < ghosts; ++g) {
        fit::GhostTrack track;
        track.id = g + 1;
        for (int i = 0; i <= 20; ++i) {
            const double angle = 0.5 * i;
            fit::GhostState disc;
            disc.shape = render::circleGhostShape(-1.5 * angle * (g + 1), 0.0, 3.0);
            disc.shading.border_rgb = {2.0, 2.0, 2.0};
            disc.shading.inner_rgb = {4.0, 4.0, 4.0};
            disc.shading.inner_falloff_mm = 0.5;
            disc.shading.outer_falloff_mm = 0.05;
            track.samples.push_back({angle, disc, 0.0});
        }
        tracks.tracks.push_back(track);
    }
    if (ghosts == 0) return shell;
    fit::SweepFitOptions options;
    options.keep_samples = keep_samples;
    auto built = fit::buildModel(tracks, shell, options);
    EXPECT_TRUE(built) << built.error().message;
    return built ? *built : shell;
}

}  // namespace flarelab::predict::testing
