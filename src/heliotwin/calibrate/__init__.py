"""Kinematic calibration from real calibration records, grouped by role.

Three groups, each importing only the ones above it in this list:

1. **Shared parts, at this package's top level** -- the vocabulary every method and every protocol speaks:
   :mod:`.params` (the 28 deviations of the chain; the Stone/Jülich 8), :mod:`.metrics` (the pointing error
   and miss distance on a :class:`~heliotwin.io.records.RecordTable`, and the residuals' Jacobian
   :func:`~.metrics.record_jacobian`; the one home of each), :mod:`.inputs` (what a method trains on),
   :mod:`.priors` (nominal, field and plant priors), :mod:`.uncertainty` (Laplace predictive error and its
   interval), :mod:`.drift` (a random-walk offset: ``--drift kalman``), :mod:`.fitloop` (the one
   early-stopping loop of the iterative fits) and :mod:`.model` (:class:`~.model.Calibrated`, what every
   method returns). Two more use what the methods make: :mod:`.scenario` (a calibration in the scenario file,
   and aiming with it) and :mod:`.report` (report layout and plots).
2. :mod:`.methods` -- the methods behind ``--method``, in its registry (:data:`.methods.METHODS`):
   :mod:`.methods.lm`, :mod:`.methods.gradient`, :mod:`.methods.hybrid`, :mod:`.methods.mlp`,
   :mod:`.methods.images` (through the ray tracer), and :mod:`.methods.nets` (their small networks).
3. :mod:`.protocol` -- how a calibration is run and judged: :mod:`.protocol.config` (a run's options),
   :mod:`.protocol.splits` (chrono, isolation, region, PAINT's azimuth/solstice/balanced/high_variance;
   coverage), :mod:`.protocol.online` (``--split online``), :mod:`.protocol.suspicious` (property checks),
   :mod:`.protocol.archive` (a plant prior learned from other heliostats, ``--prior-from``, its no-leakage
   rule), :mod:`.protocol.selection` (leave-heliostats-out cross-validation of settings),
   :mod:`.protocol.pipeline` (one run as named steps) and :mod:`.protocol.plan` (which record next).

Why the shared parts stay at the top level rather than in a ``core/`` subpackage: they are what the rest of
the package (``validate``, the workflows, the tests) reaches for by name -- ``heliotwin.calibrate.metrics``
reads as "the calibration metric" -- and the two subpackages already set them apart; a ``core/`` level would
lengthen every one of those imports without separating anything further.

The command-line jobs built on this package (``heliotwin calibrate``, ``split``, ``aim``, ``plan``) are in
:mod:`heliotwin.workflows.calibrate` and :mod:`heliotwin.cli.calibrate` / :mod:`heliotwin.cli.plan`.
"""
