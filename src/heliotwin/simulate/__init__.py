"""An in-silico plant: a PAINT folder of simulated calibration records with a known truth, and the score of
any learned plant against that truth.

* :mod:`.plant` -- true deviations, drift and steps, the calibration schedule and the records
  (:func:`simulate_plant`);
* :mod:`.writer` -- the PAINT folder and the truth scenario (:func:`write_paint_folder`,
  :func:`truth_scenario`);
* :func:`score` -- pointing, surface and flux errors of a learned scenario against the truth (it lives in
  :mod:`heliotwin.evaluation`, so that scoring a plant does not import the simulator).
"""
from ..evaluation import score
from .plant import SimulatedPlant, SimulationSettings, paint_prior, simulate_plant
from .writer import truth_scenario, write_paint_folder

__all__ = ["SimulatedPlant", "SimulationSettings", "paint_prior", "simulate_plant", "score", "truth_scenario",
           "write_paint_folder"]
