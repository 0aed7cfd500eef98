"""Calibrated models: what every method returns, and how a model is evaluated on records.

A method returns a :class:`Calibrated` model over the H heliostats of a run. Rigid-body methods (``lm``,
``gradient``) are fully described by deviations ``delta`` [H, P] added to the nominal kinematics; the
hybrid adds a network per heliostat, the MLP replaces the model by a network that outputs motor steps.
Every model answers :meth:`Calibrated.pointing_error` on a :class:`RecordTable`, so the report treats all
methods alike.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..field.plant import Kinematics
from ..io.records import RecordTable
from . import metrics
from .params import apply_deviations


@dataclass
class Calibrated:
    """A calibrated rigid body (deviations from nominal) for H heliostats.

    Attributes
    ----------
    method : str
    heliostat_ids : list of str, length H
    nominal : Kinematics
        H heliostats (after any correction of suspicious property values, see ``corrections``).
    names : tuple of str, length P
        Deviation parameters (see :mod:`heliotwin.calibrate.params`).
    delta : torch.Tensor, [H, P]
        Learned deviations (rad, m, relative for increments).
    ok : torch.Tensor, [H], bool
        False for heliostats that were not calibrated (then ``delta`` is zero and ``reasons`` says why).
    reasons : dict of str -> str
    corrections : dict of str -> dict
        Property values replaced before fitting (suspicious entries), per heliostat.
    extras : dict
        Method-specific state (e.g. networks).
    """

    method: str
    heliostat_ids: list
    nominal: Kinematics
    names: tuple
    delta: torch.Tensor
    ok: torch.Tensor
    reasons: dict = field(default_factory=dict)
    corrections: dict = field(default_factory=dict)
    extras: dict = field(default_factory=dict)

    @property
    def kinematics(self) -> Kinematics:
        """The calibrated static kinematics, H heliostats."""
        return apply_deviations(self.nominal, self.delta.detach(), self.names)

    def normals(self, batch: RecordTable) -> tuple[torch.Tensor, torch.Tensor]:
        """Model mirror normal [R, 3] and concentrator [R, 3] at the records' motor steps."""
        return metrics.model_normals(self.kinematics, batch)

    def pointing_error(self, batch: RecordTable) -> torch.Tensor:
        """Pointing error per record [rad], [R]."""
        with torch.no_grad():
            return metrics.pointing_error_of_normals(*self.normals(batch), batch)

    def miss_distance(self, batch: RecordTable) -> torch.Tensor:
        """Miss distance on the target plane per record [m], [R]."""
        with torch.no_grad():
            return metrics.miss_distance_of_normals(*self.normals(batch), batch)


def nominal_model(heliostat_ids, kin: Kinematics) -> Calibrated:
    """The uncalibrated model (zero deviations) in the same interface."""
    h, like = kin.num_heliostats, kin.position
    return Calibrated("nominal", list(heliostat_ids), kin, (), like.new_zeros(h, 0),
                      torch.ones(h, dtype=torch.bool, device=like.device))
