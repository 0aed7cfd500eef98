"""The plant page as one self-contained HTML file: Plotly figures with plotly.js inlined once, no network.

:func:`render_page` draws what :func:`heliotwin.workflows.report.plant_report` gathered: the field map
(one WebGL scatter, its colour switched by a menu, hover for every value, a click jumps to the heliostat's
section), the alarms, the calibration plan with its sky maps, the per-heliostat sections (offsets with their
2-sigma band across updates, alarms marked, residuals, a learned surface's tilt from the ideal facets), the
receiver maps on one colour scale with the aim points and the peak-flux limit contour, the plant's year when the
plant file holds one (its field map by annual energy and by the energy lost to tracking and to the mirror, the
heliostats with the most energy at stake, the monthly energy, the weather and interpolation checks), and the
provenance. It computes nothing physical.

The only hand-written JavaScript is the click handler of the field map (a few lines; Plotly has no "link"
action). Plotly is a declared dependency; without it :func:`render_page` raises a one-line error.
"""
from __future__ import annotations

import html
import json

import numpy as np

from ..errors import HeliotwinError
from ..plots import angle_origin, instant_line
from ..timefmt import AZIMUTH_CONVENTION, AZIMUTH_LABEL, utc_or_label, utc_text

try:  # a declared dependency; the message below says what to do where it is missing
    import plotly.graph_objects as go
    import plotly.io as pio
    from plotly.offline import get_plotlyjs
    from plotly.subplots import make_subplots
except ImportError:  # pragma: no cover - plotly is installed with heliotwin
    go = None

__all__ = ["render_page", "PLOTLY_MISSING"]

#: The error when plotly cannot be imported.
PLOTLY_MISSING = ("heliotwin report needs plotly (a dependency of heliotwin: pip install 'plotly>=5'); "
                  "it is not importable here")

_CSS = """
body{font-family:system-ui,sans-serif;margin:0 auto;max-width:1280px;padding:0 16px;color:#222}
h1{font-size:1.5em} h2{border-bottom:1px solid #ccc;padding-top:8px}
table{border-collapse:collapse;font-size:.9em} td,th{border:1px solid #ddd;padding:3px 7px;text-align:left}
th{background:#f3f3f3} .note{color:#666;font-size:.9em} .hl{outline:3px solid #e6550d}
nav a{margin-right:1em} section.heliostat{border-top:1px dotted #bbb;margin-top:1em}
"""

#: Draws the ``lazy-plot`` figures when they come within 600 px of the viewport (all at once without an observer);
#: ``window.heliotwinDraw(div)`` draws one now (a browser test's hook).
_LAZY = """
<script>
(function(){var els=document.querySelectorAll('.lazy-plot');
function draw(el){if(el.dataset.drawn){return;} el.dataset.drawn='1';
var f=JSON.parse(document.getElementById(el.id+'-json').textContent);
Plotly.newPlot(el,f.data,f.layout,{displaylogo:false,responsive:true});}
window.heliotwinDraw=draw;
if(!('IntersectionObserver' in window)){els.forEach(draw);return;}
var io=new IntersectionObserver(function(es){es.forEach(function(e){if(e.isIntersecting){draw(e.target);
io.unobserve(e.target);}});},{rootMargin:'600px'});
els.forEach(function(el){io.observe(el);});})();
</script>
"""

_CLICK = """
<script>
['fieldmap','yearmap'].forEach(function(name){var map=document.getElementById(name); if(!map||!map.on){return;}
map.on('plotly_click',function(ev){var id=ev.points[0].text; var el=document.getElementById('h-'+id);
var note=document.getElementById('clicked');
document.querySelectorAll('.hl').forEach(function(e){e.classList.remove('hl')});
if(el){el.classList.add('hl'); el.scrollIntoView({behavior:'smooth'}); note.textContent='';}
else{note.textContent=id+': no section of its own (only the heliostats that need attention most have one)';}});});
</script>
"""


def _e(x) -> str:
    return html.escape(str(x))


def _heliostat_link(heliostat, detail_ids: set) -> str:
    """The heliostat's id (escaped), a link to its section where it has one."""
    hid = _e(heliostat)
    return f'<a href="#h-{hid}">{hid}</a>' if heliostat in detail_ids else hid


def _div(fig, div_id: str) -> str:
    return pio.to_html(fig, full_html=False, include_plotlyjs=False, div_id=div_id,
                       config={"displaylogo": False, "responsive": True})


def _lazy_div(fig, div_id: str) -> str:
    """A figure drawn when it scrolls near the viewport (:data:`_LAZY`): the page loads as fast with 400
    heliostat sections as with 4. The figure's JSON sits in a ``<script type="application/json">``."""
    height = int(fig.layout.height or 420)
    return (f'<div id="{div_id}" class="lazy-plot" style="height:{height}px"></div>'
            f'<script type="application/json" id="{div_id}-json">{fig.to_json()}</script>')


def _fmt(v, digits: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}g}"


# -------------------------------------------------------------------------------------------- field map
def _field_map(state: dict, quantities: dict, colour: str):
    """The field map: ONE WebGL scatter of every heliostat (positions and ids once, so the page stays small at
    10,000 heliostats); the menu restyles its colour array. Unknown values (NaN) draw dark grey."""
    ids = np.asarray(state["ids"], dtype=object)
    keys = list(quantities)
    table = np.stack([np.asarray(state[k], dtype=np.float32) for k in keys], axis=1)
    hover = "<b>%{text}</b><br>" + "<br>".join(f"{_e(quantities[k][0])}: %{{customdata[{j}]:.3g}}"
                                               for j, k in enumerate(keys)) + "<extra></extra>"

    def style(k):
        v = table[:, keys.index(k)]
        return {"marker.color": [np.where(np.isfinite(v), np.round(v, 4), None).tolist()],
                "marker.colorscale": ["YlOrRd" if quantities[k][1] else "Viridis"],
                "marker.colorbar.title.text": _e(quantities[k][0])}

    first = style(colour)
    fig = go.Figure(go.Scattergl(
        x=np.asarray(state["x_m"], dtype=np.float32), y=np.asarray(state["y_m"], dtype=np.float32), text=ids,
        customdata=table, mode="markers", name="heliostats (dark grey: no value)", hovertemplate=hover,
        marker=dict(size=6 if len(ids) <= 3000 else 4, color=table[:, keys.index(colour)],
                    colorscale=first["marker.colorscale"][0], showscale=True,
                    colorbar=dict(title=dict(text=first["marker.colorbar.title.text"], side="right")))))
    nominal = np.asarray(state.get("nominal", np.zeros(len(ids))), dtype=bool)
    if nominal.any():  # their own class on every colour: a heliostat on nominal kinematics is no "missing value"
        fig.add_trace(go.Scattergl(
            x=np.asarray(state["x_m"], dtype=np.float32)[nominal],
            y=np.asarray(state["y_m"], dtype=np.float32)[nominal],
            text=ids[nominal], mode="markers", name=f"nominal kinematics, not calibrated ({int(nominal.sum())})",
            hovertemplate="<b>%{text}</b><br>nominal kinematics (not calibrated)<extra></extra>",
            marker=dict(symbol="x", size=9 if len(ids) <= 3000 else 6, color="#1f77b4",
                        line=dict(width=1, color="#1f77b4"))))
    fig.add_trace(go.Scatter(x=[0.0], y=[0.0], mode="markers", name="tower", hoverinfo="name",
                             marker=dict(symbol="triangle-up", size=14, color="black")))
    buttons = [dict(label=quantities[k][0], method="restyle", args=[style(k), [0]]) for k in keys]
    fig.update_layout(
        height=640, margin=dict(l=60, r=20, t=60, b=50), legend=dict(orientation="h", y=-0.08),
        xaxis=dict(title="east [m]"), yaxis=dict(title="north [m]", scaleanchor="x", scaleratio=1),
        updatemenus=[dict(buttons=buttons, active=keys.index(colour), x=0.0, xanchor="left", y=1.1, yanchor="top")],
        title=dict(text="colour:", x=0.0, y=0.99, font=dict(size=12)))
    return fig


# ------------------------------------------------------------------------------------------- heliostats
#: Time axis of a heliostat's history: dates (a history of one instant otherwise reads 12:58:59.999).
_DATE_AXIS = dict(type="date", tickformat="%Y-%m-%d", hoverformat="%Y-%m-%dT%H:%MZ")


def _time_range(times: list) -> list | None:
    """The x range [ISO, ISO] of a history: its span, at least a week around it (one record, or several of a
    day, would otherwise make an axis of milliseconds); None without times."""
    t = np.array([np.datetime64(x[:16]) for x in times if x]) if times else np.array([])
    if not len(t):
        return None
    lo, hi = t.min(), t.max()
    pad = max((hi - lo) / 20, np.timedelta64(3, "D"))
    return [str(lo - pad), str(hi + pad)]


def _detail_figure(d: dict):
    """A heliostat's whole history on one date axis: each encoder offset on its own y axis with its 2-sigma bars
    (the calibration's value at its latest record, then after each assimilated record; alarms marked), and the
    pointing error of every record (the calibration's records: the calibrated model's residual; the updates':
    the miss before assimilation) with the predicted error."""
    cal = d.get("calibration") or {}
    names = list(dict.fromkeys(list(d["offsets_mrad"]) + list(cal.get("offsets_mrad") or {})))
    rows = len(names) + 1
    titles = [f"{n} [mrad] (bars: 2 sigma)" for n in names] + ["pointing error of each record [mrad]"]
    fig = make_subplots(rows=rows, cols=1, shared_xaxes=True, vertical_spacing=0.06, subplot_titles=titles)
    t = d["time"]
    alarm = np.asarray(d["alarm"], dtype=bool)
    for r, name in enumerate(names, 1):
        x, y, e = [], [], []
        if name in (cal.get("offsets_mrad") or {}) and cal.get("at"):
            x, y, e = [cal["at"]], [cal["offsets_mrad"][name]], [2 * cal["offsets_std_mrad"][name]]
            fig.add_trace(go.Scatter(x=x, y=y, mode="markers", name=f"{name}: calibration",
                                     marker=dict(symbol="diamond", size=9, color="black"),
                                     error_y=dict(type="data", array=e, visible=True, thickness=1.5)), row=r, col=1)
        if name in d["offsets_mrad"]:
            mean, std = d["offsets_mrad"][name], 2 * np.asarray(d["offsets_std_mrad"][name])
            fig.add_trace(go.Scatter(x=t, y=mean, mode="lines+markers", name=f"{name}: updates",
                                     error_y=dict(type="data", array=std, visible=True, thickness=1)), row=r, col=1)
            if alarm.any():
                fig.add_trace(go.Scatter(x=list(np.asarray(t)[alarm]), y=list(np.asarray(mean)[alarm]),
                                         mode="markers", name=f"step alarm ({name})",
                                         marker=dict(symbol="x", size=12, color="red")), row=r, col=1)
    if cal.get("time"):
        fig.add_trace(go.Scatter(x=cal["time"], y=cal["error_mrad"], mode="markers", name="calibration records "
                                 "(residual of the calibrated model)", marker=dict(size=5, color="grey")),
                      row=rows, col=1)
    if t:
        fig.add_trace(go.Scatter(x=t, y=d["residual_mrad"], mode="markers", name="updates' records (miss before "
                                 "assimilation)"), row=rows, col=1)
        fig.add_trace(go.Scatter(x=t, y=d["predicted_error_mrad"], mode="lines", name="predicted error"),
                      row=rows, col=1)
    span = _time_range(list(cal.get("time") or []) + list(t) + ([cal["at"]] if cal.get("at") else []))
    fig.update_xaxes(**_DATE_AXIS, **({"range": span} if span else {}))
    fig.update_layout(height=160 + 150 * rows, margin=dict(l=60, r=20, t=40, b=40))
    return fig


def _surface_figure(hid: str, surf: dict):
    """The learned surface: per facet, the angle of its normals to the ideal facet's [mrad], one colour scale."""
    dev = [np.asarray(f, dtype=float) for f in surf["deviation_mrad"]]
    top = max(float(d.max()) for d in dev) or 1.0
    fig = make_subplots(rows=1, cols=len(dev), subplot_titles=[f"facet {k + 1}" for k in range(len(dev))],
                        horizontal_spacing=0.03)
    for k, d in enumerate(dev, 1):
        fig.add_trace(go.Heatmap(z=d, zmin=0.0, zmax=top, colorscale="Magma", showscale=k == 1,
                                 colorbar=dict(title="normal vs ideal [mrad]"),
                                 hovertemplate="%{z:.2f} mrad<extra></extra>"), row=1, col=k)
        fig.update_xaxes(showticklabels=False, row=1, col=k)
        fig.update_yaxes(showticklabels=False, row=1, col=k)
    fig.update_layout(height=260, margin=dict(l=30, r=20, t=50, b=20),
                      title=dict(text=f"{_e(hid)}: learned surface, RMS {surf['rms_mrad']:.2f} mrad from the ideal "
                                      "canted facets", font=dict(size=12)))
    return fig


def _sky_figure(p: dict):
    """The plan's sky map: the predictive spread now, averaged in 5 deg x 2.5 deg cells of sun azimuth and
    elevation (a heatmap: no WebGL context, a few hundred cells), the proposed sun positions marked."""
    sky = p["sky"]
    az, el, std = (np.asarray(sky[k], dtype=float) for k in ("sun_azimuth_deg", "sun_elevation_deg", "std_now_mrad"))
    az_edges = np.arange(np.floor(az.min() / 5) * 5, az.max() + 5.0, 5.0) if len(az) else np.array([0.0, 5.0])
    el_edges = np.arange(np.floor(el.min() / 2.5) * 2.5, el.max() + 2.5, 2.5) if len(el) else np.array([0.0, 2.5])
    total, _, _ = np.histogram2d(el, az, bins=(el_edges, az_edges), weights=std)
    count, _, _ = np.histogram2d(el, az, bins=(el_edges, az_edges))
    mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    fig = go.Figure(go.Heatmap(x=0.5 * (az_edges[1:] + az_edges[:-1]), y=0.5 * (el_edges[1:] + el_edges[:-1]),
                               z=np.round(mean, 4), colorscale="Viridis", colorbar=dict(title="spread now [mrad]"),
                               hovertemplate="azimuth %{x:.0f}, elevation %{y:.1f} deg: %{z:.3f} mrad<extra></extra>"))
    fig.add_trace(go.Scatter(x=[q["sun_azimuth_deg"] for q in p["proposals"]],
                             y=[q["sun_elevation_deg"] for q in p["proposals"]], mode="markers+text",
                             text=[str(i + 1) for i in range(len(p["proposals"]))], textposition="top center",
                             name="proposed records", marker=dict(symbol="star", size=14, color="red")))
    fig.update_layout(height=320, margin=dict(l=60, r=20, t=30, b=40),
                      xaxis=dict(title=AZIMUTH_LABEL),
                      yaxis=dict(title="sun elevation [deg]"), showlegend=False,
                      title=dict(text=f"{_e(p['heliostat'])}: sun-position coverage (stars: proposed records)",
                                 font=dict(size=12)))
    return fig


def _sections(details: list, plans: list) -> str:
    planned = {p["heliostat"]: p for p in plans if "sky" in p}
    out = []
    for k, d in enumerate(details):
        hid = d["heliostat"]
        parts = [f'<section class="heliostat" id="h-{_e(hid)}"><h3>{_e(hid)}</h3>']
        cal = d.get("calibration") or {}
        if cal.get("nominal"):
            parts.append('<p class="note nominal">nominal kinematics: the calibration left it uncalibrated</p>')
        if d["time"] or cal.get("time"):
            n_alarm = int(np.sum(d["alarm"]))
            latest = max(list(d["time"]) + list(cal.get("time") or []))
            expected = cal.get("expected_error_mrad")
            parts.append(f'<p>{len(cal.get("time") or [])} calibration records'
                         + (f" (expected error {expected:.2f} mrad)" if expected is not None else "")
                         + f', {len(d["time"])} assimilated records, {n_alarm} step alarm(s), latest '
                         f'{_e(utc_text(latest))}</p>')
            parts.append(_lazy_div(_detail_figure(d), f"hist-{k}"))
        else:
            parts.append('<p class="note">no record history stored (never updated since its calibration)</p>')
        if hid in planned:
            parts.append(_lazy_div(_sky_figure(planned[hid]), f"sky-{k}"))
        if d.get("surface"):
            parts.append(_lazy_div(_surface_figure(hid, d["surface"]), f"surface-{k}"))
        if d.get("year"):
            parts.append(_year_line(d["year"]))
        parts.append("</section>")
        out.append("".join(parts))
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------- tables
#: Most rows of the alarm table (the largest alarms; the count of the others is named below it).
ALARM_ROWS = 100


def _alarm_table(alarms: list, detail_ids: set) -> str:
    if not alarms:
        return '<p class="note">no step alarm in the latest update</p>'
    rows = []
    for a in alarms[:ALARM_ROWS]:
        link = _heliostat_link(a["heliostat"], detail_ids)
        rows.append(f"<tr><td>{link}</td><td>{_e(utc_text(a['time']))}</td><td>{a['record_id']}</td>"
                    f"<td>{a['statistic']:.1f} (threshold {_fmt(a['threshold'])})</td>"
                    f"<td>{a['innovation_mrad']:.2f}</td><td>{_e(a['action'])}</td></tr>")
    return ("<table id='alarms'><tr><th>heliostat</th><th>record time (UTC)</th><th>record</th><th>step statistic"
            "</th><th>miss [mrad]</th><th>what to do</th></tr>" + "".join(rows) + "</table>"
            + (f'<p class="note">... and {len(alarms) - ALARM_ROWS} smaller alarm(s) (heliotwin update --json lists '
               'every one)</p>' if len(alarms) > ALARM_ROWS else ""))


def _plan_table(plans: list, detail_ids: set) -> str:
    if not plans:
        return '<p class="note">no plan: the scenario stores no posterior (calibrate --method lm)</p>'
    rows = []
    for p in plans:
        link = _heliostat_link(p["heliostat"], detail_ids)
        if "error" in p:
            rows.append(f"<tr><td>{link}</td><td colspan=3>{_e(p['error'])}</td></tr>")
            continue
        props = "<br>".join(f"{_e(utc_text(q['time']))}: azimuth {q['sun_azimuth_deg']:.1f}, elevation "
                            f"{q['sun_elevation_deg']:.1f} deg -> {q['spread_after_mrad']:.3f} mrad"
                            for q in p["proposals"])
        rows.append(f"<tr><td>{link}</td><td>{_fmt(p['interval_mrad'])} / {p['alarms_latest']}</td>"
                    f"<td>{p['spread_now_mrad']:.3f} on {_e(p['spread_day'])}, {_e(p['target'])}</td>"
                    f"<td>{props}</td></tr>")
    skies = [_lazy_div(_sky_figure(p), f"plan-sky-{k}") for k, p in enumerate(plans)
             if "sky" in p and p["heliostat"] not in detail_ids]  # the others' sky maps are in their sections
    return ("<table id='plan'><tr><th>heliostat</th><th>offset interval [mrad] / alarms</th><th>predicted pointing "
            "spread [mrad] on the day</th><th>proposed sun positions over the year from the day on (UTC; sun "
            f"azimuth / elevation [deg], {_e(AZIMUTH_CONVENTION)}) -> predicted pointing spread after [mrad]</th>"
            "</tr>" + "".join(rows) + "</table>" + "".join(skies))


def _tomorrow_table(t: dict | None, detail_ids: set) -> str:
    """Tomorrow's plan for the plant: one row per record, in priority order."""
    if not t or "note" in t:
        return f'<p class="note">no plan for tomorrow: {_e((t or {}).get("note", "not asked for"))}</p>'
    if not t.get("proposals"):
        return f'<p class="note">{_e(t["day"])}: nothing to record ({t["candidates"]} candidate times)</p>'
    rows = []
    for k, q in enumerate(t["proposals"], 1):
        link = _heliostat_link(q["heliostat"], detail_ids)
        rows.append(f"<tr><td>{k}</td><td>{link}</td><td>{_e(utc_text(q['time']))}</td>"
                    f"<td>{q['sun_azimuth_deg']:.1f} / {q['sun_elevation_deg']:.1f}</td><td>{_e(q['reason'])}</td>"
                    f"<td>{_fmt(q.get('spread_now_mrad'))} -> {_fmt(q.get('spread_after_mrad'))}</td></tr>")
    fewer = f" ({_e(t['why_fewer'])})" if t.get("why_fewer") else ""
    head = (f"<p>{_e(t['day'])} (UTC), target {_e(t['target'])}: {len(t['proposals'])} of {t.get('slots', '?')} "
            f"slot(s) planned{fewer}; ranked by {_e(t.get('ranked_by', ''))}; predicted pointing spread over the "
            f"plant: median {_fmt(t.get('median_spread_mrad'))}, p95 {_fmt(t.get('p95_spread_mrad'))} mrad</p>"
            f"<p class='note' id='spread-definition'>{_e(t.get('spread_definition', ''))}</p>")
    return (head + "<table id='tomorrow'><tr><th>#</th><th>heliostat</th><th>time (UTC)</th><th>sun azimuth / "
            f"elevation [deg] ({_e(AZIMUTH_CONVENTION)})</th><th>why</th><th>predicted pointing spread now -> "
            "after this record [mrad]</th></tr>" + "".join(rows) + "</table>")


def _provenance(described: dict) -> str:
    rows = []
    for i, s in enumerate(described.get("provenance") or [], 1):
        how = ", ".join(f"{_e(k)}={_e(v)}" for k, v in s.items() if k not in ("step", "utc", "heliotwin"))
        rows.append(f"<tr><td>{i}</td><td>{_e(utc_or_label(s.get('utc')))}</td><td>{_e(s.get('step', '?'))}</td>"
                    f"<td>{how}</td><td>{_e(s.get('heliotwin', '?'))}</td></tr>")
    return ("<table id='provenance'><tr><th>#</th><th>UTC</th><th>step</th><th>inputs and settings</th>"
            "<th>heliotwin</th></tr>" + "".join(rows) + "</table>")


# ---------------------------------------------------------------------------------------------- receiver
def _receiver_figure(rec: dict):
    maps = rec["maps"]
    ext = rec["extent_m"]
    vmax = max([float(m["flux_w_m2"].max()) for m in maps.values()] + [rec["limit_w_m2"] or 0.0]) / 1e3 or 1.0
    fig = make_subplots(rows=1, cols=len(maps), shared_yaxes=True, horizontal_spacing=0.05,
                        subplot_titles=[f"{_e(k)}: peak {m['peak_w_m2'] / 1e3:.0f} kW/m², {m['power_w'] / 1e6:.2f} MW"
                                        for k, m in maps.items()])
    for c, (label, m) in enumerate(maps.items(), 1):
        a = m["flux_w_m2"] / 1e3
        rows, cols = a.shape
        xs = ext[0] + (np.arange(cols) + 0.5) * (ext[1] - ext[0]) / cols
        ys = ext[3] - (np.arange(rows) + 0.5) * (ext[3] - ext[2]) / rows
        fig.add_trace(go.Heatmap(x=xs, y=ys, z=a, zmin=0.0, zmax=vmax, colorscale="Inferno", showscale=c == 1,
                                 colorbar=dict(title="flux [kW/m²]"), name=label,
                                 hovertemplate="arc %{x:.2f} m, height %{y:.2f} m: %{z:.0f} kW/m²<extra></extra>"),
                      row=1, col=c)
        if rec["limit_w_m2"]:
            lim = rec["limit_w_m2"] / 1e3
            fig.add_trace(go.Contour(x=xs, y=ys, z=a, showscale=False, contours=dict(start=lim, end=lim, size=1,
                                                                                      coloring="none"),
                                     line=dict(color="cyan", dash="dash", width=2), hoverinfo="skip",
                                     name=f"limit {lim:.0f} kW/m²", showlegend=c == 1), row=1, col=c)
        if label == "stored aim points" and rec["aim_local_m"] is not None:
            aim = np.asarray(rec["aim_local_m"])
            fig.add_trace(go.Scattergl(x=aim[:, 0], y=aim[:, 1], mode="markers", name="aim points",
                                       marker=dict(size=3, color="cyan", opacity=0.5), hoverinfo="skip"),
                          row=1, col=c)
        fig.update_xaxes(title_text="arc along the unrolled receiver [m]" if rec["cylinder"] else "across [m]",
                         row=1, col=c)
    fig.update_yaxes(title_text="height [m]", row=1, col=1)
    fig.update_layout(height=420, margin=dict(l=60, r=20, t=60, b=50), legend=dict(orientation="h", y=-0.2))
    return fig


def _receiver_section(rec: dict | None) -> str:
    if rec is None:
        return '<p class="note">no receiver map (the plant has no receiver, or --no-flux)</p>'
    if "maps" not in rec:
        return f'<p class="note">{_e(rec["note"])}</p>'
    when = instant_line({"time_utc": rec["time_utc"], "sun_enu": rec["sun_enu"]})
    axis = f"; angle axis: {angle_origin(rec['receiver'])} (angle = arc / {rec['radius_m']:.2f} m)" \
        if rec["cylinder"] else ""
    limit = f"peak-flux limit {rec['limit_w_m2'] / 1e3:.0f} kW/m² (dashed)" if rec["limit_w_m2"] else "no stored limit"
    return (f"<p id='receiver-note'>{_e(when)}; {_e(limit)}{_e(axis)}</p>" + _div(_receiver_figure(rec), "receiver"))


# -------------------------------------------------------------------------------------------------- year
_MONTHS = ("Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec")
#: The year's honesty targets (issue 43): share of DNI energy below the horizon, interpolation errors.
BELOW_HORIZON_OK = 0.005
INTERPOLATION_OK = {"median_error": 0.01, "p95_error": 0.03, "field_error": 0.003}


def _pct(v, digits: int = 2) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.{digits}f} %"


def _year_map(year: dict, quantities: dict):
    """The field map of the year: ONE WebGL scatter, its colour switched by a menu between the year's quantities
    (stored values, unrounded beyond 1e-6); a click jumps to the heliostat's section like the field map's."""
    ids = np.asarray(year["ids"], dtype=object)
    keys = [k for k in quantities if np.isfinite(year[k]).any()]
    table = np.stack([np.asarray(year[k], dtype=np.float64) for k in keys], axis=1)
    hover = "<b>%{text}</b><br>" + "<br>".join(f"{_e(quantities[k][0])}: %{{customdata[{j}]:.4g}}"
                                               for j, k in enumerate(keys)) + "<extra></extra>"

    def values(k):
        v = table[:, keys.index(k)]
        return np.where(np.isfinite(v), np.round(v, 6), None).tolist()

    def style(k):
        return {"marker.color": [values(k)], "marker.colorscale": ["YlOrRd" if quantities[k][1] else "Viridis"],
                "marker.colorbar.title.text": _e(quantities[k][0])}

    first = keys[0]
    fig = go.Figure(go.Scattergl(
        x=np.asarray(year["x_m"], dtype=np.float32), y=np.asarray(year["y_m"], dtype=np.float32), text=ids,
        customdata=np.round(table, 6), mode="markers", name="heliostats (dark grey: no value)", hovertemplate=hover,
        marker=dict(size=6 if len(ids) <= 3000 else 4, color=values(first), colorscale=style(first)[
            "marker.colorscale"][0], showscale=True,
            colorbar=dict(title=dict(text=style(first)["marker.colorbar.title.text"], side="right")))))
    fig.add_trace(go.Scatter(x=[0.0], y=[0.0], mode="markers", name="tower", hoverinfo="name",
                             marker=dict(symbol="triangle-up", size=14, color="black")))
    fig.update_layout(
        height=560, margin=dict(l=60, r=20, t=60, b=50), legend=dict(orientation="h", y=-0.08),
        xaxis=dict(title="east [m]"), yaxis=dict(title="north [m]", scaleanchor="x", scaleratio=1),
        updatemenus=[dict(buttons=[dict(label=quantities[k][0], method="restyle", args=[style(k), [0]])
                                   for k in keys], active=0, x=0.0, xanchor="left", y=1.1, yanchor="top")],
        title=dict(text="colour:", x=0.0, y=0.99, font=dict(size=12)))
    return fig


def _monthly_figure(year: dict):
    """The monthly energy on the receiver [MWh] as bars, the stored months unchanged."""
    m = np.asarray(year["monthly_energy_mwh"], dtype=np.float64)
    fig = go.Figure(go.Bar(x=list(_MONTHS), y=np.where(np.isfinite(m), m, None).tolist(),
                           hovertemplate="%{x}: %{y:.4g} MWh<extra></extra>", marker=dict(color="#e6850d")))
    fig.update_layout(height=320, margin=dict(l=60, r=20, t=40, b=40), yaxis=dict(title="energy on the receiver "
                      "[MWh]"), title=dict(text=f"months of {year['year'] or 'the year'}: sum {np.nansum(m):.4g} MWh",
                                           font=dict(size=12)))
    return fig


def _bounds(v, lo, hi) -> str:
    if v is None:
        return "-"
    inner = f" [{_fmt(lo)}, {_fmt(hi)}]" if lo is not None and hi is not None else ""
    return f"{_fmt(v)}{inner}"


def _year_action(r: dict) -> str:
    """What a crew does first for one row: the larger loss names the job."""
    track, surf = r.get("tracking_loss_mwh") or 0.0, r.get("surface_loss_mwh") or 0.0
    if track <= 0 and surf <= 0:
        return "nothing: no loss of its own"
    if track >= surf:
        return "tracking: take calibration records / check drive and encoders"
    return "mirror: inspect the facets (canting, shape), wash if soiled"


def _year_table(rows: list, detail_ids: set) -> str:
    if not rows:
        return '<p class="note">no heliostat rows asked for</p>'
    out = []
    for r in rows:
        link = _heliostat_link(r["heliostat"], detail_ids)
        surface = _bounds(r["surface_loss_mwh"], r["surface_loss_low_mwh"], r["surface_loss_high_mwh"]) \
            if r["surface_learned"] else "ideal (not learned)"
        out.append(f"<tr><td>{r['rank']}</td><td>{link}</td><td>{_fmt(r['energy_mwh'], 4)}</td>"
                   f"<td>{_fmt(r['efficiency'])}</td>"
                   f"<td>{_bounds(r['tracking_loss_mwh'], r['tracking_loss_low_mwh'], r['tracking_loss_high_mwh'])}"
                   f"</td><td>{surface}</td>"
                   f"<td>{_bounds(r['at_stake_mwh'], r['at_stake_low_mwh'], r['at_stake_high_mwh'])}</td>"
                   f"<td>{_e(_year_action(r))}</td></tr>")
    return ("<table id='year-top'><tr><th>#</th><th>heliostat</th><th>energy [MWh]</th><th>efficiency [-]</th>"
            "<th>lost to tracking [MWh] [interval]</th><th>lost to the mirror [MWh] [interval]</th>"
            "<th>at stake [MWh]</th><th>what to do first</th></tr>" + "".join(out) + "</table>")


def _year_checks(year: dict) -> str:
    """The weather file, its time convention, the DNI share below the horizon and the interpolation check."""
    w = year["weather"]
    name = str(w.get("file") or "?").replace("\\", "/").rsplit("/", 1)[-1]
    annual = w.get("annual")
    cover = "" if annual is None else ("; a whole year" if bool(annual) else "; NOT a whole year (the energy is of "
                                                                              "the hours the file covers)")
    share = year["dni_share_below_horizon"]
    flag = "" if not np.isfinite(share) or share <= BELOW_HORIZON_OK else \
        f" -- above {_pct(BELOW_HORIZON_OK, 1)}: the file's times are likely read with the wrong convention"
    lines = [f"<li id='year-weather'>weather: {_e(name)} ({_e(w.get('kind') or '?')}){_e(cover)}</li>",
             f"<li id='year-time'>time convention: {_e(year['time_convention'])}</li>",
             f"<li id='year-below'>DNI share below the horizon: {_pct(share)}{_e(flag)} (a correct reading keeps it "
             f"at or below {_pct(BELOW_HORIZON_OK, 1)})</li>"]
    it = year["interpolation"]
    if it is None:
        lines.append("<li id='year-interpolation'>interpolation: not checked (heliotwin year --check-hours N sums "
                     "the field model directly over N hours of the weather file and compares)</li>")
    else:
        hours = f"{int(it['checked_hours'])} hours" if np.isfinite(it["checked_hours"]) else "the checked hours"
        miss = [k for k, lim in INTERPOLATION_OK.items() if np.isfinite(it[k]) and it[k] > lim]
        verdict = "within the targets" if not miss else "OUTSIDE the target for " + ", ".join(miss)
        lines.append(f"<li id='year-interpolation'>interpolation against the direct sum of the field model over "
                     f"{hours}: per heliostat median {_pct(it['median_error'])}, p95 {_pct(it['p95_error'])}; field "
                     f"total {_pct(it['field_error'])} (targets 1 %, 3 %, 0.3 %: {verdict})</li>")
    return "<ul>" + "".join(lines) + "</ul>"


def _year_section(year: dict | None, quantities: dict, detail_ids: set) -> str:
    if year is None:
        return ""
    ann, dni = year["annual_energy_mwh"], year["annual_dni_energy_on_mirrors_mwh"]
    eff = f" (mean efficiency {ann / dni:.3f})" if np.isfinite(ann) and np.isfinite(dni) and dni > 0 else ""
    track = float(np.nansum(year["tracking_loss_mwh"]))
    surf = float(np.nansum(np.where(year["surface_learned"], year["surface_loss_mwh"], 0.0)))
    learned = int(np.sum(year["surface_learned"]))
    head = (f"{year['year'] or ''} ({year['aim']} aiming): {_fmt(ann, 5)} MWh on the receiver from {_fmt(dni, 5)} "
            f"MWh of DNI on the mirrors{eff}; lost to the heliostats' own tracking {_fmt(track, 4)} MWh, to their "
            f"mirrors {_fmt(surf, 4)} MWh ({learned} learned surfaces)")
    notes = []
    months = np.nansum(year["monthly_energy_mwh"])
    for what, total in (("the months", months), ("the heliostats' rows", year["rows_sum_mwh"])):
        if np.isfinite(ann) and ann > 0 and abs(total / ann - 1.0) > 1e-3:
            notes.append(f"{what} add up to {total:.5g} MWh, not the stored annual {ann:.5g} MWh")
    facts = json.dumps({"year": year["year"], "annual_energy_mwh": ann if np.isfinite(ann) else None,
                        "top": [r["heliostat"] for r in year.get("top", [])]})
    warn = "".join(f"<p class='note'><b>check:</b> {_e(n)}</p>" for n in notes)
    return (f"<p id='year-headline'><b>{_e(head)}</b></p>{warn}"
            f"<script type='application/json' id='year-facts'>{facts}</script>" + _year_checks(year)
            + "<h3>Field map of the year</h3><p class='note'>colour by the menu; hover for every value; click a "
            "heliostat to open its section</p>" + _div(_year_map(year, quantities), "yearmap")
            + "<h3 id='year-stake-h'>The most energy at stake</h3><p class='note'>tracking and mirror losses of each "
            "heliostat's own errors against a perfect heliostat at its place [MWh/year], with their intervals (at "
            "stake: the bounds added); what a crew fixes or washes first</p>"
            + _year_table(year.get("top", []), detail_ids)
            + "<h3>Monthly energy</h3>" + _div(_monthly_figure(year), "yearmonths"))


def _year_line(r: dict) -> str:
    """A heliostat section's line of the year."""
    surface = _bounds(r["surface_loss_mwh"], r["surface_loss_low_mwh"], r["surface_loss_high_mwh"]) + " MWh" \
        if r["surface_learned"] else "ideal mirror (not learned)"
    track = _bounds(r["tracking_loss_mwh"], r["tracking_loss_low_mwh"], r["tracking_loss_high_mwh"])
    return (f"<p class='year-line'>the year: {_fmt(r['energy_mwh'], 4)} MWh, efficiency {_fmt(r['efficiency'])}; "
            f"lost to tracking {track} MWh, to the mirror {surface}; #{r['rank']} by energy at stake</p>")


# --------------------------------------------------------------------------------------------------- page
def render_page(*, described: dict, state: dict, quantities: dict, colour: str, alarms: list, details: list,
                plans: list, receiver: dict | None, tomorrow: dict | None = None, year: dict | None = None,
                year_quantities: dict | None = None) -> str:
    """The whole page as one HTML string (module docstring).

    Parameters
    ----------
    described : dict
        :func:`heliotwin.workflows.show.describe_scenario`'s dict (plant, learned, provenance).
    state : dict
        :func:`heliotwin.workflows.report.heliostat_state` (arrays [H]).
    quantities : dict
        Key -> (label with unit, higher is worse): the field map's colour choices.
    colour : str
        The initial colour quantity.
    alarms, details, plans : list of dict
        :func:`~heliotwin.workflows.report.alarm_rows`, :func:`~heliotwin.workflows.report.heliostat_detail`
        per detailed heliostat, the plan rows.
    receiver : dict or None
        The receiver maps (flux [rows, cols] [W/m^2], extent [m], aim points on the receiver [m], limit).
    tomorrow : dict, optional
        :func:`heliotwin.calibrate.protocol.plan.plant_plan`'s plan (times UTC, sun angles [deg], spreads
        [mrad]), or ``{"note": why none}``.
    year : dict, optional
        :func:`heliotwin.workflows.report.year_state` with ``top`` (the table's rows,
        :func:`~heliotwin.workflows.report.year_row`): the section "The plant's year" (energies [MWh]).
    year_quantities : dict, optional
        Key -> (label with unit, higher is worse): the year map's colour choices (needed with ``year``).

    Raises
    ------
    HeliotwinError
        plotly is not importable (:data:`PLOTLY_MISSING`).
    """
    if go is None:
        raise HeliotwinError(PLOTLY_MISSING)
    p = described["plant"]
    k = described["learned"]["kinematics"]
    detail_ids = {d["heliostat"] for d in details}
    ref = state["reference_time"]
    ref_text = "no record times" if not np.isfinite(ref) else \
        f"latest record {utc_text(ref)}"
    kin = f"calibrated ({k['method']}) for {k.get('count', 0)}" if k["calibrated"] else "nominal"
    summary = (f"{p['heliostats']} heliostats; kinematics {kin}; {len(alarms)} step alarm(s) in the latest update; "
               f"{ref_text}")
    if k.get("nominal_line"):
        summary += f"; {k['nominal_line']}"
    facts = json.dumps({"heliostats": p["heliostats"], "alarms": len(alarms), "detail": len(details),
                        "plan": len(plans)})
    body = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>heliotwin: {_e(described.get('file') or 'plant')}</title><style>{_CSS}</style>",
        f"<script type='text/javascript'>{get_plotlyjs()}</script></head><body>",
        f"<h1>The plant at a glance</h1><p>{_e(described.get('file') or '')}</p><p><b>{_e(summary)}</b></p>",
        f"<script type='application/json' id='facts'>{facts}</script>",
        "<nav><a href='#map'>field map</a><a href='#alarms-h'>alarms</a><a href='#plan-h'>calibration plan</a>"
        "<a href='#receiver-h'>receiver</a>" + ("<a href='#year-h'>the year</a>" if year is not None else "")
        + "<a href='#heliostats-h'>heliostats</a><a href='#provenance-h'>provenance</a></nav>",
        "<h2 id='map'>Field map</h2><p class='note'>colour by the menu; hover for every value; click a heliostat "
        "to open its section. Days since the last record count from the latest record the plant holds.</p>",
        _div(_field_map(state, quantities, colour), "fieldmap"), "<p id='clicked' class='note'></p>",
        "<h2 id='alarms-h'>Alarms since the last report</h2>", _alarm_table(alarms, detail_ids),
        "<h2 id='plan-h'>Calibration plan</h2><h3>Tomorrow</h3>", _tomorrow_table(tomorrow, detail_ids),
        "<h3>Sun-position coverage</h3><p class='note'>the heliostats that need records most, as tomorrow's plan "
        "ranks them (alarmed, then the largest predicted pointing spread on the day), each with the sun positions "
        "over the year from the day on that would shrink that spread most (heliotwin plan --day)</p>",
        _plan_table(plans, detail_ids),
        "<h2 id='receiver-h'>Receiver</h2>", _receiver_section(receiver),
        *(["<h2 id='year-h'>The plant's year</h2>", _year_section(year, year_quantities, detail_ids)]
          if year is not None else []),
        f"<h2 id='heliostats-h'>Heliostats ({len(details)} with a section)</h2>", _sections(details, plans),
        "<h2 id='provenance-h'>Provenance</h2>", _provenance(described),
        _LAZY, _CLICK, "</body></html>"]
    return "\n".join(body)
