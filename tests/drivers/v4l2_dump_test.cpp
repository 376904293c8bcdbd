#include "drivers/v4l2_dump.h"

#include <gtest/gtest.h>
#include <linux/videodev2.h>

#include <fstream>
#include <sstream>

#include "drivers/v4l2_formats.h"
#include "tests/test_paths.h"

namespace flarelab::drivers {
namespace {

std::string dumpPath(const std::string& name) {
    return flarelab::testing::sourcePath("tests/data/v4l2/" + name);
}

V4l2DeviceDump load(const std::string& name) {
    auto dump = loadV4l2Dump(dumpPath(name));
    EXPECT_TRUE(dump) << (dump ? "" : dump.error().message);
    return dump ? std::move(*dump) : V4l2DeviceDump{};
}

std::string readText(const std::string& name) {
    std::ifstream in(dumpPath(name));
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

Error parseError(const std::string& text) {
    auto dump = parseV4l2Dump(text, "bad.txt");
    EXPECT_FALSE(dump) << text;
    return dump ? Error{} : dump.error();
}

constexpr const char* kHeader =
    "Driver Info:\n"
    "\tDriver name      : x\n"
    "\tCapabilities     : 0x84200001\n";

TEST(ParseV4l2Dump, ReadsVividsDriverInfoFormatAndFrameRate) {
    const V4l2DeviceDump d = load("vivid-default.txt");
    EXPECT_TRUE(d.has_driver_info);
    EXPECT_EQ(d.driver, "vivid");
    EXPECT_EQ(d.card, "vivid");
    EXPECT_EQ(d.bus_info, "platform:vivid-000");
    EXPECT_EQ(d.driver_version, (6u << 16) | (1u << 8) | 192u);
    EXPECT_EQ(d.capabilities, 0x85230005u);
    EXPECT_EQ(d.device_caps, 0x05230005u);
    ASSERT_TRUE(d.format);
    EXPECT_EQ(d.format->width, 640u);
    EXPECT_EQ(d.format->height, 360u);
    EXPECT_EQ(d.format->fourcc, V4L2_PIX_FMT_YUYV);
    EXPECT_EQ(d.format->bytes_per_line, 1280u);
    EXPECT_EQ(d.format->size_image, 460800u);
    EXPECT_EQ(d.format->field, "None");
    ASSERT_TRUE(d.time_per_frame);  // "5.000 (5/1)" frames per second
    EXPECT_EQ(d.time_per_frame->first, 1u);
    EXPECT_EQ(d.time_per_frame->second, 5u);
}

TEST(ParseV4l2Dump, ReadsEveryKindOfControlVividHas) {
    const V4l2DeviceDump d = load("vivid-default.txt");
    const V4l2DumpControl* gain = d.control(V4L2_CID_GAIN);
    ASSERT_NE(gain, nullptr);
    EXPECT_EQ(gain->name, "gain");
    EXPECT_EQ(gain->type, "int");
    EXPECT_EQ(gain->control_class, "User Controls");
    EXPECT_EQ(gain->minimum, 0);
    EXPECT_EQ(gain->maximum, 255);
    EXPECT_EQ(gain->step, 1);
    EXPECT_EQ(gain->default_value, 100);
    ASSERT_TRUE(gain->value);
    EXPECT_TRUE(gain->hasFlag("inactive"));
    EXPECT_TRUE(gain->hasFlag("volatile"));

    const V4l2DumpControl* menu = d.control(0x0098f904);
    ASSERT_NE(menu, nullptr);
    EXPECT_EQ(menu->type, "menu");
    EXPECT_EQ(menu->value, 3);
    ASSERT_EQ(menu->menu.size(), 3u);
    EXPECT_EQ(menu->menu[1], (std::pair<int64_t, std::string>{3, "Menu Item 3"}));

    const V4l2DumpControl* intmenu = d.control(0x0098f907);
    ASSERT_NE(intmenu, nullptr);
    EXPECT_EQ(intmenu->menu.size(), 7u);
    EXPECT_EQ(intmenu->menu.back().second, "42 (0x2a)");

    const V4l2DumpControl* wide = d.control(0x0098f903);
    ASSERT_NE(wide, nullptr);
    EXPECT_EQ(wide->minimum, std::numeric_limits<int64_t>::min());
    EXPECT_EQ(wide->maximum, std::numeric_limits<int64_t>::max());

    const V4l2DumpControl* bitmask = d.control(0x0098f906);
    ASSERT_NE(bitmask, nullptr);
    EXPECT_EQ(bitmask->maximum, 0x80402010);
    EXPECT_EQ(bitmask->value, -2147475456);

    const V4l2DumpControl* text = d.control(0x0098f905);
    ASSERT_NE(text, nullptr);
    EXPECT_FALSE(text->value);  // a string
    const V4l2DumpControl* array = d.control(0x0098f909);
    ASSERT_NE(array, nullptr);
    EXPECT_TRUE(array->array);
    EXPECT_FALSE(array->value);
    const V4l2DumpControl* dynamic = d.control(0x0098f90d);
    ASSERT_NE(dynamic, nullptr);
    EXPECT_TRUE(dynamic->hasFlag("0x00000800"));  // a flag v4l2-ctl 1.22 has no name for
    const V4l2DumpControl* pattern = d.control(0x00f0f000);
    ASSERT_NE(pattern, nullptr);
    EXPECT_EQ(pattern->control_class, "Vivid Controls");
    EXPECT_EQ(pattern->menu.size(), 22u);
    EXPECT_EQ(d.control(V4L2_CID_EXPOSURE_ABSOLUTE), nullptr);
}

TEST(ParseV4l2Dump, ReadsVividsFormatListWithSizesAndIntervals) {
    const V4l2DeviceDump d = load("vivid-default.txt");
    EXPECT_TRUE(d.has_format_list);
    EXPECT_EQ(d.format_list_type, "Video Capture");
    ASSERT_EQ(d.formats.size(), 83u);
    EXPECT_EQ(d.formats[0].fourcc, V4L2_PIX_FMT_YUYV);
    EXPECT_EQ(d.formats[0].description, "YUYV 4:2:2");
    EXPECT_TRUE(d.formats[0].hasFlag("csc-colorspace"));
    const V4l2DumpFormat* be = d.findFormat(V4L2_PIX_FMT_Y16_BE);
    ASSERT_NE(be, nullptr);
    EXPECT_EQ(be->description, "16-bit Greyscale BE");
    const V4l2DumpFormat* y16 = d.findFormat(V4L2_PIX_FMT_Y16);
    ASSERT_NE(y16, nullptr);
    ASSERT_EQ(y16->sizes.size(), 6u);
    EXPECT_EQ(y16->sizes[0].kind, V4l2DumpFrameSize::Kind::Discrete);
    EXPECT_EQ(y16->sizes[0].width, 320u);
    EXPECT_EQ(y16->sizes[0].height, 180u);
    EXPECT_EQ(y16->sizes[5].width, 3840u);
    ASSERT_EQ(y16->sizes[0].intervals_s.size(), 12u);
    EXPECT_DOUBLE_EQ(y16->sizes[0].intervals_s[0], 1.0);
    EXPECT_DOUBLE_EQ(y16->sizes[0].intervals_s[11], 0.017);
    for (uint32_t f : {V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y10, V4L2_PIX_FMT_Y12, V4L2_PIX_FMT_SBGGR8,
                       V4L2_PIX_FMT_SRGGB10, V4L2_PIX_FMT_SGRBG12, V4L2_PIX_FMT_SGBRG16})
        EXPECT_NE(d.findFormat(f), nullptr) << fourccText(f);
}

TEST(ParseV4l2Dump, ReadsTheStateAfterARawFormatWasSet) {
    const V4l2DeviceDump d = load("vivid-y16.txt");
    ASSERT_TRUE(d.format);
    EXPECT_EQ(d.format->fourcc, V4L2_PIX_FMT_Y16);
    EXPECT_EQ(d.format->width, 320u);
    EXPECT_EQ(d.format->bytes_per_line, 640u);
    EXPECT_EQ(d.control(V4L2_CID_AUTOGAIN)->value, 0);
    EXPECT_EQ(d.control(V4L2_CID_GAIN)->value, 64);
    EXPECT_FALSE(d.control(V4L2_CID_GAIN)->hasFlag("inactive"));
}

TEST(ParseV4l2Dump, ReadsAMultiplanarNodeWithoutASinglePlanarFormat) {
    const V4l2DeviceDump d = load("vivid-multiplanar.txt");
    EXPECT_TRUE(d.device_caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE);
    EXPECT_FALSE(d.device_caps & V4L2_CAP_VIDEO_CAPTURE);
    EXPECT_FALSE(d.format);  // "Format Video Capture Multiplanar" is another section
    EXPECT_EQ(d.format_list_type, "Video Capture Multiplanar");
    EXPECT_FALSE(d.formats.empty());
}

TEST(ParseV4l2Dump, ReadsTheHandWrittenDumps) {
    const V4l2DeviceDump uvc = load("uvc-webcam-handwritten.txt");
    EXPECT_EQ(uvc.driver, "uvcvideo");
    ASSERT_NE(uvc.control(V4L2_CID_EXPOSURE_AUTO), nullptr);
    EXPECT_EQ(uvc.control(V4L2_CID_EXPOSURE_AUTO)->menu.size(), 2u);
    EXPECT_EQ(uvc.control(V4L2_CID_EXPOSURE_ABSOLUTE)->control_class, "Camera Controls");
    ASSERT_EQ(uvc.formats.size(), 2u);
    EXPECT_TRUE(uvc.formats[1].hasFlag("compressed"));
    EXPECT_EQ(uvc.formats[1].description, "Motion-JPEG");

    const V4l2DeviceDump sensor = load("csi-sensor-handwritten.txt");
    EXPECT_EQ(sensor.control(V4L2_CID_PIXEL_RATE)->type, "int64");
    EXPECT_EQ(sensor.control(V4L2_CID_PIXEL_RATE)->value, 182400000);
    EXPECT_TRUE(sensor.control(V4L2_CID_HBLANK)->hasFlag("read-only"));
    ASSERT_EQ(sensor.formats.size(), 3u);
    const V4l2DumpFrameSize& s = sensor.formats[0].sizes.at(0);
    EXPECT_EQ(s.kind, V4l2DumpFrameSize::Kind::Stepwise);
    EXPECT_EQ(s.max_width, 3280u);
    EXPECT_EQ(s.max_height, 2464u);
    EXPECT_EQ(s.step_width, 2u);

    EXPECT_TRUE(load("mjpeg-only-handwritten.txt").formats.at(0).hasFlag("compressed"));
}

TEST(ParseV4l2Dump, ReadsEitherPartAloneAndContinuousSizes) {
    const std::string text = readText("vivid-default.txt");
    const size_t list = text.find("ioctl: VIDIOC_ENUM_FMT");
    auto all = parseV4l2Dump(text.substr(0, list), "all.txt");
    ASSERT_TRUE(all) << all.error().message;
    EXPECT_TRUE(all->has_driver_info);
    EXPECT_FALSE(all->has_format_list);
    auto formats = parseV4l2Dump(text.substr(list), "formats.txt");
    ASSERT_TRUE(formats) << formats.error().message;
    EXPECT_FALSE(formats->has_driver_info);
    EXPECT_EQ(formats->formats.size(), 83u);

    auto continuous = parseV4l2Dump(
        "ioctl: VIDIOC_ENUM_FMT\n\tType: Video Capture\n\n\t[0]: 'Y16 ' (16-bit Greyscale)\n"
        "\t\tSize: Continuous 16x16 - 640x480\n"
        "\t\t\tInterval: Continuous 0.033s - 1.000s (1.000-30.000 fps)\n",
        "c.txt");
    ASSERT_TRUE(continuous) << continuous.error().message;
    const V4l2DumpFrameSize& s = continuous->formats.at(0).sizes.at(0);
    EXPECT_EQ(s.kind, V4l2DumpFrameSize::Kind::Continuous);
    EXPECT_EQ(s.max_width, 640u);
    EXPECT_EQ(s.step_width, 1u);
}

TEST(ParseV4l2Dump, ReadsAControlNameLongerThanItsColumn) {
    auto dump = parseV4l2Dump(std::string(kHeader) +
                                  "\nCamera Controls\n\n"
                                  "exposure_time_absolute_with_a_long_name 0x009a0902 (int)    : "
                                  "min=1 max=10 step=1 default=5 value=5\n",
                              "long.txt");
    ASSERT_TRUE(dump) << dump.error().message;
    ASSERT_EQ(dump->controls.size(), 1u);
    EXPECT_EQ(dump->controls[0].name, "exposure_time_absolute_with_a_long_name");
}

TEST(ParseV4l2Dump, ErrorsNameTheSourceAndLine) {
    const std::string controls = std::string(kHeader) + "\nUser Controls\n\n";
    struct Case {
        std::string text;
        std::string expect;
    };
    const Case cases[] = {
        {"\tDriver name : x\n", "bad.txt:1: an indented line before any section"},
        {std::string(kHeader) + "garbage\n", "bad.txt:4: 'garbage' is neither"},
        {"Driver Info:\n\tCapabilities     : 85200001\n", "bad.txt:2: Capabilities"},
        {"Driver Info:\n\tDriver version   : 6.1\n", "bad.txt:2: Driver version '6.1'"},
        {"Driver Info:\n\tno colon here\n", "bad.txt:2: expected 'key : value'"},
        {controls + "   gain 0x00980913 (int)    : min=0 max=x step=1 default=0 value=0\n",
         "bad.txt:7: control 'gain': max='x' is not an integer"},
        {controls + "   gain 0x00980913 (int)    : min=0 max\n",
         "bad.txt:7: control 'gain': 'max' is not key=value"},
        {controls + "   gain 0x00980913 (int    : min=0\n", "bad.txt:7: control 'gain': no ')'"},
        {controls + "   gain 0x00980913 (int)  min=0\n", "bad.txt:7: control 'gain': no ':'"},
        {controls + "   menu 0x00980913 (menu)   : min=0 max=1 default=0 value=0 (unclosed\n",
         "unbalanced"},
        {controls + "\t\t\t\t1: Item\n", "bad.txt:7: menu item 1 without a menu control"},
        {controls + "\t\t\t\tno item\n",
         "bad.txt:7: 'no item' is neither a control nor a menu item"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[1]: 'Y16 ' (x)\n", "bad.txt:2: format [1] where [0] was due"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: Y16 (x)\n", "bad.txt:2: format [0] has no 'FCC '"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: 'Y16 ' x\n", "bad.txt:2: format [0]: description"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t\tSize: Discrete 1x1\n",
         "bad.txt:2: a Size line before any format"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: 'Y16 ' (x)\n\t\tSize: Discrete 1by1\n",
         "bad.txt:3: Size 'Discrete 1by1'"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: 'Y16 ' (x)\n\t\tSize: Stepwise 1x1 2x2\n",
         "bad.txt:3: Size range"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: 'Y16 ' (x)\n\t\tSize: Odd 1x1\n",
         "bad.txt:3: Size 'Odd 1x1' of an unknown kind"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: 'Y16 ' (x)\n\t\t\tInterval: Discrete 1s\n",
         "bad.txt:3: an Interval line before any Size"},
        {"ioctl: VIDIOC_ENUM_FMT\n\t[0]: 'Y16 ' (x)\n\t\tSize: Discrete 1x1\n\t\t\tInterval: "
         "Discrete -1s\n",
         "bad.txt:4: Interval"},
        {"Format Video Capture:\n\tWidth/Height      : 640x360\n",
         "bad.txt:2: Width/Height '640x360'"},
        {"Format Video Capture:\n\tPixel Format      : YUYV\n", "bad.txt:2: Pixel Format 'YUYV'"},
        {"Streaming Parameters Video Capture:\n\tFrames per second: 5.000\n",
         "bad.txt:2: Frames per second"},
        {std::string("Driver Info:\n\tDriver name : a\0b\n", 33), "bad.txt:2: holds a NUL byte"},
    };
    for (const Case& c : cases) {
        const Error e = parseError(c.text);
        EXPECT_EQ(e.code, ErrorCode::ParseError) << c.text;
        EXPECT_NE(e.message.find(c.expect), std::string::npos)
            << "expected '" << c.expect << "' in: " << e.message;
    }
}

TEST(ParseV4l2Dump, NeverFailsWithoutNamingALineOnTruncatedDumps) {
    // Every prefix that ends inside the file at a line break, or mid-line: either it parses or
    // the error names a line of bad.txt.
    const std::string text = readText("vivid-y16.txt");
    ASSERT_GT(text.size(), 1000u);
    for (size_t cut = 0; cut < text.size(); cut += 997) {
        auto dump = parseV4l2Dump(text.substr(0, cut), "bad.txt");
        if (!dump) {
            EXPECT_EQ(dump.error().message.rfind("bad.txt:", 0), 0u) << dump.error().message;
        }
    }
}

TEST(LoadV4l2Dump, NamesAMissingFile) {
    auto missing = loadV4l2Dump(dumpPath("no-such-dump.txt"));
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_NE(missing.error().message.find("no-such-dump.txt"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::drivers
