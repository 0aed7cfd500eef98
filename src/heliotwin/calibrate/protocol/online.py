"""The online protocol (``--split online``): each test record predicted from the records before it.

As a plant runs a calibration: records arrive in time order, and the model that aims a heliostat at time t
was fitted on records before t. For every heliostat (records without a time are dropped and counted):

* test = its latest ``n_test`` records (as ``chrono``, so the figures compare);
* test record j is predicted by the method refitted on the ``n_train`` records *immediately before* it
  (a sliding window: the fit follows a drifting offset as records arrive; with the plant prior it needs
  few of them). Refits happen every ``step`` test records (``step`` = 1: before every record; larger steps
  trade fidelity for time: a block of ``step`` records is predicted by the fit on the window before the
  block, never by a fit that saw any of them).

The run's returned model (and the scenario it writes) is the fit on the window before the test block. Each
test record's predictive interval comes from the refit that predicted it (its posterior, and its
random-walk offset grown from the window's latest record to the record's time).
With the drift model (``--drift kalman``, :mod:`heliotwin.calibrate.drift`) every refit smooths the random-walk offset
over its window and predicts the block with the filtered offset at the window's latest record: the filter updates as
records arrive.
"""
from __future__ import annotations

import numpy as np
import torch


def _ordered(batch) -> list:
    """Per heliostat: global indices of its records with a time, in time order (stable)."""
    times = batch.time.detach().cpu().numpy() if batch.time is not None else np.full(len(batch), np.nan)
    out = []
    for rows in batch.rows_by_heliostat():
        rows = rows.cpu().numpy()
        rows = rows[np.isfinite(times[rows])]
        out.append(rows[np.argsort(times[rows], kind="stable")])
    return out


def online_split(batch, n_train: int, n_test: int | None):
    """(train [idx], validation [idx] (empty), test [idx], info per heliostat) of the online protocol.

    ``train`` = the ``n_train`` records just before each heliostat's test block (the returned model's fit).
    """
    order, info = _ordered(batch), {}
    tr, te = [], []
    t = 30 if n_test is None else int(n_test)
    counts = batch.counts().tolist()
    for h, rows in enumerate(order):
        n_t = min(t, max(0, len(rows) - 1))
        start = len(rows) - n_t
        te.append(rows[start:])
        tr.append(rows[max(0, start - n_train):start])
        info[batch.heliostat_ids[h]] = {"train": len(tr[-1]), "validation": 0, "test": n_t,
                                        "dropped_no_time": int(counts[h] - len(rows)),
                                        "mean_train_test_distance_rad": None}
    return _cat(tr), torch.zeros(0, dtype=torch.long), _cat(te), info


def _cat(xs) -> torch.Tensor:
    return torch.as_tensor(np.concatenate(xs) if xs else np.zeros(0, int), dtype=torch.long)


def online_errors(fit_one, batch, test_idx: torch.Tensor, n_train: int, step: int = 5, on_block=None):
    """Pointing error [rad] and miss distance [m] of every test record (in ``test_idx`` order), each predicted
    by ``fit_one(train batch) -> Calibrated`` on the ``n_train`` records before its block of ``step``.

    Every refit is one batched fit over all heliostats that still have test records in that block.
    ``on_block(model, block records, positions [B] in test_idx order, error [B] [rad])``, when given, is
    called after each refit with what it predicted (the predictive interval of that block comes from that
    refit, :func:`heliotwin.calibrate.protocol.pipeline.online_refit`).
    """
    order = _ordered(batch)
    pos = {int(g): i for i, g in enumerate(test_idx.tolist())}
    err = torch.full((len(test_idx),), float("nan"), dtype=torch.float64)
    miss = torch.full_like(err, float("nan"))
    starts = [len(rows) - sum(1 for r in rows if int(r) in pos) for rows in order]
    n_test = max((len(rows) - s for rows, s in zip(order, starts)), default=0)
    for b in range(0, n_test, max(1, step)):
        win, blk = [], []
        for rows, s in zip(order, starts):
            block = rows[s + b:s + b + step]
            if len(block):
                blk.append(block)
                win.append(rows[max(0, s + b - n_train):s + b])
        if not blk:
            continue
        train = batch.subset(torch.as_tensor(np.concatenate(win), dtype=torch.long))
        pred = batch.subset(torch.as_tensor(np.concatenate(blk), dtype=torch.long))
        model = fit_one(train)
        e, m = model.pointing_error(pred), model.miss_distance(pred)
        ok = model.ok[pred.heliostat_index]
        e, m = torch.where(ok, e.double(), torch.nan), torch.where(ok, m.double(), torch.nan)
        where = [pos[int(g)] for g in np.concatenate(blk).tolist()]
        at = torch.as_tensor(where, dtype=torch.long)
        err[at], miss[at] = e.to(err), m.to(miss)
        if on_block is not None:
            on_block(model, pred, where, e)
    return err, miss
