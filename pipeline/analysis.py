"""Reductions of traced rays: Lorentz (Cauchy) widths and haze (docs/methods.md#fwhm-and-haze)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize

HAZE_ANGLE_DEG = 2.5


def cauchy_fit(theta_deg: np.ndarray) -> tuple[float, float]:
    """Maximum-likelihood (θ0, γ) of f(θ) = γ / (π((θ − θ0)² + γ²)) [degree].

    A sample with more than half its angles equal (no spread at all, as when ΔRI = 0; or a thin
    sample most of whose rays no wall deflects) has γ = 0 exactly, at that angle: the likelihood
    grows without bound as γ → 0 there.
    """
    x = np.asarray(theta_deg, dtype=np.float64)
    if x.size == 0:
        return float("nan"), float("nan")
    med = float(np.median(x))
    if 2 * np.count_nonzero(x == med) > x.size:  # a value held by more than half is the median
        return med, 0.0
    iqr = float(np.subtract(*np.percentile(x, [75, 25])))
    scale0 = max(iqr / 2.0, 1e-9)
    newton = _cauchy_newton(x, med, math.log(scale0))
    if newton is not None:
        return newton

    def nll(p):
        loc, log_g = p
        g = np.exp(log_g)
        return -np.sum(np.log(g / np.pi) - np.log((x - loc) ** 2 + g * g))

    with np.errstate(divide="ignore", invalid="ignore"):
        res = optimize.minimize(nll, [med, np.log(scale0)], method="Nelder-Mead",
                                options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 4000})
    return float(res.x[0]), float(np.exp(res.x[1]))


def _cauchy_newton(x: np.ndarray, loc: float, log_g: float, *, max_iter: int = 100):
    """Newton's method with a backtracking line search on the Cauchy log-likelihood in
    (θ0, log γ), from (``loc``, ``log_g``); None when it does not converge (the caller then
    uses Nelder-Mead).  About twenty times faster than Nelder-Mead, to the same optimum."""
    n = x.size

    def nll(m, s):
        if 2.0 * s > 700.0:  # γ beyond any angle (e^350 degree): a step the line search must shorten
            return math.inf
        return float(np.sum(np.log((x - m) ** 2 + math.exp(2 * s)))) - n * s

    f = nll(loc, log_g)
    for _ in range(max_iter):
        g2 = math.exp(2 * log_g)
        d = x - loc
        q = d * d + g2
        w = 1.0 / q
        grad = np.array([np.sum(-2.0 * d * w), np.sum(2.0 * g2 * w) - n])
        w2 = w * w
        h = np.array([[np.sum(2.0 * (g2 - d * d) * w2), np.sum(4.0 * d * g2 * w2)],
                      [np.sum(4.0 * d * g2 * w2), np.sum(4.0 * g2 * d * d * w2)]])
        try:
            step = -np.linalg.solve(h, grad)
            if not np.all(np.isfinite(step)) or float(step @ grad) >= 0.0:
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            step = -grad / max(np.abs(np.diag(h)).max(), 1e-300)  # not convex here: descend
        t = 1.0
        while True:
            m1, s1 = loc + t * step[0], log_g + t * step[1]
            f1 = nll(m1, s1)
            if f1 <= f + 1e-4 * t * float(step @ grad) or t < 1e-10:
                break
            t *= 0.5
        if not math.isfinite(f1) or t < 1e-10:
            return None
        done = abs(m1 - loc) <= 1e-12 * (1.0 + abs(loc)) + 1e-12 * math.exp(log_g) and abs(s1 - log_g) <= 1e-12
        loc, log_g, f = m1, s1, f1
        if done:
            return float(loc), float(math.exp(log_g))
    return None


def fwhm(theta_deg: np.ndarray) -> float:
    """FWHM = 2γ of the fitted Lorentz distribution [degree]."""
    return 2.0 * cauchy_fit(theta_deg)[1]


def fwhm_ci(theta_deg: np.ndarray, *, n_boot: int = 200, seed: int = 0, level: float = 0.95):
    """Bootstrap percentile interval of the FWHM [degree]."""
    x = np.asarray(theta_deg, dtype=np.float64)
    if x.size < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    boots = [fwhm(x[rng.integers(0, x.size, x.size)]) for _ in range(n_boot)]
    a = (1.0 - level) / 2.0
    return float(np.quantile(boots, a)), float(np.quantile(boots, 1.0 - a))


def haze(directions: np.ndarray, incident=(0.0, 1.0, 0.0)) -> float:
    """Fraction of directions deviating from the incident direction by more than 2.5°
    (ASTM D1003's criterion).

    Parameters
    ----------
    directions : ndarray of shape (N, 3)
        Emergent directions (need not be unit vectors).
    incident : array-like of shape (3,) or (N, 3)
        The incident direction, one for all or one per ray (as for an
        oblique beam refracted by each ray's own entry phase).  Rows of NaN
        (no undeflected direction to compare with) are left out.
    """
    d = np.asarray(directions, dtype=np.float64)
    inc = np.broadcast_to(np.asarray(incident, dtype=np.float64), d.shape)
    keep = ~np.isnan(inc).any(axis=1)
    d, inc = d[keep], inc[keep]
    if d.shape[0] == 0:
        return float("nan")
    cosang = np.sum(d * inc, axis=1) / (np.linalg.norm(d, axis=1) * np.linalg.norm(inc, axis=1))
    return float(np.mean(np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))) > HAZE_ANGLE_DEG))


def deviates(directions: np.ndarray, incident=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Per direction: 1.0 when it deviates from the incident one by more than 2.5°, 0.0 when
    not, NaN where the incident direction is NaN (see :func:`haze`)."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    inc = np.broadcast_to(np.asarray(incident, dtype=np.float64), d.shape)
    with np.errstate(invalid="ignore"):
        cosang = np.sum(d * inc, axis=1) / (np.linalg.norm(d, axis=1) * np.linalg.norm(inc, axis=1))
        out = (np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))) > HAZE_ANGLE_DEG).astype(np.float64)
    out[np.isnan(inc).any(axis=1)] = np.nan
    return out


def haze_ci(haze_fraction: float, n: int, *, level: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a haze measured on ``n`` rays (a binomial proportion).

    Unlike the normal approximation it stays inside [0, 1] and is not empty at
    a haze of 0 or 1; with no ray it is (NaN, NaN).
    """
    from scipy.stats import norm

    if n < 1 or not math.isfinite(haze_fraction):
        return float("nan"), float("nan")
    z = float(norm.ppf(0.5 + level / 2.0))
    centre = (haze_fraction + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(haze_fraction * (1 - haze_fraction) / n + z * z / (4 * n * n))
    return max(0.0, min(haze_fraction, centre - half)), min(1.0, max(haze_fraction, centre + half))


@dataclass(frozen=True)
class Target:
    """A precision to trace to: the 95 % CI half-width of haze (a fraction) and, when
    given, of FWHM_R and FWHM_L [degree] and of FWHM_R relative to itself (``fwhm_r_rel``).

    ``over`` says which interval is judged and what is added until it is met: ``"rays"``, the
    interval of the ray sampling alone, by doubling the rays up to ``max_rays``; ``"woods"``, the
    interval with the woods (hierarchical), by tracing more wood realisations up to
    ``max_realisations`` (more rays do not narrow the wood-to-wood part)."""

    haze: float | None = None
    fwhm_deg: float | None = None
    max_rays: int = 64_000
    fwhm_r_rel: float | None = None
    over: str = "rays"
    max_realisations: int = 64

    def shortfall(self, summary: dict) -> float:
        """The largest ratio of an asked-for half-width of ``summary`` to its target (at most 1:
        met; inf where an interval is undefined)."""
        def half(ci):
            lo, hi = ci
            return (hi - lo) / 2.0 if math.isfinite(lo) and math.isfinite(hi) else math.inf

        ratios = [0.0]
        if self.haze is not None:
            ratios.append(half(summary["haze_ci"]) / self.haze)
        if self.fwhm_deg is not None:
            ratios += [half(summary["fwhm_r_ci_deg"]) / self.fwhm_deg, half(summary["fwhm_l_ci_deg"]) / self.fwhm_deg]
        if self.fwhm_r_rel is not None:
            width = summary["fwhm_r_deg"]
            ratios.append(half(summary["fwhm_r_ci_deg"]) / (self.fwhm_r_rel * width)
                          if math.isfinite(width) and width > 0 else math.inf)
        return max(ratios)

    def met(self, summary: dict) -> bool:
        """Whether every asked-for interval of ``summary`` is as narrow as the target."""
        return bool(self.shortfall(summary) <= 1.0)

    def to_dict(self) -> dict:
        return {"haze": self.haze, "fwhm_deg": self.fwhm_deg, "fwhm_r_rel": self.fwhm_r_rel, "over": self.over,
                "max_rays": self.max_rays, "max_realisations": self.max_realisations}


def voxels_read(result) -> int:
    """Voxels a voxel method read for ``result`` (0 for a surface method): the voxels along
    each path, and at each interface the normal's neighbourhood (a Gaussian window of radius
    ``radius_vox``, evaluated 1 + ``refit`` times, or the paper's SVM box)."""
    st = result.settings.voxel
    if st is None:
        return 0
    if result.settings.method == "paper":
        per_interface = st.svm_box ** 3
    else:
        per_interface = (2 * math.ceil(st.radius_vox) + 1) ** 3 * (1 + st.refit)
    voxel = result.voxel_um or 1.0  # None: the voxel backend's own result, lengths in voxels
    return int(np.sum(result.path / voxel) + np.sum(result.events) * per_interface)


def summarize(result, *, n_boot: int = 200, seed: int = 0) -> dict:
    """FWHM_R, FWHM_L (with CIs), haze and counts of a RayResult."""
    t = result.transmitted
    tr, tl = result.theta_r[t], result.theta_l[t]
    lo_r, hi_r = fwhm_ci(tr, n_boot=n_boot, seed=seed)
    lo_l, hi_l = fwhm_ci(tl, n_boot=n_boot, seed=seed + 1)
    counts = result.counts()
    h = haze(result.exit_direction[t], (0.0, 1.0, 0.0) if result.incident is None else result.incident[t])
    n_haze = int(t.sum()) if result.incident is None else int((t & ~np.isnan(result.incident).any(axis=1)).sum())
    return {
        "fwhm_r_deg": fwhm(tr) if tr.size else float("nan"),
        "fwhm_r_ci_deg": [lo_r, hi_r],
        "fwhm_l_deg": fwhm(tl) if tl.size else float("nan"),
        "fwhm_l_ci_deg": [lo_l, hi_l],
        "haze": h,
        "haze_ci": list(haze_ci(h, n_haze)),
        "n_rays": int(result.status.size),
        "n_transmitted": counts["transmitted"],
        "n_lost": int(result.status.size - counts["transmitted"]),
        "counts": counts,
        "interfaces_per_ray": float(np.mean(result.events)),
        "voxels_read": voxels_read(result),
        "degenerate_normals": int(result.fallbacks[:, 0].sum()),
        "face_disagreements": int(result.fallbacks[:, 1].sum()),
        # Normals taken at the face point: walls thinner than the smoothing.
        "thin_wall_normals": int(result.fallbacks[:, 2].sum()),
        "method": result.settings.method,
        "exit": result.settings.exit,
    }



def _percentile_ci(samples: np.ndarray, level: float) -> list:
    a = (1.0 - level) / 2.0
    ok = samples[np.isfinite(samples)]
    if ok.size < 2:
        return [float("nan"), float("nan")]
    return [float(np.quantile(ok, a)), float(np.quantile(ok, 1.0 - a))]


def pool(results: list, *, n_boot: int = 200, seed: int = 0, level: float = 0.95) -> dict:
    """FWHM_R, FWHM_L and haze of the rays of several wood realisations pooled, with intervals
    that include the wood-to-wood variation.

    Parameters
    ----------
    results : list of RayResult
        One per realisation of a scene (its wood and beam drawn with another seed).

    Returns
    -------
    dict
        The numbers of all transmitted rays pooled (realisation 0's first);
        ``*_ci``: a hierarchical bootstrap, drawing realisations with
        replacement and then rays within each drawn realisation, so the interval
        holds the wood-to-wood variance as well as the ray sampling;
        ``*_ray_ci``: the ray sampling alone (each realisation once, its rays
        redrawn).  With one realisation the two coincide, and the haze
        intervals are the Wilson interval of :func:`haze_ci`.
    """
    parts = []
    for r in results:
        t = r.transmitted
        hz = deviates(r.exit_direction[t], (0.0, 1.0, 0.0) if r.incident is None else r.incident[t])
        parts.append((r.theta_r[t], r.theta_l[t], hz))

    def reduce(chosen):
        tr = np.concatenate([parts[k][0][idx] for k, idx in chosen])
        tl = np.concatenate([parts[k][1][idx] for k, idx in chosen])
        hz = np.concatenate([parts[k][2][idx] for k, idx in chosen])
        hz = hz[np.isfinite(hz)]
        return (fwhm(tr) if tr.size else np.nan, fwhm(tl) if tl.size else np.nan,
                float(hz.mean()) if hz.size else np.nan)

    point = reduce([(k, np.arange(p[0].size)) for k, p in enumerate(parts)])
    rng = np.random.default_rng(seed)
    n_real = len(parts)
    ray_only = np.empty((n_boot, 3))
    nested = np.empty((n_boot, 3))
    for b in range(n_boot):
        ray_only[b] = reduce([(k, rng.integers(0, p[0].size, p[0].size)) for k, p in enumerate(parts)])
        if n_real == 1:
            nested[b] = ray_only[b]
            continue
        picks = rng.integers(0, n_real, n_real)
        nested[b] = reduce([(k, rng.integers(0, parts[k][0].size, parts[k][0].size)) for k in picks])
    n_haze = int(sum(np.isfinite(p[2]).sum() for p in parts))
    wilson = list(haze_ci(point[2], n_haze, level=level))
    counts = [r.counts()["transmitted"] for r in results]
    n_rays = int(sum(r.status.size for r in results))
    return {
        "fwhm_r_deg": float(point[0]), "fwhm_l_deg": float(point[1]), "haze": float(point[2]),
        "fwhm_r_ci_deg": _percentile_ci(nested[:, 0], level),
        "fwhm_l_ci_deg": _percentile_ci(nested[:, 1], level),
        "haze_ci": _percentile_ci(nested[:, 2], level) if n_real > 1 else wilson,
        "fwhm_r_ray_ci_deg": _percentile_ci(ray_only[:, 0], level),
        "fwhm_l_ray_ci_deg": _percentile_ci(ray_only[:, 1], level),
        "haze_ray_ci": wilson,
        "realisations": n_real,
        "n_rays": n_rays,
        "n_transmitted": int(sum(counts)),
        "n_lost": int(n_rays - sum(counts)),
        "interfaces_per_ray": float(np.mean(np.concatenate([r.events for r in results]))),
    }


def image_quality(image: np.ndarray, ideal: np.ndarray) -> dict:
    """How far a rendered image is from its ideal thin-lens image.

    Parameters
    ----------
    image, ideal : ndarray of shape (rows, cols)
        Pixel levels in [0, 1] (1 = light background, 0 = dark ink).

    Returns
    -------
    dict
        ``contrast``: Michelson contrast (b − d)/(b + d) of the image between
        the pixels the ideal image shows light (level > 0.5, mean b) and dark
        (mean d); 1 for a perfect black-on-white image, 0 when the object is
        washed out.  ``ideal_contrast``: the same of the ideal image.
        ``rmse``: root-mean-square difference from the ideal image [1].
    """
    image = np.asarray(image, dtype=np.float64)
    ideal = np.asarray(ideal, dtype=np.float64)
    if image.shape != ideal.shape:
        raise ValueError(f"`image` and `ideal` must have one shape, got {image.shape} and {ideal.shape}")
    light = ideal > 0.5
    if light.all() or not light.any():
        raise ValueError("`ideal` must show both light (> 0.5) and dark pixels to measure contrast")

    def michelson(a):
        b, d = a[light].mean(), a[~light].mean()
        return float((b - d) / (b + d)) if b + d > 0 else float("nan")

    return {"contrast": michelson(image), "ideal_contrast": michelson(ideal),
            "rmse": float(np.sqrt(np.mean((image - ideal) ** 2)))}
