"""The calibration report's figures at plant scale: readable and of bounded size for thousands of heliostats."""
import numpy as np
from PIL import Image

from heliotwin.calibrate.report import PER_HELIOSTAT_MOST, write_plots


def _report(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    ids = [f"H{i:04d}" for i in range(n)]
    per = 5
    arrays = {"heliostat_ids": ids, "test_heliostat": np.repeat(np.arange(n), per),
              "test_azimuth": rng.uniform(-1.5, 1.5, n * per), "test_elevation": rng.uniform(0.2, 1.2, n * per),
              "test_error_mrad": rng.gamma(2.0, 0.2, n * per)}
    heliostats = {h: {"status": "ok", "nominal_mean_test_mrad": float(rng.uniform(5, 40)),
                      "mean_test_mrad": float(rng.gamma(2.0, 0.2))} for h in ids}
    heliostats["H0003"]["mean_test_mrad"] = 9.5  # the worst: named on the plant-scale figure
    return {"config": {"method": "lm"}, "heliostats": heliostats}, arrays


def test_plant_scale_figures_keep_a_readable_size(tmp_path):
    report, arrays = _report(2000)
    paths = write_plots(tmp_path / "cal.json", report, arrays)
    assert [p.rsplit("-", 1)[1] for p in paths] == ["sky.png", "heliostats.png"]
    for p in paths:
        w, h = Image.open(p).size
        # one bar pair per heliostat made this figure 102,560 px wide; a legend entry per heliostat 1,766 px tall
        assert w <= 1600 and h <= 800, (p, w, h)


def test_few_heliostats_keep_one_bar_and_colour_each(tmp_path):
    report, arrays = _report(PER_HELIOSTAT_MOST)
    paths = write_plots(tmp_path / "cal.json", report, arrays)
    w, _ = Image.open(paths[1]).size
    assert w >= 0.6 * PER_HELIOSTAT_MOST * 72  # a bar pair per heliostat, figure width grows with them


def test_validation_figure_of_a_plant_keeps_a_readable_size(tmp_path):
    from heliotwin.plots import plot_validation

    rng = np.random.default_rng(1)
    hs = {f"H{i:04d}": {"median_pointing_error_mrad": float(rng.gamma(2, 2)),
                        "median_distance_m": float(rng.gamma(2, 0.1)), "records": int(rng.integers(5, 120)),
                        "images": 0} for i in range(2000)}
    plot_validation({"heliostats": hs, "overall": {"median_pointing_error_mrad": 4.0}}, tmp_path / "v.png")
    w, h = Image.open(tmp_path / "v.png").size
    assert w <= 1600 and h <= 800, (w, h)  # a bar per heliostat: 700 inches wide
