"""Flat objects the virtual camera looks at (docs/methods.md#virtual-camera).

A :class:`Target` is a grey-level raster (1 = light, 0 = dark) of a given
physical size, centred on the optical axis in the object plane; beyond its
edges the plane has the target's ``background`` level.  The camera reads it
by bilinear interpolation (:meth:`Target.lookup`).

Built-in targets are drawn from exact geometry with 4 × 4 supersampling:
dark characters on a light card (a 5 × 7 stroke font), a dark square, a bar
target, a Siemens star, and a dark quadrant for edge-spread widths.  Any PNG (converted to grey levels) can be used
with its physical size.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..params import ParameterError

RASTER = 512  # raster pixels across a built-in target
SUPERSAMPLE = 4

# 5 × 7 stroke font: '#' is ink.  Characters are centred on the card with a
# margin of one stroke around the 5 × 7 cell grid (7 × 9 cells across).
GLYPHS = {
    "T": ["#####", "..#..", "..#..", "..#..", "..#..", "..#..", "..#.."],
    "F": ["#####", "#....", "#....", "####.", "#....", "#....", "#...."],
    "E": ["#####", "#....", "#....", "####.", "#....", "#....", "#####"],
    "L": ["#....", "#....", "#....", "#....", "#....", "#....", "#####"],
    "H": ["#...#", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"],
    "P": ["####.", "#...#", "#...#", "####.", "#....", "#....", "#...."],
    "4": ["...#.", "..##.", ".#.#.", "#..#.", "#####", "...#.", "...#."],
    "7": ["#####", "....#", "...#.", "..#..", ".#...", ".#...", ".#..."],
}


@dataclass(frozen=True)
class Target:
    """A flat object: ``raster[row, col]`` covers width × height mm, row 0 at the top (+y)."""

    name: str
    raster: np.ndarray
    width_mm: float
    height_mm: float
    background: float = 1.0

    def lookup(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Bilinear interpolation at object-plane points (x right, y up, origin on the axis)."""
        ny, nx = self.raster.shape
        # Raster pixel centres sit at (col + 0.5, row + 0.5) of the card.
        col = (np.asarray(x_mm) / self.width_mm + 0.5) * nx - 0.5
        row = (0.5 - np.asarray(y_mm) / self.height_mm) * ny - 0.5
        # One background pixel around the card; beyond it the clip reads background too.
        padded = np.pad(self.raster, 1, constant_values=self.background)
        c = np.clip(col + 1.0, 0.0, nx + 1.0)
        r = np.clip(row + 1.0, 0.0, ny + 1.0)
        c0 = np.minimum(np.floor(c).astype(np.int64), nx)
        r0 = np.minimum(np.floor(r).astype(np.int64), ny)
        fc = c - c0
        fr = r - r0
        top = padded[r0, c0] * (1 - fc) + padded[r0, c0 + 1] * fc
        bottom = padded[r0 + 1, c0] * (1 - fc) + padded[r0 + 1, c0 + 1] * fc
        return top * (1 - fr) + bottom * fr

    def digest(self) -> str:
        h = hashlib.sha256(np.ascontiguousarray(self.raster, np.float64).tobytes())
        h.update(repr((self.width_mm, self.height_mm, self.background)).encode())
        return h.hexdigest()[:16]


def _draw(inside, size_mm: float, n: int = RASTER) -> np.ndarray:
    """Coverage of the dark shape ``inside(x, y)`` (coordinates in [-0.5, 0.5]) → 1 - coverage."""
    s = SUPERSAMPLE
    u = (np.arange(n * s) + 0.5) / (n * s) - 0.5
    x, y = np.meshgrid(u, -u)
    ink = inside(x, y).astype(np.float64).reshape(n, s, n, s).mean(axis=(1, 3))
    return 1.0 - ink


def _glyph(char: str):
    rows = GLYPHS[char]
    grid = np.array([[c == "#" for c in row] for row in rows])
    cell = 1.0 / 9.0  # 7 × 9 cells: a stroke's margin on every side of the 5 × 7 glyph

    def inside(x, y):
        col = np.floor((x + 0.5 * 5 * cell) / cell).astype(np.int64)
        row = np.floor((0.5 * 7 * cell - y) / cell).astype(np.int64)
        ok = (col >= 0) & (col < 5) & (row >= 0) & (row < 7)
        out = np.zeros(x.shape, bool)
        out[ok] = grid[row[ok], col[ok]]
        return out

    return inside


def _bars(n_bars: int):
    # n dark vertical bars, equal to the gaps, over the central 80 % of the card.
    def inside(x, y):
        period = 0.8 / (2 * n_bars - 1)
        k = np.floor((x + 0.4) / period)
        return (np.abs(x) < 0.4) & (np.abs(y) < 0.4) & (k % 2 == 0)

    return inside


def _star(spokes: int):
    def inside(x, y):
        phi = np.arctan2(y, x)
        r = np.hypot(x, y)
        return (r < 0.45) & (np.floor(phi / (np.pi / spokes)) % 2 == 0)

    return inside


def _quadrant(x, y):
    return (x < 0) & (y < 0)


def _square(fraction: float):
    return lambda x, y: (np.abs(x) < fraction / 2) & (np.abs(y) < fraction / 2)


def make_target(spec: dict, *, base: Path | None = None) -> Target:
    """A target from its description.

    ``spec`` keys: ``kind`` (``char``, ``square``, ``quadrant`` (dark for
    x < 0 and y < 0: one straight edge along each axis), ``bars``, ``star``
    or ``png``), ``size_mm`` (the card's side, or ``[width, height]``),
    ``char`` (for ``char``), ``n`` (bars or spokes), ``fraction`` (the
    square's side over the card's), ``path`` (PNG, relative to ``base``),
    ``background`` (the plane beyond the card, default 1 = light).
    """
    known = {"kind", "size_mm", "char", "n", "fraction", "path", "background"}
    for k in spec:
        if k not in known:
            raise ParameterError(f"unknown key `object.{k}` (known: {', '.join(sorted(known))})")
    kind = spec.get("kind")
    size = spec.get("size_mm")
    if isinstance(size, (int, float)) and not isinstance(size, bool):
        size = [size, size]
    if (not isinstance(size, list) or len(size) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in size)):
        raise ParameterError(f"`object.size_mm` must be a positive size or [width, height] in mm, "
                             f"got {spec.get('size_mm')!r}")
    background = spec.get("background", 1.0)
    if isinstance(background, bool) or not isinstance(background, (int, float)) or not 0 <= background <= 1:
        raise ParameterError(f"`object.background` must be a grey level in [0, 1], got {background!r}")
    w, h = float(size[0]), float(size[1])
    n = spec.get("n", 8 if kind == "bars" else 16)
    if kind in ("bars", "star") and (isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 200):
        raise ParameterError(f"`object.n` must be an integer in [1, 200], got {n!r}")
    if kind == "char":
        char = spec.get("char")
        if char not in GLYPHS:
            raise ParameterError(f"`object.char` must be one of {', '.join(GLYPHS)}, got {char!r}")
        return Target(f"char-{char}", _draw(_glyph(char), w), w, h, float(background))
    if kind == "square":
        fraction = spec.get("fraction", 0.5)
        if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0 < fraction <= 1:
            raise ParameterError(f"`object.fraction` must be in (0, 1], got {fraction!r}")
        return Target("square", _draw(_square(float(fraction)), w), w, h, float(background))
    if kind == "quadrant":
        return Target("quadrant", _draw(_quadrant, w), w, h, float(background))
    if kind == "bars":
        return Target(f"bars-{n}", _draw(_bars(n), w), w, h, float(background))
    if kind == "star":
        return Target(f"star-{n}", _draw(_star(n), w), w, h, float(background))
    if kind == "png":
        from PIL import Image

        path = spec.get("path")
        if not isinstance(path, str):
            raise ParameterError(f"`object.path` must name a PNG file, got {path!r}")
        p = Path(path)
        if base is not None and not p.is_absolute():
            p = base / p
        try:
            with Image.open(p) as im:
                raster = np.asarray(im.convert("L"), np.float64) / 255.0
        except (OSError, ValueError) as exc:
            raise ParameterError(f"`object.path` must be a readable PNG, got {str(p)!r} ({exc})") from None
        return Target(p.stem, raster, w, h, float(background))
    raise ParameterError(f"`object.kind` must be one of char, square, quadrant, bars, star, png, got {kind!r}")
