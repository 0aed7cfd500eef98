"""Kinematic calibration from real calibration records (issue 3).

Modules: :mod:`metrics` (the pointing error and miss distance on a :class:`~heliotwin.io.records.RecordTable`;
the one home of both), :mod:`splits` (chrono, isolation, region, PAINT's azimuth/solstice/balanced/high_variance;
coverage), :mod:`params` (the 28 deviations of the chain; the Stone/Jülich 8), :mod:`priors` (nominal and
field priors), :mod:`suspicious` (property checks), :mod:`inputs` (what a method trains on), :mod:`fitloop`
(the one early-stopping loop of the iterative fits), methods :mod:`lm`, :mod:`gradient`, :mod:`hybrid`,
:mod:`mlp`, :mod:`images` (through the ray tracer) in the registry :mod:`methods`, :mod:`pipeline` (one run
as named steps), :mod:`report` (report layout + plots), :mod:`scenario` (calibration file + aim), :mod:`cli`
(``calibrate``, ``split``, ``aim``). Issue 10 (accuracy that carries over): :mod:`archive` (a plant prior
learned from other heliostats, ``--prior-from``, its no-leakage rule), :mod:`uncertainty` (Laplace
predictive error and its interval), :mod:`selection` (leave-heliostats-out cross-validation of settings),
:mod:`online` (``--split online``), :mod:`plan` (which record next), :mod:`drift` (a random-walk offset:
``--drift kalman``).
"""
