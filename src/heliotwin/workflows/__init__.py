"""The workflows floor: each job a user runs is one function here, and only here.

Every workflow has the shape ``Scenario × inputs × settings → (Scenario′, report)``:

* it takes the plant it starts from as a :class:`~heliotwin.io.scenario.Scenario` (a nominal plant from a
  PAINT folder or a layout is a scenario with no learned state and no provenance yet);
* its settings are one small dataclass with defaults (the command line's defaults);
* it returns the new scenario **in memory** (:func:`~heliotwin.io.scenario.next_scenario` appends the one
  provenance step) and a JSON-ready report dict; it writes no files of its own, so that the caller decides
  where outputs go and stages them (the CLI writes all outputs of a run or none).

The command line (:mod:`heliotwin.cli`), the notebook API (:mod:`heliotwin.api`), the demo and the benchmarks
call these functions; none of them re-implements one. Below this floor sit the learners and the physics
(``calibrate``, ``surfaces``, ``optimise``, ``raytrace``, ``field``, ``io``), which never import it.
"""
