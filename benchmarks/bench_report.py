"""The plant page (``heliotwin report``) in a real browser: headless Chromium opens it from disk, takes
screenshots of the field map, an alarm's history and the receiver, and reports console errors, the file size
and the time to first paint and to load.

Needs Debian's ``chromium`` package (``apt-get install -y chromium``; not installed in CI, hence a benchmark and
not a test). No DevTools client: the benchmark opens a copy of the page with a small probe prepended to its
``<head>`` that records ``window.onerror``/``console.error`` messages and the paint/load timings into the DOM,
which ``chromium --dump-dom`` prints once the page has loaded. Screenshots use ``--screenshot`` on a copy whose
load handler moves the part to show (the field map; the first alarm's section above the alarm table; the
receiver) to the top and draws its figures.

Usage::

    python benchmarks/bench_report.py PAGE.html [PAGE2.html ...] --out docs/report-screens [--runs 3]

Writes ``<out>/<stem>_map.png``, ``<stem>_alarm.png``, ``<stem>_receiver.png`` (and ``<stem>_year.png`` for a plant
with its year stored: ``heliotwin year -o``) and ``<out>/bench_report.json``;
exits 1 when a page logs a console error, fails to render a Plotly graph, or has no field map. The per-heliostat
figures are drawn when scrolled to (``lazy-plot``): the load draws the map, the receiver and what is in view.

Measured 2026-11-28 on a busy 2-core machine (load average 6-8: timings are upper bounds; Chromium 156 from
Debian, SwiftShader WebGL), median of 3 loads, no console error on any page:

* demo plant (``heliotwin demo``: 2,000 heliostats, stored aim points, no calibration): 5.2 MB, first
  contentful paint 2.0 s, load 2.6 s, whole Chromium run 4.6 s;
* simulated 2,000 heliostats (1 year, ``calibrate --method lm`` on the first 15 records of each, then one
  ``update`` with the rest: 443 alarms), ``--paint`` given: 5.8 MB, paint 2.0 s, load 2.0 s, run 4.8 s;
* simulated 10,000 heliostats, same chain (1,871 alarms): 7.0 MB, paint 2.3 s, load 2.2 s, run 5.0 s.

plotly.js is 4.8 MB of every page; the map adds about 0.15 MB per 1,000 heliostats; the 40 heliostat sections
and 10 sky maps are drawn when scrolled to, so they cost bytes, not load time.
"""
from __future__ import annotations

import argparse
import html
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

PROBE = """<script>
window.__errors = [];
window.addEventListener('error', function (e) { window.__errors.push('error: ' + e.message); });
(function () { var orig = console.error; console.error = function () {
  window.__errors.push('console.error: ' + Array.prototype.join.call(arguments, ' ')); orig.apply(console, arguments);
}; })();
window.addEventListener('load', function () { setTimeout(function () {
  var plots = document.querySelectorAll('.js-plotly-plot');
  var drawn = Array.prototype.filter.call(plots, function (p) { return p._fullLayout !== undefined; }).length;
  var lazy = document.querySelectorAll('.lazy-plot').length;
  var map = document.getElementById('fieldmap'); var mapDrawn = !!(map && map._fullLayout);
  var paint = performance.getEntriesByType('paint').map(function (p) { return [p.name, p.startTime]; });
  var nav = performance.getEntriesByType('navigation')[0];
  var out = document.createElement('pre'); out.id = '__probe';
  out.textContent = JSON.stringify({errors: window.__errors, plots: plots.length, drawn: drawn, paint: paint,
                                    lazy: lazy, map_drawn: mapDrawn,
                                    load_ms: nav ? nav.loadEventEnd : null, probe_ms: performance.now(),
                                    gl: !!document.querySelector('.gl-container canvas, canvas')});
  document.body.appendChild(out); }, 0); });
</script>"""


def chromium() -> str:
    """The Chromium executable (Debian: ``chromium``)."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    sys.exit("bench_report: no chromium on PATH (apt-get install -y chromium)")


def _flags(tmp: str) -> list[str]:
    return ["--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader", "--hide-scrollbars", f"--user-data-dir={tmp}",
            "--allow-file-access-from-files", "--no-first-run"]


def probe(page: str, tmp: str) -> tuple[dict, float]:
    """Open a probed copy of ``page``; the probe's JSON and the wall time of the whole Chromium run [s]."""
    with open(page, encoding="utf-8") as fh:
        text = fh.read()
    probed = os.path.join(tmp, "probed.html")
    with open(probed, "w", encoding="utf-8") as fh:
        fh.write(text.replace("<head>", "<head>" + PROBE, 1))
    t0 = time.perf_counter()
    run = subprocess.run([chromium(), *_flags(os.path.join(tmp, "profile")), "--virtual-time-budget=4000",
                          "--dump-dom", f"file://{probed}"], capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    m = re.search(r'<pre id="__probe">(.*?)</pre>', run.stdout, re.S)
    if not m:
        return {"errors": [f"no probe output (chromium exit {run.returncode}): {run.stderr[-400:]}"]}, wall
    return json.loads(html.unescape(m.group(1))), wall


SHOW = """<script>window.addEventListener('load', function () {
  var ids = %s, first = document.body.firstChild;
  ids.forEach(function (id) { var el = document.getElementById(id); if (!el) { return; }
    document.body.insertBefore(el, first);
    el.querySelectorAll('.lazy-plot').forEach(function (d) { window.heliotwinDraw(d); });
    if (el.classList.contains('lazy-plot')) { window.heliotwinDraw(el); } });
  window.scrollTo(0, 0);
});</script>"""


def screenshot(page: str, elements: list, path: str, tmp: str, size=(1400, 1100)) -> None:
    """A screenshot of ``page`` with the elements of the ids ``elements`` moved to the top once loaded (their
    lazy figures drawn: what a click on the map or a link scrolls to), after 6 s of virtual time."""
    with open(page, encoding="utf-8") as fh:
        text = fh.read()
    copy = os.path.join(tmp, f"shot-{elements[0]}.html")
    with open(copy, "w", encoding="utf-8") as fh:
        head, tail = text.rsplit("</body>", 1)  # the last one: plotly.js holds the text "</body>" too
        fh.write(head + SHOW % json.dumps(list(elements)) + "</body>" + tail)
    subprocess.run([chromium(), *_flags(os.path.join(tmp, "profile-shot")), f"--window-size={size[0]},{size[1]}",
                    "--virtual-time-budget=6000", f"--screenshot={path}", f"file://{copy}"],
                   capture_output=True, text=True, timeout=600, check=False)


def first_alarm(page: str) -> str | None:
    """The id of the first alarmed heliostat with a section (the alarm table's first link)."""
    with open(page, encoding="utf-8") as fh:
        text = fh.read()
    m = re.search(r"<table id='alarms'>.*?<a href=\"#(h-[^\"]+)\">", text, re.S)
    return m.group(1) if m else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pages", nargs="+", help="HTML pages written by heliotwin report")
    ap.add_argument("--out", required=True, help="folder for the screenshots and bench_report.json")
    ap.add_argument("--runs", type=int, default=3, help="timing runs per page (median reported)")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    results, bad = {}, False
    for page in args.pages:
        stem = os.path.splitext(os.path.basename(page))[0]
        runs = []
        with tempfile.TemporaryDirectory() as tmp:
            for _ in range(args.runs):
                runs.append(probe(page, tmp))
            shots = {"map": ["map", "fieldmap"]}
            alarm = first_alarm(page)
            if alarm:
                shots["alarm"] = [alarm, "alarms"]
            shots["receiver"] = ["receiver-h", "receiver-note", "receiver"]
            shots["plan"] = ["plan-h", "tomorrow"]
            if "id='year-h'" in open(page, encoding="utf-8").read():  # a plant with its year stored
                shots["year"] = ["year-h", "yearmap", "yearmonths"]
            for name, elements in shots.items():
                screenshot(page, elements, os.path.join(args.out, f"{stem}_{name}.png"), tmp)
        p = runs[-1][0]
        fcp = [dict(r[0].get("paint") or []).get("first-contentful-paint") for r in runs]
        res = {"bytes": os.path.getsize(page), "errors": p.get("errors"), "plots": p.get("plots"),
               "drawn": p.get("drawn"), "lazy_figures": p.get("lazy"), "map_drawn": p.get("map_drawn"),
               "webgl_canvas": p.get("gl"),
               "first_contentful_paint_ms": statistics.median([v for v in fcp if v is not None] or [float("nan")]),
               "load_ms": statistics.median([r[0].get("load_ms") or float("nan") for r in runs]),
               "chromium_wall_s": statistics.median([r[1] for r in runs]), "alarm_section": alarm,
               "screenshots": sorted(f"{stem}_{n}.png" for n in shots)}
        results[page] = res
        ok = not res["errors"] and res["map_drawn"] and res["drawn"] == res["plots"]
        bad |= not ok
        print(f"{page}: {res['bytes'] / 1e6:.1f} MB, {res['drawn']}/{res['plots']} plots drawn at load (map "
              f"{'drawn' if res['map_drawn'] else 'NOT drawn'}; {res['lazy_figures']} drawn when scrolled to), "
              f"first paint "
              f"{res['first_contentful_paint_ms']:.0f} ms, load {res['load_ms']:.0f} ms, chromium run "
              f"{res['chromium_wall_s']:.1f} s, console errors: {res['errors'] or 'none'}")
    with open(os.path.join(args.out, "bench_report.json"), "w", encoding="utf-8") as fh:
        json.dump(results, fh, indent=1)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
