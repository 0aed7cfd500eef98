"""Measured flux images are read only from regular files (issue 41): a FIFO named like a PNG, a link to a device,
or a huge file is refused in one line naming it, before a byte is read, and nothing blocks; a symbolic link to a
real PNG is read as that PNG."""
from __future__ import annotations

import os
import threading

import numpy as np
import pytest
import torch
from PIL import Image

from heliotwin.errors import InputFileError
from heliotwin.io import images
from heliotwin.io.images import MAX_IMAGE_BYTES, check_image_file, load_measured_image, read_png

READERS = {"read_png": read_png, "check_image_file": check_image_file,
           "load_measured_image": lambda p: load_measured_image(p, 16, normalise="sum")}


def _refusal(reader, path) -> str:
    """The one-line refusal of ``reader(path)``, run in a thread so that a blocking open fails the test instead
    of hanging it."""
    got = {}

    def run():
        try:
            reader(path)
            got["result"] = "read"
        except InputFileError as exc:
            got["result"] = str(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(20.0)
    if t.is_alive():  # unblock the open (a writer end) so the thread ends, then fail
        with open(os.open(path, os.O_WRONLY | os.O_NONBLOCK), "wb"):
            pass
        pytest.fail(f"reading {path} blocked")
    return got["result"]


def _spot_png(path, side=32):
    y, x = np.mgrid[:side, :side]
    img = (255 * np.exp(-((x - side / 2) ** 2 + (y - side / 3) ** 2) / 20.0)).astype(np.uint8)
    Image.fromarray(img).save(path)
    return img


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs")
@pytest.mark.parametrize("reader", list(READERS))
def test_a_fifo_named_like_a_png_is_refused_at_once_naming_it(tmp_path, reader):
    fifo = tmp_path / "100330-flux-centered.png"
    os.mkfifo(fifo)
    text = _refusal(READERS[reader], fifo)
    assert "100330-flux-centered.png" in text and "not a regular file" in text and "\n" not in text, text


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="a device to link to")
@pytest.mark.parametrize("reader", list(READERS))
def test_a_link_to_a_device_is_refused_naming_the_link(tmp_path, reader):
    link = tmp_path / "zero-flux-centered.png"
    link.symlink_to("/dev/zero")
    text = _refusal(READERS[reader], link)
    assert "zero-flux-centered.png" in text and "not a regular file" in text, text


@pytest.mark.parametrize("reader", list(READERS))
def test_a_huge_file_is_refused_by_its_size_before_it_is_read(tmp_path, reader, monkeypatch):
    big = tmp_path / "big-flux-centered.png"
    _spot_png(big)
    with open(big, "r+b") as fh:  # a valid PNG's header, then sparse bytes up to one past the cap (no disk used)
        fh.truncate(MAX_IMAGE_BYTES + 1)
    read = []
    real = os.read
    monkeypatch.setattr(os, "read", lambda fd, n: (read.append(n), real(fd, n))[1])
    text = _refusal(READERS[reader], big)
    assert "big-flux-centered.png" in text and str(MAX_IMAGE_BYTES) in text.replace(",", ""), text
    assert read == []  # refused on the open file's size, not after reading 128 MiB


def test_a_link_to_a_real_png_elsewhere_is_read_as_that_png(tmp_path):
    target = tmp_path / "elsewhere" / "spot.png"
    target.parent.mkdir()
    img = _spot_png(target)
    link = tmp_path / "paint" / "100330-flux-centered.png"
    link.parent.mkdir()
    link.symlink_to(target)
    assert torch.equal(read_png(link), torch.from_numpy(img.astype(np.float32) / 255.0))
    assert check_image_file(link) == (32, 32)
    got = load_measured_image(link, 16, normalise="sum")
    assert got.shape == (16, 16) and abs(float(got.sum()) - 1.0) < 1e-5
    assert torch.equal(got, load_measured_image(target, 16, normalise="sum"))


def test_an_image_is_read_once_for_its_header_and_pixels(tmp_path, monkeypatch):
    path = tmp_path / "spot.png"
    _spot_png(path)
    calls = []
    real = images.read_regular
    monkeypatch.setattr(images, "read_regular", lambda *a, **kw: (calls.append(a[0]), real(*a, **kw))[1])
    load_measured_image(path, 16)
    assert calls == [path]
