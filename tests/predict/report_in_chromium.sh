#!/usr/bin/env bash
# The report of `flarelab predict` opened in Debian's headless Chromium (issue 21, item 6): every
# plot rendered and nothing fetched from the network.
#
#   tests/predict/report_in_chromium.sh FLARELAB OUT_DIR [--self-check]
#
# Predicts tests/data/scenes/report-test.json into OUT_DIR/report: two cameras on
# tests/data/models/moving-disc.flm (movingDiscModel(2) of tests/predict/moving_disc_model.h,
# written with fit::writeModel), a flood light, the sun over 20 minutes at 10 s steps near both
# cameras' axes (pan and tilt from `flarelab sun`), a switching plan with a cut and one frame
# instant: seven plots and two frames. Then report.html is opened in Chromium twice:
#   1. a copy with a probe script added (report/.chromium-probe.html, the same folder so that the
#      frames resolve) gives the layout: each plot's and series' box and colour, each <img>'s
#      load state and box, the page's height;
#   2. the report itself in a window as tall as the page: its DOM (--dump-dom), a screenshot and
#      Chromium's net log.
# It fails when
#   - the DOM holds fewer <svg class="plot"> than the file, the report has fewer than 4, a plot has
#     no series with path data or circles, or the report says a plot had no data;
#   - a plot's part of the screenshot is blank, or shows fewer pixels of its series' colours than
#     half the longest series' extent (a drawn line covers at least one pixel per column or row);
#   - an <img> did not load, or the screenshot does not show its PNG's pixels;
#   - either net log holds a request of the page's (its initiator is the file page's origin, or
#     its isolation key is file://) for http, https, ws, wss or ftp. Chromium's own background
#     requests (component updates, sign-in) are listed but not counted: no report can cause or
#     prevent them. A proxy on a closed port makes sure no attempt leaves the machine.
# With --self-check the checks then run on a doctored copy (a stylesheet from https, a plot
# commented out, a series without path data, a plot's series painted transparent, a frame file
# missing) and must fail naming each fault: a check that cannot fail proves nothing.
#
# Exit 0: passed; 1: failed; 2: usage; 77: Chromium is not installed (ctest's SKIP_RETURN_CODE;
# scripts/install-deps.sh installs it). About 15 s with --self-check. CHROMIUM overrides the
# browser; everything is kept under OUT_DIR for a look after a failure.
set -euo pipefail
if (($# < 2 || $# > 3)) || { (($# == 3)) && [[ $3 != --self-check ]]; }; then
    echo "usage: $0 FLARELAB OUT_DIR [--self-check]" >&2
    exit 2
fi
flarelab=$1
out=$2
self_check=${3:-}
source_dir=$(cd "$(dirname "$0")/../.." && pwd)
scene=$source_dir/tests/data/scenes/report-test.json
python3=/usr/bin/python3
chromium=${CHROMIUM:-$(command -v chromium || true)}
if [[ -z $chromium ]]; then
    echo "report_in_chromium: SKIP: no chromium (scripts/install-deps.sh installs it; or set CHROMIUM)"
    exit 77
fi
[[ -x $chromium ]] || { echo "report_in_chromium: CHROMIUM=$chromium is not executable" >&2; exit 2; }
[[ -x $flarelab ]] || { echo "report_in_chromium: $flarelab is not built" >&2; exit 2; }
[[ -x $python3 ]] || { echo "report_in_chromium: FAIL: $python3 is missing" >&2; exit 1; }

mkdir -p "$out"
out=$(cd "$out" && pwd)
rm -rf "$out/report" "$out/doctored" "$out/chromium"
mkdir -p "$out/chromium"
checker=$out/chromium/check_report.py
start_s=$SECONDS

cat >"$checker" <<'PY'
"""Probe page, layout, DOM, screenshot and net log checks for report_in_chromium.sh."""
import collections
import html.parser
import json
import pathlib
import re
import shutil
import struct
import sys
import urllib.parse
import zlib

NETWORK_SCHEMES = ('http', 'https', 'ws', 'wss', 'ftp')
MIN_PLOTS = 4
WINDOW_WIDTH_PX = 1000  # both runs: the same width, the same layout (scrollbars hidden)
MAX_PAGE_PX = 16384  # Chromium's largest screenshot side

PROBE = r"""<script>
(function () {
  function box(el) {
    var r = el.getBoundingClientRect();
    return [r.left + window.scrollX, r.top + window.scrollY, r.width, r.height];
  }
  function report() {
    var out = {plots: [], images: []};
    document.querySelectorAll('svg.plot').forEach(function (svg) {
      var t = svg.querySelector('title');
      var plot = {title: t ? t.textContent : '', box: box(svg), series: []};
      svg.querySelectorAll('.series').forEach(function (s) {
        var path = s.tagName.toLowerCase() === 'path';
        var e = {tag: s.tagName, box: box(s),
                 colour: getComputedStyle(s).getPropertyValue(path ? 'stroke' : 'fill')};
        if (path) e.length = s.getTotalLength();
        else e.circles = s.querySelectorAll('circle').length;
        plot.series.push(e);
      });
      out.plots.push(plot);
    });
    document.querySelectorAll('img').forEach(function (img) {
      var b = box(img);
      out.images.push({src: img.getAttribute('src'), complete: img.complete,
                       natural: [img.naturalWidth, img.naturalHeight],
                       content: [b[0] + img.clientLeft, b[1] + img.clientTop,
                                 img.clientWidth, img.clientHeight]});
    });
    out.page = [document.documentElement.scrollWidth, document.documentElement.scrollHeight];
    var pre = document.createElement('pre');
    pre.id = 'flarelab-probe';
    pre.textContent = JSON.stringify(out);
    document.body.appendChild(pre);
  }
  // Frames are loading="lazy": bring each into view until all have loaded or failed.
  var tries = 0;
  function waitForImages() {
    var images = Array.prototype.slice.call(document.images);
    images.forEach(function (img) { if (!img.complete) img.scrollIntoView(); });
    if (images.every(function (img) { return img.complete; }) || ++tries > 50) {
      window.scrollTo(0, 0);
      report();
    } else {
      setTimeout(waitForImages, 100);
    }
  }
  window.addEventListener('load', waitForImages);
})();
</script>
"""


def fail(problems, kind, message):
    problems.append('[%s] %s' % (kind, message))


# --- PNG, standard library only (no PIL in CI) -----------------------------------------------

def read_png(path):
    """(width, height, rows of RGB bytes): 8 or 16 bit, grey or RGB, with or without alpha
    (composited over white, as on the page), not interlaced."""
    data = pathlib.Path(path).read_bytes()
    if data[:8] != b'\x89PNG\r\n\x1a\n':
        raise ValueError('%s: not a PNG' % path)
    pos, idat, ihdr = 8, [], None
    while pos + 8 <= len(data):
        n, kind = struct.unpack('>I4s', data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if kind == b'IHDR':
            ihdr = struct.unpack('>IIBBBBB', body)
        elif kind == b'IDAT':
            idat.append(body)
        elif kind == b'IEND':
            break
    if ihdr is None:
        raise ValueError('%s: no IHDR' % path)
    width, height, depth, colour_type, _, _, interlace = ihdr
    channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(colour_type)
    if channels is None or depth not in (8, 16) or interlace:
        raise ValueError('%s: unsupported PNG (depth %d, colour type %d, interlace %d)' %
                         (path, depth, colour_type, interlace))
    bpp = channels * depth // 8
    stride = width * bpp
    raw = zlib.decompress(b''.join(idat))
    if len(raw) != height * (stride + 1):
        raise ValueError('%s: %d bytes of pixel data, expected %d' %
                         (path, len(raw), height * (stride + 1)))
    # Up, the commonest filter in Chromium's screenshots, as one wide addition: bytes added
    # without carries from one into the next.
    low = int.from_bytes(b'\x7f' * stride, 'big')
    high = int.from_bytes(b'\x80' * stride, 'big')
    rows, prev = [], bytes(stride)
    for y in range(height):
        start = y * (stride + 1)
        f = raw[start]
        line = bytearray(raw[start + 1:start + 1 + stride])
        if f == 1:
            for i in range(bpp, stride):
                line[i] = (line[i] + line[i - bpp]) & 255
        elif f == 2:
            a, b = int.from_bytes(line, 'big'), int.from_bytes(prev, 'big')
            line = bytearray((((a & low) + (b & low)) ^ ((a ^ b) & high)).to_bytes(stride, 'big'))
        elif f == 3:
            for i in range(stride):
                left = line[i - bpp] if i >= bpp else 0
                line[i] = (line[i] + (left + prev[i]) // 2) & 255
        elif f == 4:
            for i in range(stride):
                a = line[i - bpp] if i >= bpp else 0
                b = prev[i]
                c = prev[i - bpp] if i >= bpp else 0
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        elif f != 0:
            raise ValueError('%s: row %d has filter %d' % (path, y, f))
        rows.append(bytes(line))
        prev = line
    step = depth // 8
    out = []
    for line in rows:
        samples = line[::step]  # 16 bit: the high bytes
        if channels == 3:
            out.append(bytes(samples))
            continue
        rgb = bytearray()
        for x in range(width):
            px = samples[x * channels:(x + 1) * channels]
            grey = channels <= 2
            colour = (px[0],) * 3 if grey else tuple(px[:3])
            alpha = px[-1] if channels in (2, 4) else 255
            rgb += bytes((c * alpha + 255 * (255 - alpha) + 127) // 255 for c in colour)
        out.append(bytes(rgb))
    return width, height, out


def colours_in(rows, width, height, box, inflate=0.0):
    """Counter of RGB triples inside box [x, y, w, h] (CSS px = screenshot px), clipped."""
    x0 = max(0, int(box[0] - inflate))
    y0 = max(0, int(box[1] - inflate))
    x1 = min(width, int(box[0] + box[2] + inflate + 0.999))
    y1 = min(height, int(box[1] + box[3] + inflate + 0.999))
    counts = collections.Counter()
    for y in range(y0, y1):
        seg = rows[y][3 * x0:3 * x1]
        counts.update(zip(seg[0::3], seg[1::3], seg[2::3]))
    return counts, max(0, x1 - x0) * max(0, y1 - y0)


def parse_colour(text):
    m = re.fullmatch(r'\s*rgba?\(\s*(\d+),\s*(\d+),\s*(\d+)(?:,\s*([\d.]+))?\s*\)\s*', text or '')
    if not m or (m.group(4) is not None and float(m.group(4)) == 0.0):
        return None
    return tuple(int(m.group(i)) for i in (1, 2, 3))


def paints(pixel, colour):
    """Whether `pixel` is `colour` laid over white at >= 45 % coverage (a line's antialiased
    edge over the page), give or take the grid's grey under it."""
    d = [c - 255 for c in colour]
    n = sum(v * v for v in d)
    if n < 1:
        return False
    p = [c - 255 for c in pixel]
    alpha = sum(a * b for a, b in zip(p, d)) / n
    residual = sum((a - alpha * b) ** 2 for a, b in zip(p, d)) ** 0.5
    return alpha >= 0.45 and residual <= 24.0


# --- DOM ---------------------------------------------------------------------------------------

class PlotParser(html.parser.HTMLParser):
    """The plots of a DOM dump: title and series (tag, path data, circles) of each
    <svg class="plot">; the texts of <p class="empty-plot">; the probe's <pre>."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.plots, self.empty_plots = [], []
        self.probe = None
        self._svg_depth = 0
        self._g_depth = 0  # inside a <g class="series">
        self._text = None  # collecting: 'title', 'empty', 'probe'
        self._buffer = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        classes = (a.get('class') or '').split()
        if tag == 'svg':
            if self._svg_depth == 0 and 'plot' in classes:
                self.plots.append({'title': '', 'series': []})
                self._svg_depth = 1
            elif self._svg_depth:
                self._svg_depth += 1
        elif self._svg_depth:
            if tag == 'title' and not self.plots[-1]['title']:
                self._start_text('title')
            if 'series' in classes:
                self.plots[-1]['series'].append(
                    {'tag': tag, 'd': (a.get('d') or '').strip(), 'circles': 0})
                if tag == 'g':
                    self._g_depth = 1
            elif self._g_depth:
                if tag == 'g':
                    self._g_depth += 1
                if tag == 'circle':
                    self.plots[-1]['series'][-1]['circles'] += 1
        elif tag == 'p' and 'empty-plot' in classes:
            self._start_text('empty')
        elif tag == 'pre' and a.get('id') == 'flarelab-probe':
            self._start_text('probe')

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag == 'g' and self._g_depth:
            self._g_depth -= 1

    def handle_endtag(self, tag):
        if self._text and tag in ('title', 'p', 'pre'):
            text = ''.join(self._buffer)
            if self._text == 'title':
                self.plots[-1]['title'] = text
            elif self._text == 'empty':
                self.empty_plots.append(text)
            else:
                self.probe = text
            self._text = None
        if tag == 'g' and self._g_depth:
            self._g_depth -= 1
        if tag == 'svg' and self._svg_depth:
            self._svg_depth -= 1

    def handle_data(self, data):
        if self._text:
            self._buffer.append(data)

    def _start_text(self, kind):
        self._text, self._buffer = kind, []


def parse_dom(path):
    parser = PlotParser()
    parser.feed(pathlib.Path(path).read_text(encoding='utf-8', errors='replace'))
    parser.close()
    return parser


def probe_of(path):
    text = parse_dom(path).probe
    if text is None:
        raise SystemExit('report_in_chromium: FAIL: the probe wrote no result into %s '
                         '(did the page load?)' % path)
    return json.loads(text)


# --- net log -----------------------------------------------------------------------------------

def network_requests(path):
    """(the page's, Chromium's own): sorted URLs of requests and connections for network
    schemes, judged event by event (a source such as the host resolver serves everyone). The
    page's events carry an initiator that is an origin (a file page's is "null"; Chromium's
    services have "not an origin") or an isolation key naming file:// (a preconnect's socket
    group: "https://host <file:// ...>"). A bare origin (a host looked up or connected to) is
    left out where a URL of it is listed, and Chromium's own requests to an origin the page
    asked for too are left to the page's list."""
    log = json.loads(pathlib.Path(path).read_text(encoding='utf-8', errors='replace'))
    found = {True: set(), False: set()}
    for event in log.get('events', []):
        params = event.get('params') or {}
        initiator = params.get('initiator')
        keys = ' '.join(str(params.get(k, '')) for k in
                        ('network_isolation_key', 'network_anonymization_key', 'group_id'))
        page = (initiator is not None and initiator != 'not an origin') or 'file://' in keys
        for k in ('url', 'original_url', 'location', 'host', 'group_id'):
            value = params.get(k)
            if isinstance(value, str):
                value = value.split(' <')[0]
                if urllib.parse.urlsplit(value).scheme in NETWORK_SCHEMES:
                    found[page].add(value)

    def origin(u):
        return '%s://%s' % urllib.parse.urlsplit(u)[:2]

    def tidy(urls):
        full = {origin(u) for u in urls if urllib.parse.urlsplit(u)[2:] != ('', '', '')}
        return sorted(u for u in urls if u not in full)

    page_origins = {origin(u) for u in found[True]}
    return tidy(found[True]), tidy({u for u in found[False] if origin(u) not in page_origins})


# --- commands ----------------------------------------------------------------------------------

def make_probe(report, probe_page):
    text = pathlib.Path(report).read_text(encoding='utf-8')
    if '</body>' not in text:
        raise SystemExit('report_in_chromium: FAIL: %s has no </body>' % report)
    pathlib.Path(probe_page).write_text(text.replace('</body>', PROBE + '</body>', 1),
                                        encoding='utf-8')


def window_size(probe_dom=None):
    """The probe run's window, or with its DOM the report run's: as tall as the page."""
    if probe_dom is None:
        print('%d,800' % WINDOW_WIDTH_PX)
        return
    height = int(probe_of(probe_dom)['page'][1] + 0.999)
    if not 0 < height <= MAX_PAGE_PX:
        raise SystemExit('report_in_chromium: FAIL: the page is %d px tall; a screenshot takes '
                         'at most %d' % (height, MAX_PAGE_PX))
    print('%d,%d' % (WINDOW_WIDTH_PX, height))


def check(report, probe_dom, dom, shot, netlogs):
    problems = []
    report_dir = pathlib.Path(report).parent
    text = pathlib.Path(report).read_text(encoding='utf-8')
    in_file = len(re.findall(r'<svg\b[^>]*\bclass="plot"', text))
    if in_file < MIN_PLOTS:
        fail(problems, 'plot-count', 'report.html has %d <svg class="plot">, expected at least %d'
             % (in_file, MIN_PLOTS))

    # (i) The DOM Chromium built: every plot there, each with a drawn series.
    parsed = parse_dom(dom)
    if len(parsed.plots) != in_file:
        fail(problems, 'plot-count', '%d <svg class="plot"> in report.html but %d in the DOM'
             % (in_file, len(parsed.plots)))
    for said in parsed.empty_plots:
        fail(problems, 'series', 'the report drew no plot: "%s"' % said.strip())
    for i, plot in enumerate(parsed.plots, 1):
        name = 'plot %d ("%s")' % (i, plot['title'])
        if not plot['series']:
            fail(problems, 'series', '%s has no element of class "series"' % name)
        for j, s in enumerate(plot['series'], 1):
            if s['tag'] == 'path' and not re.search(r'[0-9]', s['d']):
                fail(problems, 'series', '%s: series %d is a path with no path data' % (name, j))
            elif s['tag'] == 'g' and s['circles'] == 0:
                fail(problems, 'series', '%s: series %d is a group with no circles' % (name, j))
            elif s['tag'] not in ('path', 'g'):
                fail(problems, 'series', '%s: series %d is a <%s>' % (name, j, s['tag']))

    # (ii) The screenshot: each plot painted, its series in their colours.
    probe = probe_of(probe_dom)
    width, height, rows = read_png(shot)
    if [width, height] != [WINDOW_WIDTH_PX, int(probe['page'][1] + 0.999)]:
        fail(problems, 'pixels', 'the screenshot is %dx%d, the page %gx%g'
             % (width, height, probe['page'][0], probe['page'][1]))
    if len(probe['plots']) != len(parsed.plots):
        fail(problems, 'plot-count', 'the probe found %d plots, the DOM dump %d'
             % (len(probe['plots']), len(parsed.plots)))
    drawn_plots = 0
    for i, plot in enumerate(probe['plots'], 1):
        name = 'plot %d ("%s")' % (i, plot['title'])
        counts, area = colours_in(rows, width, height, plot['box'])
        ink = sum(n for c, n in counts.items() if min(c) < 240)
        if area == 0 or ink < 0.01 * area:
            fail(problems, 'pixels', '%s is blank in the screenshot (%d of %d pixels not white, '
                 'box %s)' % (name, ink, area, plot['box']))
            continue
        colours, boxes, expected = set(), [], 5.0
        for s in plot['series']:
            extent = max(s['box'][2], s['box'][3])
            if s.get('length') or s.get('circles'):
                boxes.append(s['box'])
                colour = parse_colour(s['colour'])
                if colour:
                    colours.add(colour)
                # A line covers at least one pixel per column (or row) of its extent; a dot 10.
                want = 0.5 * extent if 'length' in s else min(0.5 * extent, 10.0 * s['circles'])
                expected = max(expected, want)
        if not boxes or not colours:
            fail(problems, 'pixels', '%s has no series with geometry and a colour to look for'
                 % name)
            continue
        x0 = min(b[0] for b in boxes)
        y0 = min(b[1] for b in boxes)
        x1 = max(b[0] + b[2] for b in boxes)
        y1 = max(b[1] + b[3] for b in boxes)
        counts, _ = colours_in(rows, width, height, [x0, y0, x1 - x0, y1 - y0], inflate=3.0)
        painted = sum(n for c, n in counts.items() if any(paints(c, k) for k in colours))
        if painted < expected:
            fail(problems, 'pixels', '%s: %d pixels in its series\' colours %s, expected at '
                 'least %d' % (name, painted, sorted(colours), expected))
        else:
            drawn_plots += 1

    # Frames: loaded, and their pixels on the screen.
    if not probe['images']:
        fail(problems, 'frame', 'the report shows no frame')
    for img in probe['images']:
        src = img['src']
        if not img['complete'] or img['natural'][0] == 0:
            fail(problems, 'frame', '%s did not load' % src)
            continue
        file = report_dir / urllib.parse.unquote(src)
        cx, cy, cw, ch = img['content']
        try:
            fw, fh, frows = read_png(file)
        except (OSError, ValueError) as e:
            fail(problems, 'frame', '%s: %s' % (src, e))
            continue
        if [fw, fh] != img['natural'] or [cw, ch] != img['natural']:
            counts, area = colours_in(rows, width, height, img['content'])
            if counts.get((255, 255, 255), 0) == area:
                fail(problems, 'frame', '%s is white on the screen' % src)
            continue
        x0, y0, diff = int(round(cx)), int(round(cy)), 0
        for y in range(fh):
            screen = rows[y0 + y][3 * x0:3 * (x0 + fw)] if y0 + y < height else b''
            if len(screen) != 3 * fw:
                diff = 255 * 3 * fw * fh
                break
            diff += sum(abs(a - b) for a, b in zip(screen, frows[y]))
        mean = diff / (3.0 * fw * fh)
        if mean > 4.0:
            fail(problems, 'frame', '%s differs from its file on the screen by %.1f levels on '
                 'average' % (src, mean))

    # (iii) The net logs: nothing the page asked for from the network.
    page_urls, own_urls = collections.defaultdict(list), set()
    for path in netlogs:
        try:
            page, own = network_requests(path)
        except (OSError, ValueError) as e:
            fail(problems, 'network', '%s: unreadable net log: %s' % (path, e))
            continue
        own_urls.update(own)
        for url in page:
            page_urls[url].append(pathlib.Path(path).name)
    for url, logs in sorted(page_urls.items()):
        fail(problems, 'network', 'the page asked the network for %s (%s)' % (url, ', '.join(logs)))
    if own_urls:
        hosts = sorted({urllib.parse.urlsplit(u).hostname or u for u in own_urls})
        print('report_in_chromium: Chromium\'s own background requests, not the page\'s '
              '(not counted): %d, to %s' % (len(own_urls), ', '.join(hosts)))

    for p in problems:
        print('report_in_chromium: FAIL %s' % p)
    if problems:
        return 1
    print('report_in_chromium: %d plots in the DOM, each painted in its series\' colours; %d '
          'frames loaded and shown pixel for pixel; no network request from the page'
          % (drawn_plots, len(probe['images'])))
    return 0


def doctor(report_dir, doctored_dir):
    """A copy of the report with one fault per check (report_in_chromium.sh --self-check)."""
    shutil.copytree(report_dir, doctored_dir)
    page = pathlib.Path(doctored_dir) / 'report.html'
    text = page.read_text(encoding='utf-8')
    # [network]: a stylesheet from https.
    text = text.replace('</head>', '<link rel="stylesheet" '
                        'href="https://example.invalid/flarelab.css">\n</head>', 1)
    plots = [m.start() for m in re.finditer(r'<svg\b[^>]*\bclass="plot"', text)]
    ends = [text.index('</svg>', s) + len('</svg>') for s in plots]
    if len(plots) < 3:
        raise SystemExit('report_in_chromium: FAIL: too few plots to doctor')
    # [plot-count]: the last plot commented out (still in the file, gone from the DOM).
    text = text[:plots[-1]] + '<!--' + text[plots[-1]:ends[-1]] + '-->' + text[ends[-1]:]
    # [series]: the second plot's first series without path data.
    second = text[plots[1]:ends[1]]
    second = re.sub(r'(<path class="series"[^>]*?) d="[^"]*"', r'\1 d=""', second, count=1)
    # [pixels]: the first plot's series painted transparent.
    first = text[plots[0]:ends[0]].replace('<path class="series"',
                                           '<path class="series" stroke-opacity="0"')
    text = text[:plots[0]] + first + text[ends[0]:plots[1]] + second + text[ends[1]:]
    page.write_text(text, encoding='utf-8')
    # [frame]: the first frame's file missing.
    frame = re.search(r'<img src="([^"]+)"', text)
    (pathlib.Path(doctored_dir) / urllib.parse.unquote(frame.group(1))).unlink()


if __name__ == '__main__':
    command, args = sys.argv[1], sys.argv[2:]
    if command == 'probe':
        make_probe(*args)
    elif command == 'window':
        window_size(*args)
    elif command == 'check':
        sys.exit(check(args[0], args[1], args[2], args[3], args[4:]))
    elif command == 'doctor':
        doctor(*args)
    elif command == 'uri':
        print(pathlib.Path(args[0]).resolve().as_uri())
    else:
        raise SystemExit('unknown command ' + command)
PY

# Quiet Chromium: no first run, sync, updates, pings or crash reports, so that its own requests
# are few; a proxy on the discard port, so that no request, the page's or its own, leaves the
# machine (the net log still records each attempt). --no-sandbox: CI runs as root in a container.
chromium_flags=(
    --headless --no-sandbox --disable-gpu --hide-scrollbars --force-device-scale-factor=1
    --no-first-run --no-default-browser-check --disable-default-apps --disable-extensions
    --disable-background-networking --disable-component-update --disable-sync
    --disable-domain-reliability --disable-client-side-phishing-detection --disable-breakpad
    --metrics-recording-only --no-pings --disable-features=NetworkTimeServiceQuerying
    --proxy-server=127.0.0.1:9 --virtual-time-budget=10000
)

# run_chromium NAME ARGS...: one headless run; its profile, net log and stderr are NAME.*.
run_chromium() {
    local name=$1
    shift
    local status=0
    timeout 30 "$chromium" "${chromium_flags[@]}" --user-data-dir="$name.profile" \
        --log-net-log="$name.netlog.json" "$@" 2>"$name.stderr" || status=$?
    rm -rf "$name.profile"
    if ((status != 0)); then
        echo "report_in_chromium: FAIL: chromium exited with $status; the end of $name.stderr:"
        tail -n 15 "$name.stderr"
        return 1
    fi
}

# check_report REPORT_DIR WORK_DIR: the checks on REPORT_DIR/report.html; 0 when all pass.
check_report() {
    local dir=$1 work=$2 window
    mkdir -p "$work"
    "$python3" "$checker" probe "$dir/report.html" "$dir/.chromium-probe.html" || return 1
    window=$("$python3" "$checker" window) || return 1
    run_chromium "$work/probe" --window-size="$window" \
        --dump-dom "$("$python3" "$checker" uri "$dir/.chromium-probe.html")" \
        >"$work/probe-dom.html" || return 1
    window=$("$python3" "$checker" window "$work/probe-dom.html") || return 1
    run_chromium "$work/report" --window-size="$window" --screenshot="$work/report.png" \
        --dump-dom "$("$python3" "$checker" uri "$dir/report.html")" \
        >"$work/report-dom.html" || return 1
    "$python3" "$checker" check "$dir/report.html" "$work/probe-dom.html" \
        "$work/report-dom.html" "$work/report.png" "$work/probe.netlog.json" \
        "$work/report.netlog.json"
}

if ! "$flarelab" predict "$scene" -o "$out/report" >"$out/chromium/predict.log" 2>&1; then
    echo "report_in_chromium: FAIL: flarelab predict $scene failed:"
    cat "$out/chromium/predict.log"
    exit 1
fi
echo "report_in_chromium: $("$chromium" --version 2>/dev/null | tail -n 1); $out/report/report.html"
if ! check_report "$out/report" "$out/chromium/report"; then
    echo "report_in_chromium: FAIL: the report did not pass in Chromium (files in $out)"
    exit 1
fi

if [[ $self_check == --self-check ]]; then
    "$python3" "$checker" doctor "$out/report" "$out/doctored"
    log=$out/chromium/doctored.log
    if check_report "$out/doctored" "$out/chromium/doctored" >"$log" 2>&1; then
        echo "report_in_chromium: FAIL: self-check: a doctored report passed:"
        cat "$log"
        exit 1
    fi
    missed=()
    for kind in network plot-count series pixels frame; do
        grep -q "FAIL \[$kind\]" "$log" || missed+=("$kind")
    done
    if ((${#missed[@]})); then
        echo "report_in_chromium: FAIL: self-check: the doctored report's faults went unseen by" \
            "the checks: ${missed[*]}; what they said:"
        cat "$log"
        exit 1
    fi
    echo "report_in_chromium: self-check: the doctored report failed as it should:"
    grep "FAIL \[" "$log" | sed 's/^/    /'
fi
echo "report_in_chromium: PASS in $((SECONDS - start_s)) s"
