"""Observations of one heliostat for surface learning: poses + measured images, and which records train.

:class:`Observations` is the data the learner sees (B images with their sun directions, mirror poses and
targets). :func:`observations_from_records` builds them from calibration records (pose aimed at the
measured focal spot, or from the motor steps; image from the one measured-image loader,
:func:`heliotwin.io.images.load_measured_image`). :func:`split_record_ids` is the one train/test split of surface
learning, over plain record columns (id, time, image path), so it can be fed from any record table.
:func:`paint_observations` does all of it for one PAINT heliostat (the one data path of the surface learner).

Calibration splits records differently, on purpose
(:func:`heliotwin.calibrate.protocol.splits.split_records`): every heliostat of a plant at once, every record
(no image needed), into train / validation / test by a named rule (chronological, random, sun-distance) with
counts and a seed. A surface split is one heliostat's records *with a centred image*: the K earliest (or given
ids) train, all the others test, no validation set (the learner holds out training images itself), and an
error when no test image is left.

Shapes: B images; R window pixels per side. Units: metres, radians.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..devices import to_device
from ..errors import HeliotwinError
from ..field import kinematics as kin_ops
from ..field.update import select_heliostats
from ..io.images import load_measured_image
from ..io.paint import PaintDataset, load_paint
from ..io.records import RecordTable

__all__ = ["Observations", "observations_from_records", "split_record_ids", "load_centered_image",
           "paint_observations"]


@dataclass
class Observations:
    """B images of one heliostat with their poses.

    Attributes
    ----------
    sun : torch.Tensor, [B, 3], float64
        Unit vectors towards the sun.
    rotation : torch.Tensor, [B, 3, 3], float64
        ``R_world_heliostat`` per image.
    concentrator : torch.Tensor, [B, 3], float64
        ENU [m].
    targets : list of PlanarTarget, length B
    images : torch.Tensor, [B, R, R], optional
        Measured centred images (any scale; they are normalised to unit sum where compared).
    ids : list of str
        Names (record ids) for reports.
    centers : torch.Tensor, [B, 2], optional
        Fixed window centres (target-local [m]) for images taken with *known* kinematics, e.g. the aim
        point: the spot's position in the window then carries information (a common tilt of all facets
        becomes observable). None (PAINT's ``flux-centered`` images): each window is centred on its own
        spot centroid.
    """

    sun: torch.Tensor
    rotation: torch.Tensor
    concentrator: torch.Tensor
    targets: list
    images: torch.Tensor | None = None
    ids: list = field(default_factory=list)
    centers: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.sun.shape[0])

    def to(self, device) -> "Observations":
        """The same observations on ``device`` (the learner follows it; targets stay as they are)."""
        mv = lambda t: None if t is None else t.to(device)  # noqa: E731
        return Observations(mv(self.sun), mv(self.rotation), mv(self.concentrator), self.targets, mv(self.images),
                            list(self.ids), mv(self.centers))

    def subset(self, idx) -> "Observations":
        """The observations ``idx`` (a sequence of k indices into B), in that order: tensors ``(k, ...)``."""
        idx = list(idx)
        return Observations(self.sun[idx], self.rotation[idx], self.concentrator[idx], [self.targets[i] for i in idx],
                            None if self.images is None else self.images[idx], [self.ids[i] for i in idx],
                            None if self.centers is None else self.centers[idx])


def load_centered_image(path, resolution: int = 64, background: float = 0.0) -> torch.Tensor:
    """A PAINT ``-flux-centered.png`` as ``[R, R]`` float32 on the comparison grid (relative scale).

    :func:`heliotwin.io.images.load_measured_image` with ``square=True``: 256x256 images (newer releases) are
    box-averaged to 64x64 so that every image is compared on the same 9.4 cm pixels; ``background``
    (fraction of the max [1]) is subtracted and clipped at 0.
    """
    return load_measured_image(path, resolution, background=background, square=True)


#: Centred images a reconstruction needs by default: it trains on every one and estimates its error by
#: cross-validation over them, which needs three (two to fit, one held out, in each of three folds).
MIN_IMAGES = 3


def _time_key(record_id: int, time, undated_first: bool = False) -> tuple:
    # Records with a DateTime in time order (ISO strings sort chronologically), the rest by id: after them, or
    # before them with ``undated_first`` (the latest images are then the latest dated ones).
    undated = 0 if undated_first else 2
    return (1, str(time), record_id) if time else (undated, "", record_id)


def split_record_ids(record_ids, times, image_paths, train_records=None, train_first: int | None = None,
                     train_latest: int | None = None) -> tuple[list[int], list[int]]:
    """Train/test split of the records that have centred images, over plain record columns.

    Parameters
    ----------
    record_ids : sequence of int, length N
    times : sequence of str or None, length N
        ISO DateTime [UTC] per record, or None/"" where unknown (only their order is used).
    image_paths : sequence of str or None, length N
        Centred image per record (None/"": none; such records are in neither set).
    train_records : iterable of int, optional
        Explicit training ids (each must have a centred image); the rest are test.
    train_first : int, optional
        Otherwise the K earliest by DateTime (records without one come after, by id): a study's split.
    train_latest : int, optional
        Otherwise the K latest by DateTime (records without one count as earlier than every dated one), the
        earlier images its test set.
    None of them (the default): every record with a centred image trains (the current surface), and ``test``
    is empty (the learner's cross-validation gives the error); at least :data:`MIN_IMAGES` are needed.

    Returns
    -------
    train, test : list of int
        Indices into the columns; ``train`` in time order, ``test`` in input order.
    """
    ids = [int(r) for r in record_ids]
    with_img = [i for i, p in enumerate(image_paths) if p]
    if not with_img:
        raise HeliotwinError("no records with a '-flux-centered.png' image for this heliostat")
    key = {i: _time_key(ids[i], times[i]) for i in with_img}
    if train_records:
        wanted = {int(x) for x in train_records}
        missing = sorted(wanted - {ids[i] for i in with_img})
        if missing:
            raise HeliotwinError(f"train record(s) {', '.join(map(str, missing))} have no centred image or do not "
                                 f"exist; records with images: {', '.join(str(ids[i]) for i in with_img)}")
        train = [i for i in with_img if ids[i] in wanted]
    elif train_first is not None:
        if int(train_first) < 1:
            raise HeliotwinError(f"--train-first must be >= 1, got {train_first}")
        train = sorted(with_img, key=key.get)[:int(train_first)]
    elif train_latest is not None:
        k = int(train_latest)
        if k < 1:
            raise HeliotwinError(f"--train-latest must be >= 1, got {k}")
        train = sorted(with_img, key=lambda i: _time_key(ids[i], times[i], undated_first=True))[-k:]
    else:
        if len(with_img) < MIN_IMAGES:
            raise HeliotwinError(f"{len(with_img)} record(s) with a centred image; a surface learned from every image "
                                 f"needs at least {MIN_IMAGES} to cross-validate (or give --train-records)")
        return sorted(with_img, key=key.get), []
    test = [i for i in with_img if i not in train]
    if not test:
        raise HeliotwinError(f"no test images left: {len(with_img)} records have centred images, all used for training")
    return sorted(train, key=key.get), test


def observations_from_records(plant, heliostat_index: int, records: RecordTable, resolution: int = 64,
                              background: float = 0.0, alignment: str = "focal-spot") -> Observations:
    """Poses and measured images of calibration records (rows of the record table, each with a centred image).

    ``alignment="focal-spot"`` aims the heliostat at each record's measured focal spot (``records.spot``:
    HeliOS, else UTIS); ``"motor"`` uses the plant's kinematics at the recorded motor steps.

    Returns
    -------
    Observations
        B = len(records) images ``[B, R, R]`` (R = ``resolution``) with poses ``[B, 3, 3]``, ``[B, 3]`` [m].
    """
    kin = plant.field.kinematics.index(heliostat_index)
    sun = records.sun
    if alignment == "focal-spot":
        rot, conc = kin_ops.aimed_pose(kin, records.spot, sun)
    elif alignment == "motor":
        rot, conc = kin_ops.forward(kin, records.motor_steps.reshape(-1, 1, 2))
        rot, conc = rot[:, 0], conc[:, 0]
    else:
        raise HeliotwinError(f"unknown alignment {alignment!r}; expected focal-spot or motor")
    # The record table holds planar-target records only.
    targets = [plant.target(name) for name in records.target]
    if any(p is None for p in records.flux_centered_png):
        raise HeliotwinError("every record needs a '-flux-centered.png' image")
    images = torch.stack([load_centered_image(p, resolution, background) for p in records.flux_centered_png])
    return Observations(sun, rot, conc, targets, images, [str(r) for r in records.record_id.tolist()])


def paint_observations(paint_dir, heliostat_id: str, *, plant=None, device: str = "cpu", train_records=None,
                       train_first: int | None = None, resolution: int = 64, background: float = 0.0,
                       alignment: str = "focal-spot", train_latest: int | None = None
                       ) -> tuple[PaintDataset, object, Observations, Observations]:
    """One PAINT heliostat's training and test observations (:func:`split_record_ids`,
    :func:`observations_from_records`).

    Parameters
    ----------
    paint_dir : path
        PAINT folder.
    heliostat_id : str
    plant : Plant, optional
        Replaces the folder's nominal plant (e.g. a calibrated scenario's): its kinematics pose the heliostat.
    device : {"cpu", "cuda"}
        Where the plant and observations go (the images are read on the CPU).
    train_records, train_first, train_latest
        The split (:func:`split_record_ids`).
    resolution : int
        R, window pixels per side.
    background : float
        Subtracted from each image, fraction of its max [1].
    alignment : {"focal-spot", "motor"}

    Returns
    -------
    dataset : PaintDataset
        The heliostat's records on the (nominal or given) plant, on the CPU.
    plant : Plant
        One heliostat, on ``device``.
    train, test : Observations
        ``[B, R, R]`` images with poses, on ``device``; ``train`` in time order; ``test`` None when every image
        trains (the default split).
    """
    ds = load_paint(paint_dir, heliostats=[heliostat_id])
    if plant is not None:
        ds = ds.on_plant(select_heliostats(plant, [heliostat_id]))
    on_device = ds.plant if device == "cpu" else to_device(ds.plant, device)
    records = ds.records_of(heliostat_id)
    tr, te = split_record_ids(records.record_id.tolist(), records.datetime, records.flux_centered_png, train_records,
                              train_first, train_latest)
    # poses from the records on the CPU (where the table is), then the observations move to the device
    train = observations_from_records(ds.plant, 0, records.subset(tr), resolution, background, alignment)
    test = observations_from_records(ds.plant, 0, records.subset(te), resolution, background, alignment) if te else None
    if device != "cpu":
        train, test = train.to(device), None if test is None else test.to(device)
    return ds, on_device, train, test
