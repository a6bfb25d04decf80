"""Pressure maps and label images as PNG files, with only zlib, struct and numpy.

No Pillow or matplotlib: the appliance runs on a small board and only the
command line imports this module. Images are 8-bit RGBA, one IDAT chunk,
filter type 0 on every row.

>>> import numpy as np
>>> encode_png(np.zeros((1, 1, 4), dtype=np.uint8))[:8]
b'\\x89PNG\\r\\n\\x1a\\n'
>>> colourise(np.array([[-1.0, 0.0, 1.0, np.nan]]), -1.0, 1.0)[0].tolist()
[[0, 0, 255, 255], [255, 255, 255, 255], [255, 0, 0, 255], [0, 0, 0, 0]]
"""

import math
import struct
import zlib
from pathlib import Path

import numpy as np

from appliance.errors import ModelInputInvalid
from appliance.files import write_atomic

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
WHITE = (255, 255, 255)
DIVERGING_NEGATIVE = (0, 0, 255)  # pure blue at -max(|vmin|, |vmax|)
DIVERGING_POSITIVE = (255, 0, 0)  # pure red at +max(|vmin|, |vmax|)
SEQUENTIAL_HIGH = (8, 48, 107)  # dark blue at vmax (ColorBrewer "Blues" darkest step)
# Okabe-Ito colour-blind-safe, opaque: water sky blue, resistive orange, conductive bluish green.
LABEL_COLOURS = {0: (86, 180, 233, 255), 1: (230, 159, 0, 255), 2: (0, 158, 115, 255)}


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def _image(values) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    if v.ndim != 2:
        raise ModelInputInvalid(f"values must be a 2-D (H, W) array, got shape {v.shape}")
    return v


def encode_png(rgba: np.ndarray) -> bytes:
    """Encode an RGBA image as PNG bytes.

    Parameters
    ----------
    rgba : np.ndarray, shape (H, W, 4), dtype uint8
        Pixels, row 0 at the top; channels red, green, blue, alpha (0 transparent).

    Returns
    -------
    bytes
        A complete PNG file: 8-bit RGBA (colour type 6), filter type 0, one IDAT chunk.
    """
    a = np.asarray(rgba)
    if a.ndim != 3 or a.shape[2] != 4 or a.dtype != np.uint8 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ModelInputInvalid(f"encode_png needs a non-empty (H, W, 4) uint8 array, got {a.shape} {a.dtype}")
    height, width = a.shape[:2]
    rows = np.concatenate([np.zeros((height, 1), np.uint8), a.reshape(height, width * 4)], axis=1)
    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows.tobytes(), 9))
            + _chunk(b"IEND", b""))


def colourise(values: np.ndarray, vmin: float, vmax: float, palette: str = "diverging") -> np.ndarray:
    """Map a scalar image to RGBA colours.

    Parameters
    ----------
    values : np.ndarray, shape (H, W), float
        Pixel values in display units (pressure change, or the 0 to 100 scale);
        NaN marks pixels outside the sensor sheet and becomes fully transparent.
    vmin, vmax : float
        Display range, finite with ``vmin < vmax``; values are clipped to it.
    palette : {"diverging", "sequential"}
        ``"diverging"``: white (255, 255, 255) at 0, linear to pure blue (0, 0, 255)
        at ``-s`` and pure red (255, 0, 0) at ``+s``, with ``s = max(|vmin|, |vmax|)``,
        so equal magnitudes get equal intensity on either side of zero.
        ``"sequential"``: white at ``vmin``, linear to dark blue (8, 48, 107) at ``vmax``.

    Returns
    -------
    np.ndarray, shape (H, W, 4), dtype uint8
        Opaque colours for finite pixels, (0, 0, 0, 0) for NaN pixels.
    """
    v = _image(values)
    if not (math.isfinite(vmin) and math.isfinite(vmax)) or vmin >= vmax:
        raise ModelInputInvalid(f"display range needs finite vmin < vmax, got vmin={vmin}, vmax={vmax}")
    nan = np.isnan(v)
    clipped = np.clip(np.where(nan, 0.0, v), vmin, vmax)
    white = np.array(WHITE, float)
    if palette == "diverging":
        t = clipped / max(abs(vmin), abs(vmax))  # in [-1, 1]; 0 stays white
        end = np.where((t < 0)[..., None], DIVERGING_NEGATIVE, DIVERGING_POSITIVE)
        rgb = white + np.abs(t)[..., None] * (end - white)
    elif palette == "sequential":
        t = (clipped - vmin) / (vmax - vmin)
        rgb = white + t[..., None] * (np.array(SEQUENTIAL_HIGH, float) - white)
    else:
        raise ModelInputInvalid(f"unknown palette {palette!r}: use 'diverging' or 'sequential'")
    out = np.concatenate([np.rint(rgb), np.full(v.shape + (1,), 255.0)], axis=-1).astype(np.uint8)
    out[nan] = 0
    return out


def labels_to_rgba(labels: np.ndarray) -> np.ndarray:
    """Colour a label image: 0 water, 1 resistive, 2 conductive.

    Parameters
    ----------
    labels : np.ndarray, shape (H, W), integer values 0, 1 or 2

    Returns
    -------
    np.ndarray, shape (H, W, 4), dtype uint8
        Opaque: sky blue (86, 180, 233), orange (230, 159, 0), bluish green (0, 158, 115).
    """
    a = np.asarray(labels)
    if a.ndim != 2:
        raise ModelInputInvalid(f"labels must be a 2-D (H, W) array, got shape {a.shape}")
    bad = ~np.isin(a, list(LABEL_COLOURS))
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise ModelInputInvalid(f"label {a[row, col].item()} at row {row}, column {col} is not 0 (water), "
                                "1 (resistive) or 2 (conductive)")
    table = np.array([LABEL_COLOURS[k] for k in sorted(LABEL_COLOURS)], np.uint8)
    return table[a.astype(np.intp)]


def write_png(path, values, *, vmin=None, vmax=None, palette="diverging", scale=1) -> None:
    """Colourise a scalar image, enlarge it and write it as a PNG file.

    Parameters
    ----------
    path : str or os.PathLike
        File to write (replaced whole, never left half-written).
    values : array_like, shape (H, W), float
        As for `colourise`; NaN pixels are transparent.
    vmin, vmax : float, optional
        Display range. Defaults: ``-m`` and ``+m`` with ``m`` the largest finite
        ``|value|`` for "diverging", the finite data range for "sequential";
        1 stands in for an empty or zero-width range (all-NaN or constant image).
    palette : {"diverging", "sequential"}
    scale : int, >= 1
        Each pixel becomes a ``scale`` x ``scale`` block (nearest neighbour),
        so the file is (H * scale, W * scale) pixels.
    """
    v = _image(values)
    if isinstance(scale, bool) or not isinstance(scale, (int, np.integer)) or scale < 1:
        raise ModelInputInvalid(f"scale must be an integer >= 1, got {scale!r}")
    finite = v[np.isfinite(v)]
    if palette == "diverging":
        m = float(np.max(np.abs(finite))) if finite.size else 0.0
        low, high = (-m, m) if m > 0 else (-1.0, 1.0)
    else:
        low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        high = high if high > low else low + 1.0
    rgba = colourise(v, low if vmin is None else vmin, high if vmax is None else vmax, palette)
    rgba = np.repeat(np.repeat(rgba, int(scale), axis=0), int(scale), axis=1)
    write_atomic(Path(path), encode_png(rgba))


def write_image(path: Path, image, normalise: bool) -> None:
    """The image as CSV (``nan`` off the sheet) or PNG; ``normalise`` maps it to 0-100 (eq. 3.4.3).

    A PNG shows log(sigma / sigma_ref), which is the relative change for small changes and
    keeps an insulator (at most -1) as visible beside a conductor (unbounded) as it deserves.
    """
    if normalise:
        low, high = np.nanmin(image), np.nanmax(image)
        image = 100.0 * (image - low) / (high - low) if high > low else np.zeros_like(image)
    if path.suffix.lower() == ".png":
        shown = image if normalise else np.log(np.clip(1.0 + image, 1e-6, None))
        write_png(path, shown, palette="sequential" if normalise else "diverging", scale=16)
    else:
        path.write_text("\n".join(",".join("nan" if np.isnan(v) else f"{v:.6g}" for v in row) for row in image)
                        + "\n")
