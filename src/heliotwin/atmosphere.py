"""Atmospheric attenuation between a heliostat and the receiver.

The reflected beam loses light to scattering and absorption on its way up to the receiver. heliotwin uses
the polynomial model of DELSOL3 and SolarPILOT: the transmitted fraction over a slant range ``s`` [km] is

    ``attenuation(s) = 1 - (c0 + c1 s + c2 s^2 + c3 s^3)``

with SolarPILOT's default (clear-day, "Barstow") coefficients ``c = (0.006789, 0.1046, -0.0107, 0.002845)``
(Kistler, "A user's manual for DELSOL3", SAND86-8018, 1986; Wagner & Wendelin, Solar Energy 171 (2018)
185). The model is valid for slant ranges of a few km at most.

The settings travel in scenario files as ``/extras/atmosphere`` (``model``: str, ``coefficients``:
float64 [4]); a scenario without them uses the default coefficients.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .errors import HeliotwinError

__all__ = ["ATMOSPHERE_MODELS", "DEFAULT_COEFFICIENTS", "Atmosphere", "attenuation"]

ATMOSPHERE_MODELS = ("polynomial",)
DEFAULT_COEFFICIENTS = (0.006789, 0.1046, -0.0107, 0.002845)  #: SolarPILOT / DELSOL3 clear day, s in km


@dataclass(frozen=True)
class Atmosphere:
    """Atmospheric attenuation settings.

    Attributes
    ----------
    model : str
        ``"polynomial"`` (the only model so far).
    coefficients : tuple of float
        ``(c0, c1, c2, c3, ...)``: loss polynomial in the slant range [km] (any degree).
    """

    model: str = "polynomial"
    coefficients: tuple = DEFAULT_COEFFICIENTS

    def to_extras(self) -> dict:
        """``{"atmosphere": {...}}`` for :func:`heliotwin.io.scenario.save_scenario`'s ``extras``."""
        return {"atmosphere": {"model": self.model, "coefficients": np.asarray(self.coefficients, dtype=np.float64)}}

    @classmethod
    def from_extras(cls, extras: dict | None) -> "Atmosphere":
        """The settings stored by :meth:`to_extras`; the default when a scenario has none."""
        entry = (extras or {}).get("atmosphere")
        if not entry:
            return cls()
        coefficients = tuple(float(c) for c in np.asarray(entry["coefficients"]).reshape(-1))
        return cls(str(entry.get("model", "polynomial")), coefficients)


def attenuation(slant_range: torch.Tensor, atmosphere: Atmosphere | None = None) -> torch.Tensor:
    """Transmitted fraction of the reflected beam over a slant range.

    Parameters
    ----------
    slant_range : torch.Tensor, shape (...)
        Heliostat -> aim point distance [m].
    atmosphere : Atmosphere, optional
        Default: SolarPILOT's default coefficients.

    Returns
    -------
    torch.Tensor, shape (...)
        ``1 - sum_k c_k s^k`` with ``s`` in km [-]; differentiable in ``slant_range``.
    """
    atm = atmosphere or Atmosphere()
    if atm.model not in ATMOSPHERE_MODELS:
        raise HeliotwinError(f"unknown atmosphere model {atm.model!r}; expected one of {', '.join(ATMOSPHERE_MODELS)}")
    s = slant_range / 1000.0
    loss = torch.zeros_like(s)
    for c in reversed(atm.coefficients):  # Horner
        loss = loss * s + float(c)
    return 1.0 - loss
