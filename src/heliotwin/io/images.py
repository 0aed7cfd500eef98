"""Measured flux images: the one loader (read, resample to the comparison grid, normalise) and PAINT's window.

Every comparison of a measured image with a prediction (surface learning, image-based calibration,
validation) goes through :func:`load_measured_image`, so they all see the same pixels: the PNG read as
luminance (:func:`read_png`), NaNs and negatives set to 0, area-resampled to the
comparison grid (a 256x256 PAINT image becomes an exact 4x4 box average at 64x64), an optional background
floor removed, and the scale chosen by the caller (unit sum for normalised L1, unit max for display, or
the PNG's own relative scale).

Shapes: ``[rows, cols]`` images (PAINT orientation: row 0 at the top, column 0 at the east edge).
PNG files in and out (:func:`read_png`, :func:`to_png`) live here too; the window side
:data:`CENTERED_WINDOW_M` is the optics' constant (:mod:`heliotwin.raytrace.flux`), re-exported for readers.
"""
from __future__ import annotations

import io
import warnings

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError

from ..errors import HeliotwinError, InputFileError
from ..raytrace.flux import CENTERED_WINDOW_M
from .paint import read_regular
from .report import atomic_path

__all__ = ["CENTERED_WINDOW_M", "NORMALISATIONS", "MAX_IMAGE_PIXELS", "MAX_IMAGE_BYTES", "MIN_IMAGE_SIDE",
           "check_image_file", "load_measured_image", "read_png", "subtract_background", "to_png"]

#: Scalings :func:`load_measured_image` offers: unit sum, unit max, or the PNG's relative scale (None).
NORMALISATIONS = ("sum", "max", None)

#: Largest measured image [pixels] read (PAINT's are 64x64 and 256x256): bounded memory, no decompression bomb.
MAX_IMAGE_PIXELS = 4096 * 4096
#: Smallest side [pixels] of a measured image: below it there is no spot to compare (a 1x1 image would be a
#: "perfect match" of any prediction after normalisation).
MIN_IMAGE_SIDE = 8
#: Largest image file [bytes] read: a 4096x4096 16-bit colour PNG stored without compression is 96 MiB (PAINT's
#: are tens of kB). Checked on the open file before a byte is read (:func:`~heliotwin.io.paint.read_regular`).
MAX_IMAGE_BYTES = 128 * 2**20


def _file_bytes(path) -> io.BytesIO:
    """The bytes of the image file ``path``, read only if it is a regular file (a symbolic link to one is read as
    that file) of at most :data:`MAX_IMAGE_BYTES`: a FIFO named like a PNG would block ``open()`` forever, a
    link to ``/dev/zero`` would never end (:class:`InputFileError` naming the file instead)."""
    return io.BytesIO(read_regular(path, MAX_IMAGE_BYTES))


def check_image_file(path) -> tuple[int, int]:
    """Read only the header of an image file: ``(rows, cols)`` if it is an image of sane size.

    Raises
    ------
    InputFileError
        Missing, not a regular file or larger than :data:`MAX_IMAGE_BYTES`, not an image, or outside
        :data:`MIN_IMAGE_SIDE` .. :data:`MAX_IMAGE_PIXELS` (checked before a pixel is decoded, so a crafted
        14000x14000 PNG costs nothing).
    """
    return _check_header(path, _file_bytes(path))


def _check_header(path, data: io.BytesIO) -> tuple[int, int]:
    """``(rows, cols)`` of the image file ``path`` whose bytes are ``data`` (see :func:`check_image_file`)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(data) as img:
                cols, rows = img.size
    except Image.DecompressionBombError:
        raise InputFileError(path, f"image larger than the {MAX_IMAGE_PIXELS} pixels a flux image may have") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise InputFileError(path, f"not a readable image ({' '.join(str(exc).split()) or type(exc).__name__})") \
            from None
    data.seek(0)
    _check_size(path, rows, cols)
    return rows, cols


def _check_size(where, rows: int, cols: int) -> None:
    if rows * cols > MAX_IMAGE_PIXELS:
        raise InputFileError(where, f"image of {cols}x{rows} pixels is larger than the {MAX_IMAGE_PIXELS} pixels "
                                    f"a flux image may have")
    if min(rows, cols) < MIN_IMAGE_SIDE:
        raise InputFileError(where, f"image of {cols}x{rows} pixels is too small to hold a flux spot "
                                    f"(at least {MIN_IMAGE_SIDE} pixels a side)")


def subtract_background(image: torch.Tensor, level: float = 0.02) -> torch.Tensor:
    """Subtract a background level (fraction of each image's max) and clip at 0.

    Camera images carry a dark/background floor; the PAINT centred PNGs are already 0 outside the spot, so
    the default removes only the faint (< 2 % of max) halo of noise and quantisation.

    Parameters
    ----------
    image : torch.Tensor, [..., rows, cols]
    level : float
        Fraction of each image's maximum [-].

    Returns
    -------
    torch.Tensor, [..., rows, cols]
    """
    m = image.amax((-2, -1), keepdim=True)
    return (image - level * m).clamp_min(0.0)


def load_measured_image(source, resolution=None, *, normalise: str | None = None, background: float = 0.0,
                        square: bool = False, name=None) -> torch.Tensor:
    """A measured flux image on the comparison grid.

    Parameters
    ----------
    source : str, os.PathLike or torch.Tensor, [rows0, cols0]
        PNG path, or an image already in memory (any scale).
    resolution : int or (int, int), optional
        Comparison grid ``rows, cols`` (an int means square); None keeps the native size. Resampling is by
        area averaging (exact box means for integer factors, so no sub-pixel shift).
    normalise : {"sum", "max", None}
        Divide by the sum (normalised-L1 comparisons), by the max, or keep the relative PNG scale.
    background : float
        Background floor to subtract first, fraction of the max (:func:`subtract_background`); 0: none.
    square : bool
        Require a square image (PAINT's centred window).
    name : str or os.PathLike, optional
        What errors name for an in-memory ``source`` (default ``"<image>"``).

    Returns
    -------
    torch.Tensor, [rows, cols], float32

    Raises
    ------
    InputFileError
        One line naming the file: unreadable, too large or too small (:func:`check_image_file`), not square
        when ``square``, non-finite, empty (all zero) or uniform (no spot) after the background is removed.
    """
    if normalise not in NORMALISATIONS:
        raise ValueError(f"normalise must be one of {NORMALISATIONS}, got {normalise!r}")
    if isinstance(source, torch.Tensor):
        where = "<image>" if name is None else name
        img = source.detach().to(torch.float32)
        if img.dim() != 2:
            raise InputFileError(where, f"expected a 2-D image, got shape {list(img.shape)}")
        _check_size(where, *img.shape)
        if bool(torch.isinf(img).any()):
            raise InputFileError(where, "image holds infinite values")
    else:
        where = source
        data = _file_bytes(source)  # read once: the header checked, then decoded
        _check_header(source, data)
        img = _decode_png(source, data)
    img = torch.nan_to_num(img, nan=0.0).clamp_min(0.0)
    if square and img.shape[0] != img.shape[1]:
        raise InputFileError(where, f"expected a square centred image, got {list(img.shape)}")
    if resolution is not None:
        rows, cols = (resolution, resolution) if isinstance(resolution, int) else (int(r) for r in resolution)
        if tuple(img.shape) != (rows, cols):
            img = F.interpolate(img[None, None], size=(rows, cols), mode="area")[0, 0]
    if background > 0:
        img = subtract_background(img, background)
    if not bool(img.sum() > 0):
        raise InputFileError(where, "image is empty (all zero)")
    if bool(img.amin() == img.amax()):
        raise InputFileError(where, "image is uniform (no flux spot to compare)")
    if normalise == "sum":
        img = img / img.sum()
    elif normalise == "max":
        img = img / img.max()
    return img


def to_png(bitmap: torch.Tensor, path) -> None:
    """Write a bitmap as a max-normalised 8-bit grayscale PNG, atomically (temp file + rename).

    Parameters
    ----------
    bitmap : torch.Tensor, shape (rows, cols)
        Any non-negative values (e.g. W/m^2); an all-zero image is written black.
    path : str or os.PathLike
    """
    a = bitmap.detach().to(torch.float64).cpu()
    if a.dim() != 2:
        raise HeliotwinError(f"to_png expects a 2-D bitmap, got shape {tuple(a.shape)}")
    a = torch.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0).clamp(min=0.0)
    m = float(a.max()) if a.numel() else 0.0
    img = (a / m * 255.0).round() if m > 0 else torch.zeros_like(a)
    arr = img.clamp(0, 255).to(torch.uint8).numpy()
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")  # uint8 2-D -> mode "L"


def read_png(path) -> torch.Tensor:
    """Read a (grayscale or colour) PNG as luminance in [0, 1].

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    torch.Tensor, shape (rows, cols), float32
        8-bit images are divided by 255, 16-bit ones by 65535; colour images are converted to luminance.

    Raises
    ------
    InputFileError
        If the file is missing, not a regular file or larger than :data:`MAX_IMAGE_BYTES`, not a readable image,
        or of more than :data:`MAX_IMAGE_PIXELS` pixels.
    """
    return _decode_png(path, _file_bytes(path))


def _decode_png(path, data: io.BytesIO) -> torch.Tensor:
    """The luminance [rows, cols] of the image file ``path`` whose bytes are ``data`` (see :func:`read_png`)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(data) as img:
                cols, rows = img.size
                if rows * cols > MAX_IMAGE_PIXELS:  # before a pixel is decoded
                    raise Image.DecompressionBombError(f"{cols}x{rows}")
                img.load()
                if img.mode in ("I;16", "I;16B", "I;16L", "I"):
                    arr = np.asarray(img, dtype=np.float64)
                    scale = 65535.0 if img.mode.startswith("I;16") or arr.max(initial=0) > 255 else 255.0
                    arr = arr / scale
                else:
                    arr = np.asarray(img.convert("L"), dtype=np.float64) / 255.0
    except Image.DecompressionBombError:
        raise InputFileError(path, f"image larger than the {MAX_IMAGE_PIXELS} pixels a flux image may have") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        detail = str(exc).splitlines()[0] if str(exc) else ""
        raise InputFileError(path, f"unreadable image ({type(exc).__name__}: {detail})") from None
    return torch.from_numpy(np.ascontiguousarray(arr)).to(torch.float32)
