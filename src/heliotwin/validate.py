"""Forward-model validation on real PAINT records: predicted vs measured focal spots and images.

For every calibration record, with the given (default: nominal) kinematics and ideal surfaces:

* pointing error [mrad]: angle between the model mirror normal at the recorded motor steps and the
  measured normal (bisector of the sun direction and the direction concentrator -> measured spot), per
  centroid source (HeliOS, UTIS) — :mod:`heliotwin.calibrate.metrics`, the metric ``calibrate`` reports;
* focal-spot distance on the target [m]: predicted flux centroid (gaussian integrator) vs measured spot,
  in the target plane; where the predicted spot leaves the target the central reflected ray is used;
* distance of the measured spot from its target plane [m] (a data-consistency check);
* per target, how far the two cameras' centroids of the same spot disagree (HeliOS - UTIS, median over the
  records with both, :func:`camera_agreement`): a constant per target that no kinematic model can explain;
* for records with a ``flux-centered`` PNG: normalised L1 (images scaled to sum 1, ``sum |a - b|``) and
  zero-mean normalised cross-correlation between the predicted and the measured 6 m x 6 m centred image,
  each centred on its own centroid (as PAINT centres the measured one).
"""
from __future__ import annotations

import math
import statistics
from collections import defaultdict

import torch

from .calibrate import metrics
from .devices import resolve_device, to_device
from .field.plant import Plant, SunSettings
from .field.targets import PlanarTarget
from .io.images import CENTERED_WINDOW_M, load_measured_image
from .io.paint import PaintDataset
from .io.records import SOURCES, RecordTable
from .progress import Progress
from .raytrace.flux import cross_correlation, normalized_l1
from .raytrace.gaussian import FootprintSettings
from .scene import central_ray_spot, trace, world_surface

# One heliostat per sample: one convolution kernel per sample is exact to second order (see trace_gaussian).
_CONVOLVE = FootprintSettings(mode="convolve")


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return statistics.median(xs) if xs else None


def validate_dataset(ds: PaintDataset, *, plant: Plant | None = None, sun: SunSettings | None = None,
                     samples=(16, 16), resolution: int = 128, batch: int = 64, with_images: bool = True,
                     progress: bool = True, device="cpu") -> dict:
    """Validate the forward model on every usable record of a PAINT dataset.

    Parameters
    ----------
    ds : PaintDataset
        From :func:`heliotwin.io.paint.load_paint`: its record table (and skipped records).
    plant : Plant, optional
        The plant to validate (e.g. a calibrated scenario's, see
        :meth:`~heliotwin.io.paint.PaintDataset.on_plant`); default ``ds.plant``. Must contain every
        heliostat of ``ds``. Its static kinematics are evaluated (the networks of a ``hybrid`` / ``mlp``
        calibration are not part of the plant).
    sun : SunSettings, optional
        Optics for the predicted images (default: the plant's).
    samples : (int, int)
        Surface samples per facet and direction.
    resolution : int
        Whole-target bitmap resolution used for the predicted centroid.
    batch : int
        Records traced at once (memory bound).
    device : str or torch.device
        Where to trace (``"auto"``: CUDA when present); the report holds plain numbers either way.

    Returns
    -------
    dict
        ``records`` (one dict per record), ``heliostats.<HID>`` medians, ``overall`` medians (the median
        over heliostats of each heliostat's median), ``skipped_records`` (with reasons).
    """
    plant = plant or ds.plant
    device = resolve_device(device)
    if device != "cpu":
        plant, ds = to_device(plant, device), to_device(ds, device)
    table = ds.records.for_heliostats(plant.field.ids) if list(ds.records.heliostat_ids) != list(plant.field.ids) \
        else ds.records
    sun = sun or plant.sun
    rows = {}
    bar = Progress(len(table), "heliotwin validate", unit="record", enabled=progress)
    for tname in dict.fromkeys(table.target):
        idx = torch.tensor([i for i, t in enumerate(table.target) if t == tname], dtype=torch.long,
                           device=table.record_id.device)
        for start in range(0, len(idx), batch):
            chunk = table.subset(idx[start:start + batch])
            rows.update(_validate_chunk(chunk, plant.target(tname), plant, sun, samples, resolution, with_images))
            bar.update(len(chunk))
    bar.close()
    out = summarise([rows[int(r)] for r in table.record_id])
    out["camera_agreement"] = camera_agreement(table)
    out["skipped_records"] = list(ds.skipped)
    out["overall"]["skipped_records"] = len(ds.skipped)
    return out


def camera_agreement(table: RecordTable) -> dict:
    """Per target, the median HeliOS - UTIS centroid difference (:meth:`RecordTable.camera_offsets`) along
    the target's right and up directions.

    Returns
    -------
    dict
        Target name -> ``{"pairs", "heliostats", "right_m", "up_m"}`` [m]; empty for tables without
        per-source centroids.
    """
    out = {}
    for name, c in table.camera_offsets().items():
        r = table.target.index(name)  # a target has one plane
        out[name] = {"pairs": c["pairs"], "heliostats": c["heliostats"],
                     "right_m": float(c["offset"] @ table.plane_right[r]),
                     "up_m": float(c["offset"] @ table.plane_up[r])}
    return out


def _pointing_errors(chunk: RecordTable, plant: Plant) -> dict:
    """Pointing error [rad] per centroid source, [R] each (NaN where a record lacks that source): the metric
    of :mod:`heliotwin.calibrate.metrics`, so validate and calibrate report the same number."""
    normal, conc = metrics.model_normals(plant.field.kinematics, chunk)
    out = {}
    for k, src in enumerate(SOURCES):
        has = torch.isfinite(chunk.focal_spots[:, k]).all(-1)
        err = metrics.pointing_error_of_normals(normal, conc, chunk.with_focal_spot(src))
        out[src] = torch.where(has, err, torch.full_like(err, float("nan")))
    return out


def _validate_chunk(chunk: RecordTable, target, plant: Plant, sun, samples, resolution, with_images) -> dict:
    s = chunk.sun
    with torch.no_grad():
        errors = _pointing_errors(chunk, plant)
        pts, nrm, area, R, c = world_surface(plant.field.kinematics, plant.field.surfaces, chunk.heliostat_index,
                                             chunk.motor_steps, samples)
        # One heliostat per sample: its points' footprints differ by a few per cent, so one convolution
        # kernel per sample ("convolve" mode) is exact to second order and ~50x faster than per-point windows.
        flux = trace(pts, nrm, area, s.to(pts), target, integrator="gaussian", resolution=(resolution, resolution),
                     sun=sun, footprint=_CONVOLVE)
        on_target = flux.intercepted_power_w > 0.5 * flux.total_power_w
        pred_local = flux.centroid_local().to(torch.float64)
        if isinstance(target, PlanarTarget):
            ray_local = target.to_local(central_ray_spot(R, c, s, target))
            pred_local = torch.where(on_target.unsqueeze(-1), pred_local, ray_local)
        meas_local = target.to_local(chunk.spot)
        distance = torch.linalg.norm(pred_local - meas_local, dim=-1)
        offset = target.distance_to_plane(chunk.spot)
        out = {}
        for i, rid in enumerate(chunk.record_id.tolist()):
            out[rid] = _row(chunk, i, errors, float(distance[i]), bool(on_target[i]), float(offset[i]))
        if with_images:
            _compare_images(chunk, target, pts, nrm, area, s, pred_local, sun, out)
    return out


def _row(chunk: RecordTable, i: int, errors: dict, distance: float, on_target: bool, offset: float) -> dict:
    sources = [src for k, src in enumerate(SOURCES) if bool(torch.isfinite(chunk.focal_spots[i, k]).all())]
    row = {
        "record": int(chunk.record_id[i]), "heliostat": chunk.heliostat_ids[int(chunk.heliostat_index[i])],
        "target": chunk.target[i],
        "sun_azimuth_deg": math.degrees(float(chunk.sun_azimuth[i])),
        "sun_elevation_deg": math.degrees(float(chunk.sun_elevation[i])),
        # The record's own centroid (``spot``: HeliOS where present) - the one calibrate scores too.
        "pointing_error_mrad": 1e3 * float(errors[chunk.source[i]][i]),
        "focal_spot_source": chunk.source[i],
        "sources": sources,
        "distance_m": distance,
        "predicted_spot_on_target": on_target,
        "measured_spot_plane_offset_m": offset,
        "datetime": chunk.datetime[i],
    }
    for src in sources:
        row[f"pointing_error_{src.lower()}_mrad"] = 1e3 * float(errors[src][i])
    return row


def _compare_images(chunk: RecordTable, target, pts, nrm, area, s, pred_local, sun, out) -> None:
    """Predicted vs measured ``flux-centered`` images for the records that have one.

    The predicted window is not clipped to the physical target: the comparison is of spot *shape*, and a
    nominal model whose spot leaves the target must still be compared (the measured one was on it).
    """
    have = [i for i, p in enumerate(chunk.flux_centered_png) if p]
    by_res = defaultdict(list)
    measured = {}
    for i in have:
        img = load_measured_image(chunk.flux_centered_png[i])  # native size, relative scale
        measured[i] = img
        by_res[tuple(img.shape[-2:])].append(i)
    for res, idx in by_res.items():
        sel = torch.tensor(idx, device=pts.device)
        half = CENTERED_WINDOW_M / 2
        size = torch.full((len(idx), 2), CENTERED_WINDOW_M, dtype=torch.float64, device=pts.device)
        window = torch.cat((pred_local[sel] - half, size), -1)
        pred = trace(pts[sel], nrm[sel], area[sel], s[sel].to(pts), target, integrator="gaussian", resolution=res,
                     sun=sun, window=window, footprint=_CONVOLVE, clip_to_target=False)
        for j, i in enumerate(idx):
            p = pred.bitmap[j].to(torch.float64)
            m = measured[i].to(p)
            row = out[int(chunk.record_id[i])]
            row["centered_l1"] = float(normalized_l1(p, m))
            row["centered_cross_correlation"] = float(cross_correlation(p, m))
            row["centered_resolution"] = list(res)


def summarise(records: list[dict]) -> dict:
    """Per-heliostat and overall medians of a list of record rows (see :func:`validate_dataset`)."""
    per = defaultdict(list)
    for row in records:
        per[row["heliostat"]].append(row)
    heliostats = {}
    for hid, rows in sorted(per.items()):
        heliostats[hid] = {
            "records": len(rows),
            "median_pointing_error_mrad": _median([r["pointing_error_mrad"] for r in rows]),
            "median_distance_m": _median([r["distance_m"] for r in rows]),
            "max_measured_spot_plane_offset_m": max(abs(r["measured_spot_plane_offset_m"]) for r in rows),
            "images": sum("centered_l1" in r for r in rows),
            "median_centered_l1": _median([r.get("centered_l1") for r in rows]),
            "median_centered_cross_correlation": _median([r.get("centered_cross_correlation") for r in rows]),
        }
    overall = {
        "heliostats": len(heliostats),
        "records": len(records),
        "median_pointing_error_mrad": _median([h["median_pointing_error_mrad"] for h in heliostats.values()]),
        "median_distance_m": _median([h["median_distance_m"] for h in heliostats.values()]),
        "median_pointing_error_over_records_mrad": _median([r["pointing_error_mrad"] for r in records]),
        "max_measured_spot_plane_offset_m": max((abs(r["measured_spot_plane_offset_m"]) for r in records),
                                                default=None),
        "images": sum("centered_l1" in r for r in records),
        "median_centered_l1": _median([r.get("centered_l1") for r in records]),
        "median_centered_cross_correlation": _median([r.get("centered_cross_correlation") for r in records]),
    }
    return {"overall": overall, "heliostats": heliostats, "records": records}
