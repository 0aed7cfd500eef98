"""Atomic writing of reports and files: nothing half-written is ever left behind."""
from __future__ import annotations

import json
import math
import os
import tempfile
from contextlib import contextmanager


def _clean(obj):
    """JSON-safe copy: tensors/arrays to lists, NaN/inf to None (strict JSON)."""
    try:
        import numpy as np
        import torch
    except ImportError:  # pragma: no cover
        np = torch = None
    if torch is not None and isinstance(obj, torch.Tensor):
        obj = obj.detach().cpu().tolist()
    elif np is not None and isinstance(obj, np.ndarray):
        obj = obj.tolist()
    elif np is not None and isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


@contextmanager
def atomic_path(path):
    """Yield a temporary path in the destination folder; rename onto ``path`` only on success."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_json(path, obj) -> None:
    """Write ``obj`` as strict, indented JSON atomically (NaN/inf become null)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(_clean(obj), fh, indent=1, allow_nan=False)
            fh.write("\n")
