"""AA39 data reading for surface learning, and the CLI's handling of bad input."""
from __future__ import annotations

import math
import subprocess
import sys

import pytest
import torch

from heliotwin.cli import main
from heliotwin.errors import HeliotwinError
from heliotwin.io.paint import load_paint
from heliotwin.surfaces.observations import load_centered_image, observations_from_records, split_record_ids


def test_aa39_centred_records_split_and_orientation(paint_dir):
    ds = load_paint(paint_dir, heliostats=["AA39"])
    records = ds.records_of("AA39")
    assert len(records) == 18
    with_img = records.select(with_centered_image=True)
    assert len(with_img) == 10
    tr, te = split_record_ids(records.record_id.tolist(), records.datetime, records.flux_centered_png, train_first=3)
    train, test = records.subset(tr), records.subset(te)
    # No DateTime for AA39 in the metadata: the earliest are by id.
    assert train.record_id.tolist() == [86520, 151375, 202558]
    assert len(test) == 7 and not set(train.record_id.tolist()) & set(test.record_id.tolist())
    # the default is the current surface: every centred image trains (in time order, by id here), no test split
    lt, le = split_record_ids(records.record_id.tolist(), records.datetime, records.flux_centered_png)
    ids = sorted(with_img.record_id.tolist())
    assert records.record_id[lt].tolist() == ids and le == []
    # the study's latest-K split: the latest three, the earlier seven its test images
    lt, le = split_record_ids(records.record_id.tolist(), records.datetime, records.flux_centered_png, train_latest=3)
    assert records.record_id[lt].tolist() == ids[-3:] and sorted(records.record_id[le].tolist()) == ids[:-3]
    obs = observations_from_records(ds.plant, 0, train)
    assert obs.images.shape == (3, 64, 64)
    # Every centred image is centred on its own centroid (PAINT) -> within a pixel of the window centre.
    img = load_centered_image(with_img.flux_centered_png[-1])  # a 256x256 one, box-averaged
    idx = torch.arange(64, dtype=torch.float64) + 0.5
    w = img.double() / img.sum()
    assert abs(float((w.sum(1) * idx).sum()) - 32) < 1.0 and abs(float((w.sum(0) * idx).sum()) - 32) < 1.0
    # The pose aimed at the measured spot faces the sun/target bisector: normal has a southward (-y) part
    # (the heliostat is north of the tower) and the mirror faces up.
    normal = obs.rotation[:, :, 2]
    assert bool((normal[:, 1] < 0).all()) and bool((normal[:, 2] > 0).all())
    assert math.isclose(float(obs.sun.norm(dim=-1).max()), 1.0, rel_tol=1e-9)


@pytest.mark.parametrize("argv, needle", [
    (["--heliostat", "ZZ99"], "ZZ99"),
    (["--heliostat", "AA39", "--train-records", "156500"], "156500"),
    (["--heliostat", "AA39", "--train-first", "10"], "no test images"),
])
def test_cli_bad_input_one_line_error_no_output(paint_dir, tmp_path, capsys, argv, needle):
    out_json = tmp_path / "report.json"
    out_h5 = tmp_path / "learned.h5"
    rc = main(["reconstruct", "--paint", str(paint_dir), *argv, "-o", str(out_h5), "--json", str(out_json),
               "--quiet", "--no-mc"])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert len(err.splitlines()) == 1 and needle in err and err.startswith("heliotwin: error:")
    assert not out_json.exists() and not out_h5.exists()
    assert list(tmp_path.iterdir()) == []


def test_cli_missing_scenario_file(tmp_path, capsys):
    rc = main(["predict", "--scenario", str(tmp_path / "nope.h5"), "--json", str(tmp_path / "o.json")])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1 and "nope.h5" in err
    assert not (tmp_path / "o.json").exists()


def test_cli_module_entry_point_reports_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "heliotwin", "predict", "--scenario",
                           str(tmp_path / "missing.h5"), "--json", str(tmp_path / "o.json")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and len(proc.stderr.strip().splitlines()) == 1


def test_the_default_split_trains_on_every_image_and_the_latest_split_on_the_latest_dated_ones():
    """Default: every record with an image trains, in time order (undated ones after the dated), none is a test
    image; fewer than three images are refused (no cross-validation). ``train_latest``: latest by DateTime (an
    undated record counts as earlier than every dated one); ``train_first`` keeps the study's earliest split."""
    ids = [10, 11, 12, 13, 14, 15]
    times = ["2023-05-01T10:00:00", "", "2021-01-01T09:00:00", "2024-02-03T12:00:00", "2022-07-07T08:00:00", None]
    pngs = ["a", "b", "c", "d", None, "f"]
    tr, te = split_record_ids(ids, times, pngs)
    assert [ids[i] for i in tr] == [12, 10, 13, 11, 15] and te == []
    with pytest.raises(HeliotwinError, match="at least 3 to cross-validate"):
        split_record_ids(ids[:2], times[:2], pngs[:2])
    tr, te = split_record_ids(ids, times, pngs, train_latest=3)
    assert [ids[i] for i in tr] == [12, 10, 13] and sorted(ids[i] for i in te) == [11, 15]
    tr, te = split_record_ids(ids, times, pngs, train_latest=1)
    assert [ids[i] for i in tr] == [13]
    tr, _ = split_record_ids(ids, times, pngs, train_first=2)
    assert [ids[i] for i in tr] == [12, 10]
