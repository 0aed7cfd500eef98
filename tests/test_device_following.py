"""The field model and the aim-point optimiser follow the device of their inputs, checked on the CPU.

A GPU run fails at the first operation that combines a tensor made without ``device=`` with the plant's
tensors; CI has no GPU, so :class:`helpers.device_audit.DeviceAudit` marks such tensors and records where they
meet the plant's (see its docstring). ``--confidence`` once built its posterior on the host this way."""
import pandas as pd
import pytest
import torch
from helpers.device_audit import DeviceAudit, mark_host
from helpers.field import learned_posterior

from heliotwin.io.scenario import Scenario
from heliotwin.optimise.testbed import generated_plant
from heliotwin.raytrace.field import field_optics
from heliotwin.sun import direction_from_time
from heliotwin.workflows.aimpoints import AimpointSettings, aimpoints

TIME = "2024-06-21T11:00:00Z"


def _sun(plant):
    s = plant.site
    return direction_from_time(pd.DatetimeIndex([pd.Timestamp(TIME)]), s.latitude_deg, s.longitude_deg,
                               s.altitude_m)[0]


def _ignores_device(x):
    return x * torch.linspace(0.0, 1.0, x.shape[-1], dtype=x.dtype)  # made on the default device


def _follows_device(x):
    scale = torch.linspace(0.0, 1.0, x.shape[-1], dtype=x.dtype, device=x.device)
    host = torch.arange(3).tolist()  # host values that never meet x are fine
    return x[torch.tensor([0])] * scale * len(host)


def test_the_audit_finds_a_tensor_made_without_the_inputs_device():
    x = torch.ones(4, 3)
    with DeviceAudit(scope=__file__) as audit:
        _follows_device(x)
        torch.ones(3).to(x.device) + x  # moved: fine
    assert not audit.hits, audit.report()
    with DeviceAudit(scope=__file__) as audit:
        _ignores_device(x)
        x.cpu() * x  # host copy mixed back in
    assert len(audit.hits) == 2 and "linspace" in audit.report() and "host" in audit.report(), audit.report()


@pytest.mark.parametrize("receiver", ["cylinder", "tilted-cylinder", "flat"])
def test_the_field_model_follows_the_plants_device(receiver):
    plant, atm = generated_plant("radial", 40, receiver, tower=40.0)
    sun = _sun(plant)
    with DeviceAudit() as audit:
        r = field_optics(plant, sun, atmosphere=atm)
    assert float(r.flux.max()) > 0
    assert not audit.hits, audit.report()


def test_aim_points_with_confidence_follow_the_plants_device():
    """The whole workflow with baselines and ``--confidence`` (posterior, draws, exceedance); the learned state
    stays on the host as in a run with ``device="cuda"``."""
    plant, atm = generated_plant("radial", 20, "cylinder", tower=30.0)
    sun = _sun(plant)
    learned = learned_posterior(plant)
    mark_host(learned)
    scenario = Scenario(plant=plant, learned=learned, extras={})
    limit = 0.8 * float(field_optics(plant, sun, atmosphere=atm).flux.max())
    with DeviceAudit() as audit:
        _, report = aimpoints(scenario, [("t", sun)], AimpointSettings(limit, confidence=0.9, draws=20))
    assert report["optimised"]["limit_met"]
    assert not audit.hits, audit.report()
