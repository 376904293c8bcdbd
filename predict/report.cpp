#include "predict/report.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/check.h"
#include "common/file_descriptor.h"
#include "common/utf8.h"

// Decisions the header leaves open:
// - A table row shorter than the header is padded with empty cells; a longer one widens the
//   table (the header gets empty cells). A report is read by people, and a caller's slip should
//   cost a blank cell, not the daemon.
// - A series whose x and y differ in length is drawn over the common prefix, for the same reason.
// - Values beyond +-1e300 are left out like non-finite ones: nothing flarelab plots gets there,
//   and an axis spanning them would overflow to an infinite width.
// - markers wins over steps; y_categories wins over log_y; a non-finite threshold (or, on a log
//   axis, a non-positive one) draws no line.
// - A line series of more than kMaxLinePoints points is thinned to the lowest and highest point
//   of each of kBuckets columns of the plot, per unbroken run: a spike survives, the page stays
//   small. Markers are never thinned: each is a fitted sample someone wants to see.

namespace flarelab::predict {
namespace {

constexpr double kLargest = 1e300;
constexpr size_t kMaxLinePoints = 2000;
constexpr int kBuckets = 999;  // at most 2 points each, and the ends of a run
constexpr int kMaxTicks = 8;

// Okabe & Ito (2008), "Color Universal Design": told apart by the common colour-vision
// deficiencies. Yellow last: it is faint on white. Series past the eighth repeat the colours
// with a dotted line.
constexpr std::array<const char*, 8> kPalette = {"#0072B2", "#D55E00", "#009E73", "#E69F00",
                                                 "#CC79A7", "#56B4E9", "#000000", "#F0E442"};

// The drawing, in SVG user units (pixels at 100 %).
constexpr double kWidth = 960.0;
constexpr double kTop = 36.0;  // room for the title
constexpr double kRight = 32.0;
constexpr double kPlotHeight = 300.0;
constexpr double kCharWidth = 7.0;  // of a 12 px sans-serif character, on average
constexpr double kLegendRow = 20.0;

// Appends `text` escaped for HTML text and attribute values alike. Bytes that are not UTF-8 and
// control characters other than tab, newline and carriage return become U+FFFD: the page
// declares UTF-8, and a browser would otherwise show them in its own way.
void appendEscaped(std::string& out, std::string_view text) {
    static constexpr std::string_view kReplacement = "\xEF\xBF\xBD";
    size_t i = 0;
    while (i < text.size()) {
        const auto c = static_cast<unsigned char>(text[i]);
        if (c < 0x80) {
            switch (c) {
                case '&':
                    out += "&amp;";
                    break;
                case '<':
                    out += "&lt;";
                    break;
                case '>':
                    out += "&gt;";
                    break;
                case '"':
                    out += "&quot;";
                    break;
                case '\'':
                    out += "&#39;";
                    break;
                default:
                    if ((c < 0x20 && c != '\t' && c != '\n' && c != '\r') || c == 0x7F)
                        out += kReplacement;
                    else
                        out += static_cast<char>(c);
            }
            ++i;
            continue;
        }
        const size_t length = c >= 0xF0 ? 4 : c >= 0xE0 ? 3 : c >= 0xC0 ? 2 : 1;
        if (length > 1 && i + length <= text.size() && validUtf8(text.substr(i, length))) {
            out += text.substr(i, length);
            i += length;
        } else {
            out += kReplacement;
            ++i;
        }
    }
}

// Characters as a browser counts them (UTF-8 lead bytes), to guess a text's width.
size_t characterCount(std::string_view text) {
    return static_cast<size_t>(std::count_if(text.begin(), text.end(), [](char c) {
        return (static_cast<unsigned char>(c) & 0xC0) != 0x80;
    }));
}

double textWidth(std::string_view text) {
    return kCharWidth * static_cast<double>(characterCount(text));
}

// At most `limit` characters, with an ellipsis where cut, so that a long category name cannot
// push the plot off the page.
std::string shortened(const std::string& text, size_t limit) {
    if (characterCount(text) <= limit) return text;
    size_t kept = 0, i = 0;
    while (i < text.size()) {
        if ((static_cast<unsigned char>(text[i]) & 0xC0) != 0x80 && kept++ == limit - 1) break;
        ++i;
    }
    return text.substr(0, i) + "\xE2\x80\xA6";
}

// %g with `digits` significant digits, written compactly: "1e6", "2.5e-5" (no '+', no leading
// zeros in the exponent), and never "-0".
std::string formatNumber(double value, int digits) {
    char text[48];
    std::snprintf(text, sizeof text, "%.*g", digits, value);
    std::string s = text;
    if (const size_t e = s.find('e'); e != std::string::npos) {
        std::string mantissa = s.substr(0, e);
        std::string exponent = s.substr(e + 1);
        std::string sign;
        if (!exponent.empty() && (exponent[0] == '+' || exponent[0] == '-')) {
            if (exponent[0] == '-') sign = "-";
            exponent.erase(0, 1);
        }
        const size_t first = std::min(exponent.find_first_not_of('0'), exponent.size() - 1);
        s = mantissa + "e" + sign + exponent.substr(first);
    }
    if (s == "-0") s = "0";
    return s;
}

// Coordinates have one decimal at most: a tenth of a pixel is finer than any screen, and the
// size of a page of long timelines is mostly coordinates.
int64_t tenthsOf(double v) {
    FLARELAB_DCHECK(std::isfinite(v));
    return std::llround(std::clamp(v, -1e7, 1e7) * 10.0);
}

void appendTenths(std::string& out, int64_t tenths) {
    if (tenths < 0) out += '-';
    const int64_t magnitude = tenths < 0 ? -tenths : tenths;
    out += std::to_string(magnitude / 10);
    if (magnitude % 10 != 0) {
        out += '.';
        out += static_cast<char>('0' + magnitude % 10);
    }
}

void appendCoordinate(std::string& out, double v) { appendTenths(out, tenthsOf(v)); }

std::string coordinate(double v) {
    std::string out;
    appendCoordinate(out, v);
    return out;
}

struct Tick {
    double at = 0.0;  // in axis units (log10 of the value on a log axis)
    std::string label;
};

struct Axis {
    double from = 0.0;  // axis units at the ends
    double to = 1.0;
    std::vector<Tick> ticks;
};

// Widens an empty or nearly empty range [lo, hi] (all values equal, up to rounding) so that
// mapping onto it divides by something: +-10 %, or +-1 around 0 and values so close to it that
// a tenth of them would leave the normal doubles (and the ticks' arithmetic).
void padDegenerate(double& lo, double& hi) {
    const double magnitude = std::max(std::abs(lo), std::abs(hi));
    if (hi - lo > 1e-12 * magnitude && hi - lo > 1e-280) return;
    const double centre = lo + (hi - lo) / 2.0;
    const double pad = std::abs(centre) < 1e-270 ? 1.0 : 0.1 * std::abs(centre);
    lo = centre - pad;
    hi = centre + pad;
}

// The smallest step of 1, 2 or 5 times a power of ten that puts at most kMaxTicks ticks on
// [lo, hi] ("nice numbers", Heckbert, Graphics Gems, 1990). With `extend`, the range is to be
// widened to whole steps, and the count is of the widened range.
double niceStep(double lo, double hi, bool extend) {
    constexpr double kSlack = 1e-9;  // in steps: rounding must not add or drop a tick
    int exponent = static_cast<int>(std::floor(std::log10(hi - lo))) - 1;
    for (int tries = 0; tries < 40; ++tries, ++exponent) {
        for (const double mantissa : {1.0, 2.0, 5.0}) {
            const double step = mantissa * std::pow(10.0, exponent);
            const double count =
                extend ? std::ceil(hi / step - kSlack) - std::floor(lo / step + kSlack) + 1.0
                       : std::floor(hi / step + kSlack) - std::ceil(lo / step - kSlack) + 1.0;
            if (count <= kMaxTicks) return step;
        }
    }
    return hi - lo;  // not reached for a finite, non-empty range
}

// Significant digits that tell ticks `step` apart up to `largest` in magnitude; in plain
// notation ("10000", not "1e4") for magnitudes from 1e-4 to 1e6, as a reader expects.
int tickDigits(double largest, double step) {
    const int top = static_cast<int>(std::floor(std::log10(std::max(largest, step))));
    const int bottom = static_cast<int>(std::floor(std::log10(step)));
    int digits = top - bottom + 1;
    if (top >= -4 && top <= 6) digits = std::max(digits, top + 1);
    return std::clamp(digits, 1, 17);
}

// A linear axis over [lo, hi] with round-number ticks; `extend` widens it to whole steps (for y,
// so that the highest value sits on a labelled line).
Axis linearAxis(double lo, double hi, bool extend) {
    padDegenerate(lo, hi);
    const double step = niceStep(lo, hi, extend);
    if (extend) {
        lo = std::floor(lo / step + 1e-9) * step;
        hi = std::ceil(hi / step - 1e-9) * step;
    }
    const double first = std::ceil(lo / step - 1e-9);
    const double last = std::floor(hi / step + 1e-9);
    const int digits = tickDigits(std::max(std::abs(first), std::abs(last)) * step, step);
    Axis axis{lo, hi, {}};
    for (double k = first; k <= last; k += 1.0) {
        const double value = k * step;
        axis.ticks.push_back({value, formatNumber(value, digits)});
    }
    return axis;
}

std::string decadeLabel(int exponent) {
    if (exponent >= -3 && exponent <= 5) return formatNumber(std::pow(10.0, exponent), 6);
    return "1e" + std::to_string(exponent);
}

// A log10 axis from 10^log_lo to 10^log_hi, widened to whole decades (or whole multiples of the
// decade step where more than kMaxTicks decades are spanned).
Axis logAxis(double log_lo, double log_hi) {
    double from = std::floor(log_lo);
    double to = std::ceil(log_hi);
    if (from == to) {
        from -= 1.0;
        to += 1.0;
    }
    // 1, 2 or 5 times a power of ten decades, as for a linear axis.
    double decades = 1.0;
    for (int i = 1; std::ceil(to / decades) - std::floor(from / decades) + 1.0 > kMaxTicks; ++i)
        decades = std::array{1.0, 2.0, 5.0}[i % 3] * std::pow(10.0, i / 3);
    from = std::floor(from / decades) * decades;
    to = std::ceil(to / decades) * decades;
    Axis axis{from, to, {}};
    for (double e = from; e <= to + 0.5; e += decades)
        axis.ticks.push_back({e, decadeLabel(static_cast<int>(e))});
    return axis;
}

// Categories sit at 0, 1, ...; the axis reaches half a step past them and past any value, so
// that no step line runs along the frame. Labels are thinned where rows would be too close.
Axis categoryAxis(const std::vector<std::string>& categories,
                  double lo,
                  double hi,
                  double plot_height) {
    const double count = static_cast<double>(categories.size());
    Axis axis{std::min(-0.5, lo - 0.5), std::max(count - 0.5, hi + 0.5), {}};
    const double rows_per_label = std::ceil(14.0 * (axis.to - axis.from) / plot_height);
    const size_t stride = static_cast<size_t>(std::max(1.0, rows_per_label));
    for (size_t i = 0; i < categories.size(); i += stride)
        axis.ticks.push_back({static_cast<double>(i), shortened(categories[i], 30)});
    return axis;
}

struct Point {
    double x = 0.0;
    double y = 0.0;
};

// A value that can be drawn: finite and within kLargest (a log axis asks for y > 0 besides).
bool usable(double v) { return std::isfinite(v) && std::abs(v) <= kLargest; }

// The runs of consecutive plottable points of `series`, in data units (log10 y on a log axis).
std::vector<std::vector<Point>> plottableRuns(const ReportSeries& series, bool log_y) {
    std::vector<std::vector<Point>> runs;
    std::vector<Point> run;
    const size_t n = std::min(series.x.size(), series.y.size());
    for (size_t i = 0; i < n; ++i) {
        const double x = series.x[i], y = series.y[i];
        if (usable(x) && usable(y) && (!log_y || y > 0.0)) {
            run.push_back({x, log_y ? std::log10(y) : y});
        } else if (!run.empty()) {
            runs.push_back(std::move(run));
            run.clear();
        }
    }
    if (!run.empty()) runs.push_back(std::move(run));
    return runs;
}

struct Frame {
    double left = 0.0, top = kTop, width = 0.0, height = kPlotHeight;
    Axis x, y;

    double px(double x_value) const { return left + (x_value - x.from) / (x.to - x.from) * width; }
    double py(double y_value) const {
        return top + height - (y_value - y.from) / (y.to - y.from) * height;
    }
    double bottom() const { return top + height; }
    double right() const { return left + width; }
};

// Thins runs (in pixels) to the lowest and highest point of each of kBuckets columns, in their
// order, so that a spike one sample wide still reaches its height; each run keeps its ends.
std::vector<std::vector<Point>> decimated(const std::vector<std::vector<Point>>& runs,
                                          const Frame& frame) {
    std::vector<std::vector<Point>> out;
    const double bucket_px = frame.width / kBuckets;
    for (const std::vector<Point>& run : runs) {
        std::vector<Point> kept;
        size_t i = 0;
        while (i < run.size()) {
            const double bucket = std::floor((run[i].x - frame.left) / bucket_px);
            size_t low = i, high = i, j = i;
            for (; j < run.size() && std::floor((run[j].x - frame.left) / bucket_px) == bucket;
                 ++j) {
                if (run[j].y < run[low].y) low = j;
                if (run[j].y > run[high].y) high = j;
            }
            // The run's ends stay where they are, too.
            std::array<size_t, 4> chosen = {i == 0 ? 0 : low, low, high,
                                            j == run.size() ? j - 1 : high};
            std::sort(chosen.begin(), chosen.end());
            for (size_t k = 0; k < chosen.size(); ++k)
                if (k == 0 || chosen[k] != chosen[k - 1]) kept.push_back(run[chosen[k]]);
            i = j;
        }
        out.push_back(std::move(kept));
    }
    return out;
}

// Whether b lies on the axis-parallel segment from a to c, so that a path may go from a to c
// directly.
bool between(int64_t a, int64_t b, int64_t c) { return (a <= b && b <= c) || (c <= b && b <= a); }

// The d attribute of a line or step line through pixel runs: one subpath per run. Points that
// round onto the previous one, or onto a straight horizontal or vertical stretch (a step line's
// held value), are left out. A lone point becomes a zero-length segment, which round caps draw as
// a dot.
std::string pathData(const std::vector<std::vector<Point>>& runs, bool steps) {
    std::string d;
    for (const std::vector<Point>& run : runs) {
        std::vector<std::pair<int64_t, int64_t>> v(run.size());
        for (size_t i = 0; i < run.size(); ++i) v[i] = {tenthsOf(run[i].x), tenthsOf(run[i].y)};
        auto [last_x, last_y] = v[0];
        d += 'M';
        appendTenths(d, last_x);
        d += ' ';
        appendTenths(d, last_y);
        if (v.size() == 1) {
            d += 'L';
            appendTenths(d, last_x);
            d += ' ';
            appendTenths(d, last_y);
            continue;
        }
        bool in_line = false;  // an 'L' already opened: further pairs continue it
        for (size_t i = 1; i < v.size(); ++i) {
            const auto [x, y] = v[i];
            const bool last = i + 1 == v.size();
            if (!last) {
                const auto [next_x, next_y] = v[i + 1];
                if (x == last_x && y == last_y) continue;
                // A step line holds its value until the next change.
                if (steps && y == last_y) continue;
                if (!steps && y == last_y && y == next_y && between(last_x, x, next_x)) continue;
                if (!steps && x == last_x && x == next_x && between(last_y, y, next_y)) continue;
            }
            if (steps) {
                // y == last_y only at the run's end, drawn even where it adds no length.
                if (x != last_x || y == last_y) {
                    d += 'H';
                    appendTenths(d, x);
                }
                if (y != last_y) {
                    d += 'V';
                    appendTenths(d, y);
                }
            } else {
                d += in_line ? ' ' : 'L';
                in_line = true;
                appendTenths(d, x);
                d += ' ';
                appendTenths(d, y);
            }
            last_x = x;
            last_y = y;
        }
    }
    return d;
}

struct LegendEntry {
    std::string label;
    std::string colour;
    std::string dash;  // stroke-dasharray, empty for solid
    bool marker = false;
};

void appendPlot(std::string& out, const ReportPlot& plot) {
    const bool categories = !plot.y_categories.empty();
    const bool log_y = plot.log_y && !categories;

    std::vector<std::vector<std::vector<Point>>> runs;  // per series
    constexpr double kInf = std::numeric_limits<double>::infinity();
    double x_lo = kInf, x_hi = -kInf, y_lo = kInf, y_hi = -kInf;
    for (const ReportSeries& series : plot.series) {
        runs.push_back(plottableRuns(series, log_y));
        for (const std::vector<Point>& run : runs.back()) {
            for (const Point& p : run) {
                x_lo = std::min(x_lo, p.x);
                x_hi = std::max(x_hi, p.x);
                y_lo = std::min(y_lo, p.y);
                y_hi = std::max(y_hi, p.y);
            }
        }
    }
    const std::string title = plot.title.empty() ? "Plot" : plot.title;
    if (!(x_lo <= x_hi)) {
        out += "<p class=\"empty-plot\">";
        appendEscaped(out, title);
        out += ": no data to plot</p>\n";
        return;
    }
    std::optional<double> threshold;
    if (plot.threshold && usable(*plot.threshold) && (!log_y || *plot.threshold > 0.0)) {
        threshold = log_y ? std::log10(*plot.threshold) : *plot.threshold;
        y_lo = std::min(y_lo, *threshold);
        y_hi = std::max(y_hi, *threshold);
    }

    // Axes first: the widest y label decides the left margin.
    Frame frame;
    if (categories)
        frame.height =
            std::clamp(24.0 * static_cast<double>(plot.y_categories.size()), kPlotHeight, 900.0);
    frame.x = linearAxis(x_lo, x_hi, false);
    frame.y = categories ? categoryAxis(plot.y_categories, y_lo, y_hi, frame.height)
              : log_y    ? logAxis(y_lo, y_hi)
                         : linearAxis(y_lo, y_hi, true);
    double widest_label = 0.0;
    for (const Tick& tick : frame.y.ticks)
        widest_label = std::max(widest_label, textWidth(tick.label));
    frame.left = std::max(64.0, 30.0 + widest_label + 10.0);
    frame.width = kWidth - frame.left - kRight;

    // The legend's rows, laid out before the height is known.
    std::vector<LegendEntry> legend;
    for (size_t i = 0; i < plot.series.size(); ++i) {
        const ReportSeries& series = plot.series[i];
        LegendEntry entry;
        entry.label = series.name.empty() ? "series " + std::to_string(i + 1) : series.name;
        if (runs[i].empty()) entry.label += " (no data)";
        entry.colour = kPalette[i % kPalette.size()];
        entry.dash = i >= kPalette.size() ? "2 3" : "";
        entry.marker = series.markers;
        legend.push_back(std::move(entry));
    }
    if (threshold) legend.push_back({"threshold", "#444444", "6 4", false});
    const bool show_legend = plot.series.size() > 1 || threshold.has_value();
    std::vector<double> legend_x;
    std::vector<int> legend_row;
    int rows = 0;
    if (show_legend) {
        double x = frame.left;
        rows = 1;
        for (const LegendEntry& entry : legend) {
            const double width = 30.0 + textWidth(entry.label) + 18.0;
            if (x > frame.left && x + width > kWidth - kRight) {
                x = frame.left;
                ++rows;
            }
            legend_x.push_back(x);
            legend_row.push_back(rows - 1);
            x += width;
        }
    }
    const double legend_top = frame.bottom() + 58.0;
    const double height = legend_top + (show_legend ? rows * kLegendRow : 0.0) + 4.0;

    const std::string w = coordinate(kWidth), h = coordinate(height);
    // No xmlns: inline SVG in HTML does without, and the page holds no URL at all.
    out += "<svg class=\"plot\" width=\"" + w + "\" height=\"" + h + "\" viewBox=\"0 0 ";
    out += w + " " + h;
    out += "\" role=\"img\" font-family=\"sans-serif\" font-size=\"12\" fill=\"#222\">\n<title>";
    appendEscaped(out, title);
    out += "</title>\n";
    out += "<text class=\"plot-title\" x=\"" + coordinate(kWidth / 2) +
           "\" y=\"22\" text-anchor=\"middle\" font-size=\"15\" font-weight=\"bold\">";
    appendEscaped(out, plot.title);
    out += "</text>\n";

    // Grid and ticks.
    const std::string left = coordinate(frame.left), right = coordinate(frame.right());
    const std::string top = coordinate(frame.top), bottom = coordinate(frame.bottom());
    std::string grid = "<path class=\"grid\" fill=\"none\" stroke=\"#e4e4e4\" d=\"";
    std::string tick_marks = "<path class=\"tick-marks\" fill=\"none\" stroke=\"#666\" d=\"";
    std::string x_labels = "<g class=\"x-ticks\" text-anchor=\"middle\">";
    for (const Tick& tick : frame.x.ticks) {
        const std::string x = coordinate(frame.px(tick.at));
        grid += "M" + x + " " + top + "V" + bottom;
        tick_marks += "M" + x + " " + bottom + "v5";
        x_labels += "<text x=\"" + x + "\" y=\"" + coordinate(frame.bottom() + 19.0) + "\">";
        appendEscaped(x_labels, tick.label);
        x_labels += "</text>";
    }
    std::string y_labels = "<g class=\"y-ticks\" text-anchor=\"end\">";
    for (const Tick& tick : frame.y.ticks) {
        const std::string y = coordinate(frame.py(tick.at));
        grid += "M" + left + " " + y + "H" + right;
        tick_marks += "M" + left + " " + y + "h-5";
        y_labels += "<text x=\"" + coordinate(frame.left - 8.0) + "\" y=\"" +
                    coordinate(frame.py(tick.at) + 4.0) + "\">";
        appendEscaped(y_labels, tick.label);
        y_labels += "</text>";
    }
    out += grid + "\"/>\n";
    out += "<rect class=\"frame\" x=\"" + left + "\" y=\"" + top + "\" width=\"" +
           coordinate(frame.width) + "\" height=\"" + coordinate(frame.height) +
           "\" fill=\"none\" stroke=\"#888\"/>\n";
    out += tick_marks + "\"/>\n" + x_labels + "</g>\n" + y_labels + "</g>\n";

    // Axis labels.
    if (!plot.x_label.empty()) {
        out += "<text class=\"x-label\" x=\"" + coordinate(frame.left + frame.width / 2) +
               "\" y=\"" + coordinate(frame.bottom() + 42.0) + "\" text-anchor=\"middle\">";
        appendEscaped(out, plot.x_label);
        out += "</text>\n";
    }
    if (!plot.y_label.empty()) {
        out += "<text class=\"y-label\" transform=\"translate(16 " +
               coordinate(frame.top + frame.height / 2) + ") rotate(-90)\" text-anchor=\"middle\">";
        appendEscaped(out, plot.y_label);
        out += "</text>\n";
    }

    // Series.
    for (size_t i = 0; i < plot.series.size(); ++i) {
        const ReportSeries& series = plot.series[i];
        if (runs[i].empty()) continue;
        size_t count = 0;
        for (std::vector<Point>& run : runs[i]) {
            count += run.size();
            for (Point& p : run) p = {frame.px(p.x), frame.py(p.y)};
        }
        const LegendEntry& style = legend[i];
        if (series.markers) {
            out += "<g class=\"series\" fill=\"" + style.colour + "\">";
            for (const std::vector<Point>& run : runs[i]) {
                for (const Point& p : run) {
                    out += "<circle cx=\"";
                    appendCoordinate(out, p.x);
                    out += "\" cy=\"";
                    appendCoordinate(out, p.y);
                    out += "\" r=\"3\"/>";
                }
            }
            out += "</g>\n";
            continue;
        }
        const std::vector<std::vector<Point>> drawn =
            count > kMaxLinePoints ? decimated(runs[i], frame) : std::move(runs[i]);
        out += "<path class=\"series\" fill=\"none\" stroke=\"" + style.colour +
               "\" stroke-width=\"1.6\" stroke-linejoin=\"round\" stroke-linecap=\"round\"";
        if (!style.dash.empty()) out += " stroke-dasharray=\"" + style.dash + "\"";
        out += " d=\"" + pathData(drawn, series.steps) + "\"/>\n";
    }

    if (threshold) {
        const double y = frame.py(*threshold);
        out +=
            "<path class=\"threshold\" fill=\"none\" stroke=\"#444444\" stroke-width=\"1.4\" "
            "stroke-dasharray=\"6 4\" d=\"M" +
            left + " " + coordinate(y) + "H" + right + "\"/>\n";
        // Above the line, or below it where the line runs along the top; a white halo keeps it
        // legible over the series.
        const double label_y = y - frame.top < 16.0 ? y + 14.0 : y - 5.0;
        out += "<text class=\"threshold-label\" x=\"" + coordinate(frame.right() - 4.0) +
               "\" y=\"" + coordinate(label_y) +
               "\" text-anchor=\"end\" fill=\"#444444\" stroke=\"#fff\" stroke-width=\"3\" " +
               "paint-order=\"stroke\">threshold</text>\n";
    }

    if (show_legend) {
        out += "<g class=\"legend\">";
        for (size_t i = 0; i < legend.size(); ++i) {
            const LegendEntry& entry = legend[i];
            const double x = legend_x[i];
            const double y = legend_top + legend_row[i] * kLegendRow;
            if (entry.marker) {
                out += "<circle cx=\"" + coordinate(x + 12.0) + "\" cy=\"" + coordinate(y - 4.0) +
                       "\" r=\"3.5\" fill=\"" + entry.colour + "\"/>";
            } else {
                out += "<path fill=\"none\" stroke=\"" + entry.colour + "\" stroke-width=\"2\"";
                if (!entry.dash.empty()) out += " stroke-dasharray=\"" + entry.dash + "\"";
                out += " d=\"M" + coordinate(x) + " " + coordinate(y - 4.0) + "h24\"/>";
            }
            out += "<text x=\"" + coordinate(x + 30.0) + "\" y=\"" + coordinate(y) + "\">";
            appendEscaped(out, entry.label);
            out += "</text>";
        }
        out += "</g>\n";
    }
    out += "</svg>\n";
}

// A cell that reads as a number ("12", "-3.5e-4", "97 %"), to be right-aligned.
bool numeric(std::string_view text) {
    size_t i = 0;
    const auto digits = [&] {
        const size_t start = i;
        while (i < text.size() && text[i] >= '0' && text[i] <= '9') ++i;
        return i - start;
    };
    while (i < text.size() && text[i] == ' ') ++i;
    if (i < text.size() && (text[i] == '+' || text[i] == '-')) ++i;
    size_t mantissa = digits();
    if (i < text.size() && text[i] == '.') {
        ++i;
        mantissa += digits();
    }
    if (mantissa == 0) return false;
    if (i < text.size() && (text[i] == 'e' || text[i] == 'E')) {
        ++i;
        if (i < text.size() && (text[i] == '+' || text[i] == '-')) ++i;
        if (digits() == 0) return false;
    }
    while (i < text.size() && text[i] == ' ') ++i;
    if (i < text.size() && text[i] == '%') ++i;
    return i == text.size();
}

void appendTable(std::string& out, const ReportTable& table) {
    size_t columns = table.header.size();
    for (const std::vector<std::string>& row : table.rows) columns = std::max(columns, row.size());
    const auto cell = [](const std::vector<std::string>& row, size_t c) -> std::string_view {
        return c < row.size() ? std::string_view(row[c]) : std::string_view();
    };
    // A column of numbers (blank cells allowed) is right-aligned, header included.
    std::vector<bool> right_aligned(columns, false);
    for (size_t c = 0; c < columns; ++c) {
        bool any = false, all = true;
        for (const std::vector<std::string>& row : table.rows) {
            const std::string_view text = cell(row, c);
            if (text.empty()) continue;
            any = true;
            all = all && numeric(text);
        }
        right_aligned[c] = any && all;
    }
    out += "<div class=\"table-wrap\"><table>\n<caption>";
    appendEscaped(out, table.title);
    out += "</caption>\n<thead><tr>";
    for (size_t c = 0; c < columns; ++c) {
        out += right_aligned[c] ? "<th class=\"num\">" : "<th>";
        appendEscaped(out, cell(table.header, c));
        out += "</th>";
    }
    out += "</tr></thead>\n<tbody>\n";
    for (const std::vector<std::string>& row : table.rows) {
        out += "<tr>";
        for (size_t c = 0; c < columns; ++c) {
            out += right_aligned[c] ? "<td class=\"num\">" : "<td>";
            appendEscaped(out, cell(row, c));
            out += "</td>";
        }
        out += "</tr>\n";
    }
    out += "</tbody>\n</table></div>\n";
}

// Whether `file` names something inside the report's folder. Absolute names, "..", any backslash
// (browsers read it as '/', so "\\host\x" is a network path) and URLs ("://") are refused.
bool insideFolder(const std::string& file) {
    return !file.empty() && file[0] != '/' && file.find('\\') == std::string::npos &&
           file.find("..") == std::string::npos && file.find("://") == std::string::npos;
}

// `file` as a relative URL: everything but unreserved characters and '/' percent-encoded, so that
// '#', '?', spaces or a colon ("c:x.png" would read as a scheme) stay part of the name.
std::string relativeUrl(const std::string& file) {
    static constexpr char kHex[] = "0123456789ABCDEF";
    std::string url;
    for (const char ch : file) {
        const auto c = static_cast<unsigned char>(ch);
        if ((c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') ||
            c == '-' || c == '.' || c == '_' || c == '~' || c == '/') {
            url += ch;
        } else {
            url += '%';
            url += kHex[c >> 4];
            url += kHex[c & 0xF];
        }
    }
    return url;
}

void appendImage(std::string& out, const ReportImage& image) {
    if (!insideFolder(image.file)) {
        out += "<p class=\"left-out\">Image left out";
        if (!image.caption.empty()) {
            out += " (";
            appendEscaped(out, image.caption);
            out += ")";
        }
        out += ": its file name \xE2\x80\x9C";  // quotation marks, U+201C and U+201D
        appendEscaped(out, image.file);
        out += "\xE2\x80\x9D does not name a file in the report's folder.</p>\n";
        return;
    }
    out += "<figure><img src=\"";
    appendEscaped(out, relativeUrl(image.file));
    out += "\" alt=\"";
    appendEscaped(out, image.caption);
    out += "\" loading=\"lazy\">";
    if (!image.caption.empty()) {
        out += "<figcaption>";
        appendEscaped(out, image.caption);
        out += "</figcaption>";
    }
    out += "</figure>\n";
}

// No url(), no @import, no web font: the page is read offline.
constexpr std::string_view kStyle = R"(body {
  font-family: system-ui, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
  max-width: 1100px; margin: 0 auto; padding: 1em 1.5em; color: #222; background: #fff;
  line-height: 1.45;
}
h1 { font-size: 1.7em; margin: 0.4em 0 0.6em; padding-bottom: 0.3em; border-bottom: 2px solid #ddd;
}
h2 { font-size: 1.3em; margin-top: 2em; padding-bottom: 0.2em; border-bottom: 1px solid #e5e5e5; }
p { max-width: 50em; }
.table-wrap { overflow-x: auto; margin: 1em 0; }
table { border-collapse: collapse; font-size: 0.92em; }
caption { text-align: left; font-weight: 600; padding: 0.3em 0; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.65em; text-align: left; vertical-align: top; }
thead th { background: #f0f0f0; }
tbody tr:nth-child(even) { background: #fafafa; }
.num { text-align: right; font-variant-numeric: tabular-nums; }
svg.plot { display: block; max-width: 100%; height: auto; margin: 1.2em 0; }
figure { margin: 1.2em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ccc; }
figcaption { font-size: 0.9em; color: #555; margin-top: 0.3em; }
.empty-plot, .left-out {
  color: #6b3a00; background: #fff7e6; padding: 0.4em 0.8em; border-left: 3px solid #E69F00;
}
footer { margin-top: 3em; padding-top: 0.5em; border-top: 1px solid #ddd; font-size: 0.85em;
  color: #777; }
)";

}  // namespace

std::string reportHtml(const Report& report) {
    const std::string title = report.title.empty() ? "flarelab report" : report.title;
    std::string out;
    out +=
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>";
    appendEscaped(out, title);
    out += "</title>\n<style>\n";
    out += kStyle;
    out += "</style>\n</head>\n<body>\n<h1>";
    appendEscaped(out, title);
    out += "</h1>\n";
    for (const ReportSection& section : report.sections) {
        out += "<section>\n";
        if (!section.title.empty()) {
            out += "<h2>";
            appendEscaped(out, section.title);
            out += "</h2>\n";
        }
        for (const std::string& paragraph : section.paragraphs) {
            out += "<p>";
            appendEscaped(out, paragraph);
            out += "</p>\n";
        }
        for (const ReportTable& table : section.tables) appendTable(out, table);
        for (const ReportPlot& plot : section.plots) appendPlot(out, plot);
        for (const ReportImage& image : section.images) appendImage(out, image);
        out += "</section>\n";
    }
    out += "<footer>made by flarelab</footer>\n</body>\n</html>\n";
    return out;
}

Status writeTextFileAtomically(const std::string& path, const std::string& text) {
    const std::filesystem::path target(path);
    const std::string file_name = target.filename().string();
    if (file_name.empty() || file_name == "." || file_name == "..")
        return makeError(ErrorCode::IoError, path + ": does not name a file");
    std::string directory = target.parent_path().string();
    if (directory.empty()) directory = ".";
    // The rename is flushed through the directory, so it must be opened first.
    FileDescriptor directory_fd(::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (!directory_fd.valid()) {
        const int error = errno;
        return makeError(ErrorCode::IoError, path + ": cannot open its directory " + directory +
                                                 ": " + osMessage(error));
    }
    return replaceFile(directory, directory_fd.get(), file_name, text, {});
}

}  // namespace flarelab::predict
