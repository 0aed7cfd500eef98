"""Detect suspicious heliostat properties (and whether correcting them is supported by the records).

A properties file can carry a wrong actuator value (PAINT's BF41: an initial stroke three times the
field's, with matching odd initial angles). A calibration would then spend its parameters repairing a
gross error and extrapolate badly, or fail outright. The check is two-fold:

1. *Values*: each actuator value is compared with the field median over every heliostat of the plant
   (relative deviation for lengths/increments, absolute for angles, thresholds :data:`THRESHOLDS`). A run
   passes the heliostats of its PAINT folder and of its ``--prior-from`` plant, so that a folder of a few
   heliostats is still judged against a field (:data:`MIN_FIELD`); the prior's archive checks its own
   heliostats the same way before fitting them (:meth:`.archive.PriorArchive.from_dataset`).
2. *Records*: the flagged values are replaced by the field medians and both variants are fitted to the
   heliostat's TRAINING records. The correction is adopted when its best fit has the lower posterior cost
   under the field prior (of the run's other heliostats, or the plant prior when they are too few); with
   neither prior, only when it lowers the nominal training error :data:`ACCEPT_FACTOR`-fold. Otherwise the
   values are reported as unusual but consistent with the records (AK32's axis 2 is such a case) and kept.

Also flagged: a nominal training error far above the field's (:data:`NOMINAL_FACTOR` x the median).
"""
from __future__ import annotations

import torch

from ...field.plant import ACTUATOR_FIELDS, Kinematics
from ...io.records import RecordTable
from .. import metrics
from ..inputs import MIN_TRAIN
from ..methods.lm import fit_lm
from ..params import STONE8
from ..priors import LOOSE_SIGMA, field_prior

#: (kind of test, threshold): relative deviation from the field median for lengths/increment, absolute
#: [rad] for the initial angle.
THRESHOLDS = {"increment": ("relative", 0.25), "offset": ("relative", 0.25), "pivot_radius": ("relative", 0.25),
              "initial_stroke_length": ("relative", 0.5), "initial_angle": ("absolute", 0.2)}
ACCEPT_FACTOR = 3.0
NOMINAL_FACTOR = 5.0
#: Fewest heliostats whose median is a field median (below it nothing is flagged).
MIN_FIELD = 5


def field_medians(field_kin: Kinematics) -> dict:
    """Median over heliostats of every actuator field, per axis ([2] each)."""
    return {f: getattr(field_kin, f).median(0).values for f in ACTUATOR_FIELDS}


def flag_values(kin: Kinematics, ids, medians: dict) -> dict:
    """Actuator values far from the field median.

    Returns
    -------
    dict of heliostat id -> list of dict(field, axis, value, field_median)
    """
    out = {}
    for h, hid in enumerate(ids):
        flags = []
        for f, (mode, thr) in THRESHOLDS.items():
            for a in range(2):
                v, m = float(getattr(kin, f)[h, a]), float(medians[f][a])
                if not bool(kin.linear[h, a]) and f != "initial_angle" and f != "increment":
                    continue  # an ideal actuator has no triangle
                dev = abs(v / m - 1.0) if (mode == "relative" and m != 0) else abs(v - m)
                if dev > thr:
                    flags.append({"field": f, "axis": a + 1, "value": v, "field_median": m})
        if flags:
            out[hid] = flags
    return out


def _map_cost(kin: Kinematics, batch: RecordTable, fp) -> float:
    """Posterior cost (data misfit + field prior, in rad^2) of the best Stone/Jülich fit of ONE heliostat."""
    _, info = fit_lm(kin, batch, names=STONE8, prior_sigma=LOOSE_SIGMA, prior_mean=fp[0].unsqueeze(0).clone(),
                     prior_sigma_vector=fp[1])
    return 2.0 * info["cost"]


def _judge_correction(kin: Kinematics, h: int, flags: list, medians: dict, train: RecordTable, before: float,
                      fp) -> dict:
    """Whether heliostat ``h``'s training records support replacing its flagged values by the field medians.

    ``before`` is its nominal training error [rad] (median over records); ``fp`` the field prior or None.
    Returns the report entry: ``corrected`` (bool), ``note`` and the numbers the decision was made on.
    """
    m = train.heliostat_index == h
    if int(m.sum()) < MIN_TRAIN:
        return {"corrected": False,
                "note": "actuator value(s) far from the field median; too few training records to check"}
    trial = {f: getattr(kin, f)[h:h + 1].clone() for f in ACTUATOR_FIELDS}
    for fl in flags:
        trial[fl["field"]][0, fl["axis"] - 1] = medians[fl["field"]][fl["axis"] - 1]
    sub = train.subset(m)
    sub.heliostat_index = torch.zeros(len(sub), dtype=torch.long, device=m.device)
    k_orig = kin.index(h)
    k_corr = k_orig.replace(**trial)
    with torch.no_grad():
        after = float(metrics.pointing_error(k_corr, sub).median())
    entry = {"nominal_train_mrad_before": before * 1e3, "nominal_train_mrad_after_correction": after * 1e3}
    if fp is not None:
        c0, c1 = _map_cost(k_orig, sub, fp), _map_cost(k_corr, sub, fp)
        entry["posterior_cost_before"], entry["posterior_cost_after_correction"] = c0, c1
        accept = c1 < c0
        why = f"posterior cost under the field prior {c0:.3g} -> {c1:.3g}"
    else:
        accept = after * ACCEPT_FACTOR <= before
        why = f"nominal training error {before * 1e3:.1f} -> {after * 1e3:.1f} mrad"
    entry["corrected"] = accept
    entry["note"] = (f"suspicious actuator value(s) replaced by the field median ({why})" if accept else
                     f"actuator value(s) far from the field median but the records prefer them ({why}); kept")
    return entry


def check_and_correct(kin: Kinematics, ids, field_kin: Kinematics, train: RecordTable, *,
                      fallback_prior=None) -> tuple[Kinematics, dict]:
    """Flag suspicious properties and adopt a correction where the training records support it.

    The decision compares, for a flagged heliostat, the original and the corrected properties by their
    posterior cost under the field prior (:mod:`~heliotwin.calibrate.priors`, learned from the *other*,
    unflagged heliostats' training records): the variant whose best fit needs the smaller, more
    field-typical deviations for the same data wins. When the run has too few heliostats for a field prior,
    ``fallback_prior`` (the plant prior of ``--prior-from``) takes its place; without either, a correction
    is adopted when it lowers the nominal training error :data:`ACCEPT_FACTOR`-fold.

    Parameters
    ----------
    kin : Kinematics
        The run's H heliostats (nominal, from the properties files).
    ids : list of str
    field_kin : Kinematics
        Every heliostat of the plant (for the field medians).
    train : RecordTable
        Training records only (validation/test are never looked at).
    fallback_prior : (torch.Tensor [8], torch.Tensor [8]), optional
        Mean and sigma of the Stone/Jülich 8 deviations (physical units) learned from other heliostats,
        used only when the run's own heliostats cannot form a field prior.

    Returns
    -------
    kin : Kinematics
        With adopted corrections.
    findings : dict of heliostat id -> dict
        ``flags`` (values), nominal training error before/after, ``corrected`` (bool), ``note``.
    """
    findings: dict = {}
    if field_kin.num_heliostats < MIN_FIELD or len(train) == 0:
        return kin, findings
    with torch.no_grad():
        err = metrics.pointing_error(kin, train)
    counts = train.counts()
    per_h = [float(err[rows].median()) if len(rows) else float("nan") for rows in train.rows_by_heliostat()]
    finite = [e for e in per_h if e == e]
    field_nominal = float(torch.tensor(finite).median()) if finite else float("nan")
    medians = field_medians(field_kin)
    flags = flag_values(kin, ids, medians)
    fp = None
    if flags:
        usable = (counts >= MIN_TRAIN) & torch.tensor([hid not in flags for hid in ids], device=counts.device)
        loose, _ = fit_lm(kin, train.subset(usable[train.heliostat_index]), names=STONE8, prior_sigma=LOOSE_SIGMA)
        fp = field_prior(loose, usable, STONE8)
        if fp is None and fallback_prior is not None:
            fp = tuple(t.to(device=loose.device, dtype=loose.dtype) for t in fallback_prior)
    changes = {f: getattr(kin, f).clone() for f in ACTUATOR_FIELDS}
    for h, hid in enumerate(ids):
        entry = {}
        if hid in flags:
            entry = {"flags": flags[hid], **_judge_correction(kin, h, flags[hid], medians, train, per_h[h], fp)}
            if entry["corrected"]:
                for fl in flags[hid]:
                    changes[fl["field"]][h, fl["axis"] - 1] = medians[fl["field"]][fl["axis"] - 1]
        if per_h[h] == per_h[h] and field_nominal == field_nominal and per_h[h] > NOMINAL_FACTOR * field_nominal:
            entry["nominal_error_far_above_field"] = {"nominal_train_mrad": per_h[h] * 1e3,
                                                      "field_median_mrad": field_nominal * 1e3}
        if entry:
            findings[hid] = entry
    return kin.replace(**changes), findings
