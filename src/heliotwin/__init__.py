"""heliotwin: a differentiable digital twin of a solar tower power plant.

The pipeline reads like the package: ``site`` & ``sun`` -> ``field`` (plant data, kinematics, facets)
-> ``nurbs`` surfaces -> ``raytrace`` (integrators mc, gaussian, conv; flux images) -> losses ->
``calibrate`` / ``surfaces`` (learning) with ``io`` and ``cli`` at the edges.

Conventions (everywhere inside the package): right-handed East-North-Up (ENU) frame in metres with the
plant reference as origin; angles in radians (``_deg`` suffix only at the edges); column vectors;
geometry in float64, rays in float32.
"""
from .errors import HeliotwinError, InputFileError, OutOfRangeError, ScenarioVersionError

__version__ = "0.1.0"

__all__ = ["HeliotwinError", "InputFileError", "OutOfRangeError", "ScenarioVersionError", "__version__"]
