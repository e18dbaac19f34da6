"""A thin-lens camera looking at a flat object through a TW sheet (docs/methods.md#virtual-camera).

Geometry (millimetres; z along the optical axis, which is the wood's T):

* the ideal thin lens (focal length f, aperture diameter A) lies at z = 0
  and is focused on the object plane at z = u (the objective distance); the
  sensor sits at z = -v with 1/u + 1/v = 1/f, and the magnification is v/u;
* the sheet's entrance face is at z = u - gap - thickness, its exit face at
  z = u - gap; the sheet is centred on the axis (width along R, length
  along L; ``r_axis`` says which sensor axis is R);
* images are shown upright: pixel (row i, column j) looks at the object
  point (x, y) = ((j - (nx-1)/2)·p, ((ny-1)/2 - i)·p) / magnification,
  p the pixel pitch (the sensor's real image is inverted; that flip is
  undone, nothing else).

Backward tracing: for each pixel, ``samples`` points on the aperture
(equal-area polar strata, one jittered point each, the pattern rotated per
pixel) start rays that the ideal lens sends toward the pixel's in-focus
object point.  Each ray crosses the air to the sheet, refracts into the
phase it meets, is traced through the wood (:func:`~pipeline.optics.trace.trace`),
refracts out into air, crosses the gap, and reads the object bilinearly.
The pixel value is the mean over its samples.  A sample whose ray does not
come out of the exit face (reflected back, total internal reflection at the
exit face, trapped, or out through the sheet's sides) sees no light: value 0,
counted per pixel as ``lost``.  The wood is generated without lateral bounds;
a ray counts as out through a side when it reaches the exit plane beyond the
sheet's width or length (rare: the field of view is 0.64 mm of a 1.5 × 1 mm
sheet in Figure 5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from .. import rng as _rng
from ..params import ParameterError, WoodParams
from ..optics.interface import TRANSMITTED
from ..optics.rays import Beam
from ..optics.settings import PRESETS, Optics, TraceSettings
from ..optics.trace import trace
from .targets import Target

APERTURE_KIND = _rng.APERTURE


@dataclass(frozen=True)
class Camera:
    """Thin-lens camera focused on the object plane."""

    focal_mm: float
    objective_mm: float  # lens to object plane
    aperture_mm: float  # aperture diameter
    pixels: tuple = (51, 51)  # (rows, columns)
    pitch_um: float = 0.5
    samples: int = 200  # aperture samples per pixel
    seed: int = 1

    def validate(self) -> "Camera":
        for name in ("focal_mm", "objective_mm", "aperture_mm", "pitch_um"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"`{name}` must be a number > 0, got {name}={v!r}")
        if not self.objective_mm > self.focal_mm:
            raise ParameterError(f"`objective_mm` must be > focal_mm = {self.focal_mm:g} mm for a real "
                                 f"image, got objective_mm={self.objective_mm:g}")
        if (len(self.pixels) != 2 or not all(isinstance(n, int) and 1 <= n <= 4096 for n in self.pixels)):
            raise ParameterError(f"`sensor_px` must be [rows, columns], each in [1, 4096], got {self.pixels!r}")
        if not (isinstance(self.samples, int) and 1 <= self.samples <= 100000):
            raise ParameterError(f"`samples` must be an integer in [1, 100000], got {self.samples!r}")
        return self

    @property
    def image_mm(self) -> float:
        """Lens-to-sensor distance v."""
        return self.focal_mm * self.objective_mm / (self.objective_mm - self.focal_mm)

    @property
    def magnification(self) -> float:
        return self.image_mm / self.objective_mm

    def object_points(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) [mm] of the in-focus object point of every pixel of ``rows`` (shape rows × columns)."""
        ny, nx = self.pixels
        p = self.pitch_um * 1e-3 / self.magnification
        i = np.asarray(rows, np.float64)[:, None]
        j = np.arange(nx, dtype=np.float64)[None, :]
        x = np.broadcast_to((j - 0.5 * (nx - 1)) * p, (i.size, nx))
        y = np.broadcast_to((0.5 * (ny - 1) - i) * p, (i.size, nx))
        return x, y


@dataclass(frozen=True)
class Sheet:
    """A TW sheet in front of the object."""

    wood: WoodParams
    seed: int
    voxel_um: float
    thickness_um: float
    width_um: float  # along R
    length_um: float  # along L
    ri_polymer: float
    delta_ri: float  # the wall's index minus the polymer's
    gap_um: float  # exit face to object plane
    r_axis: str = "x"  # the sensor axis along the wood's R

    @property
    def optics(self) -> Optics:
        """The sheet's optics: its two indices, lit from air."""
        return Optics.of_delta(self.ri_polymer, self.delta_ri, n_outside=1.0, seed=self.seed)

    def validate(self) -> "Sheet":
        self.optics.validate()
        for name in ("voxel_um", "thickness_um", "width_um", "length_um"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ParameterError(f"`{name}` must be > 0, got {name}={v!r}")
        if not (math.isfinite(self.gap_um) and self.gap_um >= 0):
            raise ParameterError(f"`gap_um` must be >= 0, got gap_um={self.gap_um!r}")
        if self.r_axis not in ("x", "y"):
            raise ParameterError(f"`r_axis` must be x or y (the sensor axis along R), got {self.r_axis!r}")
        if self.thickness_um < self.voxel_um:
            raise ParameterError(f"`thickness_mm` must be at least one voxel ({self.voxel_um:g} µm), "
                                 f"got {self.thickness_um:g} µm")
        return self


@njit(cache=True)
def _aperture_kernel(pixel_ids, samples, rings, seed):
    out = np.empty((pixel_ids.size, samples, 2))
    per_ring = samples // rings
    for p in range(pixel_ids.size):
        pid = pixel_ids[p]
        rot = 2.0 * math.pi * _rng.uniform(seed, APERTURE_KIND, pid, -1, 0)
        for s in range(samples):
            ring = s // per_ring
            sector = s - ring * per_ring
            u1 = _rng.uniform(seed, APERTURE_KIND, pid, s, 0)
            u2 = _rng.uniform(seed, APERTURE_KIND, pid, s, 1)
            r = math.sqrt((ring + u1) / rings)
            phi = rot + 2.0 * math.pi * (sector + u2) / per_ring
            out[p, s, 0] = r * math.cos(phi)
            out[p, s, 1] = r * math.sin(phi)
    return out


def strata(samples: int) -> tuple[int, int]:
    """(rings, sectors per ring): equal-area strata, about twice as many sectors as rings."""
    rings = max(k for k in range(1, int(math.isqrt(max(samples // 2, 1))) + 1) if samples % k == 0)
    return rings, samples // rings


def aperture_samples(pixel_ids: np.ndarray, samples: int, seed: int) -> np.ndarray:
    """Points on the unit disc, (pixels, samples, 2): one per equal-area stratum, jittered,
    the pattern rotated by a per-pixel angle; a hash of (seed, pixel, sample)."""
    rings, _ = strata(samples)
    return _aperture_kernel(np.asarray(pixel_ids, np.int64), int(samples), rings, np.uint64(seed))


@dataclass
class RowsImage:
    """What one block of sensor rows saw."""

    rows: np.ndarray
    image: np.ndarray  # (rows, columns) mean over samples
    lost: np.ndarray  # (rows, columns) samples that saw no light
    interfaces: float  # interfaces met, summed over rays
    chunks_loaded: int


def render_rows(camera: Camera, sheet: Sheet | None, target: Target, rows, *,
                settings: TraceSettings | None = None, medium=None) -> RowsImage:
    """Render the sensor rows ``rows`` (backward tracing, docs/methods.md#virtual-camera).

    ``medium`` is the sheet's wood as the medium ``settings`` traces
    (:func:`pipeline.optics.media.wood_medium` of ``sheet``); it may be omitted
    when ``sheet`` is None (nothing between lens and object).
    """
    rows = np.asarray(rows, np.int64)
    # Angles are needed in air, after the exit face.
    settings = replace(settings if settings is not None else PRESETS["fast"], exit="air")
    ny, nx = camera.pixels
    S = camera.samples
    xo, yo = camera.object_points(rows)
    pid = (rows[:, None] * nx + np.arange(nx)[None, :]).reshape(-1)
    ap = aperture_samples(pid, S, camera.seed) * (0.5 * camera.aperture_mm)  # (P, S, 2)
    u = camera.objective_mm
    # After the ideal lens every ray of a pixel heads for its in-focus object point.
    d = np.empty(ap.shape[:2] + (3,))
    d[..., 0] = xo.reshape(-1, 1) - ap[..., 0]
    d[..., 1] = yo.reshape(-1, 1) - ap[..., 1]
    d[..., 2] = u
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    lost = np.zeros(pid.size * S, bool)
    interfaces = 0.0
    loads = 0
    if sheet is None:
        t = u / d[..., 2]
        hit_x = (ap[..., 0] + t * d[..., 0]).reshape(-1)
        hit_y = (ap[..., 1] + t * d[..., 1]).reshape(-1)
    else:
        mm = 1e-3
        z0 = u - (sheet.gap_um + sheet.thickness_um) * mm
        if z0 <= 0:
            raise ParameterError(f"the sheet must lie between the lens and the object: gap + thickness "
                                 f"= {(sheet.gap_um + sheet.thickness_um) * mm:g} mm >= objective "
                                 f"distance {u:g} mm")
        t = z0 / d[..., 2]
        ex = (ap[..., 0] + t * d[..., 0]).reshape(-1)
        ey = (ap[..., 1] + t * d[..., 1]).reshape(-1)
        dd = d.reshape(-1, 3)
        # Camera (x, y, z) → wood (R, T, L); the sheet is centred on the wood's origin.
        r_is_x = sheet.r_axis == "x"
        er, el = (ex, ey) if r_is_x else (ey, ex)
        dr, dl = (dd[:, 0], dd[:, 1]) if r_is_x else (dd[:, 1], dd[:, 0])
        origins = np.column_stack([er / mm, np.zeros_like(er), el / mm])  # [µm]
        dirs = np.column_stack([dr, dd[:, 2], dl])
        ids = (pid[:, None] * S + np.arange(S)[None, :]).reshape(-1)
        res = trace(medium, Beam(origins, dirs, ids),
                    sheet.optics, settings)
        interfaces = float(res.events.sum())
        loads = res.diagnostics.get("chunks_loaded", 0)
        xr = res.position[:, 0] * mm
        xl = res.position[:, 2] * mm
        out = res.exit_direction
        gap = sheet.gap_um * mm
        with np.errstate(divide="ignore", invalid="ignore"):
            hr = xr + gap * out[:, 0] / out[:, 1]
            hl = xl + gap * out[:, 2] / out[:, 1]
        hit_x, hit_y = (hr, hl) if r_is_x else (hl, hr)
        lost = ((res.status != TRANSMITTED)
                | (np.abs(xr) > 0.5 * sheet.width_um * mm) | (np.abs(xl) > 0.5 * sheet.length_um * mm))
    value = np.where(lost, 0.0, target.lookup(np.where(lost, 0.0, hit_x), np.where(lost, 0.0, hit_y)))
    image = value.reshape(rows.size, nx, S).mean(axis=-1)
    return RowsImage(rows, image, lost.reshape(rows.size, nx, S).sum(axis=-1), interfaces, loads)


def ideal_image(camera: Camera, target: Target) -> np.ndarray:
    """The ideal thin-lens image: the object read at each pixel's in-focus point."""
    x, y = camera.object_points(np.arange(camera.pixels[0]))
    return target.lookup(x, y)
