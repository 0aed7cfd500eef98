"""``images``: kinematic calibration through the ray tracer from flux images.

For records with a flux image (PAINT ``<id>-flux.png``: the whole target, max-normalised, image left =
east) each record's spot is rendered by the differentiable Gaussian-footprint tracer
(:func:`heliotwin.raytrace.gaussian.trace_gaussian`) from the calibrated kinematics and the mirror surfaces,
and the deviations are learned with the published three-term loss:

* **pixel** -- normalised L1 distance between the rendered and the measured image (both scaled to unit
  sum; in [0, 2]); it sees the *shape* and orientation of the spot, so rotations invisible to a centroid
  (above all the mirror's rotation about its own normal, ``concentrator_tilt_n``: the concentrator tilt acts
  before the heliostat-frame alignment ``R_E(pi/2)``, which maps the mirror normal onto north) are learned
  too;
* **alignment** -- distance between the rendered and the measured image centroid on the target, divided by
  the slant range (an angle, weighed against the centroid noise like a centroid residual); it gives the
  gradient that the pixel term lacks while the spots do not overlap;
* **miss** -- fraction of the reflected power that misses the target (pushes a spot that left the target
  back before the other two terms can see it).

Records without an image contribute the ordinary centroid term (model minus measured mirror normal, as
in ``gradient``); records with an image contribute their centroid term too. Pre-alignment: the
Stone/Jülich LM fit with the field prior (:func:`~heliotwin.calibrate.methods.lm.stone8_field_fit`), so the
rendered spots start on their targets. Prior: field prior on the Stone/Jülich 8, the chain's nominal
prior (:data:`~heliotwin.calibrate.priors.CHAIN_SIGMA`) on the rest. Optimiser: L-BFGS (or Adam) in
natural units (mrad, mm, 0.1 %), early-stopped per heliostat on the validation loss (same three terms +
centroid term) when there are validation records, else kept at its lowest training loss.

The images and the mirror surfaces come from the pipeline (``images={record_id: path or bitmap}``,
``surfaces=Surfaces`` of the run's heliostats, ``targets={name: PlanarTarget}``, ``sun=SunSettings``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from ... import scene
from ...errors import HeliotwinError
from ...field.plant import SunSettings
from ...io.images import load_measured_image
from ...io.records import RecordTable
from ...raytrace.flux import normalized_l1, pixel_centers, target_extent
from ...raytrace.gaussian import FootprintSettings, trace_gaussian
from .. import metrics, priors
from ..fitloop import (
    actuator_barrier,
    box_and_validity,
    early_stopping_fit,
    make_optimizer,
    prior_and_start,
    tensor_state,
)
from ..inputs import FIT_FOCAL_SPOT
from ..model import Calibrated
from ..params import STONE8, actuators_valid, apply_deviations, check_names
from .gradient import prealign
from .lm import field_prior_extras

#: Learned by default: the Stone/Jülich 8 plus the mirror's rotation about its own normal (invisible to
#: centroids, visible in the image).
IMAGE_PARAMETERS = STONE8 + ("concentrator_tilt_n",)

#: Loss weights (per image record): the alignment term is an angle over ``noise`` squared like a centroid
#: residual; the pixel term (normalised L1, ~0.3 for a good match) and miss term are dimensionless.
PIXEL_WEIGHT = 100.0
MISS_WEIGHT = 100.0


def load_image(entry, resolution) -> torch.Tensor:
    """A measured image as a unit-sum bitmap [rows, cols] at the render resolution (area resampling)."""
    return load_measured_image(entry, resolution, normalise="sum")


class ImageTerms:
    """Rendering and the three image terms for a fixed set of image records (grouped by target)."""

    def __init__(self, batch: RecordTable, images: dict, surfaces, targets: dict, sun, *, resolution=(64, 64),
                 samples=(16, 16), mode: str = "convolve"):
        self.mode = mode  # one heliostat per sample: one mean footprint (FFT) is accurate and ~20x faster
        self.resolution = tuple(resolution)
        self.samples = tuple(samples)
        self.surfaces, self.sun = surfaces, sun
        self.skipped = {}
        rows = []
        meas = []
        for r in range(len(batch)):
            rid = int(batch.record_id[r])
            if rid not in images:
                continue
            tname = batch.target[r]
            t = targets.get(tname)
            if t is None or getattr(t, "kind", "") != "planar":
                self.skipped[rid] = f"target {tname!r} not planar/unknown"
                continue
            try:
                meas.append(load_image(images[rid], self.resolution))
            except (HeliotwinError, OSError) as exc:  # a broken image: the record keeps its centroid term
                self.skipped[rid] = str(exc).splitlines()[0]
                continue
            rows.append(r)
        self.index = torch.tensor(rows, dtype=torch.long)
        self.batch = batch.subset(self.index) if rows else batch.subset([])
        self.measured = torch.stack(meas) if meas else torch.zeros(0, *self.resolution)
        self.groups = {}
        for j, tname in enumerate(self.batch.target):
            self.groups.setdefault(tname, []).append(j)
        self.targets = {n: targets[n] for n in self.groups}
        # measured centroids (local target coordinates, m)
        cen = batch.spot.new_zeros(len(rows), 2)  # the records' dtype and device
        for tname, js in self.groups.items():
            ext = target_extent(self.targets[tname], 1)
            x, y = pixel_centers(ext, *self.resolution)
            m = self.measured[js].to(cen)
            x, y = x.to(cen), y.to(cen)
            cen[js, 0] = (m.sum(-2) * x).sum(-1)
            cen[js, 1] = (m.sum(-1) * y).sum(-1)
        self.measured_centroid = cen

    def __len__(self) -> int:
        return len(self.index)

    def terms(self, kin) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel [M], alignment [M] (rad) and miss [M] terms for calibrated kinematics ``kin`` (H heliostats)."""
        m, like = len(self), kin.position  # terms follow the kinematics' dtype and device
        pix, ali, mis = like.new_zeros(m), like.new_zeros(m), like.new_zeros(m)
        b = self.batch
        for tname, js in self.groups.items():
            j = torch.tensor(js, dtype=torch.long, device=like.device)
            t = self.targets[tname]
            pw, nw, ar, _, conc = scene.world_surface(kin, self.surfaces, b.heliostat_index[j], b.motor_steps[j],
                                                      samples=self.samples)
            fl = trace_gaussian(pw, nw, ar, b.sun[j].float(), t, resolution=self.resolution, sun=self.sun,
                                footprint=FootprintSettings(mode=self.mode))
            render = fl.bitmap
            p = normalized_l1(render, self.measured[j].to(render)).to(like)
            cen = fl.centroid_local().to(like)
            slant = torch.linalg.norm(t.center.to(conc) - conc, dim=-1)
            a = torch.linalg.norm(cen - self.measured_centroid[j].to(like), dim=-1) / slant
            power, total = fl.intercepted_power_w.to(like), fl.total_power_w.to(like).clamp_min(1e-30)
            frac = (power / total).clamp(0, 1)
            # an image with no flux on the target: pixel term is its maximum, alignment undefined -> miss only
            landed = power > 1e-9 * total
            pix = pix.index_copy(0, j, torch.where(landed, p, torch.full_like(p, 2.0)))
            ali = ali.index_copy(0, j, torch.where(landed, a, torch.zeros_like(a)))
            mis = mis.index_copy(0, j, 1.0 - frac)
        return pix, ali, mis


def image_loss_per_heliostat(terms: ImageTerms, kin, h: int, *, noise: float, pixel_weight: float,
                             miss_weight: float) -> tuple[torch.Tensor, dict]:
    """Sum of the image loss per heliostat [H] and the raw terms."""
    if not len(terms):
        return kin.position.new_zeros(h), {}
    pix, ali, mis = terms.terms(kin)
    per = pixel_weight * pix + (ali / noise) ** 2 + miss_weight * mis
    hidx = terms.batch.heliostat_index
    return per.new_zeros(h).index_add(0, hidx, per), {"pixel": pix, "alignment": ali, "miss": mis}


def _centroid_loss_per_heliostat(kin_nominal, delta, names, batch: RecordTable, h: int, noise: float) -> torch.Tensor:
    if not len(batch):
        return delta.new_zeros(h)
    k = apply_deviations(kin_nominal.index(batch.heliostat_index), delta[batch.heliostat_index], names)
    r = metrics.normal_residuals(k, batch, per_record=True)
    return delta.new_zeros(h).index_add(0, batch.heliostat_index, (r * r).sum(-1) / noise ** 2)


@dataclass(frozen=True)
class ImageFitSettings:
    """Settings of the image fit (:func:`fit_images`; each field is also one of its keywords).

    Attributes
    ----------
    noise : float
        Pointing noise of one centroid record [rad] the centroid and alignment terms are weighed against.
    pixel_weight, miss_weight, centroid_weight : float
        Weights of the pixel term (normalised L1), the miss term and the centroid term per record.
    iterations : int
        LBFGS outer iterations (each up to ``lbfgs_inner`` evaluations) or Adam steps.
    lr : float
        Learning rate (per natural unit of the deviations).
    resolution : (int, int)
        Rendered and measured bitmap rows, columns.
    samples : (int, int)
        Mirror samples per heliostat and direction of the Gaussian tracer.
    check_every : int
        Validation every this many iterations (early stopping).
    optimizer : str
        ``"lbfgs"`` or ``"adam"``.
    lbfgs_inner : int
        LBFGS evaluations per outer iteration.
    """

    noise: float = 1e-3
    pixel_weight: float = PIXEL_WEIGHT
    miss_weight: float = MISS_WEIGHT
    centroid_weight: float = 1.0
    iterations: int = 15
    lr: float = 1.0
    resolution: tuple = (64, 64)
    samples: tuple = (16, 16)
    check_every: int = 1
    optimizer: str = "lbfgs"
    lbfgs_inner: int = 10


def fit_images(nominal, train: RecordTable, validation: RecordTable | None, images: dict, surfaces, targets: dict,
               sun, *, names=IMAGE_PARAMETERS, init: torch.Tensor | None = None, prior_mean=None, prior_sigma=None,
               progress: bool = False, settings: ImageFitSettings | None = None,
               **options) -> tuple[torch.Tensor, dict]:
    """Learn deviations from images (+ centroids) by LBFGS (or Adam); see the module docstring.

    The prior defaults to :data:`~heliotwin.calibrate.priors.CHAIN_SIGMA`; bounds, validity restore and the
    per-heliostat early stopping on the validation loss are the loop of :mod:`~heliotwin.calibrate.fitloop`.

    Parameters
    ----------
    nominal : Kinematics
        H heliostats.
    train, validation : RecordTable
        Records over the same heliostat axis (validation may be None).
    images : dict
        Record id -> measured flux image (path or entry for :func:`load_image`).
    surfaces : Surfaces
        The H heliostats' mirror surfaces.
    targets : dict
        Target name -> target (planar targets are rendered).
    sun : SunSettings
    names : sequence of str, length P
        Deviations learned (:mod:`heliotwin.calibrate.params`).
    init, prior_mean : torch.Tensor, [H, P], optional
        Start and prior centre (physical units: [rad] for angles, [m] for lengths, [1] for relative
        increments; default zero).
    prior_sigma : dict or torch.Tensor [P], optional
        Prior standard deviation per kind or per parameter (same units: [rad], [m], [1]).
    settings : ImageFitSettings, optional
    **options
        Any field of :class:`ImageFitSettings` by keyword, replacing ``settings``'s.

    Returns
    -------
    delta : torch.Tensor, [H, P] (physical units)
    info : dict
        ``image_records`` (train, validation), ``loss_history``, per-term means before/after, ``skipped_images``.
    """
    s = replace(settings or ImageFitSettings(), **options)
    noise, centroid_weight = s.noise, s.centroid_weight
    names = check_names(names)
    h = nominal.num_heliostats
    sigma = priors.CHAIN_SIGMA if prior_sigma is None else prior_sigma
    unit, mu, inv_sig, bound, x = prior_and_start(names, h, sigma, prior_mean, init, like=nominal.position)
    tr_img = ImageTerms(train, images, surfaces, targets, sun, resolution=s.resolution, samples=s.samples)
    has_val = validation is not None and len(validation) > 0
    va_img = ImageTerms(validation, images, surfaces, targets, sun, resolution=s.resolution,
                        samples=s.samples) if has_val else None
    kw = dict(noise=noise, pixel_weight=s.pixel_weight, miss_weight=s.miss_weight)

    def objective(xx):
        delta = xx * unit
        kin = apply_deviations(nominal, delta, names)
        data = centroid_weight * _centroid_loss_per_heliostat(nominal, delta, names, train, h, noise).sum()
        img, _ = image_loss_per_heliostat(tr_img, kin, h, **kw)
        prior = (((delta - mu) * inv_sig) ** 2).sum()
        return data + img.sum() + prior + actuator_barrier(kin)

    def train_loss_per_heliostat():
        delta = x.detach() * unit
        kin = apply_deviations(nominal, delta, names)
        data = centroid_weight * _centroid_loss_per_heliostat(nominal, delta, names, train, h, noise)
        img, _ = image_loss_per_heliostat(tr_img, kin, h, **kw)
        return data + img + (((delta - mu) * inv_sig) ** 2).sum(-1)

    def val_loss():
        with torch.no_grad():
            if not has_val:  # no validation: each heliostat keeps its lowest training loss (a step that made
                return train_loss_per_heliostat()  # it worse -- bounds, validity restore -- is not kept)
            delta = x.detach() * unit
            kin = apply_deviations(nominal, delta, names)
            v = centroid_weight * _centroid_loss_per_heliostat(nominal, delta, names, validation, h, noise)
            vi, _ = image_loss_per_heliostat(va_img, kin, h, **kw)
            c = validation.counts()
            return torch.where(c > 0, (v + vi) / c.clamp_min(1), torch.full_like(v, float("inf")))

    def mean_terms():
        if not len(tr_img):
            return None
        with torch.no_grad():
            _, t = image_loss_per_heliostat(tr_img, apply_deviations(nominal, x.detach() * unit, names), h, **kw)
        return {k: float(v.mean()) for k, v in t.items()}

    before = mean_terms()
    opt, closure = make_optimizer(x, objective, s.optimizer, s.lr, lbfgs_max_iter=s.lbfgs_inner)
    validated = validation.counts() > 0 if has_val else torch.ones(h, dtype=torch.bool, device=x.device)
    log = early_stopping_fit(lambda: opt.step(closure), val_loss, tensor_state(x), s.iterations, validated=validated,
                             check_every=s.check_every, progress=progress, desc="images",
                             project=box_and_validity(x, bound, lambda xx: actuators_valid(
                                 apply_deviations(nominal, xx * unit, names))))
    x.data = log.best.clone()
    info = {"image_records_train": len(tr_img), "image_records_validation": len(va_img) if va_img is not None else 0,
            "image_terms_before": before, "image_terms_after": mean_terms(), "loss_history": log.losses,
            "best_iteration": log.best_iteration.tolist(),
            "skipped_images": {**tr_img.skipped, **(va_img.skipped if va_img is not None else {})}}
    return log.best * unit, info


def image_centroid_records(batch: RecordTable, images: dict, targets: dict, resolution=(64, 64)) -> RecordTable:
    """The records of ``batch`` that have a usable flux image, with the measured centroid replaced by the
    image's own (flux-weighted centroid of the image at ``resolution``, on the target plane, ENU [m]).

    What an image alone says about the pointing: no camera centroid of the record (``spot``, ``spot_other``,
    ``focal_spots``) is left in the returned table (K <= R records, same heliostat axis), so a fit on it has
    seen nothing but the images.
    """
    terms = ImageTerms(batch, images, None, targets, None, resolution=resolution)
    sub = terms.batch
    if not len(sub):
        return sub
    cen = terms.measured_centroid
    tgt = [targets[n] for n in sub.target]
    center = torch.stack([t.center for t in tgt]).to(cen)
    right = torch.stack([t.right for t in tgt]).to(cen)
    up = torch.stack([t.up for t in tgt]).to(cen)
    spot = center + cen[:, :1] * right + cen[:, 1:] * up
    return replace(sub, spot=spot.to(sub.spot), spot_other=None, focal_spots=None,
                   source=["image"] * len(sub))


def fit_images_method(nominal, train, validation, *, seed=0, progress=False, images=None, surfaces=None,
                      targets=None, sun=None, names=IMAGE_PARAMETERS, field_prior=True, fit_focal_spot=FIT_FOCAL_SPOT,
                      centroids: bool = True, **options) -> Calibrated:
    """``images``: Stone/Jülich pre-alignment on centroids, then image (+ centroid) loss through the tracer.

    Heliostats without image records are fitted on their centroids alone (same loss without image terms).
    ``images``, ``surfaces``, ``targets``, ``sun``: as for :func:`fit_images` (the pipeline passes the run's);
    ``options``: ``settings`` (an :class:`ImageFitSettings`) and/or its fields by keyword.

    ``centroids=False``: calibration from the images alone. The records without an image are dropped, the
    camera centroids of the others are replaced by their images' centroids
    (:func:`image_centroid_records`), so the pre-alignment starts from what the images show, and the
    centroid term is off (``centroid_weight=0``: the alignment term already weighs the image centroid).
    """
    if surfaces is None or targets is None:
        raise HeliotwinError("method 'images' needs the mirror surfaces and targets (run it through "
                             "heliotwin.calibrate.protocol.pipeline / `heliotwin calibrate`)")
    images = dict(images or {})
    if not centroids:
        res = options.get("resolution", (options.get("settings") or ImageFitSettings()).resolution)
        train = image_centroid_records(train, images, targets, res)
        if validation is not None:
            validation = image_centroid_records(validation, images, targets, res)
        options = {**options, "centroid_weight": 0.0}
    sun = sun or SunSettings()
    h = nominal.num_heliostats
    names = check_names(names)
    # centroid terms and pre-alignment exactly as lm/gradient
    ok, tr, va, init, mu, sig, fp = prealign(nominal, train, validation, names, fit_focal_spot, field_prior)
    delta, info = fit_images(nominal, tr, va, images, surfaces, targets, sun, names=names, init=init, prior_mean=mu,
                             prior_sigma=sig, progress=progress, **options)
    delta[~ok] = 0.0
    with_image = torch.tensor([int(i) in images for i in tr.record_id.tolist()], dtype=torch.bool)
    counts_img = torch.bincount(tr.heliostat_index.cpu()[with_image], minlength=h)
    per_h = {hid: {"image_records_train": int(counts_img[i])}
             for i, hid in enumerate(train.heliostat_ids) if bool(ok[i])}
    extras = {"per_heliostat": per_h,
              "summary": {k: info[k] for k in ("image_records_train", "image_records_validation", "image_terms_before",
                                               "image_terms_after", "skipped_images")},
              "field_prior": field_prior_extras(fp)}
    return Calibrated("images", list(train.heliostat_ids), nominal, names, delta, ok, extras=extras)


__all__ = ["fit_images_method", "fit_images", "image_centroid_records", "ImageFitSettings", "ImageTerms",
           "IMAGE_PARAMETERS", "load_image"]
