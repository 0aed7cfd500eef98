"""The cases of ``benchmarks/fuzz_daily.py``, one module per area (each defines ``CASES``)."""
