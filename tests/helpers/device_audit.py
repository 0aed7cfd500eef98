"""Does library code follow the device of its inputs? An audit that runs on the CPU (no GPU needed).

On a GPU, a tensor made without ``device=`` (``torch.zeros(n)``, ``torch.tensor([...])``) or moved to the host
(``.cpu()``) lands on the CPU, and the first operation that combines it with a GPU tensor raises. On a CPU
machine that mistake is invisible: everything is on the CPU. :class:`DeviceAudit` makes it visible. While it is
active (a :class:`torch.overrides.TorchFunctionMode`), every tensor made without a device, or by ``.cpu()``,
is *marked*; marks travel through operations among marked tensors; and an operation that combines a marked
tensor of one or more dimensions with an unmarked one (the inputs' tensors, e.g. a plant moved to the compute
device) is recorded with the library line it came from. Zero-dimensional tensors are exempt (a GPU
operation takes CPU scalars), as is indexing an unmarked tensor with marked indices (a GPU tensor takes CPU
indices). ``.to(device)``, ``torch.as_tensor(t, device=...)`` and ``.cpu()`` of a tensor already there return a
fresh view here, as the copy a GPU would make. ``.numpy()`` of an unmarked tensor is recorded too (on a GPU it
raises), except in functions that only take that path on the CPU (:data:`HOST_ONLY`).

Tensors that exist before the audit starts are unmarked (placed) unless passed to :func:`mark_host` (what
stays on the host in a real run, e.g. a scenario's learned state).
"""
from __future__ import annotations

import collections
import traceback
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

import heliotwin

FACTORIES = {torch.zeros, torch.ones, torch.empty, torch.full, torch.arange, torch.linspace, torch.logspace,
             torch.eye, torch.rand, torch.randn, torch.randint, torch.randperm, torch.tensor, torch.as_tensor,
             torch.scalar_tensor, torch.empty_strided, torch.tril_indices, torch.triu_indices}
MOVES = {"to", "cuda", "type_as"}
#: (file suffix, function) that call ``.numpy()`` only on the CPU (a device check guards them)
HOST_ONLY = {("raytrace/field.py", "_quantile")}
_MARK = "_device_audit_mark"
#: the package's folder (where its files live, wherever the checkout is)
LIBRARY = str(Path(heliotwin.__file__).resolve().parent).replace("\\", "/") + "/"


def _tensors(x, out: list) -> list:
    if isinstance(x, torch.Tensor):
        out.append(x)
    elif isinstance(x, (list, tuple)):
        for y in x:
            _tensors(y, out)
    elif isinstance(x, dict):
        for y in x.values():
            _tensors(y, out)
    return out


def _set(x, mark: str) -> None:
    for t in _tensors(x, []):
        try:
            setattr(t, _MARK, mark)
        except (AttributeError, RuntimeError):
            pass


def mark_host(x) -> None:
    """Mark every tensor in ``x`` (tensor, dataclass-free containers) as living on the host."""
    _set(x, "host")


def _frame(scope: str):
    """The innermost stack frame whose file path holds ``scope``."""
    for f in reversed(traceback.extract_stack()[:-2]):
        if scope in str(Path(f.filename).resolve()).replace("\\", "/"):
            return f
    return None


class DeviceAudit(TorchFunctionMode):
    """``with DeviceAudit() as audit: ...``; then ``audit.hits``: Counter of (what, "file:line code") for the
    lines of files whose path holds ``scope`` (default: the library)."""

    def __init__(self, scope: str = LIBRARY):
        super().__init__()
        self.scope = scope
        self.hits = collections.Counter()

    def _record(self, what: str) -> None:
        f = _frame(self.scope)
        if f is None:
            return
        where = str(Path(f.filename).resolve()).replace("\\", "/").split(self.scope)[-1]
        if any(where.endswith(s) and f.name == fn for s, fn in HOST_ONLY):
            return
        self.hits[(what, f"{where}:{f.lineno} {f.line}")] += 1

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = getattr(func, "__name__", "")
        first = args[0] if args else None
        if func in FACTORIES:
            if kwargs.get("device") is None:
                if not (func is torch.as_tensor and isinstance(first, torch.Tensor)):
                    _set(out, "unplaced")
            elif out is first and getattr(out, _MARK, None):
                out = out.view_as(out)  # as_tensor(t, device=...) copies on a GPU
            return out
        if name == "cpu":
            if out is first:
                out = out.view_as(out)
            _set(out, "host")
            return out
        if name in MOVES:
            rest = list(args[1:]) + list(kwargs.values())
            device = any(isinstance(a, (str, torch.device, torch.Tensor)) for a in rest)
            if not device and getattr(first, _MARK, None):
                _set(out, getattr(first, _MARK))
            elif device and out is first and getattr(out, _MARK, None):
                out = out.view_as(out)
            return out
        if name == "numpy":
            if isinstance(first, torch.Tensor) and getattr(first, _MARK, None) is None:
                self._record("numpy() of a tensor on the compute device")
            return out
        if name == "__getitem__" and isinstance(first, torch.Tensor) and getattr(first, _MARK, None) is None:
            return out
        marks = [(getattr(t, _MARK, None), t.dim() > 0) for t in _tensors(list(args) + list(kwargs.values()), [])]
        marked = sorted({m for m, big in marks if m and big})
        placed = any(m is None and big for m, big in marks)
        if marked and placed:
            self._record(f"{name}: a {'/'.join(marked)} tensor with one on the compute device")
        elif marked or (marks and all(m for m, _ in marks)):
            _set(out, marked[0] if marked else marks[0][0])
        return out

    def report(self) -> str:
        return "\n".join(f"{n} x {where} <- {what}" for (what, where), n in self.hits.most_common())
