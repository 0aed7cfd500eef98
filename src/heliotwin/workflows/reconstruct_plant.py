"""The plant-scale reconstruct workflow: learn the surface of every heliostat that has flux-centred images.

:func:`reconstruct_plant` is the one entry (``heliotwin reconstruct --heliostats all|A,B,C``,
:func:`heliotwin.api.reconstruct_plant` and ``benchmarks/bench_plant_scale.py`` call it):
``Scenario × PAINT folder × heliostat selection × ReconstructionSettings → (Scenario′, report)``.

Per heliostat it is the single-heliostat learner (:func:`heliotwin.workflows.reconstruct.learn_surface`: the same
split, optics choice, cross-validation, outlier drop and acceptance rule), so a heliostat learned here gets exactly
the surface ``heliotwin reconstruct --heliostat H`` gives it. Around it:

* Planning: the folder's records are read once (metadata, no image), and each selected heliostat's train/test split
  is made as the learner makes it (:func:`heliotwin.surfaces.observations.split_record_ids`). A heliostat without
  enough centred images (by default :data:`~heliotwin.surfaces.observations.MIN_IMAGES`: every image trains
  and cross-validation gives the error; with ``train_latest`` or ``train_first`` that many for training and one
  for the test) is *skipped*, with the reason in the report: not an error.
* Learning: one heliostat at a time per process: its images are read, its surface learned and only its result kept
  (control points, displacement, optics, report row: kilobytes). Peak memory is one heliostat's images and fit
  per process, whatever the plant's size. A heliostat whose fit raises is *failed* with a one-line reason; the
  others go on.
* ``nproc`` > 1: the heliostats still to learn are sharded (:func:`heliotwin.distributed.shard`, contiguous) over
  spawned processes (:func:`heliotwin.distributed.run_spawned`: the machine's threads split over them, workers end
  with the parent). A heliostat's fit does not depend on the others, so each result is the one of ``nproc=1`` at
  the same threads per process.
* Resume: :class:`HeliostatResults`, a folder with one file per finished heliostat, written atomically as it
  finishes (by whichever process learned it) and tagged with the settings and inputs (not the selection: a
  heliostat's result does not depend on which others were selected). A resumed run loads the finished heliostats
  and learns the rest; failed heliostats are learned again.
* Batching: the learner's choices (optics candidates, blur mode, cross-validated step counts, dropped images,
  acceptance) are per heliostat and data-dependent, so heliostats are not stacked into one tensor batch; the plant
  runs them side by side in processes instead.

The scenario holds every learned surface (``/field/surfaces`` and ``/learned/surfaces/<HID>``, as
:func:`heliotwin.surfaces.state.with_learned_surface` writes one) and one ``reconstruct`` provenance step listing
them. Units: metres; L1 of unit-sum images; seconds.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import shutil
import statistics
import tempfile
import time

import torch
import torch.distributed as dist

from ..devices import resolve_device
from ..distributed import run_spawned, shard
from ..errors import HeliotwinError
from ..field.plant import SunSettings, Surfaces
from ..field.update import with_surfaces
from ..io import checkpoint as _checkpoint
from ..io.paint import list_heliostats, load_paint
from ..io.scenario import Scenario, next_scenario, provenance_entry
from ..progress import Progress
from ..surfaces.observations import MIN_IMAGES, split_record_ids
from ..surfaces.state import KEY, PRIOR_KEY, surface_state
from .reconstruct import ReconstructionSettings, learn_surface
from .show import kinematics_note

__all__ = ["reconstruct_plant", "plan_heliostats", "check_plant_settings", "plant_reconstruction_checkpoint",
           "HeliostatResults", "with_learned_surfaces"]

_FORMAT = "heliotwin-heliostat-result"
_VERSION = 1


# ------------------------------------------------------------------------------------------------ resume
class HeliostatResults:
    """The finished heliostats of a plant reconstruction: a folder with one file ``<HID>.ckpt`` per heliostat.

    Each file is written atomically (temporary file + :func:`os.replace`) when its heliostat finishes, tagged with
    :func:`heliotwin.io.checkpoint.make_tag` of the run's settings and inputs, and read with
    ``torch.load(weights_only=True)`` (tensors, numbers, strings, containers: loading runs no code).

    Parameters
    ----------
    path : str or os.PathLike
        The folder (created at the first save).
    tag : str
    resume : bool
        Continue from an existing folder (every file's tag must be ``tag``: else one-line error); without it an
        existing folder is an error (it holds an interrupted run's work).
    """

    def __init__(self, path, tag: str, *, resume: bool = False):
        self.path, self.tag = os.fspath(path), str(tag)
        exists = os.path.exists(self.path)
        if exists and not resume:
            raise HeliotwinError(f"{self.path}: a checkpoint of an interrupted run exists; rerun with --resume to "
                                 f"continue it, or delete it to start over")
        if exists and not os.path.isdir(self.path):
            raise HeliotwinError(f"{self.path}: not a checkpoint of a plant reconstruction (a folder); delete it to "
                                 f"start over")
        self.resumed = exists
        self.done = self.read() if exists else {}

    @classmethod
    def at(cls, path, tag: str) -> "HeliostatResults":
        """The results folder ``path`` as it is (no existence check, nothing read yet): where workers write."""
        out = cls.__new__(cls)
        out.path, out.tag, out.resumed, out.done = os.fspath(path), str(tag), False, {}
        return out

    def read(self) -> dict:
        """Every saved heliostat: ``{heliostat id: result}`` (a result as :func:`reconstruct_plant` keeps it)."""
        out = {}
        if not os.path.isdir(self.path):
            return out
        for name in sorted(os.listdir(self.path)):
            if not name.endswith(".ckpt"):
                continue
            full = os.path.join(self.path, name)
            try:
                data = torch.load(full, map_location="cpu", weights_only=True)
            except Exception as exc:  # noqa: BLE001 -- any unreadable file is the same one-line error
                raise HeliotwinError(f"{full}: not a readable heliotwin checkpoint ({type(exc).__name__}); delete "
                                     f"{self.path} to start over") from None
            if not isinstance(data, dict) or data.get("format") != _FORMAT or data.get("version") != _VERSION:
                raise HeliotwinError(f"{full}: not a heliostat result of this heliotwin (field 'format'); delete "
                                     f"{self.path} to start over")
            if data.get("tag") != self.tag:
                raise HeliotwinError(f"{self.path}: checkpoint of a run with other settings or inputs (field 'tag'); "
                                     f"rerun with the same settings to resume, or delete it to start over")
            out[str(data["heliostat"])] = data["result"]
        return out

    def save(self, heliostat: str, result: dict) -> None:
        """Write ``heliostat``'s result (atomically)."""
        _save_result(self.path, self.tag, heliostat, result)

    def remove(self) -> None:
        """Delete the folder (after the run's outputs are written)."""
        shutil.rmtree(self.path, ignore_errors=True)


def _save_result(folder: str, tag: str, heliostat: str, result: dict) -> None:
    os.makedirs(folder, exist_ok=True)
    _checkpoint.save_atomic({"format": _FORMAT, "version": _VERSION, "tag": tag, "heliostat": heliostat,
                             "result": result}, os.path.join(folder, f"{heliostat}.ckpt"))


def _tag(paint, settings: ReconstructionSettings, scenario_path=None) -> str:
    tag = {"command": "reconstruct --heliostats", "device": resolve_device(settings.device),
           "paint": os.path.abspath(os.fspath(paint)), **settings.fingerprint()}
    files = [paint] + ([scenario_path] if scenario_path is not None else []) + list(settings.surface_prior_from or ())
    return _checkpoint.make_tag(tag, files)


def plant_reconstruction_checkpoint(path, paint, settings: ReconstructionSettings, *, scenario_path=None,
                                    resume: bool = False) -> HeliostatResults:
    """The :class:`HeliostatResults` of a :func:`reconstruct_plant` run at ``path`` (a folder), tagged with the
    device, :meth:`ReconstructionSettings.fingerprint` and the input files (the PAINT folder, the starting
    scenario, the surface-prior scenarios); not with the heliostat selection or ``nproc``."""
    return HeliostatResults(path, _tag(paint, settings, scenario_path), resume=resume)


# ------------------------------------------------------------------------------------------------ planning
def check_plant_settings(settings: ReconstructionSettings, nproc: int = 1) -> None:
    """One-line :class:`HeliotwinError` for options that name one heliostat's files or records, or an ``nproc``
    the run cannot use (before any file is read)."""
    settings.check()
    if settings.train_records:
        raise HeliotwinError("--train-records names one heliostat's records; with --heliostats use --train-latest "
                             "or --train-first")
    if settings.deflectometry:
        raise HeliotwinError("--deflectometry is one heliostat's file; use it with --heliostat")
    if isinstance(nproc, bool) or not isinstance(nproc, int) or nproc < 1:
        raise HeliotwinError(f"--nproc: expected a positive number of processes, got {nproc!r}")
    if nproc > 1 and resolve_device(settings.device) != "cpu":
        raise HeliotwinError("--nproc: the local process group is gloo on CPU; use --device cpu with --nproc")


def plan_heliostats(paint, heliostats, settings: ReconstructionSettings, plant=None) -> tuple[list, list, dict, object]:
    """Which heliostats to learn, and which are skipped (and why).

    Parameters
    ----------
    paint : path
        PAINT folder.
    heliostats : "all" or sequence of str
        ``"all"``: every heliostat of the folder (of ``plant`` too, when given).
    settings : ReconstructionSettings
        Its ``train_latest`` or ``train_first`` sets how many centred images a heliostat needs: that many and
        one more; by default (every image trains) :data:`~heliotwin.surfaces.observations.MIN_IMAGES`.
    plant : Plant, optional
        The starting scenario's plant: a heliostat it does not hold is skipped.

    Returns
    -------
    selected : list of str
        The selection, in its order (``"all"``: sorted ids), duplicates dropped.
    learn : list of str
        Those to learn, in selection order.
    skipped : dict
        The others: ``{heliostat: {"heliostat", "status": "skipped", "reason"}}``.
    nominal : Plant
        The folder's nominal plant (all its heliostats).
    """
    available = list_heliostats(paint)
    if isinstance(heliostats, str) and heliostats.strip().lower() == "all":
        wanted = list(available)
    else:
        wanted = [h.strip() for h in ([heliostats] if isinstance(heliostats, str) else heliostats) if h.strip()]
        if not wanted:
            raise HeliotwinError("--heliostats: give 'all' or comma-separated heliostat ids")
        unknown = [h for h in wanted if h not in set(available)]
        if unknown:
            shown = ", ".join(available[:10]) + (", ..." if len(available) > 10 else "")
            raise HeliotwinError(f"--heliostats: unknown heliostat(s) {', '.join(unknown)} in {paint} "
                                 f"({len(available)} heliostats: {shown})")
        wanted = list(dict.fromkeys(wanted))
    ds = load_paint(paint)
    rows: dict = {h: [] for h in ds.plant.field.ids}
    for i, h in enumerate(ds.records.heliostat_index.tolist()):
        rows[ds.plant.field.ids[h]].append(i)
    rec = ds.records
    ids, times, pngs = rec.record_id.tolist(), rec.datetime, rec.flux_centered_png
    in_plant = None if plant is None else set(plant.field.ids)
    learn, skipped = [], {}
    for h in wanted:
        if in_plant is not None and h not in in_plant:
            skipped[h] = {"heliostat": h, "status": "skipped", "reason": "not in the starting scenario's plant"}
            continue
        r = rows.get(h, [])
        try:
            split_record_ids([ids[i] for i in r], [times[i] for i in r], [pngs[i] for i in r],
                             train_first=settings.train_first, train_latest=settings.train_latest)
        except HeliotwinError:
            n = sum(1 for i in r if pngs[i])
            k = settings.train_first or settings.train_latest
            why = (f"needs {int(k) + 1} ({int(k)} training + 1 test)" if k else
                   f"needs {MIN_IMAGES} (every image trains; cross-validation over them)")
            skipped[h] = {"heliostat": h, "status": "skipped", "centred_images": n,
                          "reason": f"{n} centred image(s), {why}"}
            continue
        learn.append(h)
    return wanted, learn, skipped, ds.plant


# ------------------------------------------------------------------------------------------------ learning
def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if isinstance(exc, HeliotwinError) else f"{type(exc).__name__}: {text or 'no message'}"


def _median(values) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def _row(heliostat: str, report: dict) -> dict:
    """The plant report's row of one learned heliostat (JSON)."""
    tr, te = report["train"], report["test"]
    alpha = float(report["acceptance"]["alpha"])
    return {"heliostat": heliostat, "status": "learned",
            "train": {"images": len(tr), "median_l1_ideal": _median(r["l1_ideal"] for r in tr),
                      "median_l1_learned": _median(r["l1_learned"] for r in tr),
                      "worse_than_ideal": report["train_worse_than_ideal"]},
            "test": {"images": len(te), "median_l1_ideal": report["median_l1_ideal"],
                     "median_l1_learned": report["median_l1_learned"], "improved": report["test_improved"],
                     "improved_wilson95": report["test_improved_wilson95"], "is": report["test_is"]},
            # The rule always holds after shrinking; alpha = 0 keeps the ideal start: nothing learned was accepted.
            "accepted": alpha > 0.0, "acceptance_alpha": alpha,
            "kinematics": "nominal" if "no calibration" in report["kinematics"] else "calibrated",
            "choices": report["choices"], "seconds": report["seconds"]}


def _learn_one(scenario, paint, heliostat: str, settings: ReconstructionSettings) -> dict:
    """One heliostat learned (or failed): what the run keeps of it (tensors on the CPU, JSON values)."""
    t0 = time.perf_counter()
    try:
        report, fit = learn_surface(scenario, paint, heliostat, settings, progress=False)
    except Exception as exc:  # noqa: BLE001 -- one heliostat's failure is its row; the others go on
        return {"row": {"heliostat": heliostat, "status": "failed", "reason": _one_line(exc),
                        "seconds": time.perf_counter() - t0}}
    model, prior = fit["model"], fit["surface_prior"]
    surf = model.surfaces()
    return {"row": _row(heliostat, report), "control_points": surf.control_points.detach().to(torch.float64),
            "degree": [int(surf.degree_u), int(surf.degree_v)], "displacement": model.displacement.detach(),
            "optics": dataclasses.asdict(fit["optics"]), "train_records": [int(r["record"]) for r in report["train"]],
            "target": fit["test"].targets[0].name, "settings": report["settings"],
            "surface_prior": None if prior is None else prior.state()}


class _Reporter:
    """Progress per heliostat: a bar on a terminal (the last heliostat beside it), a line per heliostat in a log."""

    def __init__(self, total: int, desc: str, enabled: bool, bar: bool = True):
        self.progress = Progress(total, desc, unit="heliostat", enabled=enabled,
                                 stream=None if bar else io.StringIO())

    def done(self, result: dict) -> None:
        p, row = self.progress, result["row"]
        p.done += 1
        if not p.enabled:
            return
        what = f"{row['heliostat']} {row['status']}"
        if p.tty:
            p.bar.set_postfix_str(what)
            p.bar.update()
        else:
            print(f"{p.desc}: {p.done}/{p.total} {what} ({row['seconds']:.1f} s)", file=p.lines, flush=True)

    def close(self) -> None:
        self.progress.close()


def _learn_shard(job: dict, group) -> None:
    """One worker of an ``nproc`` run: this rank's shard of the heliostats, each saved as it finishes."""
    rank, world = dist.get_rank(group), dist.get_world_size(group)
    mine = [job["heliostats"][i] for i in shard(len(job["heliostats"]), rank, world).tolist()]
    bar = _Reporter(len(mine), f"heliotwin reconstruct: worker {rank + 1}/{world}", job["progress"], bar=False)
    results = HeliostatResults.at(job["folder"], job["tag"])
    for h in mine:
        result = _learn_one(job["scenario"], job["paint"], h, job["settings"])
        results.save(h, result)
        bar.done(result)
    bar.close()


def _learn_all(scenario, paint, todo: list, s: ReconstructionSettings, nproc: int, results: HeliostatResults | None,
               progress: bool) -> dict:
    """``{heliostat: result}`` of the heliostats ``todo``, learned here (``nproc`` 1) or by ``nproc`` workers."""
    if nproc <= 1:
        out, bar = {}, _Reporter(len(todo), "heliotwin reconstruct", progress)
        try:
            for h in todo:
                out[h] = _learn_one(scenario, paint, h, s)
                if results is not None and out[h]["row"]["status"] == "learned":
                    results.save(h, out[h])
                bar.done(out[h])
        finally:
            bar.close()
        return out
    with contextlib.ExitStack() as stack:
        folder = results.path if results is not None else stack.enter_context(
            tempfile.TemporaryDirectory(prefix="heliotwin-heliostats-"))
        tag = results.tag if results is not None else "this run"
        run_spawned(_learn_shard, {"scenario": scenario, "paint": os.fspath(paint), "heliostats": list(todo),
                                   "settings": s, "folder": folder, "tag": tag, "progress": progress}, nproc)
        got = HeliostatResults.at(folder, tag).read()
    if results is not None:  # a failed heliostat is learned again by a resumed run
        for h, r in got.items():
            if r["row"]["status"] != "learned":
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(folder, f"{h}.ckpt"))
    missing = [h for h in todo if h not in got]
    if missing:
        raise RuntimeError(f"reconstruct: the workers ended without a result for {', '.join(missing[:5])}")
    return {h: got[h] for h in todo}


# ------------------------------------------------------------------------------------------------ the scenario
def with_learned_surfaces(previous: Scenario | None, plant, results: dict, *, source: str = "",
                          settings: dict | None = None, skipped=(), failed=()) -> Scenario:
    """The scenario after a plant reconstruction, in memory: every learned heliostat's control points in
    ``plant.field.surfaces`` and its ``/learned/surfaces/<HID>`` entry
    (:func:`heliotwin.surfaces.state.surface_state`), one ``"reconstruct"`` provenance step naming them.

    Parameters
    ----------
    previous : Scenario or None
        The scenario ``plant`` came from (learned state and provenance kept), None for a PAINT folder's plant.
    plant : Plant
        The whole plant the step started from.
    results : dict
        ``{heliostat id: result}`` of the learned heliostats: ``control_points`` ``[1, F, nu, nv, 3]`` [m] (one
        net for all), ``degree``, ``displacement`` ``[F, nu, nv]`` [m], ``optics`` (SunSettings fields),
        ``train_records``, ``target``, ``settings``, ``surface_prior`` (state or None; the last one is stored).
    source, settings, skipped, failed
        Provenance: the PAINT folder, the run's settings (JSON), the skipped and failed heliostat ids.
    """
    learned = dict(previous.learned) if previous is not None else {}
    entries = dict(learned.get(KEY) or {})
    ids = list(results)
    for h in ids:
        r = results[h]
        entries[h] = surface_state(r["displacement"].reshape(r["displacement"].shape[-3:]), SunSettings(**r["optics"]),
                                   train_records=r["train_records"], target=r["target"], settings=r["settings"])
        if r.get("surface_prior") is not None:
            learned[PRIOR_KEY] = r["surface_prior"]
    if ids:
        learned[KEY] = entries
        du, dv = results[ids[0]]["degree"]
        cp = torch.cat([results[h]["control_points"] for h in ids])
        plant = with_surfaces(plant, ids, Surfaces(cp, du, dv))
    step = provenance_entry("reconstruct", heliostats=ids, source=str(source),
                            records={h: [int(x) for x in results[h]["train_records"]] for h in ids},
                            settings=settings or {}, skipped=list(skipped), failed=list(failed))
    return next_scenario(previous, plant, learned=learned, step=step)


def _summary(rows: list, nproc: int, wall: float, resumed: int) -> dict:
    learned = [r for r in rows if r["status"] == "learned"]
    count = {k: sum(r["status"] == k for r in rows) for k in ("learned", "skipped", "failed")}
    fitted = [r for r in rows if r["status"] != "skipped" and not r.get("resumed")]
    return {"heliostats": len(rows), **count, "accepted": sum(r["accepted"] for r in learned), "resumed": resumed,
            "median_test_l1_ideal": _median(r["test"]["median_l1_ideal"] for r in learned),
            "median_test_l1_learned": _median(r["test"]["median_l1_learned"] for r in learned),
            # per heliostat learned in this run: its own time in its process, and the run's wall time shared out
            "seconds_per_heliostat": _median(r["seconds"] for r in fitted),
            "wall_seconds_per_heliostat": wall / len(fitted) if fitted else None,
            "seconds": wall, "nproc": nproc}


def reconstruct_plant(scenario: Scenario | None, paint, heliostats="all",
                      settings: ReconstructionSettings | None = None, *, nproc: int = 1,
                      checkpoint: HeliostatResults | None = None, progress: bool = True) -> tuple[Scenario, dict]:
    """Learn the surface of every selected heliostat with enough flux-centred images in ``paint`` (module docstring).

    Parameters
    ----------
    scenario : Scenario or None
        The plant to start from (e.g. a calibrated one: its kinematics pose the heliostats); None: the PAINT
        folder's nominal plant.
    paint : path
        PAINT folder.
    heliostats : "all" or sequence of str
        The selection; unknown ids are a one-line error.
    settings : ReconstructionSettings, optional
        Per heliostat, as for :func:`heliotwin.workflows.reconstruct.reconstruct` (``train_records`` and
        ``deflectometry`` name one heliostat's data: refused).
    nproc : int
        Worker processes (1: this process).
    checkpoint : HeliostatResults, optional
        From :func:`plant_reconstruction_checkpoint`: finished heliostats are saved there as they finish, and
        those it already holds are not learned again; the caller removes it once its outputs are written.
    progress : bool
        Progress per heliostat (:mod:`heliotwin.progress`); the learner's own progress stays quiet.

    Returns
    -------
    scenario : Scenario
        The next scenario (not written): :func:`with_learned_surfaces` of the learned heliostats.
    report : dict
        JSON-ready: ``heliostats`` (one row per selected heliostat, selection order: ``status`` learned / skipped /
        failed, ``reason`` of the latter two; a learned one's ``train`` and ``test`` image counts and median L1
        of the ideal and the learned surface, ``accepted`` and ``acceptance_alpha``, ``choices``, ``seconds``,
        ``resumed``), ``summary`` (counts, median over heliostats of the test median L1 ideal and learned,
        ``seconds_per_heliostat`` (median over the heliostats learned in this run), ``wall_seconds_per_heliostat``,
        ``nproc``), ``settings``, ``paint``, ``device``.
    """
    s = settings or ReconstructionSettings()
    check_plant_settings(s, nproc)
    t0 = time.perf_counter()
    plant = scenario.plant if scenario is not None else None
    selected, learn, skipped, nominal = plan_heliostats(paint, heliostats, s, plant)
    nominal_kinematics = [h for h in learn if "no calibration" in kinematics_note(scenario, h)]
    if progress and nominal_kinematics:  # a surface learned on nominal kinematics must say so, up front
        where = f"in {scenario.path or 'the scenario'}" if scenario is not None else "(no scenario)"
        print(f"heliotwin reconstruct: {len(nominal_kinematics)} of {len(learn)} heliostats run on their nominal "
              f"kinematics (no calibration {where})", flush=True)
    done = dict(checkpoint.done) if checkpoint is not None else {}
    done = {h: r for h, r in done.items() if h in set(learn) and r["row"]["status"] == "learned"}
    todo = [h for h in learn if h not in done]
    fresh = _learn_all(scenario, paint, todo, s, min(int(nproc), max(1, len(todo))), checkpoint, progress)
    results = {**{h: dict(r, row=dict(r["row"], resumed=True)) for h, r in done.items()},
               **{h: dict(r, row=dict(r["row"], resumed=False)) for h, r in fresh.items()}}
    rows = [results[h]["row"] if h in results else skipped[h] for h in selected]
    ok = {h: results[h] for h in learn if results[h]["row"]["status"] == "learned"}
    failed = [h for h in learn if results[h]["row"]["status"] == "failed"]
    nxt = with_learned_surfaces(scenario, plant if plant is not None else nominal, ok,
                                source=os.path.abspath(os.fspath(paint)), settings=s.fingerprint(),
                                skipped=list(skipped), failed=failed)
    report = {"heliostats": rows, "summary": _summary(rows, int(nproc), time.perf_counter() - t0, len(done)),
              "settings": s.fingerprint(), "paint": os.fspath(paint), "device": resolve_device(s.device),
              "plant": "paint" if plant is None else "scenario"}
    return nxt, report
