"""Where tensors live: choosing a device and moving plant pieces between CPU and GPU.

One home for the two helpers every compute step uses (the CLI's ``--device``, the API's ``device=``):
:func:`resolve_device` turns ``"auto"`` into ``"cuda"`` when torch sees a CUDA device, and :func:`to_device`
moves a plant, a target, a record table, a flux image or a network -- anything built of tensors and
dataclasses -- keeping dtypes. The physics never calls them: it follows the device of its inputs.
"""
from __future__ import annotations

import copy
import dataclasses

import torch

__all__ = ["resolve_device", "to_device"]


def resolve_device(device) -> str:
    """``"auto"`` -> ``"cuda"`` when torch sees a CUDA device, else ``"cpu"``; anything else as given."""
    name = str(device)
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def to_device(obj, device):
    """``obj`` with every tensor on ``device``: tensors, dataclasses (plants, targets, record tables, flux
    images), modules (networks, copied), and lists/tuples/dicts of them; anything else is returned as is.
    Dtypes are kept."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, torch.nn.Module):
        return copy.deepcopy(obj).to(device)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {f.name: to_device(getattr(obj, f.name), device) for f in dataclasses.fields(obj) if f.init}
        return dataclasses.replace(obj, **changes)
    if isinstance(obj, dict):
        return {k: to_device(v, device) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if all(isinstance(v, _PLAIN) for v in obj):  # a field's ids: nothing to move, one copy (not 30,000 calls)
            return type(obj)(obj)
        return type(obj)(to_device(v, device) for v in obj)
    return obj


_PLAIN = (str, bytes, int, float, bool, type(None))
