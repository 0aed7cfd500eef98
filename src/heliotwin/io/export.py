"""A plant and its results in the formats of the tools plant engineers already use.

* :func:`write_flux_map_csv` / :func:`read_flux_map_csv`: a receiver flux map as a plain CSV matrix that a
  spreadsheet opens: the first row holds the arc (or width) position of every column's cell centre [m], the
  first column the height of every row's cell centre [m] (top row first, as the figures draw it), the
  values are flux [W/m^2].
* :func:`export_solarpilot`: the layout as SolarPILOT writes its per-heliostat table (``id, x_location,
  y_location, z_location, x_aimpoint, y_aimpoint, z_aimpoint``: positions and aim points, east/north/up [m]
  about the tower base) plus the TOML plant description that ``heliotwin scenario from-layout`` reads
  (:mod:`heliotwin.field.layout`): the two re-read give the same plant (tested).
* :func:`export_soltrace`: a SolTrace input file (``.stinput``, SolTrace 3.x text format: sun, optics,
  a heliostat stage with one rectangular element per heliostat oriented for one sun, a receiver stage) and
  :func:`read_soltrace`, which reads such a file back (positions, mirror normals, sizes, optics, receiver).

What the formats cannot hold is refused in one line rather than dropped silently: heliostats of different
sizes or facet placements (one TOML ``[heliostat]``), facets canted otherwise than on-axis, a receiver other
than a cylinder or a plane. Facets that do not tile the mirror (PAINT's, with gaps) are written as
``facet_centers``/``facet_size``, on-axis canting at another distance than the slant range as the layout's
``focal_length`` column, a tilted cylinder with its ``axis``: re-importing a PAINT, simulated or demo plant
gives the same field figures (tested). Learned kinematics and learned
surfaces stay in the scenario: a layout holds pivots and the ideal mirror only (the exported TOML says so in
a comment), and SolTrace gets one flat or spherical element per heliostat, not its facets.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..errors import HeliotwinError, InputFileError
from ..field.facets import receiver_canting
from ..field.targets import CylinderTarget
from .report import atomic_path

__all__ = ["write_flux_map_csv", "read_flux_map_csv", "plant_description", "write_plant_toml",
           "export_solarpilot", "export_soltrace", "read_soltrace"]


# ------------------------------------------------------------------------------------------- flux maps
def _cell_centres(extent, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    e = [float(v) for v in extent]
    xs = e[0] + (np.arange(cols) + 0.5) * (e[1] - e[0]) / cols
    ys = e[3] - (np.arange(rows) + 0.5) * (e[3] - e[2]) / rows
    return xs, ys


def write_flux_map_csv(path, flux, extent) -> None:
    """Write a receiver flux map as a CSV matrix (module docstring), atomically.

    Parameters
    ----------
    path : path
    flux : torch.Tensor or numpy.ndarray, [rows, cols]
        [W/m^2], row 0 = top of the receiver.
    extent : sequence of 4 floats
        ``(x_min, x_max, y_min, y_max)`` [m] of the map (arc along the unrolled cylinder, height).
    """
    a = flux.detach().cpu().numpy() if torch.is_tensor(flux) else np.asarray(flux)
    a = a.astype(np.float64)
    xs, ys = _cell_centres(extent, *a.shape)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["height_m \\ arc_m (flux W/m2)"] + [f"{x:.4f}" for x in xs])
        for y, row in zip(ys, a):
            w.writerow([f"{y:.4f}"] + [f"{v:.6g}" for v in row])


def read_flux_map_csv(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read :func:`write_flux_map_csv`'s file: ``(flux [rows, cols] [W/m^2], arc centres [cols] [m],
    height centres [rows] [m])``."""
    try:
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r]
        xs = np.array([float(v) for v in rows[0][1:]])
        ys = np.array([float(r[0]) for r in rows[1:]])
        flux = np.array([[float(v) for v in r[1:]] for r in rows[1:]])
    except (OSError, ValueError, IndexError) as exc:
        raise InputFileError(path, f"not a flux map CSV ({exc})") from None
    return flux, xs, ys


# ------------------------------------------------------------------------------------- plant description
def _uniform(values: torch.Tensor, what: str, rtol: float = 1e-9) -> float:
    v = values.to(torch.float64)
    if float(v.max() - v.min()) > rtol * max(1.0, float(v.abs().max())):
        raise HeliotwinError(f"export: heliostats of different {what} ({float(v.min()):.4g} to {float(v.max()):.4g}); "
                             "a layout file describes one heliostat type")
    return float(v[0])


def _facet_grid(facets) -> tuple[int, int, str]:
    """(nx, ny, canting) of the first heliostat's facets (uniform plants only)."""
    t = facets.translation[0].to(torch.float64)
    nx = len(torch.unique(torch.round(t[:, 0] * 1e6)))
    ny = len(torch.unique(torch.round(t[:, 1] * 1e6)))
    tilted = bool((facets.canting_e[..., 2].abs() > 1e-9).any() | (facets.canting_n[..., 2].abs() > 1e-9).any())
    return nx, ny, "on-axis" if tilted else "flat"


def _facet_placement(field, nx: int, ny: int) -> dict:
    """The TOML keys that place the facets when they do not tile the mirror: ``facet_centers`` [F, 3] and
    ``facet_size`` [2] [m] (uniform over heliostats, else refused in one line)."""
    t = field.facets.translation.detach().cpu().to(torch.float64)
    if float((t - t[:1]).abs().max()) > 1e-9:
        raise HeliotwinError("export: heliostats with different facet placements; a layout file describes one "
                             "heliostat type")
    spans = [torch.linalg.vector_norm(v.detach().cpu(), dim=-1).flatten()
             for v in (field.facets.canting_e, field.facets.canting_n)]
    hw, hh = _uniform(spans[0], "facet widths", 1e-6), _uniform(spans[1], "facet heights", 1e-6)
    width, height = float(field.width[0]), float(field.height[0])
    ex = [(-width / 2 + (2 * i + 1) * width / (2 * nx)) for i in range(nx)]
    ey = [(height / 2 - (2 * j + 1) * height / (2 * ny)) for j in range(ny)]
    tile = torch.tensor([(x, y, 0.0) for y in ey for x in ex], dtype=torch.float64)
    out = {}
    if tile.shape != t[0].shape or float((tile - t[0]).abs().max()) > 1e-9:
        out["facet_centers"] = [[float(v) for v in row] for row in t[0].tolist()]
    if abs(hw - width / (2 * nx)) > 1e-9 or abs(hh - height / (2 * ny)) > 1e-9:
        out["facet_size"] = [2 * hw, 2 * hh]
    return out


def canting_focal_length(facets) -> torch.Tensor:
    """Each heliostat's on-axis canting distance [H] [m], recovered from its facets' normals (the inverse of
    :func:`heliotwin.field.facets.receiver_canting`: the facet at ``t`` has the normal of ``z = |t|^2 / (4 f)``).

    Raises
    ------
    HeliotwinError
        Facets canted otherwise (the layout format holds on-axis canting only).
    """
    t = facets.translation.detach().cpu().to(torch.float64)
    ce, cn = (v.detach().cpu().to(torch.float64) for v in (facets.canting_e, facets.canting_n))
    n = torch.nn.functional.normalize(torch.linalg.cross(ce, cn, dim=-1), dim=-1)
    slope = -n[..., :2] / n[..., 2:3]  # = t_xy / (2 f)
    inv_f = 2.0 * (slope * t[..., :2]).sum((-1, -2)) / (t[..., :2] ** 2).sum((-1, -2)).clamp_min(1e-30)
    focal = 1.0 / inv_f.clamp_min(1e-12)
    again = receiver_canting(t, 1.0, 1.0, focal)
    unit = (torch.nn.functional.normalize(ce, dim=-1), torch.nn.functional.normalize(cn, dim=-1))
    if any(float((a - b).abs().max()) > 1e-7 for a, b in zip(again, unit)):
        raise HeliotwinError("export: facets canted otherwise than on-axis (towards one point per heliostat); a "
                             "layout file holds flat or on-axis canting only")
    return focal


def plant_description(plant, atmosphere: Atmosphere | None = None) -> dict:
    """The TOML plant description (:mod:`heliotwin.field.layout`) of ``plant`` as nested dicts.

    Raises
    ------
    HeliotwinError
        Heliostats of different sizes, or no target named ``"receiver"`` (one line).
    """
    if "receiver" not in plant.targets:
        raise HeliotwinError(f"export: the plant has no target named 'receiver' (targets: {', '.join(plant.targets)})")
    f, s, rec = plant.field, plant.sun, plant.targets["receiver"]
    nx, ny, canting = _facet_grid(f.facets)
    site = plant.site
    out = {"site": {"latitude": float(site.latitude_deg), "longitude": float(site.longitude_deg),
                    "altitude": float(site.altitude_m)},
           "heliostat": {"width": _uniform(f.width, "widths"), "height": _uniform(f.height, "heights"),
                         "facets": [nx, ny], "canting": canting, "reflectivity": float(s.reflectivity),
                         "slope_error_mrad": float(s.slope_error) * 1e3, **_facet_placement(f, nx, ny)}}
    if isinstance(rec, CylinderTarget):
        axis = rec.axis_point.tolist()
        out["receiver"] = {"type": "cylinder", "radius": float(rec.radius), "height": float(rec.height),
                           "center": [float(v) for v in axis], "normal": [float(v) for v in rec.normal.tolist()],
                           "axis": [float(v) for v in rec.up.tolist()],
                           "opening_angle_deg": math.degrees(float(rec.opening_angle))}
    else:
        out["receiver"] = {"type": "planar", "width": float(rec.width), "height": float(rec.height),
                           "center": [float(v) for v in rec.center.tolist()],
                           "normal": [float(v) for v in rec.normal.tolist()]}
    sun = {"shape": s.sunshape, "dni": float(s.dni)}
    if s.sunshape == "gaussian":
        sun["sigma_mrad"] = float(s.sigma) * 1e3
    elif s.sunshape == "buie":
        sun["csr"] = float(s.csr)
    else:
        sun["radius_mrad"] = float(s.radius) * 1e3
    out["sun"] = sun
    atm = atmosphere or Atmosphere()
    out["atmosphere"] = {"model": atm.model, "coefficients": [float(c) for c in atm.coefficients]}
    return out


def _toml_value(v) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, int):
        return str(v)
    return repr(float(v))


def write_plant_toml(path, description: dict, *, header: str = "") -> None:
    """Write :func:`plant_description`'s dict as TOML (atomically); ``header`` lines become comments."""
    lines = [f"# {h}" for h in header.splitlines()]
    for section, table in description.items():
        lines.append(f"\n[{section}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines).lstrip("\n") + "\n", encoding="utf-8")


def export_solarpilot(plant, layout_path, toml_path, *, atmosphere: Atmosphere | None = None,
                      aim=None, source: str = "") -> None:
    """The plant as SolarPILOT's per-heliostat layout table plus heliotwin's TOML plant description.

    Parameters
    ----------
    plant : Plant
    layout_path, toml_path : path
        ``heliotwin scenario from-layout LAYOUT --config TOML`` reads them back into the same plant.
    atmosphere : Atmosphere, optional
    aim : torch.Tensor, [H, 3], optional
        Aim points, ENU [m] (e.g. a ``field`` run's or the scenario's stored ones); default: the receiver's
        centre (SolarPILOT re-aims anyway with its own aiming strategy).
    source : str
        Named in both files' comment header (the scenario file).
    """
    desc = plant_description(plant, atmosphere)
    pos = plant.field.kinematics.position.detach().cpu().to(torch.float64)
    rec = plant.targets["receiver"]
    aim = rec.center.detach().cpu().expand_as(pos) if aim is None else aim.detach().cpu().to(torch.float64)
    focal = None
    if desc["heliostat"]["canting"] == "on-axis":  # the layout's default distance is the slant range to the axis
        focal = canting_focal_length(plant.field.facets)
        slant = torch.linalg.vector_norm((rec.axis_point if isinstance(rec, CylinderTarget) else rec.center)
                                         .detach().cpu().to(torch.float64) - pos, dim=-1)
        if float(((focal - slant) / slant).abs().max()) < 1e-9:
            focal = None
    note = (f"exported by heliotwin from {source or 'a plant'}: pivots and the ideal mirror only (learned "
            "kinematics and surfaces stay in the scenario)")
    with atomic_path(layout_path) as tmp, open(tmp, "w", newline="") as fh:
        fh.write(f"# {note}\n# east, north, up [m] about the tower base\n")
        w = csv.writer(fh)
        w.writerow(["id", "x_location", "y_location", "z_location", "x_aimpoint", "y_aimpoint", "z_aimpoint"]
                   + (["focal_length"] if focal is not None else []))
        extra = [[f"{v:.9g}"] for v in focal.tolist()] if focal is not None else [[]] * len(pos)
        for hid, p, a, e in zip(plant.field.ids, pos.tolist(), aim.tolist(), extra):
            w.writerow([hid] + [f"{v:.6f}" for v in p] + [f"{v:.6f}" for v in a] + e)
    write_plant_toml(toml_path, desc, header=note)


# --------------------------------------------------------------------------------------------- SolTrace
_SOLTRACE_HEADER = "# SOLTRACE VERSION 3.1.0 INPUT FILE"


def _tab(*fields) -> str:
    return "\t".join(str(f) for f in fields)


def export_soltrace(plant, path, sun: torch.Tensor, normal: torch.Tensor, *, source: str = "") -> None:
    """A SolTrace input file of ``plant`` at one sun (SolTrace's 3.x ``.stinput`` text format).

    Parameters
    ----------
    plant : Plant
        Uniform heliostat size; a cylindrical or planar target named ``"receiver"``.
    path : path
    sun : torch.Tensor, [3]
        Unit vector towards the sun, ENU (SolTrace's frame: x east, y north, z up, tower base at the origin).
    normal : torch.Tensor, [H, 3]
        Mirror normals at that sun (e.g. :class:`heliotwin.raytrace.field.FieldResult` ``normal``): each
        element's aim point is its pivot plus the normal.
    source : str
        Named in the file's stage name.

    Notes
    -----
    One element per heliostat: a rectangle (width x height) that is flat, or spherical with curvature
    ``1 / (2 f)`` for on-axis canting at the slant range f. Sunshape: Gaussian (sigma) or pillbox (radius;
    also for the limb-darkened and Buie suns, which SolTrace takes as tables); optics: reflectivity and the
    slope error [mrad] (SolTrace's is the error per axis too). The receiver is a second stage: a cylinder
    (aperture ``l``, surface ``t`` of curvature ``1 / radius``) or a flat rectangle.
    """
    desc = plant_description(plant)
    h = desc["heliostat"]
    s = plant.sun
    pos = plant.field.kinematics.position.detach().cpu().to(torch.float64)
    nrm = normal.detach().cpu().to(torch.float64)
    rec = plant.targets["receiver"]
    shape, sigma, half = ("g", s.sigma * 1e3, 0.0) if s.sunshape == "gaussian" else ("p", 0.0, s.radius * 1e3)
    sun_xyz = (sun.detach().cpu().to(torch.float64) * 1e4).tolist()
    lines = [_SOLTRACE_HEADER,
             _tab("SUN", "PTSRC", 0, "SHAPE", shape, "SIGMA", f"{sigma:.6g}", "HALFWIDTH", f"{half:.6g}"),
             _tab("XYZ", *(f"{v:.6f}" for v in sun_xyz), "USELDH", 0, "LDH", 0, 0, 0),
             _tab("USER SHAPE DATA", 0),
             _tab("OPTICS LIST COUNT", 2)]
    for name, refl, slope in (("heliostat", s.reflectivity, s.slope_error * 1e3), ("receiver", 0.0, 0.0)):
        lines.append(_tab("OPTICAL PAIR", name))
        for _ in range(2):
            lines.append(_tab("OPTICAL", "g", 0, 1, 0, f"{refl:.6g}", 0, f"{slope:.6g}", 0, 1, 1.2, 0, 0, 0, 0, 0, 0))
    lines.append(_tab("STAGE LIST COUNT", 2))
    lines += [_tab("STAGE", "XYZ", 0, 0, 0, "AIM", 0, 0, 1, "ZROT", 0, "VIRTUAL", 0, "MULTIHIT", 1, "ELEMENTS",
                   len(pos), "TRACETHROUGH", 0), f"heliostat field{f' of {source}' if source else ''}"]
    aim_centre = rec.axis_point if isinstance(rec, CylinderTarget) else rec.center
    slant = torch.linalg.vector_norm(aim_centre.detach().cpu() - pos, dim=-1)
    for p, n, d in zip(pos.tolist(), nrm.tolist(), slant.tolist()):
        aim = [pi + ni * 100.0 for pi, ni in zip(p, n)]
        surface = ("s", 1.0 / (2.0 * d)) if h["canting"] == "on-axis" else ("f", 0.0)
        lines.append(_tab(1, *(f"{v:.6f}" for v in p), *(f"{v:.6f}" for v in aim), 0,
                          "r", f"{h['width']:.6g}", f"{h['height']:.6g}", *([0] * 6),
                          surface[0], f"{surface[1]:.9g}", *([0] * 7), "", "heliostat", 2))
    lines += [_tab("STAGE", "XYZ", 0, 0, 0, "AIM", 0, 0, 1, "ZROT", 0, "VIRTUAL", 0, "MULTIHIT", 1, "ELEMENTS", 1,
                   "TRACETHROUGH", 0), "receiver"]
    if isinstance(rec, CylinderTarget):
        c = rec.axis_point.tolist()
        r, height = float(rec.radius), float(rec.height)
        # A SolTrace cylinder element lies along its local y axis: aim the local z horizontally, rotate so
        # that y is up (zrot 90 deg about the aim line); the aperture spans x in [-r, r] and the height.
        lines.append(_tab(1, *(f"{v:.6f}" for v in (c[0], c[1], c[2] - height / 2)),
                          *(f"{v:.6f}" for v in (c[0], c[1] - 1.0, c[2] - height / 2)), 90,
                          "l", f"{-r:.6g}", f"{r:.6g}", f"{height:.6g}", *([0] * 5),
                          "t", f"{1.0 / r:.9g}", *([0] * 7), "", "receiver", 2))
    else:
        c, n = rec.center.tolist(), rec.normal.tolist()
        lines.append(_tab(1, *(f"{v:.6f}" for v in c), *(f"{a + b:.6f}" for a, b in zip(c, n)), 0,
                          "r", f"{float(rec.width):.6g}", f"{float(rec.height):.6g}", *([0] * 6),
                          "f", *([0] * 8), "", "receiver", 2))
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_soltrace(path) -> dict:
    """Read a SolTrace input file written by :func:`export_soltrace` (or one laid out the same way).

    Returns
    -------
    dict
        ``sun`` [3] (unit, ENU), ``sunshape`` (``"gaussian"``/``"pillbox"``), ``sigma_mrad``,
        ``halfwidth_mrad``, ``optics`` (name -> reflectivity, slope_error_mrad), ``stages`` (list of
        ``{"name", "elements": [{"position" [3], "aim" [3], "zrot_deg", "aperture" (char, params),
        "surface" (char, params), "optic"}]}``), and for the first stage ``position`` [H, 3] and ``normal``
        [H, 3] (unit, from each element's aim point) as float64 tensors.

    Raises
    ------
    InputFileError
        A line that does not match the format (names the line).
    """
    path = Path(path)
    try:
        lines = [ln.rstrip("\r\n") for ln in path.read_text(encoding="utf-8").splitlines()]
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read ({exc})") from None
    it = iter(enumerate(lines, 1))

    def nxt():
        for no, ln in it:
            if ln.strip() and not ln.startswith("#"):
                return no, ln.split("\t")
        raise InputFileError(path, "ends early")

    def expect(tok, word):
        no, t = tok
        if t[0] != word:
            raise InputFileError(path, f"expected {word!r}, got {t[0]!r}", field=f"line {no}")
        return t

    try:
        t = expect(nxt(), "SUN")
        shape, sigma, half = t[4], float(t[6]), float(t[8])
        t = expect(nxt(), "XYZ")
        sun = torch.tensor([float(v) for v in t[1:4]], dtype=torch.float64)
        t = expect(nxt(), "USER SHAPE DATA")
        for _ in range(int(t[1])):
            nxt()
        optics = {}
        for _ in range(int(expect(nxt(), "OPTICS LIST COUNT")[1])):
            name = expect(nxt(), "OPTICAL PAIR")[1]
            front = expect(nxt(), "OPTICAL")
            expect(nxt(), "OPTICAL")
            optics[name] = {"reflectivity": float(front[5]), "slope_error_mrad": float(front[7])}
        stages = []
        for _ in range(int(expect(nxt(), "STAGE LIST COUNT")[1])):
            st = expect(nxt(), "STAGE")
            count = int(st[st.index("ELEMENTS") + 1])
            name = nxt()[1][0]
            elements = []
            for _ in range(count):
                no, e = nxt()
                if len(e) < 29:
                    raise InputFileError(path, f"element with {len(e)} fields (expected 29)", field=f"line {no}")
                elements.append({"position": [float(v) for v in e[1:4]], "aim": [float(v) for v in e[4:7]],
                                 "zrot_deg": float(e[7]), "aperture": (e[8], [float(v) for v in e[9:17]]),
                                 "surface": (e[17], [float(v) for v in e[18:26]]), "optic": e[27]})
            stages.append({"name": name, "elements": elements})
    except (ValueError, IndexError) as exc:
        raise InputFileError(path, f"malformed SolTrace input ({exc})") from None
    first = stages[0]["elements"] if stages else []
    position = torch.tensor([e["position"] for e in first], dtype=torch.float64).reshape(-1, 3)
    aims = torch.tensor([e["aim"] for e in first], dtype=torch.float64).reshape(-1, 3)
    normal = torch.nn.functional.normalize(aims - position, dim=-1)
    return {"sun": sun / torch.linalg.vector_norm(sun), "sunshape": {"g": "gaussian", "p": "pillbox"}.get(shape, shape),
            "sigma_mrad": sigma, "halfwidth_mrad": half, "optics": optics, "stages": stages,
            "position": position, "normal": normal}
