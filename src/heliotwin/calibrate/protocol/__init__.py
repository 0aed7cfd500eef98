"""How a calibration is run and judged: its options, splits, the online protocol, property checks, plant priors
from an archive, settings by cross-validation, one run as named steps, and which record to take next (see
:mod:`heliotwin.calibrate` for the map)."""
