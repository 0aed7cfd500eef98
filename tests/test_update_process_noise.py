"""The update's random walk chosen on the plant's own records when the calibration has no drift model: small
for a plant whose offsets barely walk, large for one whose offsets walk fast, stored with the calibration and
read back (not chosen again) by later updates."""
from __future__ import annotations

import math

import pytest
import torch
from helpers.calibrate import F64, TRUE, jueliche_like, plant_of, simulate

from heliotwin.calibrate import priors
from heliotwin.calibrate import twinstate as twinstate_module
from heliotwin.calibrate.assimilate import FilterState, choose_process_noise
from heliotwin.calibrate.methods.lm import laplace
from heliotwin.calibrate.model import Calibrated
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.scenario import calibrated_scenario
from heliotwin.io.records import RecordTable
from heliotwin.io.scenario import load_scenario, write_scenario
from heliotwin.workflows import update as update_module
from heliotwin.workflows.update import CHOICE_KEY, update

DAY = 86400.0
TRUTH = torch.tensor([TRUE[n] for n in STONE8], dtype=F64)
NOISE = 1.5e-4  # the simulated plant's centroid noise [rad]
EVERY = 10.0  # days between a heliostat's records


def _walked(h: int, n: int, q_mrad2_per_day: float, seed: int, id0: int = 0, start: float = 1.6e9):
    """``n`` records per heliostat ``EVERY`` days apart whose axis offsets walk with ``q`` [mrad^2/day] from
    the known deviations; the records and the kinematics."""
    kin = jueliche_like(h)
    g = torch.Generator().manual_seed(seed)
    walk = (torch.randn(h, n, 2, generator=g, dtype=F64) * math.sqrt(1e-6 * q_mrad2_per_day * EVERY)).cumsum(1)
    dev = TRUTH.expand(h, n, 8).clone()
    dev[..., :2] += walk
    hidx = torch.arange(h).repeat_interleave(n)
    recs = simulate(apply_deviations(kin.index(hidx), dev.reshape(h * n, 8), STONE8), 1, seed=seed + 1, noise=NOISE)
    recs.heliostat_index = hidx
    recs.heliostat_ids = [f"S{i}" for i in range(h)]
    recs.record_id = id0 + torch.arange(h * n)
    recs.time = start + (torch.arange(h * n) % n).to(F64) * EVERY * DAY
    return recs, kin


def _posterior(kin, recs):
    prec = torch.diag(1.0 / priors.sigma_vector(STONE8, priors.STONE8_SIGMA) ** 2)
    return laplace(kin, recs, TRUTH.expand(kin.num_heliostats, 8).clone(), prec)


@pytest.mark.parametrize("q_true, low, high", [(0.0003, 0.0, 0.00464), (0.1, 0.0215, 0.1)])
def test_the_chosen_walk_follows_the_plants_own_walk(q_true, low, high):
    h, n = 20, 70
    recs, kin = _walked(h, n, q_true, seed=3)
    post = _posterior(kin, recs)
    state = FilterState(mean=TRUTH.expand(h, 8).clone(), covariance=post["covariance"],
                        time=torch.full((h,), float("nan"), dtype=F64), noise=torch.full((h,), NOISE, dtype=F64),
                        process_noise=0.0, drift_columns=(0, 1), names=STONE8)
    choice = choose_process_noise(kin, recs, state)
    assert low <= choice["process_noise_mrad2_per_day"] <= high, choice
    assert choice["validation_heliostats"] == h and choice["validation_records"] == h * round(0.25 * n)
    # the score is the prediction error of the latest records: the noise when the walk is slow, the walk's
    # growth between records (1 mrad per component at q = 0.1 over 10 days) when it is fast
    errors = torch.tensor(choice["validation_error_mrad"])
    if q_true < 0.01:
        assert errors.min() < 1e3 * NOISE and errors[0] < errors[-1]
    else:
        assert 1.0 < errors.min() < 1.5 and errors[0] > 1.5 * errors.min()


def _plant(h: int, q_true: float):
    """A calibrated scenario without a drift model (Laplace posterior at the truth) over records whose offsets
    walk with ``q_true``, those records, and later ones of the same walk's statistics."""
    n = 60
    seen, kin = _walked(h, n, q_true, seed=3)
    ids = seen.heliostat_ids
    post = _posterior(kin, seen)
    model = Calibrated("lm", ids, kin, STONE8, TRUTH.expand(h, 8).clone(), torch.ones(h, dtype=torch.bool),
                       extras={"posterior": dict(post, walk_scale=1.0)})
    by_id = {ids[j]: seen.record_id[seen.heliostat_index == j].tolist() for j in range(h)}
    sc = calibrated_scenario(plant_of(kin, ids), model, records=by_id, source="synthetic")
    new, _ = _walked(h, 4, q_true, seed=11, id0=10 ** 6, start=1.6e9 + n * EVERY * DAY)
    return sc, seen, new


def test_the_first_update_chooses_the_walk_stores_it_and_later_updates_read_it(tmp_path, monkeypatch):
    sc, seen, new = _plant(8, 0.0003)
    assert not sc.learned["calibration"].get("drift")
    first, report = update(sc, RecordTable.concatenate([seen, new]))
    noise = report["process_noise"]
    assert noise["source"].startswith("chosen now") and report["process_noise_mrad2_per_day"] == noise["mrad2_per_day"]
    assert noise["mrad2_per_day"] <= 0.00464 and len(noise["validation_error_mrad"]) == len(noise["grid_mrad2_per_day"])
    stored = first.learned["calibration"][CHOICE_KEY]
    back = load_scenario(write_scenario(first, tmp_path / "u1.h5"))
    again = back.learned["calibration"][CHOICE_KEY]
    for k in ("process_noise_mrad2_per_day", "grid_mrad2_per_day", "validation_error_mrad"):
        torch.testing.assert_close(torch.as_tensor(again[k], dtype=F64), torch.as_tensor(stored[k], dtype=F64))
    assert again["method"] == stored["method"] and "latest" in again["method"]

    def refuse(*args, **kwargs):
        raise AssertionError("the stored choice must be read, not made again")

    monkeypatch.setattr(twinstate_module, "choose_process_noise", refuse)
    later, _ = _walked(8, 2, 0.0003, seed=12, id0=2 * 10 ** 6, start=1.6e9 + 70 * EVERY * DAY)
    second, rep2 = update(back, later)  # the new records only: nothing to choose on, the stored choice stands
    assert rep2["process_noise"]["source"].startswith("stored choice") and rep2["counts"]["new"] == len(later)
    assert rep2["process_noise"]["mrad2_per_day"] == pytest.approx(noise["mrad2_per_day"])


def test_a_fast_walking_plant_gets_a_fast_walk_and_a_given_q_still_wins():
    sc, seen, new = _plant(8, 0.1)
    _, report = update(sc, RecordTable.concatenate([seen, new]))
    assert report["process_noise"]["mrad2_per_day"] >= 0.0215
    _, given = update(sc, RecordTable.concatenate([seen, new]), update_module.UpdateSettings(process_noise=0.002))
    assert given["process_noise"] == {"mrad2_per_day": pytest.approx(0.002), "source": "given"}


def test_without_seen_records_the_default_stands_and_the_calibration_can_store_the_choice():
    sc, seen, new = _plant(8, 0.0003)
    _, report = update(sc, new)
    assert report["process_noise"]["source"].startswith("default")
    assert report["process_noise"]["mrad2_per_day"] == update_module.DEFAULT_PROCESS_NOISE
    # calibrate stores the choice where the records it saw are at hand: an update of new records reads it
    chosen, made = update_module.with_process_noise_choice(sc, seen)
    _, report = update(chosen, new)
    assert report["process_noise"]["source"].startswith("stored choice")
    assert report["process_noise"]["mrad2_per_day"] == made["process_noise_mrad2_per_day"] <= 0.00464
