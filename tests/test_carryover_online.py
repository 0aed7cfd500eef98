"""The online protocol: every test record predicted by a refit on the records before it, never after."""
import torch
from helpers.calibrate import TRUE, jueliche_like, simulate, with_weekly_times

from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.calibrate.protocol.online import online_errors, online_split
from heliotwin.io.records import RecordTable

F64 = torch.float64


def drifting_records(h: int = 2, chunks: int = 8, per_chunk: int = 8):
    """Records whose axis-1 encoder offset steps by 1 mrad every chunk (a drift no static fit can follow)."""
    kin = jueliche_like(h)
    parts = []
    for c in range(chunks):
        d = torch.tensor([[TRUE[n] for n in STONE8]] * h, dtype=F64)
        d[:, 0] += 1e-3 * c
        parts.append(simulate(apply_deviations(kin, d, STONE8), per_chunk, 10 + c, noise=2e-4))
    return kin, with_weekly_times(RecordTable.concatenate(parts))


def test_online_split_takes_the_window_before_the_latest_records():
    kin, batch = drifting_records()
    tr, va, te, info = online_split(batch, 10, 16)
    assert len(va) == 0 and info["S0"]["train"] == 10 and info["S0"]["test"] == 16
    for h in range(2):
        t_tr = batch.time[tr][batch.heliostat_index[tr] == h]
        t_te = batch.time[te][batch.heliostat_index[te] == h]
        assert t_tr.max() < t_te.min()
        assert int((batch.heliostat_index == h).sum()) - 16 - 10 == int(
            ((batch.heliostat_index == h) & (batch.time < t_tr.min())).sum())  # the window is just before


def test_online_refits_never_see_what_they_predict_and_follow_a_drift():
    kin, batch = drifting_records()
    _, _, te, _ = online_split(batch, 10, 16)
    seen = []

    def fit_one(train):
        seen.append([train.time[train.heliostat_index == h].max().item() for h in range(2)])
        return fit_lm_method(kin, train, None, bags=0, field_prior=False, fit_focal_spot=None)

    err, miss = online_errors(fit_one, batch, te, 10, step=4)
    assert len(seen) == 4 and bool(torch.isfinite(err).all()) and bool(torch.isfinite(miss).all())
    # the k-th refit precedes every record of the k-th block (blocks of 4 per heliostat, in time order)
    t_te = batch.time[te]
    for k, t_max in enumerate(seen):
        for h in range(2):
            assert t_max[h] < t_te[batch.heliostat_index[te] == h].sort().values[4 * k:4 * k + 4].min()
    # chrono: one fit on the earliest 10 records; the 1 mrad-per-chunk drift makes it fall behind
    first = torch.cat([batch.of(h)[:10] for h in range(2)])
    static = fit_lm_method(kin, batch.subset(first), None, bags=0, field_prior=False, fit_focal_spot=None)
    chrono = static.pointing_error(batch.subset(te))
    assert err.mean() < 0.5 * chrono.mean(), (err.mean(), chrono.mean())


def test_online_intervals_come_from_the_refit_before_each_block():
    """Correct model, Gaussian centroid noise, the online protocol: each test record's 90 % interval is the one
    of the refit that predicted it (the first block: the fit on the window before the test block), and about
    90 % of the test records fall inside their interval."""
    from heliotwin.calibrate.protocol.pipeline import (
        Evaluation,
        RunConfig,
        Split,
        online_refit,
        predict_intervals,
        record_intervals,
    )

    kin = jueliche_like(4)
    true = apply_deviations(kin, torch.tensor([[TRUE[n] for n in STONE8]] * 4, dtype=F64), STONE8)
    batch = with_weekly_times(simulate(true, 60, 11, noise=5e-4))
    options = {"bags": 0, "field_prior": False, "fit_focal_spot": None}
    cfg = RunConfig(paint="synthetic", split="online", train=20, test=40, online_step=10, method_options=options)
    tr, va, te, _ = online_split(batch, 20, 40)
    parts = Split(batch.subset(tr), batch.subset(va), batch.subset(te), te)
    run = online_refit(cfg, kin, batch, parts, None, Evaluation({}))
    run = predict_intervals(cfg, None, parts, run)  # the online intervals stay those of the refits
    iv, err = run.intervals, run.errors["test"][0]
    assert iv["upper"].shape == (len(te),) and bool(torch.isfinite(iv["upper"]).all())
    assert 0.8 <= iv["inside"].double().mean().item() <= 0.97, iv["inside"].double().mean()
    assert len(run.interval_inputs["heliostat"]) == len(te)
    # test records are in heliostat order, each heliostat's in time order: the first block is its first 10
    first = torch.cat([torch.arange(10) + 40 * h for h in range(4)])
    window = fit_lm_method(kin, batch.subset(tr), None, **options)
    pred, _ = record_intervals(window, batch.subset(te[first]), err[first], 0)
    assert torch.allclose(iv["upper"][first], pred["upper"]) and torch.equal(iv["inside"][first], pred["inside"])
    later = torch.cat([torch.arange(30, 40) + 40 * h for h in range(4)])
    stale, _ = record_intervals(window, batch.subset(te[later]), err[later], 0)
    assert not torch.allclose(iv["upper"][later], stale["upper"])  # later blocks: later refits


def test_cli_online_on_real_records(paint_dir, tmp_path, capsys):
    import json

    from helpers.cli import run_cli

    js = tmp_path / "online.json"
    code, out, err = run_cli(capsys, "calibrate", "--paint", paint_dir, "--heliostats", "BH60", "--split", "online",
                             "--train", "30", "--test", "10", "--online-step", "5", "--json", js, "--no-plots")
    assert code == 0, err
    rep = json.loads(js.read_text())
    r = rep["heliostats"]["BH60"]
    assert r["split"]["test"] == 10 and r["split"]["train"] == 30 and r["test"]["n"] == 10
    assert r["mean_test_mrad"] < 2.0 and r["nominal_mean_test_mrad"] > 10 * r["mean_test_mrad"]
    # each test record has the predictive interval of the refit that predicted it
    assert rep["overall"]["interval_90_coverage"] == r["interval_90_coverage"] >= 0.5
    assert 0.3 < r["expected_test_mrad"] / r["mean_test_mrad"] < 3.0 and r["interval_90_mrad"][1] > 0
    code, out, err = run_cli(capsys, "calibrate", "--paint", paint_dir, "--method", "gradient", "--half-life-days", "5")
    assert code == 2 and "--method lm only" in err and len(err.strip().splitlines()) == 1


def test_recency_weights_track_a_drifting_offset():
    """Chrono on drifting records: weighting the training records by recency (half-life 3 weeks) predicts the
    next records better than the static fit; weights halve every half-life, records without time weigh 1."""
    from heliotwin.calibrate.methods.lm import recency_weights

    kin, batch = drifting_records(chunks=6, per_chunk=10)
    w = recency_weights(batch, 7.0)
    for h in range(2):
        rows = batch.of(h)
        assert w[rows].max() == 1.0 and w[rows][batch.time[rows].argmax()] == 1.0
    i, j = batch.of(0)[-1], batch.of(0)[-2]
    dt = (batch.time[i] - batch.time[j]) / 86400.0
    assert torch.isclose(w[j], 0.5 ** (dt / 7.0))
    tr = torch.cat([batch.of(h)[:40] for h in range(2)])
    te = torch.cat([batch.of(h)[40:50] for h in range(2)])
    static = fit_lm_method(kin, batch.subset(tr), None, bags=0, field_prior=False, fit_focal_spot=None)
    recent = fit_lm_method(kin, batch.subset(tr), None, bags=0, field_prior=False, fit_focal_spot=None,
                           half_life_days=21.0)
    e_static, e_recent = (m.pointing_error(batch.subset(te)).mean() for m in (static, recent))
    assert e_recent < 0.7 * e_static, (e_recent, e_static)


def test_cli_drift_flags_become_lm_options():
    from heliotwin.cli import build_parser
    from heliotwin.cli.calibrate import _config

    args = build_parser().parse_args(["calibrate", "--paint", "P", "--half-life-days", "20", "--drift-mrad", "1.5",
                                      "--prior", "plant", "--split", "online", "--online-step", "3"])
    cfg = _config(args, args.method)
    assert cfg.method_options == {"half_life_days": 20.0, "drift": 1.5e-3}
    assert cfg.prior == "plant" and cfg.split == "online" and cfg.online_step == 3
