"""Geometry statistics of a binary wood volume, for comparing generators by measurement.

The volume is indexed ``[R, T, L]`` (radial, tangential, longitudinal), with
non-zero = cell wall and 0 = polymer (lumen), on an isotropic grid of
``voxel_um`` micrometres.  Only numpy and scipy are used, so any generator's
output (twray's stores, another program's NRRD files) can be measured the same
way.  :func:`volume_statistics` states every definition in its docstring.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

#: Lumens whose equivalent diameter exceeds this are vessels [µm].
VESSEL_DIAMETER_UM = 30.0
#: Lumens smaller than this equivalent diameter are dropped as specks [µm].
MIN_LUMEN_DIAMETER_UM = 2.0
#: A lumen is ray-like when its R extent is at least this multiple of its T extent ...
RAY_ASPECT = 2.0
#: ... and its R extent is at least this long [µm].
RAY_MIN_LENGTH_UM = 12.0


def _interior_wall_runs(wall: np.ndarray, axis: int) -> np.ndarray:
    """Lengths [voxels] of the runs of wall along ``axis`` bounded by polymer on both sides.

    Runs touching either end of their line are left out (their extent is unknown).
    """
    w = np.moveaxis(wall, axis, -1).reshape(-1, wall.shape[axis]).astype(np.int8)
    # A sentinel column (2) ends every line, so no run continues onto the next line.
    flat = np.concatenate([w, np.full((w.shape[0], 1), 2, np.int8)], axis=1).ravel()
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    starts = np.concatenate([[0], change])
    lengths = np.diff(np.concatenate([starts, [flat.size]]))
    values = flat[starts]
    prev = np.concatenate([[2], values[:-1]])
    nxt = np.concatenate([values[1:], [2]])
    keep = (values == 1) & (prev == 0) & (nxt == 0)
    return lengths[keep]


def _quartiles(x: np.ndarray) -> tuple[float, float, float]:
    if x.size == 0:
        return (float("nan"),) * 3
    q25, q50, q75 = np.percentile(x, [25.0, 50.0, 75.0])
    return float(q25), float(q50), float(q75)


def lumen_table(slice_rt: np.ndarray, voxel_um: float) -> dict[str, np.ndarray]:
    """Per-lumen measurements of one R-T slice (non-zero = wall).

    Lumens are the 4-connected polymer regions.  Returns arrays, one entry per
    lumen: ``d_um`` (equivalent diameter 2 sqrt(A/π)), ``area_um2``,
    ``len_r_um`` and ``len_t_um`` (bounding-box extents), ``border`` (touches
    any slice edge) and ``t_border`` (touches a T edge).
    """
    lab, n = ndi.label(slice_rt == 0)
    if n == 0:
        e = np.zeros(0)
        return {"d_um": e, "area_um2": e, "len_r_um": e, "len_t_um": e,
                "border": e.astype(bool), "t_border": e.astype(bool)}
    area = np.bincount(lab.ravel(), minlength=n + 1)[1:] * voxel_um**2
    boxes = ndi.find_objects(lab)
    len_r = np.array([b[0].stop - b[0].start for b in boxes]) * voxel_um
    len_t = np.array([b[1].stop - b[1].start for b in boxes]) * voxel_um
    nr, nt = slice_rt.shape
    r_border = np.array([b[0].start == 0 or b[0].stop == nr for b in boxes])
    t_border = np.array([b[1].start == 0 or b[1].stop == nt for b in boxes])
    return {"d_um": 2.0 * np.sqrt(area / np.pi), "area_um2": area, "len_r_um": len_r,
            "len_t_um": len_t, "border": r_border | t_border, "t_border": t_border}


def is_ray_like(tab: dict[str, np.ndarray]) -> np.ndarray:
    """Ray-cell lumens of a :func:`lumen_table`: elongated along R, not cut by a T edge.

    R extent ≥ ``RAY_ASPECT`` × T extent and ≥ ``RAY_MIN_LENGTH_UM``, equivalent
    diameter ≥ ``MIN_LUMEN_DIAMETER_UM`` and ≤ ``VESSEL_DIAMETER_UM``.  Touching an
    R edge is allowed (rays run along R and leave the sample there).
    """
    return ((tab["len_r_um"] >= RAY_ASPECT * tab["len_t_um"])
            & (tab["len_r_um"] >= RAY_MIN_LENGTH_UM) & ~tab["t_border"]
            & (tab["d_um"] >= MIN_LUMEN_DIAMETER_UM) & (tab["d_um"] <= VESSEL_DIAMETER_UM))


def wall_normals_l(wall: np.ndarray, sigma_vox: float = 1.0) -> np.ndarray:
    """|n_L| of the wall normal at the wall-surface voxels.

    The normal is the gradient of the wall indicator smoothed by a Gaussian of
    ``sigma_vox`` voxels (edges: nearest), normalised.  Surface voxels are wall
    voxels with a polymer 6-neighbour; the sample's own faces do not count.
    """
    g = ndi.gaussian_filter(wall.astype(np.float32), sigma_vox, mode="nearest")
    surface = wall & ~ndi.binary_erosion(wall, border_value=1)
    gr, gt, gl = (np.gradient(g, axis=a)[surface] for a in range(3))
    norm = np.sqrt(gr * gr + gt * gt + gl * gl)
    ok = norm > 1e-6
    return np.abs(gl[ok]) / norm[ok]


def ridge_thickness(wall: np.ndarray, step: int = 4) -> np.ndarray:
    """Wall thickness [voxels] at the wall's medial ridge, in every ``step``-th L slice.

    In each R-T slice, d is the Euclidean distance of a wall voxel to the nearest
    polymer voxel; ridge voxels are the wall voxels where d is a 3 x 3 local
    maximum; the thickness there is 2 d - 1 (exact for an odd number of voxels,
    one voxel low for an even number).  Ridges of walls reaching the slice edge
    count too.
    """
    out = []
    for k in range(0, wall.shape[2], step):
        w = wall[:, :, k]
        if not w.any() or w.all():
            continue
        d = ndi.distance_transform_edt(w)
        ridge = w & (d == ndi.maximum_filter(d, size=3))
        out.append(2.0 * d[ridge] - 1.0)
    return np.concatenate(out) if out else np.zeros(0)


def volume_statistics(volume: np.ndarray, voxel_um: float, *, sigma_vox: float = 1.0) -> dict:
    """Geometry statistics of a binary volume ``[R, T, L]`` (non-zero = wall).

    Definitions (lengths in µm, voxels isotropic of ``voxel_um``):

    * ``wall_fraction``: share of wall voxels.
    * Lumens: in every L slice, the 4-connected polymer regions of the R-T plane;
      equivalent diameter d = 2 sqrt(A/π); regions with d < 2 µm are specks and
      ignored.  *Vessels* are lumens with d > 30 µm (``VESSEL_DIAMETER_UM``),
      *ray-cell lumens* those of :func:`is_ray_like`, *fibre lumens* the rest.
    * ``wall_fraction_outside_vessels``: wall voxels over the voxels that are not
      vessel lumen (vessels as below, edge-cut ones included): the fibre tissue's
      wall fraction, which a sample's chance share of vessels does not move.
    * ``fibre_lumen_d_um_{median,q25,q75}``: quartiles of d over the fibre lumens
      of all slices that touch no slice edge (cut lumens would bias d low).
    * ``vessel_area_fraction``: area of vessel lumens (edge-touching ones
      included, classified by their visible area) over the slice area, averaged
      over slices.
    * ``double_wall_{r,t}_um_{median,q25,q75}``: lengths of the runs of wall
      voxels along R (resp. T) lines that have lumen on both sides, i.e. the
      compound wall between two lumens measured along the axis (≥ its normal
      thickness where the wall is oblique; runs reaching the sample edge are left
      out).  ``double_wall_um_median`` pools both directions.
    * ``interfaces_per_mm_t``: number of wall/polymer changes along T lines
      divided by the line length (n_T · voxel), averaged over all T lines.
    * ``normal_l_{median,p90,p99}`` and ``normal_l_share_gt_0.1``: distribution
      of |n_L| at the wall-surface voxels (:func:`wall_normals_l`; σ = ``sigma_vox``).
    * ``ray_slice_share``: share of L slices with at least one ray-cell lumen
      (elongated along R: R extent ≥ 2 × T extent and ≥ 12 µm; not cut by a T edge).
      A slice through the end walls between two ray cells along L, or through a
      solid band of ray tissue, does not count.
    * ``ray_lumen_t_um_median``: median T extent of those ray-cell lumens.
    * ``slice_wall_fraction_{median,max}``: statistics of the per-slice wall fraction.

    Parameters
    ----------
    volume : numpy.ndarray
        3-D array ``[R, T, L]``; non-zero voxels are wall.
    voxel_um : float
        Edge of a (cubic) voxel in micrometres.
    sigma_vox : float, optional
        Gaussian smoothing for the wall normals, in voxels.

    Returns
    -------
    dict
        Statistic name to float (NaN where there is nothing to measure), plus
        ``shape`` and ``voxel_um``.
    """
    wall = np.asarray(volume) != 0
    if wall.ndim != 3:
        raise ValueError(f"volume must be 3-D [R, T, L], got shape {wall.shape}")
    nr, nt, nl = wall.shape
    v = float(voxel_um)
    out: dict = {"shape": [nr, nt, nl], "voxel_um": v, "wall_fraction": float(wall.mean())}

    fibre_d, vessel_frac, ray_t, ray_slices, n_ray_lumens = [], [], [], 0, 0
    for k in range(nl):
        tab = lumen_table(wall[:, :, k], v)
        big = tab["d_um"] >= MIN_LUMEN_DIAMETER_UM
        vessel = big & (tab["d_um"] > VESSEL_DIAMETER_UM)
        ray = is_ray_like(tab)
        fibre = big & ~vessel & ~ray & ~tab["border"]
        fibre_d.append(tab["d_um"][fibre])
        vessel_frac.append(tab["area_um2"][vessel].sum() / (nr * nt * v * v))
        ray_t.append(tab["len_t_um"][ray])
        ray_slices += bool(ray.any())
        n_ray_lumens += int(ray.sum())
    d = np.concatenate(fibre_d) if fibre_d else np.zeros(0)
    q = _quartiles(d)
    out.update({"fibre_lumen_d_um_q25": q[0], "fibre_lumen_d_um_median": q[1],
                "fibre_lumen_d_um_q75": q[2], "fibre_lumens_counted": int(d.size),
                "vessel_area_fraction": float(np.mean(vessel_frac)),
                "wall_fraction_outside_vessels": out["wall_fraction"] / (1.0 - float(np.mean(vessel_frac)))
                if np.mean(vessel_frac) < 1.0 else float("nan"),
                "ray_slice_share": ray_slices / nl, "ray_lumens_per_slice": n_ray_lumens / nl,
                "ray_lumen_t_um_median": _quartiles(np.concatenate(ray_t))[1]})

    runs = {}
    for name, axis in (("r", 0), ("t", 1)):
        runs[name] = _interior_wall_runs(wall, axis) * v
        q = _quartiles(runs[name])
        out.update({f"double_wall_{name}_um_q25": q[0], f"double_wall_{name}_um_median": q[1],
                    f"double_wall_{name}_um_q75": q[2]})
    q = _quartiles(np.concatenate([runs["r"], runs["t"]]))
    out.update({"double_wall_um_q25": q[0], "double_wall_um_median": q[1], "double_wall_um_q75": q[2]})

    q = _quartiles(ridge_thickness(wall) * v)
    out.update({"wall_ridge_um_q25": q[0], "wall_ridge_um_median": q[1], "wall_ridge_um_q75": q[2]})

    changes = np.count_nonzero(wall[:, 1:, :] != wall[:, :-1, :])
    out["interfaces_per_mm_t"] = float(changes / (nr * nl) / (nt * v * 1e-3))

    nl_abs = wall_normals_l(wall, sigma_vox)
    if nl_abs.size:
        p50, p90, p99 = np.percentile(nl_abs, [50.0, 90.0, 99.0])
        share = float(np.mean(nl_abs > 0.1))
    else:
        p50 = p90 = p99 = share = float("nan")
    out.update({"normal_l_median": float(p50), "normal_l_p90": float(p90),
                "normal_l_p99": float(p99), "normal_l_share_gt_0.1": share})

    per_slice = wall.mean(axis=(0, 1))
    out.update({"slice_wall_fraction_median": float(np.median(per_slice)),
                "slice_wall_fraction_max": float(per_slice.max())})
    return out
