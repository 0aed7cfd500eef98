"""Heliostats with too few records for the full model: the best model their records support, chosen by validation.

A ``current`` run fits the full model (the Stone/Jülich 8 under the run's field prior, bagged, perhaps with a
random-walk offset) on heliostats with at least ``--min-records`` usable records. A heliostat with fewer is not
left at its nominal kinematics (tens of mrad): it gets a *reduced* model, the plant prior learned from the
fully calibrated heliostats (:func:`~heliotwin.calibrate.priors.plant_prior`: mean + shrunk covariance over their
loose fits, :class:`~heliotwin.calibrate.protocol.archive.PriorArchive`) with fewer free parameters:

* ``axis offsets``: the two encoder offsets fitted, the six others held at the plant prior's mean;
* ``all 8``: all eight under the plant prior (its covariance holds the near-degenerate pairs).

Which set a heliostat with ``n`` records gets (the *rule*) is chosen per run by validation on the fully
calibrated heliostats, never on the heliostats it is applied to (:func:`choose_rule`):

1. leave-heliostats-out: the fully calibrated heliostats are dealt into :data:`FOLDS` folds; a heliostat's
   plant prior is learned from the other folds' fits only (no record of it enters its own prior);
2. chronological held-out records inside each heliostat's own records: its latest :data:`HOLDOUT` records are
   held out, the ``n`` records just before them are all a candidate may see (a reduced heliostat's records are
   its recent ones, and the future follows them);
3. for every ``n`` of :data:`GRID` below ``--min-records``, the candidate with the lowest median over heliostats
   of the mean held-out error wins (a richer set only when strictly lower); none, when nominal is lower still.
   A heliostat with ``m`` records takes the choice at the largest validated ``n <= m``.

The interval: the Laplace posterior of the eight parameters under the plant prior around the reduced fit (the
held parameters keep their prior spread), its record noise pooled with the plant's (:data:`NOISE_DOF`: a
fit through 3 records cannot estimate its own noise), widened by the offset drift whose 90 % intervals cover
the validation's held-out records closest to 0.9 (:func:`~.selection.choose_drift`). With fewer than
``FOLDS`` fully calibrated heliostats nothing can be validated: the rule is then ``axis offsets`` for every
heliostat with a record (the fewest free parameters), under the plant prior when there are
:data:`~heliotwin.calibrate.priors.MIN_HELIOSTATS` to learn one from, else the nominal prior, and the report
says it was not validated.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ...field.plant import Kinematics
from ...io.records import RecordTable
from .. import metrics, priors
from ..inputs import NOISE, fit_spots
from ..methods.lm import LM_F_SCALE, LM_LOSS, fit_lm
from ..model import Calibrated
from ..params import STONE8, apply_deviations
from ..uncertainty import residual_variance
from .config import CURRENT_HOLDOUT
from .selection import choose_drift

#: The reduced parameter sets, fewest free parameters first: name -> the free parameters of :data:`STONE8`.
PARAMETER_SETS = {"axis offsets": ("initial_angle_1", "initial_angle_2"), "all 8": STONE8}

#: What each set of :data:`PARAMETER_SETS` fits, in words (reports).
DESCRIPTIONS = {"axis offsets": "the two axis offsets free, the six others at the plant prior's mean",
                "all 8": "all 8 parameters under the plant prior"}

#: Record counts the rule is validated at (those below the run's ``--min-records``).
GRID = (1, 2, 3, 5, 8, 12, 20, 30, 40)

#: Folds of the leave-heliostats-out validation (also the fewest fully calibrated heliostats it needs).
FOLDS = 5

#: Latest records of each validation heliostat held out (as the run's own validation inside the records).
HOLDOUT = CURRENT_HOLDOUT

#: Degrees of freedom of the plant's record noise pooled with a reduced fit's own residuals.
NOISE_DOF = 4.0

#: A record's residual counts in a reduced fit's noise up to this many plant noise sigmas (a Rayleigh residual
#: of the plant's noise exceeds it with probability exp(-OUTLIER_SIGMAS^2 / 2), 4e-6; :func:`posterior_of`).
OUTLIER_SIGMAS = 5.0

#: Fewest records whose median residual sets a heliostat's own noise scale (:func:`robust_sigma`).
ROBUST_MIN = 5

#: Variance factor that holds a parameter at the prior mean (relative to its prior variance).
PINNED = 1e-8


@dataclass(frozen=True)
class Rule:
    """Which parameter set a heliostat with ``n`` usable records gets.

    Attributes
    ----------
    steps : tuple of (int, str)
        ``(n, set)`` ascending in ``n``: from ``n`` records on, ``set`` (a key of :data:`PARAMETER_SETS` or
        ``"nominal"``), until the next step.
    validated : bool
        Chosen by :func:`choose_rule` (False: the fallback of a run with too few fully calibrated heliostats).
    evidence : dict
        Per ``n`` (str): each candidate's and nominal's median held-out error [mrad], the heliostats scored,
        the choice, and the Laplace expected error of the choice; ``protocol`` says how.
    drift_rad : float
        Offset drift [rad] added to the reduced fits' posterior noise (interval calibration).
    """

    steps: tuple
    validated: bool
    evidence: dict = field(default_factory=dict)
    drift_rad: float = 0.0

    def choice(self, n: int) -> str:
        """The parameter set for ``n`` usable records (``"nominal"`` below the first step)."""
        chosen = "nominal"
        for least, name in self.steps:
            if n >= least:
                chosen = name
        return chosen if n > 0 else "nominal"

    @property
    def fewest(self) -> int | None:
        """Fewest records that get a model (None: no count does)."""
        for least, name in self.steps:
            if name != "nominal":
                return least
        return None

    def text(self) -> str:
        """One line: the rule as thresholds."""
        parts = []
        for i, (least, name) in enumerate(self.steps):
            upto = self.steps[i + 1][0] - 1 if i + 1 < len(self.steps) else None
            span = f"{least}+" if upto is None else (f"{least}" if upto == least else f"{least}-{upto}")
            parts.append(f"{span} records: {name}")
        return "; ".join(parts) + ("" if self.validated else " (not validated: too few fully calibrated heliostats)")

    def json(self) -> dict:
        """The rule as JSON values: ``steps``, ``validated``, ``rule`` (:meth:`text`), ``drift_mrad`` [mrad],
        ``evidence``."""
        return {"steps": [[int(n), s] for n, s in self.steps], "validated": self.validated, "rule": self.text(),
                "drift_mrad": 1e3 * self.drift_rad, "evidence": self.evidence}


def pinned_prior(prior: priors.PlantPrior | None, free) -> tuple[torch.Tensor, torch.Tensor]:
    """Prior mean [P] and covariance [P, P] of a fit whose ``free`` parameters keep the prior's marginal spread
    and whose others are held at its mean (variance x :data:`PINNED`, uncorrelated). Without a plant prior:
    the nominal prior (:data:`~heliotwin.calibrate.priors.STONE8_SIGMA`, centred at zero)."""
    mean, cov = _prior_moments(prior)
    keep = torch.tensor([n in free for n in STONE8])
    out = cov.clone()
    out[~keep] = 0.0
    out[:, ~keep] = 0.0
    idx = (~keep).nonzero().flatten()
    out[idx, idx] = PINNED * cov.diagonal()[idx]
    return mean, out


def _prior_moments(prior) -> tuple[torch.Tensor, torch.Tensor]:
    if prior is None:
        sigma = priors.sigma_vector(STONE8, priors.STONE8_SIGMA)
        return torch.zeros(len(STONE8), dtype=torch.float64), torch.diag(sigma ** 2)
    return prior.mean.double().cpu(), prior.covariance.double().cpu()


def fit_set(nominal: Kinematics, records: RecordTable, mean: torch.Tensor, covariance: torch.Tensor) -> torch.Tensor:
    """MAP deviations [H, 8] of every heliostat of ``records`` under per-heliostat priors ``mean`` [H, 8] and
    ``covariance`` [H, 8, 8] (one batched LM, the robust loss of ``lm``, the centroids its fits train on)."""
    dev = nominal.position.device
    chol = torch.linalg.cholesky(covariance.double())
    eye = torch.eye(len(STONE8), dtype=torch.float64).expand_as(chol)
    w = torch.linalg.solve_triangular(chol, eye, upper=False)
    delta, _ = fit_lm(nominal, fit_spots(records), names=STONE8, prior_mean=mean.to(dev),
                      prior_whitening=w.to(dev), loss=LM_LOSS, f_scale=LM_F_SCALE)
    return delta


def posterior_of(nominal: Kinematics, records: RecordTable, delta: torch.Tensor, covariance: torch.Tensor,
                 n_free: torch.Tensor, plant_noise: float, drift: float = 0.0) -> dict:
    """Laplace posterior of the eight parameters around ``delta`` [H, 8] under the (unpinned) prior
    ``covariance`` [H, 8, 8]: ``{"covariance": [H, 8, 8], "noise_rad": [H], "drift_rad"}``. The record noise
    per component pools the fit's residuals (over ``2 n - n_free`` degrees of freedom, ``n_free`` [H]) with
    ``plant_noise`` [rad] at :data:`NOISE_DOF` degrees of freedom; each record's squared residual counts at most
    (:data:`OUTLIER_SIGMAS` sigma)^2, sigma the larger of ``plant_noise`` and the heliostat's own median-based
    noise (:func:`robust_sigma`): the robust fit gives a bad centroid (tens of mrad, a few of a real heliostat's
    records) almost no weight, and a posterior whose noise it set would put a heliostat that fits its other
    records to 1 mrad at a 20 mrad expected error."""
    h = nominal.num_heliostats
    hidx = records.heliostat_index
    res, jac = metrics.record_jacobian(nominal.index(hidx), records, delta.detach()[hidx], STONE8)
    f64 = dict(dtype=torch.float64, device=jac.device)
    r2 = (res ** 2).sum(-1)
    sigma = robust_sigma(r2.sqrt(), hidx, h).clamp_min(plant_noise)
    ss = torch.zeros(h, **f64).index_add_(0, hidx, torch.minimum(r2, (OUTLIER_SIGMAS * sigma[hidx]) ** 2))
    dof = (2.0 * torch.bincount(hidx, minlength=h).double().to(jac.device) - n_free.to(jac.device)).clamp_min(0.0)
    s2 = (ss + NOISE_DOF * plant_noise ** 2) / (dof + NOISE_DOF)
    jtj = torch.zeros(h, 8, 8, **f64).index_add_(0, hidx, torch.einsum("rci,rcj->rij", jac, jac))
    eye = torch.eye(8, **f64)
    prec = jtj / s2[:, None, None] + torch.linalg.inv(covariance.to(**f64))
    cov = torch.linalg.solve(prec + 1e-12 * eye, eye.expand(h, 8, 8))
    return {"covariance": 0.5 * (cov + cov.transpose(-1, -2)), "noise_rad": s2.sqrt(), "drift_rad": float(drift)}


def robust_sigma(norm: torch.Tensor, heliostat_index: torch.Tensor, num_heliostats: int) -> torch.Tensor:
    """Per heliostat [H]: the record noise per component [rad] that its median residual norm ``norm`` [R] [rad]
    implies (a Rayleigh median is sigma sqrt(2 ln 2)); 0 for heliostats with fewer than :data:`ROBUST_MIN`
    records (a median of fewer says nothing)."""
    h = heliostat_index.cpu().numpy()
    x = norm.detach().double().cpu().numpy()
    order = np.lexsort((x, h))
    counts = np.bincount(h, minlength=num_heliostats)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    have = counts >= ROBUST_MIN
    mid = x[order][np.minimum(start + counts // 2, max(len(x) - 1, 0))] if len(x) else np.zeros(num_heliostats)
    out = np.where(have, mid / np.sqrt(2.0 * np.log(2.0)), 0.0)
    return torch.as_tensor(out, dtype=torch.float64, device=norm.device)


def rank_from_latest(records: RecordTable) -> torch.Tensor:
    """Per record [R]: how many of its heliostat's records are later (0 = the latest; records without a time
    count as the oldest, ties by table order)."""
    t = records.time.detach().double().cpu().numpy() if records.time is not None else np.zeros(len(records))
    t = np.where(np.isfinite(t), t, -np.inf)
    h = records.heliostat_index.cpu().numpy()
    order = np.lexsort((np.arange(len(h)), t, h))
    counts = np.bincount(h, minlength=records.num_heliostats)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(h)) - start[h[order]]
    rank = np.empty(len(h), dtype=np.int64)
    rank[order] = counts[h[order]] - 1 - pos
    return torch.as_tensor(rank, device=records.heliostat_index.device)


def plant_noise(nominal: Kinematics, records: RecordTable, delta: torch.Tensor) -> float:
    """Median over heliostats of the record noise per component [rad] of fits ``delta`` [H, 8] on ``records``."""
    if len(records) == 0:
        return NOISE
    hidx = records.heliostat_index
    res, _ = metrics.record_jacobian(nominal.index(hidx), records, delta.detach()[hidx], STONE8)
    s2 = residual_variance(res, hidx, nominal.num_heliostats, len(STONE8))
    have = torch.bincount(hidx, minlength=nominal.num_heliostats) > len(STONE8)
    return float(s2[have].sqrt().median()) if bool(have.any()) else NOISE


def _fold_priors(deviations: torch.Tensor, ids: list, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Leave-heliostats-out plant priors: per heliostat [A] the mean [A, 8] and covariance [A, 8, 8] learned
    from the heliostats of the other folds."""
    a = len(ids)
    fold = np.random.default_rng(seed).permutation(a) % FOLDS
    means, covs = torch.zeros(a, 8, dtype=torch.float64), torch.zeros(a, 8, 8, dtype=torch.float64)
    for k in range(FOLDS):
        mine = torch.as_tensor(fold == k)
        if not bool(mine.any()):
            continue
        pp = priors.plant_prior(deviations[~mine], STONE8, [i for i, m in zip(ids, mine.tolist()) if not m])
        means[mine], covs[mine] = pp.mean.double().cpu(), pp.covariance.double().cpu()
    return means, covs


def choose_rule(nominal: Kinematics, records: RecordTable, deviations: torch.Tensor, min_records: int,
                seed: int = 0, prior: priors.PlantPrior | None = None) -> Rule:
    """The rule of a run, validated on its fully calibrated heliostats (module docstring).

    Parameters
    ----------
    nominal : Kinematics
        The A fully calibrated heliostats (``records``' heliostat axis; property corrections applied).
    records : RecordTable
        Their usable records.
    deviations : torch.Tensor, [A, 8]
        Each one's loose fit on all its records (what the fold priors are learned from).
    min_records : int
        The run's ``--min-records``: the rule covers fewer records than that.
    seed : int
        Deals the folds.
    prior : PlantPrior, optional
        The prior of the fallback rule (fewer than :data:`FOLDS` heliostats).
    """
    ids = list(records.heliostat_ids)
    if len(ids) < FOLDS:
        return Rule(((1, "axis offsets"),), False,
                    {"protocol": f"not validated: {len(ids)} fully calibrated heliostat(s), {FOLDS} needed"})
    means, covs = _fold_priors(deviations.double().cpu(), ids, seed)
    noise0 = plant_noise(nominal, records, deviations)
    rank = rank_from_latest(records)
    counts = records.counts().cpu()
    test_all = records.subset(rank < HOLDOUT)
    evidence, steps, inputs = {}, [], []
    for n in [g for g in GRID if g < max(min_records, 2)]:
        enough = counts >= n + HOLDOUT
        if int(enough.sum()) < FOLDS:
            continue
        mine = enough.to(rank.device)[records.heliostat_index]
        train = records.subset((rank >= HOLDOUT) & (rank < HOLDOUT + n) & mine)
        test = test_all.subset(enough.to(rank.device)[test_all.heliostat_index])
        nominal_err = _held_out(nominal, test, torch.zeros(len(ids), 8, dtype=torch.float64), enough)
        row = {"heliostats": int(enough.sum()), "nominal": _median(nominal_err)}
        fits = {}
        for name, free in PARAMETER_SETS.items():
            keep = torch.tensor([p in free for p in STONE8])
            pinned = covs.clone()
            pinned[:, ~keep] = 0.0
            pinned[:, :, ~keep] = 0.0
            idx = (~keep).nonzero().flatten()
            pinned[:, idx, idx] = PINNED * covs[:, idx, idx]
            delta = fit_set(nominal, train, means, pinned).cpu()
            err = _held_out(nominal, test, delta, enough)
            fits[name] = (delta, len(free))
            row[name] = _median(err)
        best = "nominal"
        for name in PARAMETER_SETS:  # fewest free parameters first: a richer set must be strictly better
            if row[name] is not None and (best == "nominal" or row[name] < row[best]) and row[name] < row["nominal"]:
                best = name
        row["chosen"] = best
        if best != "nominal":
            delta, n_free = fits[best]
            post = posterior_of(nominal, fit_spots(train), delta, covs, torch.full((len(ids),), float(n_free)), noise0)
            inputs.append(_interval_inputs(nominal, test, delta, post))
        if not steps or steps[-1][1] != best:
            steps.append((n, best))
        evidence[str(n)] = row
    if not steps:
        return Rule(((1, "axis offsets"),), False,
                    {"protocol": f"not validated: no fully calibrated heliostat has {GRID[0] + HOLDOUT} records"})
    drift = 0.0
    if inputs:
        drift, cov = choose_drift(inputs)
        evidence["interval_90_coverage"] = {f"{1e3 * d:g} mrad": c for d, c in cov.items()}
    evidence["protocol"] = (f"leave-heliostats-out ({FOLDS} folds over {len(ids)} fully calibrated heliostats; each "
                            f"one's plant prior from the other folds) x chronological: each heliostat's latest "
                            f"{HOLDOUT} records predicted from the n records just before them; median over "
                            "heliostats of the mean held-out error [mrad]")
    return Rule(tuple(steps), True, evidence, drift)


def _held_out(nominal: Kinematics, test: RecordTable, delta: torch.Tensor, scored: torch.Tensor) -> list:
    """Mean held-out pointing error [mrad] per scored heliostat."""
    with torch.no_grad():
        err = metrics.pointing_error(apply_deviations(nominal, delta.to(nominal.position.device), STONE8), test)
    per = metrics.per_heliostat_mean(err.double(), test.heliostat_index, nominal.num_heliostats).cpu()
    return [1e3 * float(per[h]) for h in scored.nonzero().flatten().tolist() if torch.isfinite(per[h])]


def _median(xs):
    return float(np.median(xs)) if xs else None


def _interval_inputs(nominal: Kinematics, test: RecordTable, delta: torch.Tensor, post: dict) -> dict:
    """What :func:`~.selection.coverage` needs for the held-out records ``test`` of a reduced fit."""
    hidx = test.heliostat_index
    kin = apply_deviations(nominal, delta.to(nominal.position.device), STONE8)
    _, jac = metrics.record_jacobian(nominal.index(hidx), test, delta.to(nominal.position.device)[hidx], STONE8)
    with torch.no_grad():
        normal, _ = metrics.model_normals(kin, test)
        err = metrics.pointing_error(kin, test).double()
    cov = post["covariance"].to(jac.device)[hidx]
    return {"jacobian": jac.cpu(), "normal": normal.double().cpu(), "covariance": cov.cpu(),
            "walk": cov.new_zeros(()).expand_as(cov).cpu(), "noise": post["noise_rad"].to(jac.device)[hidx].cpu(),
            "error": err.cpu(), "heliostat": [test.heliostat_ids[h] for h in hidx.tolist()]}


def fit_reduced(nominal: Kinematics, records: RecordTable, rule: Rule, prior: priors.PlantPrior | None,
                noise: float) -> tuple[Calibrated, dict]:
    """The reduced models of the heliostats of ``records`` (H, nominal kinematics ``nominal``), each by the set
    ``rule`` gives its record count, under ``prior`` (None: the nominal prior).

    Returns the model (``ok`` False where the rule gives nominal; ``extras["posterior"]`` the Laplace posterior
    with the rule's drift) and per heliostat id its set and record count."""
    h = nominal.num_heliostats
    counts = records.counts().cpu()
    chosen = [rule.choice(int(c)) for c in counts.tolist()]
    mean0, cov0 = _prior_moments(prior)
    means = mean0.expand(h, 8).clone()
    pinned = torch.zeros(h, 8, 8, dtype=torch.float64)
    n_free = torch.zeros(h, dtype=torch.float64)
    for i, name in enumerate(chosen):
        free = PARAMETER_SETS.get(name, ())
        pinned[i] = pinned_prior(prior, free)[1] if free else cov0
        n_free[i] = len(free)
    ok = torch.tensor([c != "nominal" for c in chosen], dtype=torch.bool)
    dev = nominal.position.device
    use = records.subset(ok.to(dev)[records.heliostat_index])
    delta = fit_set(nominal, use, means, pinned) if len(use) else torch.zeros(h, 8, dtype=torch.float64, device=dev)
    delta = delta.clone()
    delta[~ok.to(delta.device)] = 0.0
    post = posterior_of(nominal, fit_spots(use), delta, cov0.expand(h, 8, 8), n_free, noise, rule.drift_rad)
    model = Calibrated("lm", list(records.heliostat_ids), nominal, STONE8, delta, ok.to(dev),
                       reasons={hid: "no usable record" for hid, o in zip(records.heliostat_ids, ok.tolist()) if not o},
                       extras={"posterior": dict(post, walk_scale=1.0)})
    t = records.time.double() if records.time is not None else torch.full((len(records),), float("nan"))
    known = torch.isfinite(t)
    latest = torch.full((h,), -float("inf"), dtype=torch.float64, device=t.device).scatter_reduce(
        0, records.heliostat_index[known].to(t.device), t[known], reduce="amax")
    nan = torch.full_like(latest, float("nan"))
    model.extras["latest_time"] = torch.where(torch.isfinite(latest), latest, nan).cpu()
    info = {hid: {"parameters": name, "records": int(c)}
            for hid, name, c in zip(records.heliostat_ids, chosen, counts.tolist())}
    return model, info


def merged(full: Calibrated | None, reduced: Calibrated, order: list) -> Calibrated:
    """One model over the heliostats of ``order`` from the full run's model (None: none ran) and the reduced
    one (both lm, :data:`STONE8`). The posterior is concatenated; the reduced heliostats' interval drift is
    folded into their record noise (the stored posterior has one drift for the plant: the full run's), never
    narrower than their own noise. A random-walk state of the full model gets rows for the reduced heliostats:
    no offset yet, its covariance the posterior's over the walk's columns, at their latest record's time."""
    parts = [m for m in (full, reduced) if m is not None]
    where = {hid: (k, i) for k, m in enumerate(parts) for i, hid in enumerate(m.heliostat_ids)}
    order = [h for h in order if h in where]
    pick = [where[h] for h in order]

    def gather(get):
        return torch.cat([get(parts[k])[i:i + 1].cpu() for k, i in pick])

    nominal = Kinematics.concatenate([parts[k].nominal.index([i]) for k, i in pick])
    nominal = nominal if full is None else _to_device(nominal, full.nominal.position.device)
    extras = dict(full.extras) if full is not None else {}
    post_full = (full.extras.get("posterior") if full is not None else None) or {}
    post_red = reduced.extras["posterior"]
    drift_full = float(post_full.get("drift_rad", post_red["drift_rad"]))
    red_noise = (post_red["noise_rad"] ** 2 + max(0.0, post_red["drift_rad"] ** 2 - drift_full ** 2)).sqrt()
    posts = [post_full, dict(post_red, noise_rad=red_noise)] if full is not None else [dict(post_red,
                                                                                          noise_rad=red_noise)]
    if full is None or post_full:
        extras["posterior"] = {"covariance": torch.cat([posts[k]["covariance"][i:i + 1].cpu() for k, i in pick]),
                               "noise_rad": torch.cat([posts[k]["noise_rad"][i:i + 1].cpu() for k, i in pick]),
                               "drift_rad": drift_full, "walk_scale": float(post_full.get("walk_scale", 1.0))}
    state = extras.get("drift_state")
    if state:
        extras["drift_state"] = _walk_rows(state, full, reduced, pick, post_red)
    reasons = {**(full.reasons if full is not None else {}), **reduced.reasons}
    corrections = {**(full.corrections if full is not None else {}), **reduced.corrections}
    dev = nominal.position.device
    return Calibrated("lm", order, nominal, STONE8, gather(lambda m: m.delta.detach().double()).to(dev),
                      gather(lambda m: m.ok).to(dev), reasons=reasons, corrections=corrections, extras=extras)


def _to_device(kin: Kinematics, device) -> Kinematics:
    return Kinematics(**{f: getattr(kin, f).to(device) for f in kin.__dataclass_fields__})


def _walk_rows(state: dict, full: Calibrated, reduced: Calibrated, pick: list, post_red: dict) -> dict:
    """The random-walk state (``drift_state`` of lm) over ``pick``'s heliostats (see :func:`merged`)."""
    h = len(full.heliostat_ids)
    cols = state["columns"].cpu()
    out = dict(state)
    per_h = {k: v for k, v in state.items() if torch.is_tensor(v) and v.dim() >= 1 and v.shape[0] == h
             and k != "columns"}
    fill = {"offset": lambda i: torch.zeros(1, len(cols), dtype=torch.float64),
            "covariance": lambda i: post_red["covariance"][i:i + 1].cpu()[:, cols[:, None], cols[None, :]],
            "time": lambda i: reduced.extras.get("latest_time", torch.full((len(reduced.heliostat_ids),),
                                                                           float("nan")))[i:i + 1].double(),
            "record_noise": lambda i: post_red["noise_rad"][i:i + 1].cpu(),
            "static_deviations": lambda i: reduced.delta[i:i + 1].detach().double().cpu()}
    for key, v in per_h.items():
        rows = []
        for k, i in pick:
            if k == 0:
                rows.append(v[i:i + 1].cpu())
            else:
                rows.append(fill[key](i).to(v.dtype) if key in fill else torch.zeros_like(v[:1].cpu()))
        out[key] = torch.cat(rows).to(v.device)
    return out
