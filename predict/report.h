// ============================================================================
//  flarelab predict: ReportSeries, ReportPlot, ReportTable, ReportImage, ReportSection, Report,
//                    reportHtml, writeTextFileAtomically
// ============================================================================
//
// The report people open (item 6 of issue 21): one HTML page that needs no network, no script and
// nothing but the files beside it. Plots are inline SVG drawn here (axes with round-number ticks,
// lines, step lines, a threshold line, a legend); tables are HTML tables; frames are <img> links to
// PNG files in the report's folder. Every text is escaped for HTML.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "common/result.h"

namespace flarelab::predict {

struct ReportSeries {
    std::string name;
    std::vector<double> x;  // the same length as y; non-finite points break the line there
    std::vector<double> y;
    bool steps = false;    // drawn as a step line (a value holds until the next x)
    bool markers = false;  // a dot at every point (fitted samples) instead of a line
};

struct ReportPlot {
    std::string title;
    std::string x_label;
    std::string y_label;
    std::vector<ReportSeries> series;
    std::optional<double> threshold;  // a dashed horizontal line
    bool log_y = false;               // logarithmic y (non-positive values are left out)
    // Category labels for y (a switching plan: y = camera index); empty for numbers.
    std::vector<std::string> y_categories;
};

struct ReportTable {
    std::string title;
    std::vector<std::string> header;
    std::vector<std::vector<std::string>> rows;  // each as long as the header
};

struct ReportImage {
    std::string caption;
    std::string file;  // relative to the report's folder
};

struct ReportSection {
    std::string title;
    std::vector<std::string> paragraphs;
    std::vector<ReportTable> tables;
    std::vector<ReportPlot> plots;
    std::vector<ReportImage> images;
};

struct Report {
    std::string title;
    std::vector<ReportSection> sections;
};

// The page. Each plot is an <svg class="plot"> with a <title>, each series a <path> or <g> of
// circles with class "series"; a plot whose series hold no finite point says so in a text instead
// of drawing empty axes.
std::string reportHtml(const Report& report);

// Writes `text` to `path` through a temporary file beside it, flushed and renamed into place.
// IoError naming the path on failure; `path` then keeps what it held.
Status writeTextFileAtomically(const std::string& path, const std::string& text);

}  // namespace flarelab::predict
