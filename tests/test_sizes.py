"""Size arguments of reconstruct / trace / validate / bench are bounded before any work: an absurd control-point
net, resolution, sample or ray count is refused with one line naming the option (exit 2), a run whose memory
estimate exceeds the machine's with the out-of-memory line -- never an allocation that grows for minutes."""
from __future__ import annotations

import pytest
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.errors import HeliotwinError
from heliotwin.workflows.bench import run_benchmark
from heliotwin.workflows.reconstruct import ReconstructionSettings
from heliotwin.workflows.sizes import MAX_RAYS, check_memory_estimate, check_trace_sizes, physical_memory


def test_reconstruct_refuses_a_huge_control_net_before_reading_anything(tmp_path, capsys):
    # The PAINT folder does not exist: the refusal comes first, and nothing is written.
    code, _, err = run_cli(capsys, "reconstruct", "--paint", tmp_path / "nope", "--heliostat", "AA39",
                           "--control-points", "200x200", "--json", tmp_path / "r.json", "-o", tmp_path / "r.h5")
    assert code == 2
    assert_one_line_error(code, err, "--control-points", "200", "at most the 24 mirror samples")
    assert list(tmp_path.iterdir()) == []
    for kw, option in (({"control_points": "4x4", "degree": 4}, "--degree"), ({"steps": 10 ** 7}, "--steps"),
                       ({"train_first": 0}, "--train-first"), ({"control_points": "25x7"}, "--control-points")):
        with pytest.raises(HeliotwinError, match=option):
            ReconstructionSettings(**kw).check()
    ReconstructionSettings(control_points="24x24").check()  # the largest net the samples determine


def test_trace_sizes_bound_rays_resolution_samples_and_memory():
    with pytest.raises(HeliotwinError, match=r"--rays-per-point: 4000000 mirror points x 100000 rays"):
        check_trace_sizes(resolution=64, samples=1000, facets=4, rays_per_point=100_000)
    for kw, option in (({"resolution": 100_000}, "--resolution"), ({"resolution": 64, "samples": 0}, "--samples"),
                       ({"resolution": 64, "rays_per_point": 10 ** 7, "points": 1}, "--rays-per-point")):
        with pytest.raises(HeliotwinError, match=option):
            check_trace_sizes(**kw)
    check_trace_sizes(resolution=256, samples=50, facets=4, rays_per_point=100)  # the defaults pass
    assert 4 * 50 ** 2 * 100 < MAX_RAYS
    with pytest.raises(MemoryError, match="GiB"):
        check_memory_estimate("a map", physical_memory())
    with pytest.raises(HeliotwinError, match="--surface-points"):
        run_benchmark(surface_points=10 ** 9, rays_per_point=1, resolution=16, time_to_accuracy=False)
