"""``plan``: the next calibration records are where the posterior is least sure (greedy I-optimal design)."""
import json
import math

import numpy as np
import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate
from PIL import Image

from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.protocol.plan import greedy_design, plan

F64 = torch.float64


def test_greedy_first_choice_is_the_brute_force_best():
    g = torch.Generator().manual_seed(0)
    cand = torch.randn(40, 3, 4, generator=g, dtype=F64)
    ref = torch.randn(100, 3, 4, generator=g, dtype=F64)
    prec = torch.diag(torch.tensor([1.0, 10.0, 100.0, 0.1], dtype=F64))
    chosen, rms = greedy_design(prec, 0.5, cand, ref, 3)
    m = torch.einsum("tci,tcj->ij", ref, ref) / 100
    brute = [torch.trace(torch.linalg.inv(prec + c.T @ c / 0.25) @ m).item() for c in cand]
    assert chosen[0] == min(range(40), key=brute.__getitem__)
    assert math.isclose(rms[1], math.sqrt(min(brute)), rel_tol=1e-9)
    assert rms[0] > rms[1] > rms[2] > rms[3] and len(set(chosen)) == 3


def test_plan_proposes_sun_positions_away_from_the_training_sky(tmp_path):
    """Trained on morning-only (east) sun positions, the heliostat is least sure about the afternoon: the
    first proposals lie in the west, and each record lowers the predictive spread."""
    kin = jueliche_like(1)
    true = apply_deviations(kin, torch.tensor([[TRUE[n] for n in STONE8]], dtype=F64), STONE8)
    recs = simulate(true, 60, 1, noise=3e-4)
    east = recs.subset(recs.sun_azimuth > 0.6)  # PAINT azimuth: + = east
    model = fit_lm_method(kin, east, None, bags=0, field_prior=False, fit_focal_spot=None)
    sc = scenario_round_trip(tmp_path, kin, model)
    ans = plan(sc, "S0", year=2023, every="2h", count=3, sky=True)
    assert ans["candidates"] > 100
    rms = [ans["spread_now_mrad"]] + [p["spread_after_mrad"] for p in ans["proposals"]]
    assert all(a > b for a, b in zip(rms, rms[1:])) and rms[-1] < 0.8 * rms[0], rms
    assert ans["proposals"][0]["sun_azimuth_deg"] < 0, ans["proposals"]  # west
    # The sky map's error per candidate: its mean square over the year's sun positions every 2 h is the
    # spread (the same year's, sampled every 25 h), and the unseen west is the least sure part of the sky.
    sky = ans["sky"]
    assert len(sky["std_now_mrad"]) == ans["candidates"]
    assert math.isclose(float((sky["std_now_mrad"] ** 2).mean()), ans["spread_now_mrad"] ** 2, rel_tol=0.1), (
        float((sky["std_now_mrad"] ** 2).mean()), ans["spread_now_mrad"] ** 2)
    west, east = sky["sun_azimuth_deg"] < -30, sky["sun_azimuth_deg"] > 30
    assert np.median(sky["std_now_mrad"][west]) > 2 * np.median(sky["std_now_mrad"][east])


def test_plan_command(tmp_path, capsys):
    from heliotwin.cli import main

    kin = jueliche_like(1)
    true = apply_deviations(kin, torch.tensor([[TRUE[n] for n in STONE8]], dtype=F64), STONE8)
    model = fit_lm_method(kin, simulate(true, 12, 2, noise=3e-4), None, bags=0, field_prior=False,
                          fit_focal_spot=None)
    scenario_round_trip(tmp_path, kin, model)
    js = tmp_path / "plan.json"
    argv = ["plan", "--scenario", str(tmp_path / "calibrated.h5"), "--heliostat", "S0", "--year", "2023",
            "--every", "3h", "--count", "2", "--json", str(js)]
    assert main(argv) == 0
    report = json.loads(js.read_text())
    assert len(report["proposals"]) == 2 and "predicted pointing spread on 2023-01-01" in capsys.readouterr().out
    assert report["plots"] == ["plan-plan.png"] and "sky" not in report
    with Image.open(tmp_path / "plan-plan.png") as im:
        assert im.size[0] > 400
    (tmp_path / "plan-plan.png").unlink()
    assert main(argv + ["--no-plots"]) == 0
    assert not (tmp_path / "plan-plan.png").exists() and "plots" not in json.loads(js.read_text())
    assert main(argv[:4] + ["ZZ9", "--year", "2023"]) == 2
    assert "not calibrated" in capsys.readouterr().err
