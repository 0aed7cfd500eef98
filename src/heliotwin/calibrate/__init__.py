"""Kinematic calibration from real calibration records (issue 3).

Modules: :mod:`records` (validated, batched records), :mod:`metrics` (pointing error by atan2, miss
distance), :mod:`splits` (chrono, isolation, region, PAINT's azimuth/solstice/balanced/high_variance;
coverage), :mod:`params` (the 28 deviations of the chain; the Stone/Jülich 8), :mod:`priors` (field prior),
:mod:`suspicious` (property checks), methods :mod:`lm`, :mod:`gradient`, :mod:`hybrid`, :mod:`mlp`,
:mod:`images` (through the ray tracer), :mod:`pipeline` (one run), :mod:`report` (JSON + plots), :mod:`scenario`
(calibration file + aim), :mod:`cli` (``calibrate``, ``split``, ``aim``).
"""
