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
#: ``"UTIS"``, ``"HeliOS"``, ``"average"`` or ``None`` (= the metric's source). Chosen by validation that
#: never touches the test records (see docs in :func:`fit_spots`).
FIT_FOCAL_SPOT = "UTIS"


def fit_spots(batch: RecordTable, source: str | None = FIT_FOCAL_SPOT) -> RecordTable:
    """The batch with the centroids a fit trains on.

    Both camera systems measure the same spot; on the 11 PAINT heliostats, training on UTIS where a record
    has it (HeliOS elsewhere) extrapolated better to *later* records evaluated in HeliOS (median of the
    per-heliostat mean error on the records between the chronological train and test blocks: 1.14 vs
    1.22 mrad at N=30, 1.77 vs 1.85 at N=10; pseudo-splits inside the 30 training records could not
    separate the variants: 0.55 vs 0.53). ``average`` = mean of both where both exist.
    """
    if source is None or batch.spot_other is None or len(batch) == 0:
        return batch
    src = source if source == "average" else normalise_source(source)
    has = torch.isfinite(batch.spot_other).all(-1)
    if src == "average":
        new = torch.where(has.unsqueeze(-1), 0.5 * (batch.spot + batch.spot_other), batch.spot)
    else:
        other = torch.tensor([s != src for s in batch.source], dtype=torch.bool, device=has.device)
        new = torch.where((has & other).unsqueeze(-1), batch.spot_other, batch.spot)
    out = batch.subset(torch.arange(len(batch), device=has.device))
    out.spot = new
    return out


def trainable(train: RecordTable) -> torch.Tensor:
    """[H] bool: heliostats with at least :data:`MIN_TRAIN` training records."""
    return train.counts() >= MIN_TRAIN


def restrict(batch: RecordTable | None, ok: torch.Tensor) -> RecordTable | None:
    """The records of the heliostats ``ok`` [H] bool (heliostat axis unchanged); None stays None."""
    return None if batch is None else batch.subset(ok[batch.heliostat_index])
