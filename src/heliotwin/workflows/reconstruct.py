"""The reconstruct workflow: learn one heliostat's mirror surface from its PAINT flux images.

:func:`reconstruct` is the one entry (the command line's ``heliotwin reconstruct``, :func:`heliotwin.api.reconstruct`
and the benchmarks call it): ``Scenario × PAINT folder × heliostat × ReconstructionSettings → (Scenario′,
report, fit)``. There is one learner (:mod:`heliotwin.surfaces.generalise`): camera model, optics chosen on the
training images, settings and step count by leave-one-training-image-out, outlier drop, acceptance rule;
optionally a plant surface prior (:mod:`heliotwin.surfaces.plantprior`) and a PAINT deflectometry file the learned
surface is compared with (:func:`heliotwin.surfaces.deflectometry.deflectometry_report`).

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
from ..progress import Stages
from ..surfaces.deflectometry import deflectometry_report
from ..surfaces.fit import SurfaceSettings
from ..surfaces.generalise import CV_BATCH_IMAGES, CV_FOLDS, CV_OPTICS_IMAGES, reconstruct_generalising
from ..surfaces.learning import parse_grid
from ..surfaces.observations import paint_observations
from ..surfaces.plantprior import check_leakage, load_surface_prior
from ..surfaces.state import with_learned_surface
from .show import kinematics_note
from .sizes import check_range

__all__ = ["ReconstructionSettings", "reconstruct", "learn_surface", "reconstruction_checkpoint", "CHECKPOINT_LAYOUT"]

#: What a reconstruction checkpoint holds, part of its tag. 2: a blur mode's leave-one-out fits are one batched
#: fit under one key; a checkpoint of the serial layout (1) cannot be continued, so --resume refuses it. 3: the
#: fits also keep each held-out image's evaluation (the cross-validation rows of an every-image run).
CHECKPOINT_LAYOUT = 3


@dataclass
class ReconstructionSettings:
    """Settings of one surface reconstruction (defaults: the command line's).

    Attributes
    ----------
    train_records : tuple of int, optional
        Record ids to train on (each with a centred image); the others with images are the test set.
    train_first : int, optional
        Otherwise the K earliest records with centred images (a study: the written surface is years old).
    train_latest : int, optional
        Otherwise the K latest, evaluated on the earlier images (a study). None of the three (the default): every
        centred image trains the surface (the current one), its error estimated by cross-validation over them
        (:data:`~heliotwin.surfaces.generalise.CV_FOLDS` folds, :data:`~heliotwin.surfaces.generalise.CV_BATCH_IMAGES`
        images per fit and step, so a step costs the same however many images a heliostat has).
    control_points : str or (int, int)
        NURBS control points per facet, e.g. ``"7x7"``.
    degree : int
        NURBS degree in both directions.
    steps : int, optional
        The cross-validation step budget (default :attr:`SurfaceSettings.steps`, 300; held-out L1 every
        ``min(30, steps // 2)`` steps).
    slope_error_mrad : float, optional
        Mirror slope error [mrad]; None chooses it on the training images.
    alignment : {"focal-spot", "motor"}
        Pose of each image: aimed at the measured focal spot, or the plant's kinematics at the motor steps.
    deflectometry : str, optional
        A PAINT deflectometry HDF5 file: its NURBS fit is evaluated on the test images like the ideal and learned
        surfaces and compared with the learned surface in mm and mrad (report key ``deflectometry``).
    surface_prior_from : tuple of str, optional
        Scenario files whose learned surfaces (>= 2 other heliostats of the same design) give a plant prior on the
        facets' canting and low-order shape, or one scenario holding a stored prior
        (:func:`heliotwin.surfaces.plantprior.load_surface_prior`); refused when it was learned from the heliostat
        being reconstructed.
    device : {"auto", "cpu", "cuda"}
        Where the surface is learned and evaluated (results come back on the CPU).
    """

    train_records: tuple | None = None
    train_first: int | None = None
    train_latest: int | None = None
    control_points: str | tuple = "7x7"
    degree: int = 3
    steps: int | None = None
    slope_error_mrad: float | None = None
    alignment: str = "focal-spot"
    deflectometry: str | None = None
    surface_prior_from: tuple | None = None
    device: str = "auto"

    def check(self) -> None:
        """One-line :class:`HeliotwinError` for inconsistent options (before any file is read)."""
        given = [n for n, v in (("--train-records", self.train_records), ("--train-first", self.train_first),
                                ("--train-latest", self.train_latest)) if v]
        if len(given) > 1:
            raise HeliotwinError(f"use one of --train-records, --train-first, --train-latest, not "
                                 f"{' and '.join(given)}")
        # More control points per side than mirror samples are not determined by the images; the dense fit
        # state grows with their square (a 200x200 net took 20 GB).
        most = min(SurfaceSettings().samples)
        nu, nv = parse_grid(self.control_points)
        for n in (nu, nv):
            check_range("--control-points", n, 2, most, f"per side, at most the {most} mirror samples per side")
        check_range("--degree", self.degree, 1, min(nu, nv) - 1, "below the control points per side")
        if self.steps is not None:
            check_range("--steps", self.steps, 1, 100_000)
        if self.train_first is not None:
            check_range("--train-first", self.train_first, 1, 10_000)
        if self.train_latest is not None:
            check_range("--train-latest", self.train_latest, 1, 10_000)

    @property
    def every_image(self) -> bool:
        """Every centred image trains (no split option given): the current surface."""
        return not (self.train_records or self.train_first is not None or self.train_latest is not None)

    def learner(self) -> SurfaceSettings:
        """The learner's settings (:class:`~heliotwin.surfaces.fit.SurfaceSettings`); training on every image,
        K-fold cross-validation and mini-batches (a study's split keeps leave-one-out over full batches)."""
        base = SurfaceSettings()
        steps = int(self.steps or base.steps)
        kw = dict(control_points=parse_grid(self.control_points), degree=(int(self.degree), int(self.degree)),
                  steps=steps, eval_every=min(base.eval_every, max(1, steps // 2)))
        if self.every_image:
            kw.update(folds=CV_FOLDS, batch_images=CV_BATCH_IMAGES, optics_images=CV_OPTICS_IMAGES)
        if self.slope_error_mrad is not None:
            kw["slope_grid"] = (self.slope_error_mrad * 1e-3,)
        return SurfaceSettings(**kw)

    def fingerprint(self) -> dict:
        """What a checkpoint of this run is tagged with (everything that changes the fit; not ``device``, which
        the tag holds on its own; the files named here are fingerprinted as inputs by
        :func:`reconstruction_checkpoint`)."""
        out = {k: v for k, v in dataclasses.asdict(self).items() if k != "device"}
        out["learner"] = dataclasses.asdict(self.learner())
        return out


def reconstruction_checkpoint(path, paint, heliostat: str, settings: ReconstructionSettings, *,
                              scenario_path=None, resume: bool = False,
                              min_interval_s: float | None = None) -> _checkpoint.Checkpoint:
    """The :class:`~heliotwin.io.checkpoint.Checkpoint` of a :func:`reconstruct` run at ``path``, tagged with the
    heliostat, the device, :meth:`ReconstructionSettings.fingerprint` and the input files (the PAINT folder, the
    starting scenario, the deflectometry file and the surface-prior scenarios)."""
    tag = {"command": "reconstruct", "layout": CHECKPOINT_LAYOUT, "heliostat": heliostat,
           "device": resolve_device(settings.device),
           "paint": os.path.abspath(os.fspath(paint)), **settings.fingerprint()}
    files = [paint] + [p for p in (scenario_path, settings.deflectometry) if p is not None]
    files += list(settings.surface_prior_from or ())
    opts = {} if min_interval_s is None else {"min_interval_s": min_interval_s}
    return _checkpoint.Checkpoint(path, _checkpoint.make_tag(tag, files), resume=resume, **opts)


def reconstruct(scenario: Scenario | None, paint, heliostat: str, settings: ReconstructionSettings | None = None, *,
                checkpoint: _checkpoint.Checkpoint | None = None,
                progress: bool = True) -> tuple[Scenario, dict, dict]:
    """Learn ``heliostat``'s surface from its centred images in ``paint`` (by default every one, evaluated by
    cross-validation; a study's split evaluates on the images it left out).

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
        Progress of the stages and of the cross-validation fits (:mod:`heliotwin.progress`: bars on a terminal,
        plain lines in a log).

    Returns
    -------
    scenario : Scenario
        The next scenario (not written): the plant with the learned control points, the learned-surface entry
        (:func:`heliotwin.surfaces.state.with_learned_surface`) and one ``"reconstruct"`` provenance step.
    report : dict
        JSON-ready (:func:`heliotwin.surfaces.generalise.reconstruct_generalising`): per test (and training) image L1
        of the ideal and the learned surface, medians, what the learner chose (``choices``), ``seconds``.
    fit : dict
        In memory, for figures and notebooks: ``model`` (:class:`~heliotwin.surfaces.learning.LearnableSurface`,
        ``model.surfaces()`` the learned surface ``[1, F, nu, nv, 3]`` [m]), ``facets``, ``train``/``test``
        observations, ``ideal`` (Surfaces), ``optics``, and the learner's ``info`` (predicted test images
        through the camera model: ``info["test_images"]``, ``{"ideal", "learned"}`` ``[B, R, R]``).
    """
    s = settings or ReconstructionSettings()
    s.check()
    report, fit = learn_surface(scenario, paint, heliostat, s, checkpoint=checkpoint, progress=progress)
    plant = scenario.plant if scenario is not None else None
    base_plant = plant if plant is not None else scenario_from_paint(paint)
    model, prior = fit["model"], fit["surface_prior"]
    nxt = with_learned_surface(scenario, base_plant, heliostat, model.surfaces(), model.displacement.detach(),
                               fit["optics"], train_records=[int(r["record"]) for r in report["train"]],
                               target=fit["test"].targets[0].name, settings=report["settings"],
                               source=os.path.abspath(paint), surface_prior=None if prior is None else prior.state())
    return nxt, report, fit


def learn_surface(scenario: Scenario | None, paint, heliostat: str, s: ReconstructionSettings, *,
                  checkpoint: _checkpoint.Checkpoint | None = None, progress: bool = True) -> tuple[dict, dict]:
    """:func:`reconstruct` without the next scenario: ``heliostat``'s images read, its surface learned and
    evaluated; ``(report, fit)`` as there (``fit["model"]``, ``fit["surface_prior"]`` on the CPU). Reads only
    this heliostat's records and images (the plant workflow calls it once per heliostat)."""
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
    stages = Stages(2, "heliotwin reconstruct", enabled=progress)
    stages.start(f"reading {heliostat}'s images")
    _, on_device, train, test = paint_observations(
        paint, heliostat, plant=plant, device=device, train_records=list(s.train_records) if s.train_records else None,
        train_first=s.train_first, resolution=learner.resolution, alignment=s.alignment, train_latest=s.train_latest)
    facets = _facets(on_device, torch.float64)
    stages.step(f"reading {len(train)} training and {0 if test is None else len(test)} test images")
    stages.start("learning the surface")
    with _checkpoint.active(checkpoint):
        report, model, info = reconstruct_generalising(facets, train, test, SunSettings(sunshape="buie", csr=0.05),
                                                       learner, progress, prior=prior)
    test = train if test is None else test  # every image trained: the test rows are its cross-validation
    stages.step("learning the surface")
    stages.close()
    fit = {"facets": facets, "train": train, "test": test, "info": info, "optics": info["optics"],
           "ideal": info["ideal"]}
    if s.deflectometry:
        report["deflectometry"] = deflectometry_report(s.deflectometry, facets, model.surfaces(), info["ideal"],
                                                       test, info, learner, report["test"])
    report.update(heliostat=heliostat, paint=str(paint), alignment=s.alignment, device=device,
                  plant="paint" if plant is None else "scenario", seconds=time.perf_counter() - t0)
    report["kinematics"] = note
    report["split"] = split_note(s)
    report["choices"] = _choices(report)
    report["settings"] = dict(report["settings"], chosen=report["choices"])  # the stored surface records its choices
    if device != "cpu":  # results come back on the CPU
        model, fit = model.cpu(), to_device(fit, "cpu")
        fit["train"], fit["test"] = train.to("cpu"), test.to("cpu")
    return report, dict(fit, model=model, surface_prior=prior)


def split_note(s: ReconstructionSettings) -> dict:
    """Which images the written surface learned from, in words a report reader needs (the current surface by
    default; a study's split says that the written surface saw only its training part)."""
    if s.train_records:
        return {"rule": "the given training records", "current": False,
                "note": "the written surface learned from the given records only"}
    if s.train_first is not None:
        return {"rule": f"the {int(s.train_first)} earliest centred images (a study's split)", "current": False,
                "note": "the written surface saw only the earliest images: not the surface now"}
    if s.train_latest is not None:
        return {"rule": f"the {int(s.train_latest)} latest centred images (a study's split)", "current": False,
                "note": "the written surface saw only the latest images; test images are the earlier ones"}
    return {"rule": "every centred image (the current surface)", "current": True,
            "note": f"the test rows are cross-validation: each image evaluated by a fit that did not see it "
                    f"({CV_FOLDS} folds, or one image per fold with fewer images)"}


def _facets(plant, dtype=None) -> Facets:
    """The facets ``[1, F, 3]`` [m] of a one-heliostat plant (``dtype``: converted)."""
    parts = (getattr(plant.field.facets, a)[:1] for a in ("translation", "canting_e", "canting_n"))
    return Facets(*(t if dtype is None else t.to(dtype) for t in parts))


def _choices(report: dict) -> dict:
    """What the learner chose (JSON): optics, blur mode, penalty weight, steps, drops, acceptance."""
    chosen = report["optics"]["chosen"]
    out = {"focal_length_m": chosen["focal_length_m"], "focus_multiple": chosen["focus_multiple"],
           "slope_error_rad": report["optics_used"]["slope_error_rad"], "blur_mode": report["blur_mode"],
           "slope_weight": report["selection"]["slope_weight"], "steps": report["selection"]["steps"],
           "dropped": [d["record"] for d in report["dropped"]], "acceptance_alpha": report["acceptance"]["alpha"]}
    if "prior" in report:
        out.update(surface_prior_weight=report["prior"]["weight"],
                   surface_prior_heliostats=report["prior"]["heliostats"])
    return out
