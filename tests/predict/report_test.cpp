#include "predict/report.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "common/durable_io.h"
#include "tests/test_files.h"

namespace flarelab::predict {
namespace {

using flarelab::testing::readText;
using flarelab::testing::TempDir;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();
const std::string kHostile = "<script>alert(\"x\")</script>&'";

size_t countOf(const std::string& text, const std::string& needle) {
    size_t count = 0;
    for (size_t at = text.find(needle); at != std::string::npos; at = text.find(needle, at + 1))
        ++count;
    return count;
}

std::string lowered(std::string text) {
    std::transform(text.begin(), text.end(), text.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    return text;
}

// The <svg>...</svg> elements of a page.
std::vector<std::string> svgsOf(const std::string& html) {
    std::vector<std::string> svgs;
    for (size_t at = html.find("<svg"); at != std::string::npos; at = html.find("<svg", at + 1)) {
        const size_t end = html.find("</svg>", at);
        EXPECT_NE(end, std::string::npos);
        if (end == std::string::npos) break;
        svgs.push_back(html.substr(at, end + 6 - at));
    }
    return svgs;
}

// The d attributes of the line series in `svg`.
std::vector<std::string> seriesPaths(const std::string& svg) {
    std::vector<std::string> paths;
    const std::string open = "<path class=\"series\"";
    for (size_t at = svg.find(open); at != std::string::npos; at = svg.find(open, at + 1)) {
        const size_t d = svg.find(" d=\"", at);
        const size_t end = svg.find('"', d + 4);
        paths.push_back(svg.substr(d + 4, end - d - 4));
    }
    return paths;
}

struct Point {
    double x = 0.0;
    double y = 0.0;
};

// The vertices a path's d attribute visits (M, L with implicit repeats, H, V; absolute).
std::vector<Point> verticesOf(const std::string& d) {
    std::vector<Point> points;
    std::istringstream in(d);
    char command = 0;
    Point at;
    while (in >> std::ws, !in.eof()) {
        const int next = in.peek();
        if (std::isalpha(next)) {
            command = static_cast<char>(in.get());
            continue;
        }
        if (command == 'M' || command == 'L') {
            in >> at.x >> at.y;
            if (command == 'M') command = 'L';  // further pairs are lines
        } else if (command == 'H') {
            in >> at.x;
        } else if (command == 'V') {
            in >> at.y;
        } else {
            ADD_FAILURE() << "unexpected command in " << d;
            break;
        }
        if (in.fail()) {
            ADD_FAILURE() << "cannot read " << d;
            break;
        }
        points.push_back(at);
    }
    return points;
}

// The texts of a page (between tags), to look for a label.
bool hasText(const std::string& html, const std::string& text) {
    return html.find(">" + text + "<") != std::string::npos;
}

ReportSeries line(std::string name, std::vector<double> x, std::vector<double> y) {
    ReportSeries series;
    series.name = std::move(name);
    series.x = std::move(x);
    series.y = std::move(y);
    return series;
}

std::vector<double> range(size_t n, double from = 0.0, double step = 1.0) {
    std::vector<double> values(n);
    for (size_t i = 0; i < n; ++i) values[i] = from + step * static_cast<double>(i);
    return values;
}

Report oneSection(ReportSection section, std::string title = "Report") {
    Report report;
    report.title = std::move(title);
    report.sections.push_back(std::move(section));
    return report;
}

Report onePlot(ReportPlot plot) {
    ReportSection section;
    section.title = "Section";
    section.plots.push_back(std::move(plot));
    return oneSection(std::move(section));
}

// A report using everything a report can hold.
Report everything() {
    ReportSection section;
    section.title = "Glare at the north gate";
    section.paragraphs = {"Three cameras, one afternoon.", "Times are UTC."};
    section.tables.push_back({"Cameras",
                              {"camera", "peak (DN/s)", "share"},
                              {{"east", "1520.5", "12 %"}, {"west", "3.1e4", "88 %"}}});
    ReportPlot timeline;
    timeline.title = "Flare over the afternoon";
    timeline.x_label = "time (s)";
    timeline.y_label = "flare (DN/s)";
    timeline.series = {line("east", range(100), range(100, 5.0, 0.5)),
                       line("west", range(100), range(100, 50.0, -0.5))};
    timeline.threshold = 30.0;
    ReportPlot plan;
    plan.title = "Switching plan";
    plan.y_categories = {"east", "west"};
    ReportSeries steps = line("camera", {0, 10, 20, 30}, {0, 1, 1, 0});
    steps.steps = true;
    plan.series = {steps};
    ReportPlot fit;
    fit.title = "Fitted samples";
    fit.log_y = true;
    ReportSeries samples = line("samples", {1, 2, 3}, {1, 10, 100});
    samples.markers = true;
    fit.series = {samples, line("model", {1, 2, 3}, {1.5, 12, 90})};
    section.plots = {timeline, plan, fit};
    section.images = {{"frame at 14:00", "frames/frame-1400.png"}};
    return oneSection(std::move(section), "Glare study");
}

TEST(ReportHtml, IsACompleteSelfContainedPage) {
    const std::string html = reportHtml(everything());
    EXPECT_EQ(html.rfind("<!DOCTYPE html>\n", 0), 0u);
    EXPECT_NE(html.find("<meta charset=\"utf-8\">"), std::string::npos);
    EXPECT_EQ(countOf(html, "<style>"), 1u);
    EXPECT_NE(html.find("<title>Glare study</title>"), std::string::npos);
    EXPECT_NE(html.find("<h1>Glare study</h1>"), std::string::npos);
    EXPECT_NE(html.find("<h2>Glare at the north gate</h2>"), std::string::npos);
    EXPECT_NE(html.find("<p>Times are UTC.</p>"), std::string::npos);
    EXPECT_NE(html.find("<footer>made by flarelab</footer>"), std::string::npos);
    EXPECT_EQ(countOf(html, "<section>"), countOf(html, "</section>"));
    EXPECT_EQ(html.substr(html.size() - 8), "</html>\n");
    // Nothing that would reach the network or run.
    for (const char* banned : {"<script", "http:", "https:", "//", "@import", "url(", "src=\"/",
                               "<link", "<iframe", "<object", "xlink:href", "javascript:"})
        EXPECT_EQ(html.find(banned), std::string::npos) << banned;
}

TEST(ReportHtml, DrawsOneSvgWithATitlePerPlot) {
    const std::string html = reportHtml(everything());
    const std::vector<std::string> svgs = svgsOf(html);
    ASSERT_EQ(svgs.size(), 3u);
    const char* const titles[] = {"Flare over the afternoon", "Switching plan", "Fitted samples"};
    for (size_t i = 0; i < svgs.size(); ++i) {
        EXPECT_EQ(svgs[i].rfind("<svg class=\"plot\" width=\"", 0), 0u);
        EXPECT_NE(svgs[i].find("viewBox=\"0 0 "), std::string::npos);
        EXPECT_NE(svgs[i].find(std::string("<title>") + titles[i] + "</title>"), std::string::npos);
        EXPECT_EQ(countOf(svgs[i], "<title>"), 1u);
    }
}

TEST(ReportHtml, DrawsOnePathPerLineSeriesAndADotPerMarker) {
    const std::vector<std::string> svgs = svgsOf(reportHtml(everything()));
    ASSERT_EQ(svgs.size(), 3u);
    EXPECT_EQ(seriesPaths(svgs[0]).size(), 2u);
    EXPECT_EQ(countOf(svgs[0], "class=\"series\""), 2u);
    EXPECT_EQ(seriesPaths(svgs[1]).size(), 1u);
    EXPECT_EQ(seriesPaths(svgs[2]).size(), 1u);  // the model
    EXPECT_EQ(countOf(svgs[2], "<g class=\"series\""), 1u);
    const size_t group = svgs[2].find("<g class=\"series\"");
    const std::string dots = svgs[2].substr(group, svgs[2].find("</g>", group) - group);
    EXPECT_EQ(countOf(dots, "<circle"), 3u);
}

TEST(ReportHtml, GivesEachSeriesItsOwnColour) {
    ReportPlot plot;
    plot.title = "Ten cameras";
    for (int i = 0; i < 10; ++i)
        plot.series.push_back(line("camera " + std::to_string(i), range(10), range(10, i)));
    const std::string svg = svgsOf(reportHtml(onePlot(plot)))[0];
    std::set<std::string> styles;
    const std::string open = "<path class=\"series\"";
    for (size_t at = svg.find(open); at != std::string::npos; at = svg.find(open, at + 1)) {
        const size_t stroke = svg.find("stroke=\"", at);
        const size_t d = svg.find(" d=\"", at);
        styles.insert(svg.substr(stroke, d - stroke));  // colour and dashes
    }
    EXPECT_EQ(styles.size(), 10u);
    EXPECT_EQ(seriesPaths(svg).size(), 10u);
}

TEST(ReportHtml, EscapesEveryText) {
    ReportSection section;
    section.title = kHostile;
    section.paragraphs = {kHostile};
    section.tables.push_back({kHostile, {kHostile, "b"}, {{kHostile, "1"}}});
    ReportPlot plot;
    plot.title = kHostile;
    plot.x_label = kHostile;
    plot.y_label = kHostile;
    plot.series = {line(kHostile, {1, 2}, {0, 1}), line("b", {1, 2}, {1, 0})};
    plot.y_categories = {kHostile, "ok"};
    section.plots = {plot};
    section.images = {{kHostile, "x<y>&\"'.png"}, {kHostile, "/" + kHostile}};
    const std::string html = reportHtml(oneSection(section, kHostile));

    EXPECT_EQ(html.find("<script"), std::string::npos);
    EXPECT_EQ(html.find("</script"), std::string::npos);
    EXPECT_EQ(html.find("\"x\""), std::string::npos);
    EXPECT_EQ(html.find("&'"), std::string::npos);
    const std::string escaped = "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt;&amp;&#39;";
    // Page title, h1, h2, paragraph, caption, header, cell, plot title twice, two labels, the
    // legend, a category, the image's alt and caption, the left-out image's caption.
    EXPECT_GE(countOf(html, escaped), 16u);
    EXPECT_NE(html.find("src=\"x%3Cy%3E%26%22%27.png\""), std::string::npos);
    EXPECT_NE(html.find("\xE2\x80\x9C/" + escaped + "\xE2\x80\x9D"), std::string::npos);
}

TEST(ReportHtml, ReplacesBytesThatAreNotUtf8) {
    ReportSection section;
    section.paragraphs = {std::string("a") + "\xFF" + "b\x01" + "c\xC3\xA9"};
    const std::string html = reportHtml(oneSection(section));
    const std::string replacement = "\xEF\xBF\xBD";  // U+FFFD
    EXPECT_NE(html.find("<p>a" + replacement + "b" + replacement + "c\xC3\xA9</p>"),
              std::string::npos);
}

TEST(ReportHtml, NonFinitePointsBreakTheLine) {
    ReportPlot plot;
    plot.title = "gaps";
    plot.series = {
        line("a", {0, 1, 2, 3, 4, 5, 6, 7, kNaN, 9}, {1, 2, kNaN, 3, 4, kInf, 5, 6, 7, 8})};
    const std::vector<std::string> paths = seriesPaths(svgsOf(reportHtml(onePlot(plot)))[0]);
    ASSERT_EQ(paths.size(), 1u);
    // {0,1} {3,4} {6,7} {9}: the lone point is still drawn (a zero-length segment).
    EXPECT_EQ(countOf(paths[0], "M"), 4u);
    EXPECT_EQ(verticesOf(paths[0]).size(), 8u);
}

TEST(ReportHtml, StepsGoAcrossThenUpOrDown) {
    ReportPlot plot;
    plot.title = "plan";
    ReportSeries series = line("camera", {0, 1, 2}, {0, 1, 0});
    series.steps = true;
    plot.series = {series};
    const std::vector<std::string> paths = seriesPaths(svgsOf(reportHtml(onePlot(plot)))[0]);
    ASSERT_EQ(paths.size(), 1u);
    const std::vector<Point> v = verticesOf(paths[0]);
    ASSERT_EQ(v.size(), 5u);
    EXPECT_EQ(v[1].y, v[0].y);  // across at the old value
    EXPECT_EQ(v[2].x, v[1].x);  // then up
    EXPECT_LT(v[2].y, v[1].y);
    EXPECT_EQ(v[3].y, v[2].y);
    EXPECT_EQ(v[4].x, v[3].x);
    EXPECT_EQ(v[4].y, v[0].y);
}

TEST(ReportHtml, LogAxisLeavesOutNonPositiveValues) {
    ReportPlot plot;
    plot.title = "log";
    plot.log_y = true;
    plot.series = {line("a", {0, 1, 2, 3, 4, 5}, {1, 10, 0, 100, -5, 1000})};
    const std::string html = reportHtml(onePlot(plot));
    const std::string svg = svgsOf(html)[0];
    const std::vector<std::string> paths = seriesPaths(svg);
    ASSERT_EQ(paths.size(), 1u);
    EXPECT_EQ(countOf(paths[0], "M"), 3u);  // {1, 10} {100} {1000}
    for (const char* decade : {"1", "10", "100", "1000"}) EXPECT_TRUE(hasText(svg, decade));
    EXPECT_FALSE(hasText(svg, "500"));
    const std::string text = lowered(svg);
    EXPECT_EQ(text.find("nan"), std::string::npos);
    EXPECT_EQ(text.find("inf"), std::string::npos);

    // Decades are thinned over a wide range, and labels stay compact.
    plot.series = {line("a", {0, 1}, {1e-30, 1e30})};
    const std::string wide = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_TRUE(hasText(wide, "1e-30"));
    EXPECT_TRUE(hasText(wide, "1e30"));
    EXPECT_LE(countOf(wide, "</text>"), 30u);
}

TEST(ReportHtml, PlotWithoutPlottablePointsSaysSo) {
    ReportPlot nothing;
    nothing.title = "Empty <one>";
    ReportPlot all_nan;
    all_nan.title = "NaNs";
    all_nan.series = {line("a", {1, 2}, {kNaN, kNaN}), line("b", {kInf, kNaN}, {1, 2})};
    ReportPlot negative_log;
    negative_log.title = "Negative";
    negative_log.log_y = true;
    negative_log.series = {line("a", {1, 2}, {0, -1})};
    negative_log.threshold = 5.0;
    ReportSection section;
    section.plots = {nothing, all_nan, negative_log};
    const std::string html = reportHtml(oneSection(section));
    EXPECT_EQ(html.find("<svg"), std::string::npos);
    EXPECT_NE(html.find("<p class=\"empty-plot\">Empty &lt;one&gt;: no data to plot</p>"),
              std::string::npos);
    EXPECT_NE(html.find("<p class=\"empty-plot\">NaNs: no data to plot</p>"), std::string::npos);
    EXPECT_NE(html.find("<p class=\"empty-plot\">Negative: no data to plot</p>"),
              std::string::npos);
}

TEST(ReportHtml, DegenerateRangesStayFinite) {
    const std::vector<std::pair<std::vector<double>, std::vector<double>>> cases = {
        {{5}, {7}},                          // one point
        {{0, 0, 0}, {0, 0, 0}},              // all zero
        {{1, 2, 3}, {4, 4, 4}},              // flat
        {{3, 3}, {-1, 1}},                   // vertical
        {{1e300, -1e300}, {1e300, -1e300}},  // the widest range drawn
        {{1e-300, 2e-300}, {5e-324, 5e-324}},
        {{1e9, 1e9 + 1e-7}, {1, 2}},  // a span below the numbers' resolution
        {{1, 2}, {1e308, kInf}},      // beyond 1e300: left out
        {{1, 2}, {-0.0, -0.0}},
    };
    for (const bool log_y : {false, true}) {
        for (const auto& [x, y] : cases) {
            ReportPlot plot;
            plot.title = "case";
            plot.log_y = log_y;
            ReportSeries series = line("a", x, y);
            plot.series = {series, series};
            plot.series[1].markers = true;
            plot.threshold = y[0];
            const std::string html = lowered(reportHtml(onePlot(plot)));
            EXPECT_EQ(html.find("nan"), std::string::npos) << x[0] << " " << y[0];
            EXPECT_EQ(html.find("inf"), std::string::npos) << x[0] << " " << y[0];
            EXPECT_EQ(html.find(">-0<"), std::string::npos) << x[0] << " " << y[0];
        }
    }
}

TEST(ReportHtml, TicksAreRoundNumbers) {
    ReportPlot plot;
    plot.title = "ticks";
    plot.series = {line("a", range(10800), range(10800, 0.0, 0.93 / 10799))};
    const std::string svg = svgsOf(reportHtml(onePlot(plot)))[0];
    for (const char* label : {"0", "2000", "4000", "6000", "8000", "10000"})
        EXPECT_TRUE(hasText(svg, label)) << label;
    EXPECT_FALSE(hasText(svg, "1000"));
    // x ends with the data, y on a tick.
    EXPECT_FALSE(hasText(svg, "12000"));
    for (const char* label : {"0.2", "0.4", "0.6", "0.8", "1"})
        EXPECT_TRUE(hasText(svg, label)) << label;
    EXPECT_FALSE(hasText(svg, "0.93"));

    plot.series = {line("a", {-1, 1}, {-1e-6, 2.5e-6})};
    const std::string small = svgsOf(reportHtml(onePlot(plot)))[0];
    for (const char* label : {"-1", "-0.5", "0", "0.5", "1", "-1e-6", "0", "1e-6", "2e-6"})
        EXPECT_TRUE(hasText(small, label)) << label;
    EXPECT_FALSE(hasText(small, "-0"));
    EXPECT_EQ(small.find("e-06"), std::string::npos);  // compact exponents

    plot.series = {line("a", {1e9, 1e9 + 10}, {0, 1})};
    const std::string offset = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_TRUE(hasText(offset, "1000000002"));  // ticks told apart
    EXPECT_TRUE(hasText(offset, "1000000010"));
}

TEST(ReportHtml, ThinnedLineKeepsItsSpike) {
    std::vector<double> y(100000, 0.0);
    y[54321] = 1e6;
    ReportPlot plot;
    plot.title = "spike";
    plot.series = {line("a", range(y.size()), y)};
    const std::string html = reportHtml(onePlot(plot));
    EXPECT_LT(html.size(), 200'000u);
    const std::vector<std::string> paths = seriesPaths(svgsOf(html)[0]);
    ASSERT_EQ(paths.size(), 1u);
    const std::vector<Point> v = verticesOf(paths[0]);
    EXPECT_LE(v.size(), 2000u);
    double y_min = v[0].y, y_max = v[0].y;
    for (const Point& p : v) {
        y_min = std::min(y_min, p.y);
        y_max = std::max(y_max, p.y);
    }
    EXPECT_GE(y_max - y_min, 290.0);  // from 0 to the top of a 300 px plot
    // Its x is where the spike is: 54321 of 99999 along the axis.
    const auto top = std::min_element(v.begin(), v.end(),
                                      [](const Point& a, const Point& b) { return a.y < b.y; });
    const double fraction = (top->x - v.front().x) / (v.back().x - v.front().x);
    EXPECT_NEAR(fraction, 54321.0 / 99999.0, 0.002);
}

TEST(ReportHtml, LongTimelinesStaySmall) {
    ReportPlot plot;
    plot.title = "ten cameras, three hours";
    for (int s = 0; s < 10; ++s) {
        std::vector<double> y(10800);
        for (size_t i = 0; i < y.size(); ++i) y[i] = std::sin(0.01 * i * (s + 1)) + s;
        plot.series.push_back(line("camera " + std::to_string(s), range(y.size()), y));
    }
    const std::string html = reportHtml(onePlot(plot));
    EXPECT_LT(html.size(), 400'000u);
    for (const std::string& d : seriesPaths(svgsOf(html)[0]))
        EXPECT_LE(verticesOf(d).size(), 2000u);
}

TEST(ReportHtml, MarkersAreNeverThinned) {
    ReportPlot plot;
    plot.title = "samples";
    ReportSeries series = line("a", range(5000), range(5000, 0.0, 0.1));
    series.markers = true;
    plot.series = {series};
    const std::string svg = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_EQ(countOf(svg, "<circle"), 5000u);
}

TEST(ReportHtml, CategoriesLabelTheYAxis) {
    ReportPlot plot;
    plot.title = "plan";
    plot.y_categories = {"east gate", "west <gate>", "roof"};
    ReportSeries series = line("camera", {0, 60, 120, 180}, {0, 2, 1, 1});
    series.steps = true;
    plot.series = {series};
    const std::string svg = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_TRUE(hasText(svg, "east gate"));
    EXPECT_TRUE(hasText(svg, "west &lt;gate&gt;"));
    EXPECT_TRUE(hasText(svg, "roof"));
    EXPECT_FALSE(hasText(svg, "0.5"));                           // no numbers on that axis
    EXPECT_EQ(svg.find("class=\"legend\""), std::string::npos);  // one series, no threshold
}

TEST(ReportHtml, LegendForSeveralSeriesOrAThreshold) {
    ReportPlot plot;
    plot.title = "legend";
    plot.series = {line("only", {0, 1}, {0, 1})};
    EXPECT_EQ(reportHtml(onePlot(plot)).find("class=\"legend\""), std::string::npos);

    plot.threshold = 0.5;
    const std::string with_threshold = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_NE(with_threshold.find("class=\"legend\""), std::string::npos);
    EXPECT_NE(with_threshold.find("<path class=\"threshold\""), std::string::npos);
    EXPECT_NE(with_threshold.find("stroke-dasharray"), std::string::npos);
    EXPECT_EQ(countOf(with_threshold, ">threshold<"), 2u);  // on the line and in the legend
    EXPECT_TRUE(hasText(with_threshold, "only"));

    plot.threshold.reset();
    plot.series.push_back(line("other", {0, 1}, {1, 0}));
    const std::string two = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_NE(two.find("class=\"legend\""), std::string::npos);
    EXPECT_TRUE(hasText(two, "other"));
    EXPECT_EQ(two.find("threshold"), std::string::npos);
}

TEST(ReportHtml, ThresholdWidensTheAxis) {
    ReportPlot plot;
    plot.title = "threshold";
    plot.series = {line("a", {0, 1}, {0, 1})};
    plot.threshold = 40.0;
    const std::string svg = svgsOf(reportHtml(onePlot(plot)))[0];
    EXPECT_TRUE(hasText(svg, "40"));
}

TEST(ReportHtml, TablesPadRowsToTheWidestAndRightAlignNumbers) {
    ReportSection section;
    section.tables.push_back(
        {"Peaks", {"camera", "peak", "note"}, {{"east", "12.5"}, {"west", "-3e4", "", "extra"}}});
    const std::string html = reportHtml(oneSection(section));
    EXPECT_NE(html.find("<caption>Peaks</caption>"), std::string::npos);
    EXPECT_EQ(countOf(html, "<thead>"), 1u);
    EXPECT_EQ(countOf(html, "<tbody>"), 1u);
    EXPECT_EQ(countOf(html, "</th>"), 4u);  // the header widened to the longest row
    EXPECT_EQ(countOf(html, "</td>"), 8u);  // the short row padded
    EXPECT_NE(html.find("<th class=\"num\">peak</th>"), std::string::npos);
    EXPECT_NE(html.find("<td class=\"num\">12.5</td>"), std::string::npos);
    EXPECT_NE(html.find("<td>east</td>"), std::string::npos);
    EXPECT_NE(html.find("<td>extra</td>"), std::string::npos);
}

TEST(ReportHtml, ImagesOutsideTheFolderAreLeftOut) {
    ReportSection section;
    section.images = {{"up", "../x.png"},
                      {"passwd", "/etc/passwd"},
                      {"deep", "frames/../../y.png"},
                      {"web", "http://example.com/z.png"},
                      {"share", "\\\\server\\share\\w.png"},
                      {"none", ""},
                      {"kept", "frames/frame 01#2.png"}};
    const std::string html = reportHtml(oneSection(section));
    EXPECT_EQ(countOf(html, "<p class=\"left-out\">"), 6u);
    EXPECT_EQ(countOf(html, "<img "), 1u);
    EXPECT_NE(html.find("<img src=\"frames/frame%2001%232.png\" alt=\"kept\""), std::string::npos);
    EXPECT_NE(html.find("<figcaption>kept</figcaption>"), std::string::npos);
    for (const char* banned : {"src=\"..", "src=\"/", "src=\"http", "src=\"%5C", "src=\"\""})
        EXPECT_EQ(html.find(banned), std::string::npos) << banned;
}

TEST(WriteTextFileAtomically, WritesAndReplaces) {
    TempDir scratch;
    ASSERT_FALSE(scratch.path().empty());
    const std::string path = scratch.path() + "/report.html";
    const Status first = writeTextFileAtomically(path, "first");
    ASSERT_TRUE(first) << first.error().message;
    EXPECT_EQ(readText(path), "first");
    const Status second = writeTextFileAtomically(path, reportHtml(everything()));
    ASSERT_TRUE(second) << second.error().message;
    EXPECT_EQ(readText(path), reportHtml(everything()));
    // No temporary file left beside it.
    size_t files = 0;
    for ([[maybe_unused]] const auto& entry : std::filesystem::directory_iterator(scratch.path()))
        ++files;
    EXPECT_EQ(files, 1u);
}

TEST(WriteTextFileAtomically, WritesIntoTheWorkingDirectoryForABareName) {
    TempDir scratch;
    ASSERT_FALSE(scratch.path().empty());
    const std::filesystem::path before = std::filesystem::current_path();
    std::filesystem::current_path(scratch.path());
    const Status written = writeTextFileAtomically("bare.html", "bare");
    std::filesystem::current_path(before);
    ASSERT_TRUE(written) << written.error().message;
    EXPECT_EQ(readText(scratch.path() + "/bare.html"), "bare");
}

TEST(WriteTextFileAtomically, FailsWithIoErrorNamingThePath) {
    TempDir scratch;
    ASSERT_FALSE(scratch.path().empty());
    const std::string path = scratch.path() + "/missing/report.html";
    const Status missing = writeTextFileAtomically(path, "x");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::IoError);
    EXPECT_NE(missing.error().message.find(path), std::string::npos) << missing.error().message;

    const Status directory = writeTextFileAtomically(scratch.path() + "/", "x");
    ASSERT_FALSE(directory);
    EXPECT_EQ(directory.error().code, ErrorCode::IoError);
}

TEST(WriteTextFileAtomically, KeepsTheOldContentsWhenTheWriteFails) {
    TempDir scratch;
    ASSERT_FALSE(scratch.path().empty());
    const std::string path = scratch.path() + "/report.html";
    ASSERT_TRUE(writeTextFileAtomically(path, "old"));
    {
        ScopedFileFaults faults({[](const std::string&) { return ENOSPC; }, {}});
        const Status failed = writeTextFileAtomically(path, "new");
        ASSERT_FALSE(failed);
        EXPECT_EQ(failed.error().code, ErrorCode::IoError);
        EXPECT_NE(failed.error().message.find("report.html"), std::string::npos);
    }
    EXPECT_EQ(readText(path), "old");
}

}  // namespace
}  // namespace flarelab::predict
