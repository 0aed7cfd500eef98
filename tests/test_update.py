"""``heliotwin update``: new records assimilated as a posterior update (Kalman), step alarms, seen records
skipped, the state and its history in the scenario, and the command line's refusals."""
from __future__ import annotations

import inspect
import math
from types import SimpleNamespace

import pytest
import torch
from helpers.calibrate import F64, TRUE, jueliche_like, simulate
from helpers.cli import assert_one_line_error, run_cli
from helpers.learned import calibrated_scenario_of

from heliotwin.calibrate import priors
from heliotwin.calibrate.assimilate import (
    FALSE_ALARM_RATE,
    FALSE_ALARMS_PER_HELIOSTAT_YEAR,
    AssimilationOptions,
    FilterState,
    alarm_threshold,
    assimilate,
    false_alarm_rate_for,
    kalman_update,
    leave_one_out_d2,
)
from heliotwin.calibrate.methods.lm import laplace
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.scenario import aim, calibrated_scenario
from heliotwin.calibrate.twinstate import records_per_heliostat_year
from heliotwin.io.records import RecordTable
from heliotwin.io.scenario import load_scenario, write_scenario
from heliotwin.workflows.update import UpdateSettings, state_history, update

DAY = 86400.0
TRUTH = torch.tensor([TRUE[n] for n in STONE8], dtype=F64)


def test_kalman_updates_one_by_one_equal_the_batch_posterior():
    """Linear-Gaussian: assimilating n records one at a time gives the least-squares posterior of all n."""
    g = torch.Generator().manual_seed(0)
    b, p, n, s = 3, 8, 12, 0.3
    a = torch.randn(b, p, p, generator=g, dtype=F64)
    p0 = a @ a.transpose(1, 2) + 0.5 * torch.eye(p, dtype=F64)
    m0 = torch.randn(b, p, generator=g, dtype=F64)
    hs = torch.randn(n, b, 2, p, generator=g, dtype=F64)
    ys = torch.randn(n, b, 2, generator=g, dtype=F64)
    m, cov = m0.clone(), p0.clone()
    for h, y in zip(hs, ys):
        m, cov, _ = kalman_update(m, cov, y - torch.einsum("bkp,bp->bk", h, m), h, torch.full((b,), s * s, dtype=F64))
    prec = torch.linalg.inv(p0) + torch.einsum("nbkp,nbkq->bpq", hs, hs) / s ** 2
    rhs = torch.einsum("bpq,bq->bp", torch.linalg.inv(p0), m0) + torch.einsum("nbkp,nbk->bp", hs, ys) / s ** 2
    batch_cov = torch.linalg.inv(prec)
    torch.testing.assert_close(cov, batch_cov, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(m, torch.einsum("bpq,bq->bp", batch_cov, rhs), rtol=1e-9, atol=1e-12)


def test_the_chi_square_threshold_and_its_validation_scale():
    t = alarm_threshold(1e-3)
    assert t["threshold"] == pytest.approx(-2 * math.log(1e-3)) and t["kappa"] == 1.0
    g = torch.Generator().manual_seed(1)
    chi2 = (torch.randn(4000, 2, generator=g, dtype=F64) ** 2).sum(-1)
    assert alarm_threshold(1e-3, chi2)["kappa"] == pytest.approx(1.0, abs=0.08)  # Gaussian residuals: chi-square
    wide = alarm_threshold(1e-3, 4.0 * chi2)  # residuals twice as wide: a threshold four times higher
    assert wide["kappa"] == pytest.approx(4.0, rel=0.08)


def test_the_default_rate_spends_a_budget_per_heliostat_year_at_the_plants_record_rate():
    """A plant that records daily gets a ten times smaller per-record rate than one recording every ten days:
    the same false alarms per heliostat-year (the operator's budget), not ten times more."""
    def table(every_days: float, years: float = 2.0, heliostats: int = 5):
        n = int(years * 365.25 / every_days)
        t = 1.6e9 + torch.arange(n, dtype=F64).repeat(heliostats) * every_days * DAY
        t[3] = float("nan")  # an untimed record does not count
        return SimpleNamespace(time=t, heliostat_index=torch.arange(heliostats).repeat_interleave(n))

    rates = {}
    for every in (1.0, 10.0):
        per_year = records_per_heliostat_year(table(every))
        assert per_year == pytest.approx(365.25 / every, rel=0.02)
        rates[every] = false_alarm_rate_for(per_year)
        assert rates[every] * per_year == pytest.approx(FALSE_ALARMS_PER_HELIOSTAT_YEAR, rel=1e-9)
    assert rates[10.0] == pytest.approx(10 * rates[1.0], rel=0.02)
    assert false_alarm_rate_for(float("nan")) == FALSE_ALARM_RATE  # unknown record rate: the per-record default
    assert false_alarm_rate_for(0.5) == 1e-2  # within FALSE_ALARM_RATE_RANGE


def _calibrated(h: int, n_train: int = 30, noise: float = 5e-4, seed: int = 0):
    """Heliostats with known deviations, the Laplace posterior of ``n_train`` records (a week apart) around
    the truth, and those records (ids 0..; times before 1.6e9 s)."""
    kin = jueliche_like(h)
    truth = TRUTH.expand(h, 8).clone()
    true_kin = apply_deviations(kin, truth, STONE8)
    train = simulate(true_kin, n_train, seed=seed, noise=noise)
    train.time = 1.6e9 - (n_train - torch.arange(len(train), dtype=F64) % n_train) * 7 * DAY
    prec = torch.diag(1.0 / priors.sigma_vector(STONE8, priors.STONE8_SIGMA) ** 2)
    post = laplace(kin, train, truth, prec)
    return kin, truth, train, post


def _stream(kin, truth, h: int, n: int, noise: float, seed: int, step=None):
    """``n`` records per heliostat a day apart after 1.6e9 s (ids from 10**6), deviations ``truth`` plus
    ``step`` = (heliostat, first record, [2] rad) on the axis offsets."""
    dev = truth.repeat_interleave(n, 0).clone()
    if step is not None:
        j, k0, jump = step
        rows = torch.arange(j * n + k0, (j + 1) * n)
        dev[rows, :2] += torch.as_tensor(jump, dtype=F64)
    recs = []
    for j in range(h):  # a few heliostats: each simulated with its own deviations per record
        for k in range(n):
            r = simulate(apply_deviations(kin.index([j]), dev[j * n + k][None], STONE8), 1, seed=seed + 1000 * j + k,
                         noise=noise)
            r.heliostat_index[:] = j
            recs.append(r)
    out = RecordTable.concatenate(recs)
    out.heliostat_ids = [f"S{i}" for i in range(h)]
    out.record_id = 10 ** 6 + torch.arange(len(out))
    out.time = 1.6e9 + (1 + torch.arange(len(out), dtype=F64) % n) * DAY
    return out


def _state(kin, truth, post, time=1.6e9):
    h = kin.num_heliostats
    return FilterState(mean=truth.clone(), covariance=post["covariance"], time=torch.full((h,), time, dtype=F64),
                       noise=post["noise_rad"], process_noise=1e-9, drift_columns=(0, 1), names=STONE8)


def test_an_injected_step_raises_an_alarm_and_the_state_follows_it():
    h, n = 3, 16
    kin, truth, train, post = _calibrated(h)
    state = _state(kin, truth, post)
    threshold = alarm_threshold(1e-3, leave_one_out_d2(kin, train, state))["threshold"]
    stream = _stream(kin, truth, h, n, 5e-4, seed=7, step=(1, 6, [6e-3, -3e-3]))
    new, hist = assimilate(kin, stream, state, AssimilationOptions(threshold=threshold))
    k = (hist["record_id"] - 10 ** 6) % n
    alarms = [(int(j), int(kk)) for j, kk in zip(hist["heliostat"][hist["alarm"]], k[hist["alarm"]])]
    assert (1, 6) in alarms  # the step's first record
    assert all(j == 1 and kk in (6, 7) for j, kk in alarms)  # nowhere else
    after = (hist["heliostat"] == 1) & (k >= 8)
    assert float(hist["predicted_error"][after].max()) < 2.5e-3  # followed: back to the noise within 2 records
    clean = hist["heliostat"] != 1
    followed = float(hist["predicted_error"][after].mean())
    assert followed < 2.0 * float(hist["predicted_error"][clean].mean())
    # without the alarm the jump is averaged away slowly: the same records are predicted far worse
    _, quiet = assimilate(kin, stream, state, AssimilationOptions(threshold=float("inf")))
    assert not bool(quiet["alarm"].any()) and float(quiet["predicted_error"][after].mean()) > 2.5 * followed
    # the axis offsets took the step (the rest of it went into correlated deviations of the same pointing)
    moved = new.mean[1, :2] - truth[1, :2]
    assert float(torch.dot(moved, torch.tensor([6e-3, -3e-3], dtype=F64))) / 45e-6 > 0.8
    torch.testing.assert_close(new.mean[0], truth[0], atol=1.5e-3, rtol=0)


def test_a_step_no_single_record_shows_is_found_by_the_records_together():
    """A 1.8 mrad step at 0.5 mrad noise: no record is beyond the threshold alone, two in a row are."""
    h, n = 3, 16
    kin, truth, train, post = _calibrated(h)
    state = _state(kin, truth, post)
    threshold = alarm_threshold(1e-3, leave_one_out_d2(kin, train, state), tests=3)["threshold"]
    stream = _stream(kin, truth, h, n, 5e-4, seed=7, step=(1, 6, [1.5e-3, -1e-3]))
    _, hist = assimilate(kin, stream, state, AssimilationOptions(threshold=threshold, window=3))
    k = (hist["record_id"] - 10 ** 6) % n
    assert hist["alarm"].sum() == 1
    i = int(hist["alarm"].nonzero()[0, 0])
    assert int(hist["heliostat"][i]) == 1 and int(k[i]) == 7 and int(hist["window"][i]) >= 2
    assert bool((hist["d2"][(hist["heliostat"] == 1) & (k >= 6) & (k <= 7)] < threshold).all())


def test_no_alarm_on_clean_records_at_the_chosen_threshold():
    h, n = 4, 40
    kin, truth, train, post = _calibrated(h, seed=3)
    state = _state(kin, truth, post)
    threshold = alarm_threshold(1e-3, leave_one_out_d2(kin, train, state))["threshold"]
    stream = _stream(kin, truth, h, n, 5e-4, seed=11)
    _, hist = assimilate(kin, stream, state, AssimilationOptions(threshold=threshold))
    assert len(hist["d2"]) == h * n
    assert int(hist["alarm"].sum()) == 0  # 160 clean records at a 1e-3 false-alarm rate (seeded)
    # the normalised innovations are what the model says: mean of chi-square(2) = 2
    assert 1.3 < float(hist["d2"].mean()) < 3.0


def _scenario(h=2):
    kin, truth, train, post = _calibrated(h)
    sc, _ = calibrated_scenario_of(kin, truth, train, post)
    return sc, kin, truth, train


def test_update_round_trips_state_and_history_and_never_reassimilates(tmp_path):
    sc, kin, truth, train = _scenario()
    stream = _stream(kin, truth, 2, 5, 5e-4, seed=5)
    table = RecordTable.concatenate([train, stream])
    first, report = update(sc, table)
    assert report["counts"]["seen"] == len(train) and report["counts"]["new"] == len(stream)
    assert report["overall"]["records"] == len(stream) and report["threshold"]["validation_records"] == len(train)
    path = write_scenario(first, tmp_path / "u1.h5")
    back = load_scenario(path)
    cal = back.learned["calibration"]
    torch.testing.assert_close(torch.as_tensor(cal["deviations"]), torch.as_tensor(first.learned["calibration"]
                                                                                   ["deviations"]))
    # the plant's kinematics are the updated state, so every reader aims with it
    torch.testing.assert_close(back.plant.field.kinematics.initial_angle,
                               apply_deviations(kin, torch.as_tensor(cal["deviations"]), STONE8).initial_angle)
    hist = state_history(path, "S1")
    assert len(hist["time"]) == 5 and list(hist["record_id"]) == sorted(stream.record_id[stream.heliostat_index == 1]
                                                                        .tolist())
    assert hist["mean"].shape == (5, 8) and (hist["variance"] > 0).all() and (hist["update"] == 1).all()
    # a second update over the same folder: nothing new; the history is unchanged, one more provenance step
    second, rep2 = update(back, table)
    assert rep2["counts"]["new"] == 0 and rep2["counts"]["seen"] == len(table)
    assert len(state_history(second, "S1")["time"]) == 5
    assert [p["step"] for p in second.provenance] == ["calibrate", "update", "update"]
    torch.testing.assert_close(torch.as_tensor(second.learned["calibration"]["deviations"]),
                               torch.as_tensor(cal["deviations"]))
    assert tuple(torch.as_tensor(back.learned["assimilation"]["window"]["g"]).shape) == (2, 2, 2)
    assert rep2["threshold"]["stored"]
    # a new calibration restarts the update's threshold and step evidence (the history stays)
    from heliotwin.io.scenario import next_scenario, provenance_entry

    recal = next_scenario(back, back.plant, learned=dict(back.learned), step=provenance_entry("calibrate", records={}))
    third, rep3 = update(recal, table)
    assert not rep3["threshold"]["stored"] and len(state_history(third, "S1")["time"]) == 5
    # aim reads the updated posterior (the walk grows from the state's time)
    ans = aim(back, "S0", 0.3, 0.6, [0.0, -3.24, 40.0], time=1.6e9 + 30 * DAY)
    assert 0 < ans["expected_error_mrad"] < 5 and ans["drift_days"] == pytest.approx(25.0, abs=1.0)


def test_history_is_stored_compact_and_reads_back_exactly(tmp_path, monkeypatch):
    """The history on disk: int32 counters, float32 state, compressed when large (here: every array, as a
    plant-year's history is); ``state_history`` reads back exactly what it reads from the scenario in memory."""
    import h5py
    import numpy as np

    import heliotwin.io.scenario as scenario_io

    sc, kin, truth, train = _scenario()
    stream = _stream(kin, truth, 2, 6, 5e-4, seed=7)
    first = update(sc, RecordTable.concatenate([train, stream]))
    monkeypatch.setattr(scenario_io, "COMPRESS_BYTES", 1)
    path = write_scenario(first.scenario, tmp_path / "u.h5")
    for hid, h in (("S0", 0), ("S1", 1)):
        mem, disk = state_history(first.scenario, hid), state_history(path, hid)
        assert mem["parameter_names"] == disk["parameter_names"] and set(mem) == set(disk)
        for k in mem:
            if isinstance(mem[k], np.ndarray):
                assert mem[k].dtype == disk[k].dtype and np.array_equal(mem[k], disk[k]), k
        assert disk["window"].dtype == np.int64 and disk["update"].dtype == np.int64
        # the stored state is this update's to float32 rounding
        mine = first.history["heliostat"] == h
        order = torch.argsort(first.history["time"][mine], stable=True)
        np.testing.assert_allclose(disk["mean"], first.history["mean"][mine][order].numpy(), rtol=1e-6, atol=1e-12)
    with h5py.File(path, "r") as h5:
        g = h5["learned/assimilation/history"]
        assert g["mean"].compression == "gzip" and g["mean"].dtype == np.float32
        assert g["heliostat"].dtype == np.int32 and g["update"].dtype == np.int32 and g["time"].dtype == np.float64
    # a later update appends to the loaded (narrow) history
    more = _stream(kin, truth, 2, 3, 5e-4, seed=8)
    more.record_id += 10 ** 5
    more.time += 30 * DAY
    second, _ = update(load_scenario(path), RecordTable.concatenate([train, stream, more]))
    assert len(state_history(second, "S1")["time"]) == 9
    assert list(state_history(second, "S1")["update"]) == [1] * 6 + [2] * 3


def test_update_refuses_a_scenario_without_a_posterior(tmp_path):
    sc, kin, truth, train = _scenario()
    nominal = sc.__class__(plant=sc.plant, extras={}, metadata={}, learned={}, provenance=[])
    with pytest.raises(Exception, match="no calibration to update"):
        update(nominal, train)
    with pytest.raises(Exception, match="false-alarm-rate"):
        update(sc, train, UpdateSettings(false_alarm_rate=0.0))
    with pytest.raises(Exception, match="process-noise"):
        update(sc, train, UpdateSettings(process_noise="lots"))


def test_update_settings_are_the_cli_defaults():
    from heliotwin.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices["update"]
    cli = {a.dest: a.default for a in sub._actions if a.option_strings}
    checked = 0
    for name, p in inspect.signature(UpdateSettings).parameters.items():
        if name in cli:
            assert p.default == cli[name], name
            checked += 1
    assert checked >= 5


def test_cli_refuses_bad_input_with_one_line(tmp_path, capsys):
    sc, *_ = _scenario()
    path = write_scenario(sc, tmp_path / "cal.h5")
    paint = tmp_path / "paint"
    paint.mkdir()
    code, _, err = run_cli(capsys, "update", "--scenario", path, "--paint", paint, "-o", path)
    assert_one_line_error(code, err, "cal.h5", "-o")
    code, _, err = run_cli(capsys, "update", "--scenario", tmp_path / "missing.h5", "--paint", paint, "-o",
                           tmp_path / "out.h5")
    assert_one_line_error(code, err, "missing.h5")
    with pytest.raises(SystemExit) as exc:
        run_cli(capsys, "update", "--scenario", path, "--paint", paint, "-o", tmp_path / "out.h5",
                "--false-alarm-rate", "2")
    assert exc.value.code == 2
    assert_one_line_error(2, capsys.readouterr().err, "--false-alarm-rate")
    code, _, err = run_cli(capsys, "update", "--scenario", path, "--paint", tmp_path / "nope", "-o",
                           tmp_path / "out.h5")
    assert_one_line_error(code, err, "nope")
    assert not (tmp_path / "out.h5").exists()
    code, _, err = run_cli(capsys, "history", "--scenario", path, "--heliostat", "S0")
    assert_one_line_error(code, err, "cal.h5", "/learned/assimilation")


def test_real_records_are_predicted_before_they_are_assimilated(paint_dir):
    """AK46's later PAINT records, each predicted by the state before it, after an lm fit on its earliest 20."""
    from heliotwin.calibrate.methods.lm import fit_lm_method
    from heliotwin.io.scenario import load_records

    ds, _ = load_records(paint_dir, None, ["AK46"])
    recs = ds.records
    order = torch.argsort(recs.time)
    train = recs.subset(order[:20])
    model = fit_lm_method(ds.plant.field.kinematics, train, None, bags=0)
    sc = calibrated_scenario(ds.plant, model, records={"AK46": train.record_id.tolist()}, source=str(paint_dir))
    new, report = update(sc, ds)
    assert report["counts"]["seen"] == 20 and report["overall"]["records"] == report["counts"]["new"] >= 25
    # as well as a chrono calibration predicts later records of this heliostat (~1.3 mrad), and no worse
    # than the fit without updates predicts them
    mine = report["overall"]["median_of_mean_predicted_error_mrad"]
    later = recs.subset(order[20:])
    static = 1e3 * float(model.pointing_error(later).mean())
    assert mine < 2.0 and mine < static + 0.05
    assert update(new, ds).report["counts"]["new"] == 0


@pytest.mark.slow  # an lm calibration with bagging and two command-line runs (~45 s)
def test_calibrate_then_update_on_real_records_by_command_line(paint_dir, tmp_path, capsys):
    """PAINT records: an lm calibration on each heliostat's earliest records, then ``heliotwin update`` assimilates
    every later record (and none it saw), ``heliotwin history`` reads the state back, and a second update of
    the same folder finds nothing new."""
    import json

    from helpers.paint import copy_paint

    from heliotwin import api

    root = copy_paint(paint_dir, tmp_path, ("AK46", "BG23"), metadata=True)
    cal = tmp_path / "cal.h5"
    report, _, _ = api.calibrate(root, train=20, test=10, min_records=20, settings="given", device="cpu",
                                 progress=False, output=cal)
    code, out, err = run_cli(capsys, "update", "--scenario", cal, "--paint", root, "-o", tmp_path / "u.h5",
                             "--json", tmp_path / "u.json")
    assert code == 0, err
    rep = json.loads((tmp_path / "u.json").read_text())
    c = rep["counts"]
    assert c["seen"] == 40 and c["new"] == rep["overall"]["records"] > 40 and c["new"] + c["seen"] + c[
        "older_than_state"] + c["without_time"] == c["records"]
    # the records are predicted before they are assimilated: as well as a calibration predicts its test block
    assert rep["overall"]["median_of_mean_predicted_error_mrad"] < 2.0
    # calibrate (no drift model) chose the offsets' walk on the records it saw; the update read it
    assert rep["process_noise"]["source"].startswith("stored choice") and 0.001 <= rep["process_noise"][
        "mrad2_per_day"] <= 0.1
    assert "assimilated" in out
    code, out, err = run_cli(capsys, "history", "--scenario", tmp_path / "u.h5", "--heliostat", "BG23", "--json",
                             tmp_path / "h.json")
    assert code == 0, err
    hist = json.loads((tmp_path / "h.json").read_text())
    assert len(hist["time"]) == rep["heliostats"]["BG23"]["records"] and hist["time"] == sorted(hist["time"])
    again, scenario, _ = api.update(tmp_path / "u.h5", root)
    assert again["counts"]["new"] == 0 and [p["step"] for p in scenario.provenance][-2:] == ["update", "update"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_assimilation_on_cuda_matches_the_cpu():
    h, n = 2, 6
    kin, truth, train, post = _calibrated(h)
    state = _state(kin, truth, post)
    stream = _stream(kin, truth, h, n, 5e-4, seed=2, step=(1, 2, [6e-3, 0.0]))
    options = AssimilationOptions(threshold=16.0)
    cpu_state, cpu_hist = assimilate(kin, stream, state, options)
    from heliotwin.devices import to_device

    gpu_state, gpu_hist = assimilate(to_device(kin, "cuda"), to_device(stream, "cuda"), to_device(state, "cuda"),
                                     options)
    assert gpu_state.mean.device.type == "cuda"
    torch.testing.assert_close(gpu_state.mean.cpu(), cpu_state.mean, atol=1e-9, rtol=0)
    assert torch.equal(gpu_hist["alarm"].cpu(), cpu_hist["alarm"])
