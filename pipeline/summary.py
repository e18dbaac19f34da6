"""Summaries of traced rays: every width estimator and haze, with intervals that count each
source of variation once (docs/methods.md#realisations-and-intervals).

One wood: the rays are the sample, and an interval is a percentile bootstrap over them.  Several
woods: each wood is one draw of the microstructure, and its rays are a sample within it.  The
pooled value's interval comes from resampling woods only, each drawn wood with all its rays: the
spread of the woods' pooled rays already holds the ray noise once, so redrawing rays inside them
(a nested bootstrap) would count it twice.  The woods' bootstrap standard error, scaled by
√(R/(R − 1)), with Student's t on R − 1 degrees of freedom, gives the interval (for a mean of equal
woods this is exactly the classical t interval of their means).  For haze and the chosen width it
is never narrower than the interval of the rays alone: the pooled value varies at least as much as
its rays do.
"""

from __future__ import annotations

import math

import numpy as np

from .analysis import (ESTIMATORS, LORENTZ_MLE, FwhmSpec, cauchy_newton, cauchy_fit, deviates, fwhm, half_max_of_counts,
                       haze_ci, hist_bins, kde_plan, lorentz_hist_of_counts, lorentz_ks)

N_BOOT = 2000  # resamples: the bounds move by about 1/√(2 · 2000) ≈ 1.6 % of the half-width from seed to seed
N_BOOT_WOOD = 200  # resamples of one wood's rays for the ray part of the variance components
LEVEL = 0.95
_CHUNK = 100  # bootstrap rows at a time (memory: rows × rays)
INTERVAL_WOODS = ("woods bootstrap (all rays of each drawn wood), standard error × √(R/(R−1)), Student t on R−1 "
                  "d.o.f.; for haze and the chosen width at least the rays' interval")
INTERVAL_RAYS = "bootstrap percentile over rays"


def t_interval(point: float, draws: np.ndarray, n_woods: int, level: float = LEVEL,
               bounds: tuple = (-math.inf, math.inf)) -> list:
    """``point`` ± t(R − 1) · SE, SE the standard deviation of the woods' bootstrap ``draws`` scaled
    by √(R/(R − 1)) (the bootstrap over R clusters sees (R − 1)/R of their variance), kept within
    ``bounds`` (a width is at least 0, a haze within [0, 1])."""
    from scipy.special import stdtrit  # Student's t quantile (scipy.stats' t.ppf; that import is slow)

    ok = draws[np.isfinite(draws)]
    if ok.size < 2 or n_woods < 2 or not math.isfinite(point):
        return [float("nan"), float("nan")]
    se = float(np.std(ok, ddof=1)) * math.sqrt(n_woods / (n_woods - 1))
    half = float(stdtrit(n_woods - 1, 0.5 + level / 2.0)) * se
    return [max(point - half, bounds[0]), min(point + half, bounds[1])]


def hull(a: list, b: list) -> list:
    """The smallest interval holding intervals ``a`` and ``b`` (NaN bounds ignored)."""
    lo = np.nanmin([a[0], b[0]]) if np.isfinite([a[0], b[0]]).any() else float("nan")
    hi = np.nanmax([a[1], b[1]]) if np.isfinite([a[1], b[1]]).any() else float("nan")
    return [float(lo), float(hi)]


def percentile_interval(draws: np.ndarray, level: float = LEVEL) -> list:
    a = (1.0 - level) / 2.0
    ok = draws[np.isfinite(draws)]
    if ok.size < 2:
        return [float("nan"), float("nan")]
    return [float(np.quantile(ok, a)), float(np.quantile(ok, 1.0 - a))]


def woods_weights(n_woods: int, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """(n_boot, n_woods): how many times each wood is drawn in each resample of the woods."""
    picks = rng.integers(0, n_woods, (n_boot, n_woods))
    return np.stack([np.bincount(p, minlength=n_woods) for p in picks]).astype(np.float64)


class Angles:
    """One projected angle (θ_R or θ_L) of the transmitted rays of several woods, with the binned
    grids of the histogram estimators fixed from the pooled sample (held for every resample)."""

    def __init__(self, parts: list, spec: FwhmSpec):
        self.parts = [np.asarray(p, dtype=np.float64) for p in parts]
        self.x = np.concatenate(self.parts) if self.parts else np.empty(0)
        self.spec = spec
        ok = self.x.size >= 2
        self.kde = kde_plan(self.x) if ok else None
        self.hist = hist_bins(self.x, spec) if ok else None
        self._start = None  # the whole sample's Cauchy fit (loc, log γ), where resamples start

    def _mle(self, x: np.ndarray) -> float:
        """2γ of the Cauchy fit to a resample ``x``, Newton's method started from the whole sample's
        fit (the usual start for a bootstrap; cauchy_fit's own start and fallbacks where it fails)."""
        if self._start is None:
            loc, g = cauchy_fit(self.x)
            self._start = (loc, math.log(g)) if g > 0 else ()
        if self._start:
            fit = cauchy_newton(x, *self._start)
            if fit is not None:
                return 2.0 * fit[1]
        return 2.0 * cauchy_fit(x)[1]

    def _grid(self, est: str):
        if est == "half-max":
            return None if self.kde is None else self.kde[0]
        return self.hist

    def of_counts(self, est: str, counts: np.ndarray) -> np.ndarray:
        if est == "half-max":
            return half_max_of_counts(counts, *self.kde)
        return lorentz_hist_of_counts(counts, self.hist)

    def point(self, est: str) -> float:
        return fwhm(self.x, self.spec.of(est)) if self.x.size else float("nan")

    def woods_draws(self, est: str, weights: np.ndarray) -> np.ndarray:
        """The estimate on each resample of woods (rows of ``weights``).  A resample drawn more than
        once is estimated once (a row's estimate depends on that row alone): R woods have at most
        C(2R − 1, R) distinct resamples, 126 for 5 woods, whatever the number of rows."""
        if self.x.size < 2:
            return np.full(len(weights), np.nan)
        distinct, back = np.unique(weights, axis=0, return_inverse=True)
        return self._woods_draws(est, distinct)[np.reshape(back, -1)]

    def _woods_draws(self, est: str, weights: np.ndarray) -> np.ndarray:
        if est == LORENTZ_MLE:
            return np.array([self._mle(np.concatenate([np.tile(p, int(w)) for p, w in zip(self.parts, row) if w]))
                             for row in weights])
        grid = self._grid(est)
        if grid is None:
            return np.zeros(len(weights))
        counts = np.stack([grid.counts(p) for p in self.parts])
        return self.of_counts(est, weights @ counts)

    def ray_draws(self, est: str, picks: list) -> np.ndarray:
        """The estimate on each resample of rays: ``picks`` holds per wood an array (rows, n_k) of
        ray indices."""
        return self.draws_of(est, [self.ray_sample(est, picks)])

    def ray_sample(self, est: str, picks: list) -> np.ndarray:
        """What :meth:`draws_of` needs of the resamples of rays ``picks`` (none of the picks is kept):
        their binned counts (rows, m) for an estimator on a grid, to be fitted together with the
        other batches; else the estimates themselves (rows,)."""
        rows = picks[0].shape[0] if picks else 0
        if self.x.size < 2:
            return np.full(rows, np.nan)
        if est == LORENTZ_MLE:
            return np.array([self._mle(np.concatenate([p[i[b]] for p, i in zip(self.parts, picks)])) for b in range(rows)])
        grid = self._grid(est)
        if grid is None:
            return np.zeros(rows)
        flat = []
        for p, i in zip(self.parts, picks):
            b = grid.index(p)[i]
            flat.append((b + grid.m * np.arange(rows)[:, None])[b >= 0])
        return np.bincount(np.concatenate(flat), minlength=rows * grid.m).reshape(rows, grid.m).astype(np.float64)

    def draws_of(self, est: str, samples: list) -> np.ndarray:
        """The estimates of consecutive :meth:`ray_sample` results, in order.  The counts of an
        estimator on a grid are fitted together, as one array (each row's fit depends on that row
        alone; one call instead of one per batch of resamples)."""
        if not samples:
            return np.empty(0)
        if self.x.size < 2 or est == LORENTZ_MLE or self._grid(est) is None:
            return np.concatenate(samples)
        return self.of_counts(est, np.concatenate(samples))


def fwhm_ci(theta_deg: np.ndarray, *, n_boot: int = N_BOOT, seed: int = 0, level: float = LEVEL,
            estimator: str = "half-max") -> list:
    """Bootstrap percentile interval over the rays of one sample's FWHM by ``estimator`` [degree]."""
    x = np.asarray(theta_deg, dtype=np.float64)
    if x.size < 2:
        return [float("nan"), float("nan")]
    rng = np.random.default_rng(seed)
    a = Angles([x], FwhmSpec(estimator))
    samples = [a.ray_sample(estimator, [rng.integers(0, x.size, (min(_CHUNK, n_boot - lo), x.size))])
               for lo in range(0, n_boot, _CHUNK)]
    return percentile_interval(a.draws_of(estimator, samples), level)


def _components(each: np.ndarray, ray_var: np.ndarray) -> dict:
    """Between-wood and within-wood (ray) standard deviations of one wood's value: the woods'
    variance minus the mean ray variance of one wood's value (method of moments, at least 0)."""
    ok = np.isfinite(each) & np.isfinite(ray_var)
    if ok.sum() < 2:
        return {"between_woods": float("nan"), "rays_per_wood": float(math.sqrt(np.mean(ray_var[ok])))
                if ok.any() else float("nan")}
    within = float(np.mean(ray_var[ok]))
    return {"between_woods": math.sqrt(max(0.0, float(np.var(each[ok], ddof=1)) - within)),
            "rays_per_wood": math.sqrt(within)}


def reduce_angles(parts: list, *, spec: FwhmSpec = FwhmSpec(), n_boot: int = N_BOOT, seed: int = 0,
                  level: float = LEVEL) -> dict:
    """Every estimator's FWHM_R and FWHM_L and the haze of the transmitted rays of one or more woods
    pooled, with intervals.

    Parameters
    ----------
    parts : list of (theta_r, theta_l, deviated)
        Per wood: the transmitted rays' angles [degree] and whether each deviates more than 2.5°
        (1.0, 0.0, or NaN where undefined).
    spec : FwhmSpec
        Which estimator ``fwhm_*_deg`` is (the others are under ``estimators``).
    n_boot : int
        Resamples per interval; 0 computes no interval.

    Returns
    -------
    dict
        ``fwhm_r_deg``, ``fwhm_l_deg``, ``haze`` and their intervals ``*_ci``: with one wood over
        its rays, with several over the woods (:func:`t_interval`); ``*_ray_ci``: the rays alone
        (haze: Wilson's interval); ``estimators``: each estimator's values, intervals and per-wood
        values; ``lorentz_ks_r``/``_l``; ``components``: between-wood and ray standard deviations of
        one wood's value.
    """
    n_real = len(parts)
    rng = np.random.default_rng(seed)
    angles = {q: Angles([p[i] for p in parts], spec) for i, q in ((0, "r"), (1, "l"))}
    dev = [np.asarray(p[2], dtype=np.float64) for p in parts]
    dev_n = np.array([np.isfinite(d).sum() for d in dev], dtype=np.float64)
    dev_k = np.array([np.nansum(d) for d in dev], dtype=np.float64)
    n_haze = int(dev_n.sum())
    haze = float(dev_k.sum() / n_haze) if n_haze else float("nan")
    nan2 = [float("nan"), float("nan")]
    est_out = {e: {} for e in ESTIMATORS}
    for q, a in angles.items():
        for e in ESTIMATORS:
            one = spec.of(e)
            est_out[e][f"fwhm_{q}_deg"] = a.point(e)
            est_out[e][f"fwhm_{q}_each"] = [fwhm(p, one) if p.size else float("nan") for p in a.parts]
            est_out[e][f"fwhm_{q}_ci_deg"] = nan2
    out = {"haze_ci": nan2, "haze_ray_ci": list(haze_ci(haze, n_haze, level=level))}
    ray_ci = {q: nan2 for q in angles}
    if n_boot and n_real > 1:
        w = woods_weights(n_real, n_boot, rng)
        for q, a in angles.items():
            for e in ESTIMATORS:
                est_out[e][f"fwhm_{q}_ci_deg"] = t_interval(est_out[e][f"fwhm_{q}_deg"], a.woods_draws(e, w), n_real, level,
                                                            bounds=(0.0, math.inf))
        with np.errstate(invalid="ignore", divide="ignore"):
            out["haze_ci"] = t_interval(haze, (w @ dev_k) / (w @ dev_n), n_real, level, bounds=(0.0, 1.0))
    if n_boot:
        # Rays alone: every wood once, its rays redrawn (with one wood, every estimator's interval).
        ests = ESTIMATORS if n_real == 1 else (spec.estimator,)
        draws = {(q, e): [] for q in angles for e in ests}
        sizes = [a.size for a in angles["r"].parts]
        for lo in range(0, n_boot, _CHUNK):
            rows = min(_CHUNK, n_boot - lo)
            picks = [rng.integers(0, n, (rows, n)) for n in sizes]
            for (q, e), acc in draws.items():
                acc.append(angles[q].ray_sample(e, picks))
        for (q, e), acc in draws.items():
            ci = percentile_interval(angles[q].draws_of(e, acc), level)
            if e == spec.estimator:
                ray_ci[q] = ci
            if n_real == 1:
                est_out[e][f"fwhm_{q}_ci_deg"] = ci
        if n_real == 1:
            out["haze_ci"] = out["haze_ray_ci"]
    if n_boot and n_real > 1:
        # The pooled value varies at least as much as its rays do (the woods' variance is >= 0): a woods'
        # interval narrower than the rays' (few woods that happen to agree; every ray deviating) is widened to it.
        out["haze_ci"] = hull(out["haze_ci"], out["haze_ray_ci"])
        for q in angles:
            key = f"fwhm_{q}_ci_deg"
            est_out[spec.estimator][key] = hull(est_out[spec.estimator][key], ray_ci[q])
    chosen = est_out[spec.estimator]
    comps = {}
    if n_boot and n_real > 1:
        with np.errstate(invalid="ignore", divide="ignore"):
            p_k = dev_k / dev_n
            comps["haze"] = _components(p_k, p_k * (1.0 - p_k) / np.maximum(dev_n - 1.0, 1.0))
        for q, a in angles.items():
            ray_var = []
            for p in a.parts:  # each wood's value from its own rays, redrawn
                if p.size < 2:
                    ray_var.append(float("nan"))
                    continue
                d = Angles([p], spec).ray_draws(spec.estimator, [rng.integers(0, p.size, (N_BOOT_WOOD, p.size))])
                ray_var.append(float(np.nanvar(d, ddof=1)) if np.isfinite(d).sum() > 1 else float("nan"))
            comps[f"fwhm_{q}"] = _components(np.array(chosen[f"fwhm_{q}_each"]), np.array(ray_var))
    out.update({
        "fwhm_r_deg": chosen["fwhm_r_deg"], "fwhm_r_ci_deg": chosen["fwhm_r_ci_deg"], "fwhm_r_ray_ci_deg": ray_ci["r"],
        "fwhm_l_deg": chosen["fwhm_l_deg"], "fwhm_l_ci_deg": chosen["fwhm_l_ci_deg"], "fwhm_l_ray_ci_deg": ray_ci["l"],
        "haze": haze, "haze_each": [float(k / n) if n else float("nan") for k, n in zip(dev_k, dev_n)],
        "fwhm": spec.to_dict(), "estimators": est_out,
        "lorentz_ks_r": lorentz_ks(angles["r"].x), "lorentz_ks_l": lorentz_ks(angles["l"].x),
        "components": comps, "realisations": n_real, "n_boot": int(n_boot),
        "interval": INTERVAL_WOODS if n_real > 1 else INTERVAL_RAYS,
    })
    return out


def _parts(results) -> list:
    parts = []
    for r in results:
        t = r.transmitted
        hz = deviates(r.exit_direction[t], (0.0, 1.0, 0.0) if r.incident is None else r.incident[t])
        parts.append((r.theta_r[t], r.theta_l[t], hz))
    return parts


def pool(results: list, *, spec: FwhmSpec = FwhmSpec(), n_boot: int = N_BOOT, seed: int = 0,
         level: float = LEVEL) -> dict:
    """:func:`reduce_angles` of the transmitted rays of several wood realisations (RayResults,
    realisation 0 first), with their ray counts."""
    out = reduce_angles(_parts(results), spec=spec, n_boot=n_boot, seed=seed, level=level)
    counts = [r.counts()["transmitted"] for r in results]
    n_rays = int(sum(r.status.size for r in results))
    out.update({"n_rays": n_rays, "n_transmitted": int(sum(counts)), "n_lost": int(n_rays - sum(counts)),
                "interfaces_per_ray": float(np.mean(np.concatenate([r.events for r in results])))})
    return out


def summarize(result, *, spec: FwhmSpec = FwhmSpec(), n_boot: int = N_BOOT, seed: int = 0) -> dict:
    """FWHM_R, FWHM_L (every estimator, intervals over the rays), haze and the counts of one
    RayResult."""
    out = pool([result], spec=spec, n_boot=n_boot, seed=seed)
    out.update({
        "counts": result.counts(),
        "method": result.settings.method,
        "exit": result.settings.exit,
    })
    out.update(result.voxel_counts())  # none for a surface medium
    return out
