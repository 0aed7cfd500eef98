"""The reconstruct workflow: learn one heliostat's mirror surface from its PAINT flux images.

:func:`reconstruct` is the one entry (the command line's ``heliotwin reconstruct``, :func:`heliotwin.api.reconstruct`
and the benchmarks call it): ``Scenario × PAINT folder × heliostat × ReconstructionSettings → (Scenario′,
report, fit)``. The learner is a setting (:attr:`ReconstructionSettings.method`):

* ``"generalising"`` (default, :mod:`heliotwin.surfaces.generalise`): camera model, optics chosen on the training
  images, settings and step count by leave-one-training-image-out, outlier drop, acceptance rule; optionally a
  plant surface prior (:mod:`heliotwin.surfaces.plantprior`).
* ``"legacy"`` (:mod:`heliotwin.surfaces.study`): a chosen image loss (KL by default) with early stopping on the
  latest training image; the learner of the in-silico study, and the only one that takes the Monte-Carlo
  training integrator, a background cut, and a PAINT deflectometry file (traced beside the ideal and learned
  surfaces and compared with the learned one, or used as the start).

:meth:`ReconstructionSettings.check` refuses (one line) an option the chosen learner does not take, so the
command line and the API share one table of what each learner accepts.

Units: metres, radians (``slope_error_mrad`` in mrad); L1 of unit-sum images.
"""
from __future__ import annotations

import dataclasses
import os
import sys
import time
from dataclasses import dataclass

import torch

from ..devices import resolve_device, to_device
from ..errors import HeliotwinError
from ..field.plant import Facets, SunSettings
from ..io import checkpoint as _checkpoint
from ..io.deflectometry import read_deflectometry
from ..io.scenario import Scenario, scenario_from_paint
from ..surfaces.generalise import GeneraliseSettings, reconstruct_generalising
from ..surfaces.learning import parse_grid
from ..surfaces.observations import paint_observations
from ..surfaces.plantprior import check_leakage, load_surface_prior
from ..surfaces.state import with_learned_surface
from ..surfaces.study import reconstruct_observed
from ..surfaces.training import TrainSettings
from .show import kinematics_note

__all__ = ["ReconstructionSettings", "reconstruct", "reconstruction_checkpoint", "METHODS"]

#: The learners :func:`reconstruct` can run.
METHODS = ("generalising", "legacy")

#: Step budget of each learner when :attr:`ReconstructionSettings.steps` is None.
DEFAULT_STEPS = {"generalising": GeneraliseSettings.steps, "legacy": 200}


@dataclass
class ReconstructionSettings:
    """Settings of one surface reconstruction (defaults: the command line's).

    Attributes
    ----------
    method : {"generalising", "legacy"}
        The learner (module docstring).
    train_records : tuple of int, optional
        Record ids to train on (each with a centred image); the others with images are the test set.
    train_first : int, optional
        Otherwise the K earliest records with centred images (default 3).
    control_points : str or (int, int)
        NURBS control points per facet, e.g. ``"7x7"``.
    degree : int
        NURBS degree in both directions.
    steps : int, optional
        Legacy: most optimiser steps (default 200); generalising: the leave-one-out step budget (default 300,
        held-out L1 every ``min(30, steps // 2)`` steps).
    slope_error_mrad : float, optional
        Mirror slope error [mrad]; None chooses it on the training images.
    alignment : {"focal-spot", "motor"}
        Pose of each image: aimed at the measured focal spot, or the plant's kinematics at the motor steps.
    loss : {"kl", "l1", "l2"}, optional
        Legacy only: image loss (None: ``"kl"``).
    integrator : {"conv", "mc"}
        Renderer of the training images (``"mc"``: legacy only).
    background : float
        Legacy only: background subtracted from each image, fraction of its max.
    deflectometry : str, optional
        Legacy only: a PAINT deflectometry HDF5 file, traced on the test images and compared with the learned
        surface (report key ``deflectometry``).
    start_from_deflectometry : bool
        Legacy only: start the learning from the deflectometry surface instead of flat.
    evaluate_mc : bool
        Legacy only: also evaluate the test images with the Monte-Carlo tracer.
    surface_prior_from : tuple of str, optional
        Generalising only: scenario files whose learned surfaces (>= 2 other heliostats of the same design) give
        a plant prior on the facets' canting and low-order shape, or one scenario holding a stored prior
        (:func:`heliotwin.surfaces.plantprior.load_surface_prior`); refused when it was learned from the
        heliostat being reconstructed.
    device : {"auto", "cpu", "cuda"}
        Where the surface is learned and evaluated (results come back on the CPU).
    """

    method: str = "generalising"
    train_records: tuple | None = None
    train_first: int | None = None
    control_points: str | tuple = "7x7"
    degree: int = 3
    steps: int | None = None
    slope_error_mrad: float | None = None
    alignment: str = "focal-spot"
    loss: str | None = None
    integrator: str = "conv"
    background: float = 0.0
    deflectometry: str | None = None
    start_from_deflectometry: bool = False
    evaluate_mc: bool = True
    surface_prior_from: tuple | None = None
    device: str = "auto"

    def check(self) -> None:
        """One-line :class:`HeliotwinError` for an option the chosen method does not take (before any file is
        read)."""
        if self.method not in METHODS:
            raise HeliotwinError(f"reconstruct: method must be 'generalising' or 'legacy', got {self.method!r}")
        if self.train_records and self.train_first is not None:
            raise HeliotwinError("use either --train-records or --train-first, not both")
        if self.method == "generalising":
            for flag, given, why in _LEGACY_ONLY:
                if given(self):
                    raise HeliotwinError(f"{flag} is not supported with --method generalising ({why}); "
                                         f"use --method legacy")
        elif self.surface_prior_from:
            raise HeliotwinError("--surface-prior-from is not supported with --method legacy; use --method "
                                 "generalising")
        if self.start_from_deflectometry and not self.deflectometry:
            raise HeliotwinError("--start-from-deflectometry needs --deflectometry FILE")

    def learner(self) -> GeneraliseSettings | TrainSettings:
        """The chosen learner's own settings (:class:`GeneraliseSettings` or :class:`TrainSettings`)."""
        net, degree = parse_grid(self.control_points), (int(self.degree), int(self.degree))
        steps = int(self.steps or DEFAULT_STEPS[self.method])
        if self.method == "legacy":
            return TrainSettings(control_points=net, degree=degree, integrator=self.integrator,
                                 loss=self.loss or "kl", steps=steps)
        base = GeneraliseSettings()
        kw = dict(control_points=net, degree=degree, steps=steps, eval_every=min(base.eval_every, max(1, steps // 2)))
        if self.slope_error_mrad is not None:
            kw["slope_grid"] = (self.slope_error_mrad * 1e-3,)
        return GeneraliseSettings(**kw)

    def fingerprint(self) -> dict:
        """What a checkpoint of this run is tagged with (everything that changes the fit; not ``device``, which
        the tag holds on its own, nor the evaluation-only ``evaluate_mc``; the files named here are
        fingerprinted as inputs by :func:`reconstruction_checkpoint`)."""
        out = {k: v for k, v in dataclasses.asdict(self).items() if k not in ("device", "evaluate_mc")}
        out["learner"] = dataclasses.asdict(self.learner())
        return out


#: Options of the legacy learner that the generalising one does not take: (flag, is it set?, why).
_LEGACY_ONLY = (
    ("--loss", lambda s: s.loss is not None, "it fits the L1 of unit-sum images after the camera model"),
    ("--integrator", lambda s: s.integrator != "conv", "it renders with the conv integrator"),
    ("--background", lambda s: s.background > 0, "it models each image's background cut instead"),
    ("--deflectometry", lambda s: s.deflectometry is not None, "deflectometry comparison is legacy-only"),
    ("--start-from-deflectometry", lambda s: s.start_from_deflectometry, "it starts from the canting focus"),
)


def reconstruction_checkpoint(path, paint, heliostat: str, settings: ReconstructionSettings, *,
                              scenario_path=None, resume: bool = False,
                              min_interval_s: float | None = None) -> _checkpoint.Checkpoint:
    """The :class:`~heliotwin.io.checkpoint.Checkpoint` of a :func:`reconstruct` run at ``path``, tagged with the
    heliostat, the device, :meth:`ReconstructionSettings.fingerprint` and the input files (the PAINT folder, the
    starting scenario, the deflectometry file and the surface-prior scenarios)."""
    tag = {"command": "reconstruct", "heliostat": heliostat, "device": resolve_device(settings.device),
           "paint": os.path.abspath(os.fspath(paint)), **settings.fingerprint()}
    files = [paint] + [p for p in (scenario_path, settings.deflectometry) if p is not None]
    files += list(settings.surface_prior_from or ())
    opts = {} if min_interval_s is None else {"min_interval_s": min_interval_s}
    return _checkpoint.Checkpoint(path, _checkpoint.make_tag(tag, files), resume=resume, **opts)


def reconstruct(scenario: Scenario | None, paint, heliostat: str, settings: ReconstructionSettings | None = None, *,
                checkpoint: _checkpoint.Checkpoint | None = None,
                progress: bool = True) -> tuple[Scenario, dict, dict]:
    """Learn ``heliostat``'s surface from its earliest centred images in ``paint``; evaluate on the others.

    Parameters
    ----------
    scenario : Scenario or None
        The plant to start from (e.g. a calibrated one: its kinematics pose the heliostat); None: the PAINT
        folder's nominal plant.
    paint : path
        PAINT folder with the heliostat's calibration records and ``-flux-centered.png`` images.
    heliostat : str
    settings : ReconstructionSettings, optional
        Defaults: the command line's.
    checkpoint : heliotwin.io.checkpoint.Checkpoint, optional
        From :func:`reconstruction_checkpoint`: every fit saves its state and a resumed one continues it; the
        caller removes it once its outputs are written.
    progress : bool
        tqdm bars.

    Returns
    -------
    scenario : Scenario
        The next scenario (not written): the plant with the learned control points, the learned-surface entry
        (:func:`heliotwin.surfaces.state.with_learned_surface`) and one ``"reconstruct"`` provenance step.
    report : dict
        JSON-ready: per test (and training) image L1 of the ideal and the learned surface, medians, what the
        learner chose (``choices`` for generalising), ``method``, ``seconds``.
    fit : dict
        In memory, for figures and notebooks: ``model`` (:class:`~heliotwin.surfaces.learning.LearnableSurface`,
        ``model.surfaces()`` the learned surface ``[1, F, nu, nv, 3]`` [m]), ``facets``, ``train``/``test``
        observations, ``ideal`` (Surfaces), ``optics``, and the learner's predicted images (legacy:
        ``ideal_images``/``learned_images`` ``[B, R, R]``; generalising: ``info["test_images"]``).
    """
    s = settings or ReconstructionSettings()
    s.check()
    prior = load_surface_prior(list(s.surface_prior_from), heliostat_id=heliostat) if s.surface_prior_from else None
    if prior is not None:
        check_leakage(prior, heliostat)
    if s.deflectometry:
        read_deflectometry(s.deflectometry)  # fail fast (one line naming the file) before training
    learner = s.learner()
    device = resolve_device(s.device)
    t0 = time.perf_counter()
    plant = scenario.plant if scenario is not None else None
    note = kinematics_note(scenario, heliostat)  # a surface learned on nominal kinematics must say so, up front
    if progress and "no calibration" in note:  # stdout: a failing run's stderr holds only its one-line error
        print(f"heliotwin reconstruct: {note}", file=sys.stdout, flush=True)
    _, on_device, train, test = paint_observations(
        paint, heliostat, plant=plant, device=device, train_records=list(s.train_records) if s.train_records else None,
        train_first=s.train_first, resolution=learner.resolution, background=s.background, alignment=s.alignment)
    with _checkpoint.active(checkpoint):
        if s.method == "generalising":
            report, model, fit = _generalising(on_device, train, test, learner, prior, progress)
            report.update(heliostat=heliostat, paint=str(paint), alignment=s.alignment, device=device,
                          plant="paint" if plant is None else "scenario", seconds=time.perf_counter() - t0)
        else:
            report, model, fit = _legacy(on_device, train, test, learner, s, progress)
            report = {"heliostat": heliostat, "paint": str(paint), **report, "seconds": time.perf_counter() - t0}
    report["method"] = s.method
    report["kinematics"] = note
    if s.method == "generalising":
        report["choices"] = _generalising_choices(report)
        # the stored surface records what chose it
        report["settings"] = dict(report["settings"], method="generalising", chosen=report["choices"])
    if device != "cpu":  # results come back on the CPU
        model, fit = model.cpu(), to_device(fit, "cpu")
        fit["train"], fit["test"] = train.to("cpu"), test.to("cpu")
    fit = dict(fit, model=model, surface_prior=prior)
    base_plant = plant if plant is not None else scenario_from_paint(paint)
    nxt = with_learned_surface(scenario, base_plant, heliostat, model.surfaces(), model.displacement.detach(),
                               fit["optics"], train_records=[int(r["record"]) for r in report["train"]],
                               target=fit["test"].targets[0].name, settings=report["settings"],
                               source=os.path.abspath(paint), surface_prior=None if prior is None else prior.state())
    return nxt, report, fit


def _facets(plant, dtype=None) -> Facets:
    """The facets ``[1, F, 3]`` [m] of a one-heliostat plant (``dtype``: converted)."""
    parts = (getattr(plant.field.facets, a)[:1] for a in ("translation", "canting_e", "canting_n"))
    return Facets(*(t if dtype is None else t.to(dtype) for t in parts))


def _generalising(plant, train, test, learner: GeneraliseSettings, prior, progress) -> tuple[dict, object, dict]:
    facets = _facets(plant, torch.float64)
    report, model, info = reconstruct_generalising(facets, train, test, SunSettings(sunshape="buie", csr=0.05),
                                                   learner, progress, prior=prior)
    return report, model, {"facets": facets, "train": train, "test": test, "info": info, "optics": info["optics"],
                           "ideal": info["ideal"]}


def _legacy(plant, train, test, learner: TrainSettings, s: ReconstructionSettings,
            progress) -> tuple[dict, object, dict]:
    slope = None if s.slope_error_mrad is None else s.slope_error_mrad * 1e-3
    return reconstruct_observed(_facets(plant), train, test, learner, slope_error=slope, evaluate_mc=s.evaluate_mc,
                                progress=progress, deflectometry=s.deflectometry,
                                start_from_deflectometry=s.start_from_deflectometry, alignment=s.alignment,
                                background=s.background)


def _generalising_choices(report: dict) -> dict:
    """What the generalising method chose (JSON): optics, blur mode, penalty weight, steps, drops, acceptance."""
    chosen = report["optics"]["chosen"]
    out = {"focal_length_m": chosen["focal_length_m"], "focus_multiple": chosen["focus_multiple"],
           "slope_error_rad": report["optics_used"]["slope_error_rad"], "blur_mode": report["blur_mode"],
           "slope_weight": report["selection"]["slope_weight"], "steps": report["selection"]["steps"],
           "dropped": [d["record"] for d in report["dropped"]], "acceptance_alpha": report["acceptance"]["alpha"]}
    if "prior" in report:
        out.update(surface_prior_weight=report["prior"]["weight"],
                   surface_prior_heliostats=report["prior"]["heliostats"])
    return out
