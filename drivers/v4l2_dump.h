// ============================================================================
//  flarelab drivers: V4l2DeviceDump, V4l2DumpControl, V4l2DumpFormat, V4l2DumpFrameSize,
//                    V4l2DumpPixFormat, parseV4l2Dump, loadV4l2Dump
// ============================================================================
//
// A V4L2 device as `v4l2-ctl --all` and `v4l2-ctl --list-formats-ext` (v4l-utils 1.22, Debian
// 12) print it: driver, card, bus, capabilities, the current capture format, the frame rate,
// every control with its range, value and flags, and every capture format with its frame sizes.
// The output of both commands may be given in one text, one after the other (either alone
// parses too; the fields of the missing one stay empty). It serves the playback device
// (v4l2_device.h), which answers the camera's ioctls from a recorded device, and the tests that
// check the camera's control mapping and format choice against real devices' dumps
// (tests/data/v4l2/).
//
// What is read, by section:
//   "Driver Info:"                     Driver name, Card type, Bus info, Driver version,
//                                      Capabilities, Device Caps
//   "Format Video Capture:"            Width/Height, Pixel Format, Field, Bytes per Line,
//                                      Size Image, Colorspace
//   "Streaming Parameters Video Capture:"   Frames per second (its exact fraction)
//   "<Class> Controls" and the control lines under it:
//        name 0xID (type) : min=.. max=.. step=.. default=.. value=.. flags=a, b
//        and the "N: name" menu lines under a menu or integer menu control
//   "ioctl: VIDIOC_ENUM_FMT" and what follows: "[i]: 'FCC ' (description, flags)", "Size:"
//        lines (Discrete WxH, Stepwise WxH - WxH with step W/H, Continuous WxH - WxH) and their
//        "Interval: Discrete T s" lines.
// Other sections (tuner, media, overlay, selection, ...) are skipped. Inside the sections that
// are read, a line that does not follow the grammar is a ParseError naming the source and line
// ("vivid.txt:12: ..."), as is a column-0 line that is neither a section nor a control class.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/result.h"

namespace flarelab::drivers {

struct V4l2DumpControl {
    std::string name;  // as v4l2-ctl writes it: "exposure_time_absolute"
    uint32_t id = 0;
    std::string type;  // "int", "int64", "bool", "menu", "intmenu", "bitmask", "button", "str", ...
    std::string control_class;  // the heading above it: "Camera Controls"
    int64_t minimum = 0;
    int64_t maximum = 0;
    int64_t step = 0;  // 0 where v4l2-ctl prints none (bool, menu)
    int64_t default_value = 0;
    std::optional<int64_t> value;    // none for strings, arrays, areas and other compound types
    std::vector<std::string> flags;  // "inactive", "read-only", "volatile", ...; unknown bits as
                                     // v4l2-ctl prints them ("0x00000800")
    std::vector<std::pair<int64_t, std::string>> menu;  // index, item (menu) or value text
    bool array = false;                                 // has dims=[..]
    int line = 0;                                       // where it was read

    bool hasFlag(std::string_view flag) const;
};

struct V4l2DumpFrameSize {
    enum class Kind { Discrete, Stepwise, Continuous };
    Kind kind = Kind::Discrete;
    uint32_t width = 0;  // Discrete
    uint32_t height = 0;
    uint32_t min_width = 0, max_width = 0, step_width = 1;  // Stepwise and Continuous
    uint32_t min_height = 0, max_height = 0, step_height = 1;
    std::vector<double> intervals_s;  // the discrete frame intervals listed under it
};

struct V4l2DumpFormat {
    uint32_t fourcc = 0;
    std::string description;         // "16-bit Greyscale"
    std::vector<std::string> flags;  // "compressed", "emulated", "csc-colorspace", ...
    std::vector<V4l2DumpFrameSize> sizes;
    int line = 0;

    bool hasFlag(std::string_view flag) const;
};

struct V4l2DumpPixFormat {
    uint32_t width = 0;
    uint32_t height = 0;
    uint32_t fourcc = 0;
    std::string field;  // "None"
    uint32_t bytes_per_line = 0;
    uint32_t size_image = 0;
    std::string colorspace;  // "sRGB", "Raw"
};

struct V4l2DeviceDump {
    std::string source;  // the file or name it was parsed from

    bool has_driver_info = false;
    std::string driver;
    std::string card;
    std::string bus_info;
    uint32_t driver_version = 0;  // KERNEL_VERSION(a, b, c) of "a.b.c"
    uint32_t capabilities = 0;
    uint32_t device_caps = 0;

    std::optional<V4l2DumpPixFormat> format;  // "Format Video Capture"
    // "Frames per second: 5.000 (5/1)": the time per frame as a fraction, 1/5 s.
    std::optional<std::pair<uint32_t, uint32_t>> time_per_frame;

    std::vector<V4l2DumpControl> controls;  // in the order printed

    bool has_format_list = false;         // an "ioctl: VIDIOC_ENUM_FMT" part was read
    std::string format_list_type;         // its "Type:": "Video Capture", "... Multiplanar"
    std::vector<V4l2DumpFormat> formats;  // capture formats, in index order

    // nullptr when the dump has no control or format of that id.
    const V4l2DumpControl* control(uint32_t id) const;
    const V4l2DumpFormat* findFormat(uint32_t fourcc) const;
};

// ParseError "<source>:<line>: <what>" for a line the grammar above does not allow, a number out
// of its type's range, a menu line without a menu control above it, a format index out of order
// or a size or interval line without a format above it.
Result<V4l2DeviceDump> parseV4l2Dump(std::string_view text, std::string_view source);

// Reads and parses a file (at most 16 MiB): NotFound or IoError naming the path, else as above.
Result<V4l2DeviceDump> loadV4l2Dump(const std::string& path);

}  // namespace flarelab::drivers
