"""What a method trains on: the heliostats it may calibrate and the centroids it fits.

Shared by every method (:mod:`~heliotwin.calibrate.methods`); the metric never uses these choices: it
evaluates on the run's ``--focal-spot`` centroids.
"""
from __future__ import annotations

import torch

from ..io.records import RecordTable, normalise_source

#: Fewest training records per heliostat a method accepts (below, the heliostat is skipped with a reason).
MIN_TRAIN = 4

#: Centroid source the rigid-body fits train on, where a record has it (the metric keeps ``--focal-spot``).
#: ``"UTIS"``, ``"HeliOS"``, ``"average"``, ``"harmonised"`` or ``None`` (= the metric's source). Chosen by
#: validation that never touches the test records (see docs in :func:`fit_spots`).
FIT_FOCAL_SPOT = "UTIS"

#: Pointing noise of one centroid record [rad] (camera-target centroids scatter by ~1 mrad): what the least-squares
#: fits weigh their priors and drift against.
NOISE = 1e-3


def fit_spots(batch: RecordTable, source: str | None = FIT_FOCAL_SPOT) -> RecordTable:
    """The batch with the centroids a fit trains on.

    Both camera systems measure the same spot; on the 11 PAINT heliostats, training on UTIS where a record
    has it (HeliOS elsewhere) extrapolated better to *later* records evaluated in HeliOS (median of the
    per-heliostat mean error on the records between the chronological train and test blocks: 1.14 vs
    1.22 mrad at N=30, 1.77 vs 1.85 at N=10; pseudo-splits inside the 30 training records could not
    separate the variants: 0.55 vs 0.53). ``average`` = mean of both where both exist. ``harmonised`` =
    UTIS moved into the metric source's frame, see :func:`source_offsets`.
    """
    if source is None or batch.spot_other is None or len(batch) == 0:
        return batch
    src = source if source in ("average", "harmonised") else normalise_source(source)
    has = torch.isfinite(batch.spot_other).all(-1)
    if src == "average":
        new = torch.where(has.unsqueeze(-1), 0.5 * (batch.spot + batch.spot_other), batch.spot)
    elif src == "harmonised":
        shift, known = source_offsets(batch)
        new = torch.where(known.unsqueeze(-1), batch.spot_other + shift, batch.spot)
    else:
        other = torch.tensor([s != src for s in batch.source], dtype=torch.bool, device=has.device)
        new = torch.where((has & other).unsqueeze(-1), batch.spot_other, batch.spot)
    out = batch.subset(torch.arange(len(batch), device=has.device))
    out.spot = new
    return out


#: Fewest records with both centroids on one target before :func:`source_offsets` trusts its median.
MIN_SOURCE_PAIRS = 3


def source_offsets(batch: RecordTable) -> tuple[torch.Tensor, torch.Tensor]:
    """Per record, the median HeliOS - UTIS centroid difference on its target, from ``batch`` alone.

    The two camera systems disagree by a constant per target: on the Jülich records HeliOS sits about 8 cm
    *above* UTIS on the lower target (median of 429 pairs; 1.6 to 16 cm between heliostats), 2 cm below on
    the upper one and 4 cm above on the multi-focus tower, alike in 2022, 2023 and 2024; the sideways part
    varies more between heliostats (``docs/carryover.md``, the row on harmonised UTIS). UTIS
    centroids scatter less, so ``harmonised`` fits UTIS shifted by that difference: the smaller noise, in the
    frame the metric scores. The difference is the plant's (pooled over the batch's heliostats, median per
    target, so one bad centroid cannot move it) and uses only the records given (a training batch never sees
    test records). Whether it beats plain UTIS is left to the CV
    (:data:`~heliotwin.calibrate.protocol.selection.CANDIDATES`): on the shared heliostats it does not (CV N=30 1.069
    against 0.969 mrad, run prior): in an exploratory run, moving the training centroids by ~0.1 mrad of normal moved
    the test-block predictions of BE36 and BF55 by ~0.5, the way their test blocks' own offsets already lay: a small
    shift of the training data lands on weakly determined parameters that the extrapolation to new sun positions
    amplifies.

    Parameters
    ----------
    batch : RecordTable
        R records; ``spot`` in the metric's source, ``spot_other`` the other source (NaN where absent),
        ``focal_spots`` both (:meth:`~heliotwin.io.records.RecordTable.camera_offsets`).

    Returns
    -------
    shift : torch.Tensor, [R, 3]
        [m] to add to ``spot_other``; zero where ``known`` is False.
    known : torch.Tensor, [R], bool
        Records whose ``spot`` is HeliOS, ``spot_other`` UTIS, on a target with >= :data:`MIN_SOURCE_PAIRS`
        records that have both; elsewhere ``spot`` is kept (no UTIS centroid, UTIS is already the metric's,
        or a target too rare to estimate its offset).
    """
    shift = torch.zeros_like(batch.spot)
    known = torch.zeros(len(batch), dtype=torch.bool, device=batch.spot.device)
    utis = torch.isfinite(batch.spot_other).all(-1) & torch.tensor(
        [s != "UTIS" for s in batch.source], dtype=torch.bool, device=known.device)
    for name, pairs in batch.camera_offsets().items():  # HeliOS - UTIS per target
        if pairs["pairs"] >= MIN_SOURCE_PAIRS:
            on = utis & batch.on_target(name)
            shift[on] = pairs["offset"]
            known |= on
    return shift, known


def trainable(train: RecordTable) -> torch.Tensor:
    """[H] bool: heliostats with at least :data:`MIN_TRAIN` training records."""
    return train.counts() >= MIN_TRAIN


def restrict(batch: RecordTable | None, ok: torch.Tensor) -> RecordTable | None:
    """The records of the heliostats ``ok`` [H] bool (heliostat axis unchanged); None stays None."""
    return None if batch is None else batch.subset(ok[batch.heliostat_index])
