"""The sample's two faces, handled once for every medium (docs/methods.md#media).

A backend (the voxel march, or a surface medium's own march) gives the phase at
each entry point and marches the interior; :func:`through_faces` does the rest
the same way for all: a ray starting outside a finite volume leaves through a
side; refraction from the outside medium into the phase each ray enters (total
reflection there: reflected); the rays that leave through the exit face
refracted into air (``settings.exit``; total reflection there: "tir at exit
face"); and the direction an undeflected ray would leave in, from which haze
is measured.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from .interface import ACTIVE, REFLECTED, SIDE, TIR_EXIT, TRANSMITTED, enter_from, leave_into_air
from .rays import RayResult
from .settings import Optics, TraceSettings

NO_PHASE = 255  # an entry point outside the medium's volume


class Interior(Protocol):
    """What a backend does between the faces, in one unit of length for positions and paths."""

    def entry_phase(self, origins: np.ndarray) -> np.ndarray:
        """The phase (1 wall, 0 polymer; NO_PHASE outside the volume) at each entry point."""

    def march(self, origins: np.ndarray, dirs: np.ndarray, phase: np.ndarray, ray_ids: np.ndarray, *,
              optics: Optics, settings: TraceSettings) -> tuple[dict, dict]:
        """Rays from their entry points (T = 0), directions inside the sample, in phase ``phase``, to
        where they end: per-ray ``position``, ``direction``, ``status``, ``events``, ``path``,
        ``medium`` (the phase each ends in) and the backend's own per-ray arrays; and the
        backend's numbers of the whole trace (RayResult.diagnostics)."""


def through_faces(interior: Interior, origins: np.ndarray, dirs: np.ndarray, ray_ids: np.ndarray,
                  optics: Optics, settings: TraceSettings) -> RayResult:
    """Trace rays entering the T = 0 face at ``origins`` (their T taken as 0) with unit
    directions ``dirs`` (in ``optics.n_outside``, or inside the sample without one) through
    ``interior``; positions and lengths in the interior's unit."""
    n = len(ray_ids)
    dirs = np.array(dirs, np.float64, copy=True)
    position = np.array(origins, np.float64, copy=True).reshape(-1, 3)
    position[:, 1] = 0.0
    phase = np.asarray(interior.entry_phase(position), np.uint8)
    status = np.full(n, ACTIVE, np.int64)
    status[phase == NO_PHASE] = SIDE
    phase = np.where(phase == NO_PHASE, 0, phase).astype(np.uint8)
    n_entry = np.where(phase == 1, optics.n_wall, optics.n_poly)
    if optics.n_outside is not None:
        reflected = enter_from(dirs, n_entry, float(optics.n_outside)) == REFLECTED
        status[reflected & (status == ACTIVE)] = REFLECTED
    entered = dirs.copy()
    live = np.flatnonzero(status == ACTIVE)
    out, diagnostics = interior.march(position[live], dirs[live], phase[live], ray_ids[live], optics=optics,
                                      settings=settings)
    direction = dirs.copy()
    events, path = np.zeros(n, np.int64), np.zeros(n)
    medium = phase.copy()
    for name, arr in (("position", position), ("direction", direction), ("status", status), ("events", events),
                      ("path", path), ("medium", medium)):
        arr[live] = out.pop(name)
    extras = {"medium": medium}
    for name, arr in out.items():
        full = np.zeros((n,) + arr.shape[1:], arr.dtype)
        full[live] = arr
        extras[name] = full
    exit_dirs, incident = direction.copy(), entered
    if settings.exit == "air":
        done = status == TRANSMITTED
        exit_dirs, tir = leave_into_air(direction, np.where(medium == 1, optics.n_wall, optics.n_poly), done)
        status[done & tir] = TIR_EXIT
        # Undeflected, a ray keeps the phase and direction it entered with: it leaves along the
        # beam's own direction in air (Snell both ways).
        incident, blocked = leave_into_air(entered, n_entry, np.ones(n, bool))
        incident[blocked] = np.nan
    return RayResult(position, direction, exit_dirs, status, events, path, settings, incident, extras=extras,
                     diagnostics=diagnostics)
