"""A calibration run's options (:class:`RunConfig`, the command line's flags) and their checks.

The options are checked once, before any work (:func:`validate_config`: one-line errors naming the flag);
``--settings auto`` is resolved by :func:`settings_mode`. :mod:`.pipeline` runs a config, :mod:`.selection`
derives configs from one (a candidate's settings), the workflow (:mod:`heliotwin.workflows.calibrate`) builds
one from its settings.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace

from ...errors import HeliotwinError
from ...io.records import normalise_source
from ..methods import get_method
from .splits import SPLIT_TYPES


@dataclass
class RunConfig:
    """Options of a calibration run (the CLI's flags)."""

    paint: str
    method: str = "lm"
    split: str = "chrono"
    train: int = 30
    validation: int | None = None
    test: int | None = 30
    heliostats: list | None = None
    min_records: int = 50
    focal_spot: str = "HeliOS"
    seed: int = 0
    plane_tolerance: float = 0.1
    correct_suspicious: bool = True
    progress: bool = False
    method_options: dict = field(default_factory=dict)
    #: ``"run"``: the method's own prior (lm: field prior of the run's training records); ``"plant"``: a plant
    #: prior learned from the heliostats of the PAINT folder that are NOT calibrated (see :mod:`.archive`).
    prior: str = "run"
    #: ``--prior-from``: a PAINT folder or scenario path, or an already built
    #: :class:`~heliotwin.calibrate.protocol.archive.PriorArchive` / :class:`~heliotwin.calibrate.priors.PlantPrior`;
    #: implies ``prior="plant"``.
    prior_from: object = None
    #: Settings of the plant prior (:meth:`~heliotwin.calibrate.protocol.archive.PriorArchive.prior`).
    prior_options: dict = field(default_factory=dict)
    #: Heliostats that must not enter the plant prior besides the calibrated ones (cross-validation folds).
    prior_exclude: list = field(default_factory=list)
    #: ``--split online``: test records predicted per refit (see :mod:`.online`).
    online_step: int = 5
    #: ``--drift``: ``"none"`` (static rigid body) or ``"kalman"`` (rigid body + random-walk offset of the two
    #: axis offsets, :mod:`heliotwin.calibrate.drift`; lm only).
    drift_model: str = "none"
    #: ``--process-noise``: the walk's process noise [mrad^2/day] per component, or ``"auto"`` (chosen by
    #: chronological validation inside the training records,
    #: :func:`~heliotwin.calibrate.methods.lm.choose_process_noise`).
    process_noise: object = "auto"
    #: ``--drift-basis``: which deviations drift (:data:`heliotwin.calibrate.drift.BASES`).
    drift_basis: str = "axes"
    #: ``--settings``: ``"given"`` (the fields above) or ``"cv"`` (lm settings chosen by leave-heliostats-out
    #: CV on the ``prior_from`` PAINT folder, :func:`~heliotwin.calibrate.protocol.selection.choose_for_run`).
    settings: str = "given"
    #: ``--learn-settings``: also choose the lm settings and the interval calibration by leave-heliostats-out
    #: CV on this run's own PAINT folder (every eligible heliostat but ``prior_exclude``), with the plant prior
    #: they use, for a scenario that later runs reuse (``--prior-from`` it: ``--settings stored``); the run's
    #: own fit keeps the settings above.
    learn_settings: bool = False

    def fit_options(self) -> dict:
        """The method's options: ``method_options`` plus the drift model's settings."""
        opts = dict(self.method_options)
        if self.drift_model != "none":
            opts.update(drift_model=self.drift_model, process_noise=self.process_noise, drift_basis=self.drift_basis)
        return opts

    def uses_plant_prior(self) -> bool:
        """Whether the run fits against a plant prior (``--prior plant`` or a ``--prior-from`` source)."""
        return self.prior == "plant" or self.prior_from is not None

    def n_validation(self) -> int:
        """Validation records carved out of ``train``: default 20 % (at least 2 when train >= 8, else 0)."""
        if self.validation is not None:
            return int(self.validation)
        return max(2, int(round(0.2 * self.train))) if self.train >= 8 else 0


def settings_mode(mode: str, *, method: str, prior_from=None, fixed_by_hand: bool = False) -> str:
    """``--settings auto`` resolved: ``"cv"`` when ``prior_from`` is a PAINT folder (heliostats to choose on),
    ``"stored"`` when it is a scenario file (the choice a ``cv`` run stored there, where it applies), for lm
    with no lm setting fixed by hand (``fixed_by_hand``); ``"given"`` otherwise. Other modes pass through."""
    if mode != "auto":
        return mode
    if method != "lm" or fixed_by_hand or not isinstance(prior_from, (str, os.PathLike)):
        return "given"
    return "cv" if os.path.isdir(prior_from) else "stored" if os.path.isfile(prior_from) else "given"


#: Split types of a calibration run: ``current`` (the plant as it is now: every usable record fitted, nothing held
#: out; the workflow validates inside the records, :func:`heliotwin.workflows.calibrate.calibrate`), the record
#: splits of the study protocols and the online protocol (:mod:`.online`).
RUN_SPLITS = ("current",) + SPLIT_TYPES + ("online",)
#: ``--train`` of a ``current`` run: every record a heliostat has.
EVERY_RECORD = 10 ** 9
#: ``--split current``: each heliostat's latest this many records are predicted from its earlier ones to tell
#: the written plant's expected error, and to score settings by CV (a sixth or less of a heliostat's records at
#: the default --min-records 50, about the records a plant gathers per heliostat in four months).
CURRENT_HOLDOUT = 10


def validation_protocol(cfg: "RunConfig") -> "RunConfig":
    """The study protocol that measures a ``current`` run's settings inside its records: chronological, each
    heliostat's latest ``cfg.test`` (default :data:`CURRENT_HOLDOUT`) records predicted from every earlier one.
    Other configs are returned as they are."""
    if cfg.split != "current":
        return cfg
    return replace(cfg, split="chrono", train=EVERY_RECORD, validation=0, test=cfg.test or CURRENT_HOLDOUT)


def validate_config(cfg: RunConfig) -> None:
    """Check a run's settings before any data is read: :class:`HeliotwinError` (naming the flag or value) when
    one is out of range or unknown."""
    if cfg.split not in RUN_SPLITS:
        raise HeliotwinError(f"unknown split type {cfg.split!r}; known: {', '.join(RUN_SPLITS)}")
    if cfg.online_step < 1:
        raise HeliotwinError(f"--online-step must be >= 1, got {cfg.online_step}")
    get_method(cfg.method)
    normalise_source(cfg.focal_spot)
    if cfg.train < 1:
        raise HeliotwinError(f"--train must be >= 1, got {cfg.train}")
    v = cfg.n_validation()
    if v < 0 or v >= cfg.train:
        raise HeliotwinError(f"--validation must be in [0, train) (validation is carved out of --train {cfg.train}), "
                             f"got {v}")
    if cfg.test is not None and cfg.test < 1:
        raise HeliotwinError(f"--test must be >= 1, got {cfg.test}")
    if cfg.min_records < 0:
        raise HeliotwinError(f"--min-records must be >= 0, got {cfg.min_records}")
    if cfg.prior not in ("run", "plant"):
        raise HeliotwinError(f"--prior must be 'run' or 'plant', got {cfg.prior!r}")
    if cfg.drift_model not in ("none", "kalman"):
        raise HeliotwinError(f"--drift must be 'none' or 'kalman', got {cfg.drift_model!r}")
    if cfg.drift_model != "none":
        if cfg.method != "lm":
            raise HeliotwinError(f"--drift {cfg.drift_model} is implemented for --method lm only, not {cfg.method}")
        if cfg.drift_basis not in ("axes", "rotation"):
            raise HeliotwinError(f"--drift-basis must be 'axes' or 'rotation', got {cfg.drift_basis!r}")
        if cfg.method_options.get("half_life_days"):
            raise HeliotwinError("--drift kalman and --half-life-days are two drift models: give one")
        pn = cfg.process_noise
        if pn != "auto" and not (isinstance(pn, (int, float)) and math.isfinite(pn) and pn >= 0):
            raise HeliotwinError(f"--process-noise must be 'auto' or a number >= 0 [mrad^2/day], got {pn!r}")
    _validate_settings(cfg)
    if cfg.learn_settings and cfg.method != "lm":
        raise HeliotwinError(f"--learn-settings chooses lm settings; --method is {cfg.method}")
    if cfg.uses_plant_prior() and cfg.method != "lm":
        raise HeliotwinError(f"a plant prior (--prior-from / --prior plant) is implemented for --method lm only, "
                             f"not {cfg.method}")


def _validate_settings(cfg: RunConfig) -> None:
    """``--settings``: a known mode, and what ``cv`` / ``stored`` need (lm, and a folder / a scenario)."""
    if cfg.settings not in ("given", "cv", "stored"):
        raise HeliotwinError(f"--settings must be 'given', 'cv' or 'stored', got {cfg.settings!r}")
    if cfg.settings == "stored":
        if cfg.method != "lm":
            raise HeliotwinError(f"--settings stored applies lm settings; --method is {cfg.method}")
        if not isinstance(cfg.prior_from, (str, os.PathLike)) or not os.path.isfile(cfg.prior_from):
            raise HeliotwinError("--settings stored needs --prior-from a scenario file written by a --settings cv run")
    if cfg.settings == "cv":
        if cfg.method != "lm":
            raise HeliotwinError(f"--settings cv chooses lm settings; --method is {cfg.method}")
        if not isinstance(cfg.prior_from, (str, os.PathLike)) or not os.path.isdir(cfg.prior_from):
            raise HeliotwinError("--settings cv needs --prior-from a PAINT folder of the same plant (the heliostats "
                                 "the settings are chosen on)")
