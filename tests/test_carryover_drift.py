"""The random-walk offset (``--drift kalman``): the smoother follows a known walk, q = 0 is the static fit,
no NaN at the edges, and the offset state travels through the scenario file to ``aim``."""
import pytest
import torch
from helpers.calibrate import TRUE, jueliche_like, scenario_round_trip, simulate

from heliotwin.calibrate import drift as D
from heliotwin.calibrate.methods.lm import fit_lm_method
from heliotwin.calibrate.params import STONE8, apply_deviations
from heliotwin.io.records import RecordTable

F64 = torch.float64
DAYS = 3.0  # one record every 3 days


def walk_records(h: int = 3, n: int = 60, q_mrad2: float = 0.05, seed: int = 0):
    """``n`` records per heliostat, ``DAYS`` apart, whose two axis offsets follow a random walk of process
    noise ``q_mrad2`` [mrad^2/day] (0 at the first record) on top of :data:`TRUE`; centroid noise 0.2 mrad."""
    kin = jueliche_like(h)
    g = torch.Generator().manual_seed(seed)
    steps = torch.randn(n, h, 2, generator=g, dtype=F64) * (q_mrad2 * DAYS) ** 0.5 * 1e-3
    walk = torch.cumsum(steps, 0)
    walk = walk - walk[0]
    parts = []
    for i in range(n):
        d = torch.tensor([[TRUE[k] for k in STONE8]] * h, dtype=F64)
        d[:, :2] += walk[i]
        rec = simulate(apply_deviations(kin, d, STONE8), 1, 100 + i, noise=2e-4)
        rec.time = torch.full((h,), 1.6e9 + i * DAYS * 86400.0, dtype=F64)
        parts.append(rec)
    return kin, RecordTable.concatenate(parts), walk


def _fit(kin, batch, **kw):
    return fit_lm_method(kin, batch, None, bags=0, field_prior=False, fit_focal_spot=None, **kw)


def test_smoother_recovers_the_walk_and_chrono_beats_the_static_fit():
    kin, batch, walk = walk_records()
    tr = torch.cat([batch.of(h)[:45] for h in range(3)])
    te = torch.cat([batch.of(h)[45:] for h in range(3)])
    train, test = batch.subset(tr), batch.subset(te)
    static = _fit(kin, train)
    kal = _fit(kin, train, drift_model="kalman", process_noise=0.05)
    state = kal.extras["drift_state"]
    # the walk starts at 0 at the first record (the static part holds the offset there): the state at the
    # latest training record lies within its reported 2.5 sigma of the walk's value there
    sd = state["covariance"].diagonal(dim1=1, dim2=2).sqrt()
    assert bool(((state["offset"] - walk[44]).abs() < 2.5 * sd).all()), (state["offset"], walk[44], sd)
    # smoothed offsets over the training records follow the walk
    sm = D.smooth(kin, train, state["static_deviations"], 0.05e-6, 1e-3)["smoothed"]
    rows = torch.cat([train.of(h) for h in range(3)])
    true_rec = walk[:45].transpose(0, 1).reshape(-1, 2)  # heliostat-major, in time order like ``rows``
    rms_fit = (sm[rows] - true_rec).pow(2).mean().sqrt()
    rms_walk = (true_rec - true_rec.mean(0)).pow(2).mean().sqrt()
    assert rms_fit < 0.5 * rms_walk, (rms_fit, rms_walk)
    e_static, e_kal = static.pointing_error(test).mean(), kal.pointing_error(test).mean()
    assert e_kal < 0.9 * e_static, (e_kal, e_static)
    # the offset's predictive covariance grows with the time since the latest training record
    c = D.predicted_covariance(state, test.heliostat_index, test.time)
    later = test.time > test.time.min()
    assert bool((c[later].diagonal(dim1=1, dim2=2) > state["covariance"][test.heliostat_index[later]]
                 .diagonal(dim1=1, dim2=2)).all())


def test_zero_process_noise_is_the_static_fit():
    kin, batch, _ = walk_records(h=2, n=20)
    static = _fit(kin, batch)
    q0 = _fit(kin, batch, drift_model="kalman", process_noise=0.0)
    assert torch.equal(static.delta, q0.delta)
    assert float(q0.extras["drift_state"]["offset"].abs().max()) == 0.0
    w = D.whitener(kin, batch, 0.0, 1e-3)
    x = torch.randn(len(batch), 3, 8, dtype=F64, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(w(x), x, atol=1e-15)


def test_auto_process_noise_chooses_a_walk_on_drifting_records():
    kin, batch, _ = walk_records(h=3, n=40)
    model = _fit(kin, batch, drift_model="kalman", process_noise="auto")
    s = model.extras["summary"]
    assert s["process_noise_mrad2_per_day"] > 0 and set(s["process_noise_choice"]) == set(D.Q_GRID)
    assert s["process_noise_choice"][s["process_noise_mrad2_per_day"]] < s["process_noise_choice"][0.0]


def test_records_without_time_and_whitening_gradients_are_nan_free():
    kin, batch, _ = walk_records(h=2, n=12)
    batch.time[batch.of(1)] = float("nan")  # heliostat 1: no time at all
    batch.time[batch.of(0)[3]] = float("nan")  # heliostat 0: one record without time
    model = _fit(kin, batch, drift_model="kalman", process_noise=0.1)
    st = model.extras["drift_state"]
    assert bool(torch.isfinite(model.delta).all()) and bool(torch.isfinite(st["covariance"]).all())
    assert float(st["offset"][1].abs().max()) == 0.0 and bool(torch.isnan(st["time"][1]))
    c = D.predicted_covariance(st, torch.tensor([0, 1]), torch.tensor([float("nan"), 1.7e9], dtype=F64))
    assert bool(torch.isfinite(c).all())
    w = D.whitener(kin, batch, 0.1e-6, 1e-3)
    x = torch.randn(len(batch), 3, dtype=F64, generator=torch.Generator().manual_seed(2), requires_grad=True)
    assert torch.autograd.gradcheck(w, (x,))


def test_drift_state_round_trips_through_the_scenario_and_aim(tmp_path):
    from heliotwin.calibrate.scenario import KEY, aim

    kin, batch, _ = walk_records(h=2, n=30)
    model = _fit(kin, batch, drift_model="kalman", process_noise=0.05)
    sc = scenario_round_trip(tmp_path, kin, model)
    d = sc.learned[KEY]["drift"]
    st = model.extras["drift_state"]
    assert list(d["names"]) == list(D.DRIFT_NAMES)
    assert float(torch.as_tensor(sc.learned[KEY]["posterior"]["walk_scale"]).reshape(-1)[0]) == 1.0
    assert torch.allclose(torch.as_tensor(d["offset"]), st["offset"])
    assert torch.allclose(torch.as_tensor(d["covariance"]), st["covariance"])
    assert torch.allclose(torch.as_tensor(d["time"]), st["time"])
    # the stored deviations are the static part + the current offset: aim points with the offset of now
    dev = torch.as_tensor(sc.learned[KEY]["deviations"])
    assert torch.allclose(dev, D.with_offset(st["static_deviations"], st["offset"]))
    now = aim(sc, "S0", 0.3, 0.7, [0.0, -3.24, 40.0])
    later = aim(sc, "S0", 0.3, 0.7, [0.0, -3.24, 40.0], time=float(st["time"][0]) + 200 * 86400.0)
    assert now["motor_steps"] == later["motor_steps"] and later["drift_days"] == pytest.approx(200.0)
    assert later["error_interval_90_mrad"][1] > now["error_interval_90_mrad"][1]


def test_cli_drift_flags_become_run_settings():
    from heliotwin.cli import build_parser
    from heliotwin.cli.calibrate import _config
    from heliotwin.errors import HeliotwinError

    args = build_parser().parse_args(["calibrate", "--paint", "P", "--drift", "kalman", "--process-noise", "0.02"])
    cfg = _config(args, args.method)
    assert cfg.drift_model == "kalman" and cfg.process_noise == 0.02
    assert cfg.fit_options()["process_noise"] == 0.02 and cfg.fit_options()["drift_basis"] == "axes"
    args = build_parser().parse_args(["calibrate", "--paint", "P", "--drift", "kalman"])
    assert _config(args, args.method).process_noise == "auto"
    for bad in (["--process-noise", "-1"], ["--process-noise", "fast"], ["--half-life-days", "20"]):
        args = build_parser().parse_args(["calibrate", "--paint", "P", "--drift", "kalman", *bad])
        with pytest.raises(HeliotwinError):
            _config(args, args.method)


def test_cli_aim_time_flag():
    from heliotwin.errors import HeliotwinError
    from heliotwin.workflows.plan import aim_time as _aim_time

    assert _aim_time(None) is None and _aim_time("2023-05-01T12:00:00Z") == pytest.approx(1682942400.0)
    with pytest.raises(HeliotwinError, match="--time"):
        _aim_time("yesterday")


def test_choose_interval_shrinks_a_walk_that_overstates_the_drift():
    """Errors of noise s only, but a walk covariance that claims 3 mrad of offset: the chosen walk scale
    is below 1 and its coverage is near 0.9; runs without a walk keep scale 1."""
    import math

    from heliotwin.calibrate.protocol import selection

    g = torch.Generator().manual_seed(0)
    n, s = 1000, 1e-3
    err = (torch.randn(n, 2, generator=g, dtype=F64) * s).norm(dim=-1)
    jac = torch.zeros(n, 3, 8, dtype=F64)
    jac[:, 0, 0] = 1.0  # the normal's x moves with the axis-1 offset
    walk = torch.zeros(n, 8, 8, dtype=F64)
    walk[:, 0, 0] = 9e-6
    x = {"jacobian": jac, "normal": torch.tensor([[0.0, 0.0, 1.0]] * n, dtype=F64),
         "covariance": 1e-20 * torch.eye(8, dtype=F64).expand(n, 8, 8), "noise": torch.full((n,), s, dtype=F64),
         "error": err}
    drift, scale, cov = selection.choose_interval([dict(x, walk=walk)], samples=1000)
    assert scale < 1.0 and abs(cov[(drift, scale)] - 0.9) < 0.05 and cov[(0.0, 1.0)] > 0.97
    drift, scale, cov = selection.choose_interval([x], samples=1000)
    assert scale == 1.0 and all(k[1] == 1.0 for k in cov) and math.isfinite(drift)


def test_recursive_whitening_and_smoother_equal_the_dense_gaussian_forms():
    """The Kalman-form whitening (one pass over the records) against the dense Cholesky factor of Sigma, and
    the filter + RTS smoother against the dense Gaussian conditional; records out of time order (the whitening
    then differs, a valid factor all the same: equal inner products, s^2 x^T Sigma^-1 z) and one without a
    time included."""
    kin, batch, _ = walk_records(h=3, n=30)
    batch.time[batch.of(1)[5]] = float("nan")
    g = torch.Generator().manual_seed(5)
    x = torch.randn(len(batch), 3, 8, dtype=F64, generator=g)
    delta = torch.tensor([[TRUE[k] for k in STONE8]] * 3, dtype=F64) * 0.5
    for q in (0.0, 0.05e-6, 1e-6):
        assert torch.allclose(D.whitener(kin, batch, q, 1e-3)(x), D.dense_whitener(kin, batch, q, 1e-3)(x),
                              rtol=0, atol=1e-12)
        s, sd = D.smooth(kin, batch, delta, q, 1e-3), D.dense_smooth(kin, batch, delta, q, 1e-3)
        for key, tol in (("smoothed", 1e-14), ("offset", 1e-14), ("covariance", 1e-18)):
            assert torch.allclose(s[key], sd[key], rtol=0, atol=tol), key
        assert torch.equal(s["time"], sd["time"])
    perm = torch.randperm(len(batch), generator=g)
    shuffled, xs, zs = batch.subset(perm), x[perm], torch.randn(len(batch), 3, 8, dtype=F64, generator=g)

    def inner(w):
        return torch.zeros(3, 8, 8, dtype=F64).index_add_(0, shuffled.heliostat_index,
                                                          torch.einsum("rcp,rcq->rpq", w(xs), w(zs)))
    assert torch.allclose(inner(D.whitener(kin, shuffled, 1e-6, 1e-3)),
                          inner(D.dense_whitener(kin, shuffled, 1e-6, 1e-3)), rtol=0, atol=1e-11)


def test_the_walk_learns_the_records_noise_not_the_static_residuals():
    """Under the walk the update's filter gets the records' own noise (the centroid noise, 0.4 mrad as a
    reflected-ray angle for ``noise=2e-4``), not the static residuals' (which count the wandering offset as
    noise and stay the predictive interval's); the offset's state keeps the fit's smoothing, and its scale
    factor turns the covariance and q into the records' units."""
    kin, batch, _ = walk_records(h=6, n=60, q_mrad2=0.05)
    static = _fit(kin, batch)
    kal = _fit(kin, batch, drift_model="kalman", process_noise=0.05)
    true = 2 * 2e-4
    state = kal.extras["drift_state"]
    s_rec, s_static = state["record_noise"], static.extras["posterior"]["noise_rad"]
    assert bool(((s_rec > 0.8 * true) & (s_rec < 1.5 * true)).all()), s_rec
    assert float(s_static.median()) > 1.8 * float(s_rec.median()), (s_static, s_rec)
    assert float(kal.extras["posterior"]["noise_rad"].median()) > 1.3 * float(s_rec.median())  # the interval's
    assert state["filter_scale"] == pytest.approx((float(s_rec.median()) / 1e-3) ** 2)
    ref = D.smooth(kin, batch, state["static_deviations"], 0.05e-6, 1e-3)
    torch.testing.assert_close(state["offset"], ref["offset"], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(state["covariance"], ref["covariance"], rtol=1e-9, atol=1e-18)


def test_after_a_walk_calibration_a_step_alarms_and_clean_records_do_not(tmp_path):
    """The update's innovations are normalised by the walk's learned noise: a 3 mrad step of one heliostat's
    axis offsets alarms at its first new record, the five unstepped heliostats' records do not (with the static
    residuals' noise, 2-3x wider here, the step's d^2 of ~26 would be ~4, far below the threshold of 16)."""
    from heliotwin.workflows.update import update

    h, n = 6, 60
    kin, batch, walk = walk_records(h=h, n=n, q_mrad2=0.05)
    model = _fit(kin, batch, drift_model="kalman", process_noise=0.05)
    sc = scenario_round_trip(tmp_path, kin, model)
    step = torch.tensor([2.4e-3, -1.8e-3], dtype=F64)
    parts = []
    for k in range(3):  # three records per heliostat, DAYS apart after the last training record
        d = torch.tensor([[TRUE[name] for name in STONE8]] * h, dtype=F64)
        d[:, :2] += walk[-1]
        d[2, :2] += step
        rec = simulate(apply_deviations(kin, d, STONE8), 1, 900 + k, noise=2e-4)
        rec.time = torch.full((h,), 1.6e9 + (n + k) * DAYS * 86400.0, dtype=F64)
        parts.append(rec)
    new = RecordTable.concatenate(parts)
    new.heliostat_ids = list(batch.heliostat_ids)
    new.record_id = 10 ** 6 + torch.arange(len(new))
    result = update(sc, new)
    alarmed = {a["heliostat"] for a in result.report["alarms"]}
    assert alarmed == {batch.heliostat_ids[2]}, result.report["alarms"]
