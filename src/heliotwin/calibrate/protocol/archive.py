"""A plant prior learned from an archive of other heliostats' records (``--prior-from``).

An *archive* is a PAINT folder (or the run's own folder) of the same plant: every heliostat in it is fitted
once, alone, on all its records (loose prior, robust loss, the centroids the fits train on), and
:meth:`PriorArchive.prior` turns the fits of the heliostats it may use into a
:class:`~heliotwin.calibrate.priors.PlantPrior` (mean + covariance over heliostats).

No leakage (the rule, enforced in :meth:`PriorArchive.prior` and by the pipeline's ``learn_prior`` step):
**a heliostat that is being calibrated or tested never contributes to the prior — none of its records**,
whether the archive is another folder or the run's own. Leave-heliostats-out cross-validation
(:mod:`.selection`) also excludes the held-out fold. A stored prior (scenario file) lists the heliostats it
came from; it is refused when any of them is calibrated in the run.

Caveat stated, not hidden: archive heliostats' records may cover the same months as the calibrated
heliostats' test records, so a plant-wide change in that period (e.g. a camera moved) is visible in the
prior's mean. The prior carries no record of a calibrated heliostat.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import torch

from ...errors import HeliotwinError
from ...field.plant import Kinematics
from ...io.paint import load_paint
from ...io.scenario import load_scenario
from .. import priors
from ..inputs import fit_spots
from ..methods.lm import LM_F_SCALE, LM_LOSS, fit_lm
from ..params import STONE8
from ..scenario import KEY
from .suspicious import check_and_correct


@dataclass
class PriorArchive:
    """One loose fit per archive heliostat, ready to become plant priors over any subset.

    Attributes
    ----------
    heliostat_ids : list of str, length H
    deviations : torch.Tensor, [H, P]
        Fit of each heliostat on all its records (physical units).
    counts : torch.Tensor, [H]
        Records per heliostat.
    names : tuple of str, length P
    source : str
        Where the records came from (a path, for reports).
    corrected : dict
        Heliostat id -> the suspicious property values replaced before its fit
        (:func:`~heliotwin.calibrate.protocol.suspicious.check_and_correct`); empty when none.
    properties : Kinematics or None
        Nominal kinematics of every heliostat of the archive's plant, with ``property_ids``: the field whose
        medians judge a run's suspicious property values (:func:`reference_kinematics`).
    property_ids : list of str
    """

    heliostat_ids: list
    deviations: torch.Tensor
    counts: torch.Tensor
    names: tuple = STONE8
    source: str = ""
    corrected: dict = field(default_factory=dict)
    properties: Kinematics | None = None
    property_ids: list = field(default_factory=list)

    @classmethod
    def fit(cls, kinematics: Kinematics, records, *, names=STONE8, source: str = "",
            min_records: int = priors.MIN_PRIOR_RECORDS) -> PriorArchive:
        """Fit every heliostat of ``records`` with at least ``min_records`` records (one batched LM).

        Parameters
        ----------
        kinematics : Kinematics
            Nominal kinematics of the record table's H heliostats (``records.heliostat_index`` indexes them).
        records : heliotwin.io.records.RecordTable
        """
        counts = records.counts()
        use = counts >= min_records
        batch = fit_spots(records.subset(use[records.heliostat_index]))
        delta, _ = fit_lm(kinematics, batch, names=names, prior_sigma=priors.LOOSE_SIGMA, loss=LM_LOSS,
                          f_scale=LM_F_SCALE)
        keep = use.nonzero().flatten()
        return cls([records.heliostat_ids[i] for i in keep.tolist()], delta[keep], counts[keep], tuple(names),
                   str(source))

    @classmethod
    def from_dataset(cls, dataset, *, focal_spot: str = "HeliOS", min_records: int = priors.MIN_PRIOR_RECORDS,
                     source: str = "", exclude=()) -> PriorArchive:
        """Fit every heliostat of a loaded PAINT folder (:class:`heliotwin.io.paint.PaintDataset`) except
        ``exclude`` (never fitted: they could not enter a prior for a run that calibrates them anyway).

        Suspicious property values are checked first, as a run checks its own heliostats
        (:func:`~heliotwin.calibrate.protocol.suspicious.check_and_correct`, field medians over the whole plant, every
        record of the archive heliostat): a heliostat with a wrong actuator value (PAINT's BF41) would
        otherwise enter the prior with deviations of hundreds of mrad. Winsorising bounds such a heliostat to
        3 robust sigmas but still lets it widen the covariance and couple the parameters it is wrong in.
        """
        keep = [h for h in dataset.records.heliostat_ids if h not in set(exclude)]
        table = dataset.records.for_heliostats(keep).with_focal_spot(focal_spot)
        plant_kin = dataset.plant.field.kinematics
        ids = list(dataset.plant.field.ids)
        kin = plant_kin.index([ids.index(h) for h in table.heliostat_ids])
        kin, findings = check_and_correct(kin, table.heliostat_ids, plant_kin, table)
        archive = cls.fit(kin, table, source=source or str(getattr(dataset, "root", "")), min_records=min_records)
        archive.corrected = {h: f["flags"] for h, f in findings.items() if f.get("corrected")}
        archive.properties, archive.property_ids = plant_kin, ids
        return archive

    def prior(self, exclude=(), *, covariance: str = "full", shrink: float = 0.2, widen: float = 1.0,
              min_records: int = priors.MIN_PRIOR_RECORDS) -> priors.PlantPrior:
        """Plant prior from every archive heliostat except ``exclude`` (and those with < ``min_records``).

        Raises a one-line :class:`HeliotwinError` when fewer than :data:`~heliotwin.calibrate.priors.MIN_HELIOSTATS`
        remain.
        """
        exclude = set(exclude)
        keep = [i for i, h in enumerate(self.heliostat_ids) if h not in exclude and int(self.counts[i]) >= min_records]
        if len(keep) < priors.MIN_HELIOSTATS:
            raise HeliotwinError(f"{self.source or 'prior archive'}: only {len(keep)} heliostat(s) with >= "
                                 f"{min_records} records outside the calibrated ones; a plant prior needs "
                                 f"{priors.MIN_HELIOSTATS}")
        pp = priors.plant_prior(self.deviations[keep], self.names, [self.heliostat_ids[i] for i in keep],
                                covariance=covariance, shrink=shrink, widen=widen)
        used = {self.heliostat_ids[i] for i in keep}
        pp.settings.update({"min_records": int(min_records), "source": self.source,
                            "corrected_properties": sorted(h for h in self.corrected if h in used)})
        return pp


def load_prior_source(path, plane_tolerance: float = 0.1, exclude=()):
    """``--prior-from PATH``: a PAINT folder (-> :class:`PriorArchive`, its heliostats in ``exclude`` not
    fitted) or a scenario with a stored prior (-> :class:`~heliotwin.calibrate.priors.PlantPrior`)."""
    if os.path.isdir(path):
        return PriorArchive.from_dataset(load_paint(path, plane_tolerance=plane_tolerance), source=os.fspath(path),
                                         exclude=exclude)
    if not os.path.isfile(path):
        raise HeliotwinError(f"{path}: --prior-from needs a PAINT folder or a scenario file")
    sc = load_scenario(path)
    state = (sc.learned.get(KEY) or {}).get("prior")
    if not state:
        raise HeliotwinError(f"{path} [/learned/{KEY}/prior]: the scenario holds no calibration prior")
    return priors.PlantPrior.from_state(state, path)


def resolve_prior(source, calibrated, *, settings: dict | None = None) -> priors.PlantPrior:
    """The plant prior for a run calibrating ``calibrated`` (ids), applying the no-leakage rule.

    ``source`` is a :class:`PriorArchive` (its heliostats in ``calibrated`` are excluded) or a stored
    :class:`~heliotwin.calibrate.priors.PlantPrior` (refused when it was learned from any of them).
    """
    calibrated = list(calibrated)
    if isinstance(source, PriorArchive):
        return source.prior(calibrated, **(settings or {}))
    overlap = sorted(set(source.heliostats) & set(calibrated))
    if overlap:
        raise HeliotwinError(f"the stored prior was learned from heliostat(s) {', '.join(overlap)} that this run "
                             "calibrates; a prior must come from other heliostats")
    if tuple(source.names) != tuple(STONE8):
        raise HeliotwinError(f"the stored prior is over {', '.join(source.names)}, lm needs the Stone/Jülich 8")
    return source


def reference_kinematics(source, skip=()) -> tuple[list, Kinematics | None]:
    """Property values of the heliostats of a ``--prior-from`` source, for the field medians that judge a
    run's suspicious property values (:func:`~heliotwin.calibrate.protocol.suspicious.check_and_correct`).

    A run on a small PAINT folder (a few heliostats) has too few heliostats of its own for a field median;
    the prior's plant has more. Only property files are read, never a record.

    Parameters
    ----------
    source : str, path, PriorArchive, PlantPrior or None
        A PAINT folder, a scenario file (its plant's heliostats), a :class:`PriorArchive` or anything else
        (-> nothing).
    skip : iterable of str
        Heliostat ids already in the run's own plant (not counted twice).

    Returns
    -------
    ids : list of str
        The heliostats returned (possibly empty).
    kinematics : Kinematics or None
        Their nominal kinematics; None when there are none.
    """
    if isinstance(source, PriorArchive):
        ids, kin = source.property_ids, source.properties
    elif isinstance(source, (str, os.PathLike)) and os.path.isdir(source):
        fld = load_paint(source, with_records=False).plant.field
        ids, kin = list(fld.ids), fld.kinematics
    elif isinstance(source, (str, os.PathLike)) and os.path.isfile(source):
        fld = load_scenario(source).plant.field
        ids, kin = list(fld.ids), fld.kinematics
    else:
        return [], None
    if kin is None:
        return [], None
    skip = set(skip)
    keep = [i for i, h in enumerate(ids) if h not in skip]
    if not keep:
        return [], None
    return [ids[i] for i in keep], kin.index(keep)
