"""The read-ahead helper: a hint that never changes what is read, and leaves nothing behind."""
import glob
import os
import tempfile

import pytest

from heliotwin.io.readahead import read_ahead


def _files(tmp_path, n):
    paths = []
    for i in range(n):
        p = tmp_path / f"{i}-calibration-properties.json"
        p.write_text('{"a": %d}' % i)
        paths.append(str(p))
    return paths


def _leftovers():
    return set(glob.glob(os.path.join(tempfile.gettempdir(), "heliotwin-read-ahead-*")))


@pytest.mark.skipif(not hasattr(os, "posix_fadvise"), reason="posix_fadvise is Linux's")
def test_a_helper_runs_for_many_files_and_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.delenv("HELIOTWIN_READ_AHEAD", raising=False)
    before = _leftovers()
    paths = _files(tmp_path, 30) + [str(tmp_path / "gone.json")]  # a file that went: skipped by the helper
    with read_ahead(paths, min_files=10) as running:
        assert running
        texts = [open(p).read() for p in paths[:-1]]
    assert texts[7] == '{"a": 7}'
    assert _leftovers() == before  # its list file removed, the child reaped (wait() in the block's end)


def test_no_helper_for_few_files_or_when_switched_off(tmp_path, monkeypatch):
    paths = _files(tmp_path, 5)
    with read_ahead(paths, min_files=10) as running:
        assert not running
    monkeypatch.setenv("HELIOTWIN_READ_AHEAD", "0")
    with read_ahead(paths, min_files=1) as running:
        assert not running


def test_an_error_in_the_block_still_stops_the_helper(tmp_path):
    before = _leftovers()
    with pytest.raises(RuntimeError), read_ahead(_files(tmp_path, 20), min_files=1):
        raise RuntimeError("parser failed")
    assert _leftovers() == before
