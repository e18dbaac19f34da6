"""Reductions of traced rays: Lorentz (Cauchy) widths and haze (docs/methods.md#fwhm-and-haze)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
    newton = cauchy_newton(x, med, math.log(scale0))
    if newton is not None:
        return newton

    def nll(p):
        loc, log_g = p
        g = np.exp(log_g)
        return -np.sum(np.log(g / np.pi) - np.log((x - loc) ** 2 + g * g))

    from scipy import optimize  # Nelder-Mead, where Newton fails: rare, and its import is slow

    with np.errstate(divide="ignore", invalid="ignore"):
        res = optimize.minimize(nll, [med, np.log(scale0)], method="Nelder-Mead",
                                options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 4000})
    return float(res.x[0]), float(np.exp(res.x[1]))


def cauchy_newton(x: np.ndarray, loc: float, log_g: float, *, max_iter: int = 100):
    """Newton's method with a backtracking line search on the Cauchy log-likelihood in
    (θ0, log γ), from (``loc``, ``log_g``); None when it does not converge (the caller then
    uses Nelder-Mead).  About twenty times faster than Nelder-Mead, to the same optimum; each step
    is compiled (:func:`pipeline._cauchy.newton_step`, the same numbers as in NumPy)."""
    from ._cauchy import newton_step

    x = np.ascontiguousarray(x, dtype=np.float64)
    n = x.size
    work = np.empty((6, 128))
    buf = np.empty(n)

    def nll(m, s):
        if 2.0 * s > 700.0:  # γ beyond any angle (e^350 degree): a step the line search must shorten
            return math.inf
        # sum(log((x - m)² + γ²)) − n log γ, in place (the same operations as the expression)
        np.subtract(x, m, out=buf)
        np.multiply(buf, buf, out=buf)
        np.add(buf, math.exp(2 * s), out=buf)
        np.log(buf, out=buf)
        return float(np.add.reduce(buf)) - n * s

    f = nll(loc, log_g)
    for _ in range(max_iter):
        step, slope, ok = newton_step(x, loc, log_g, math.exp(2 * log_g), work)
        if not ok:  # not convex here: descend
            grad = work[5, :2].copy()
            step = -grad / max(max(work[5, 2], work[5, 3]), 1e-300)
            slope = float(step @ grad)
        t = 1.0
        while True:
            m1, s1 = loc + t * step[0], log_g + t * step[1]
            f1 = nll(m1, s1)
            if f1 <= f + 1e-4 * t * slope or t < 1e-10:
                break
            t *= 0.5
        if not math.isfinite(f1) or t < 1e-10:
            return None
        done = abs(m1 - loc) <= 1e-12 * (1.0 + abs(loc)) + 1e-12 * math.exp(log_g) and abs(s1 - log_g) <= 1e-12
        loc, log_g, f = m1, s1, f1
        if done:
            return float(loc), float(math.exp(log_g))
    return None


# ------------------------------------------------------------------ widths
# Three estimators of a width (docs/methods.md#fwhm-and-haze); the default is the source's own definition.
HALF_MAX, LORENTZ_HIST, LORENTZ_MLE = "half-max", "lorentz-hist", "lorentz-mle"
ESTIMATORS = (HALF_MAX, LORENTZ_HIST, LORENTZ_MLE)
SLUG = {e: e.replace("-", "_") for e in ESTIMATORS}  # an estimator's name in variable names: FWHM_R_half_max
DEFAULT_ESTIMATOR = HALF_MAX
# half-max: a Gaussian kernel density estimate of bandwidth h = KDE_C · IQR · n^(-1/5), binned at h/4.
KDE_C = 0.3
KDE_BINS_PER_H = 4
# lorentz-hist: bins of Freedman–Diaconis width 2 · IQR · n^(-1/3) unless fixed, over the median ± HIST_RANGE_IQR · IQR.
HIST_RANGE_IQR = 5.0
HIST_MIN_BINS = 10
FWHM_GAUSS = 2.0 * math.sqrt(2.0 * math.log(2.0))  # a Gaussian's FWHM in standard deviations


@dataclass(frozen=True)
class FwhmSpec:
    """Which width FWHM_R and FWHM_L are (``estimator``), and the histogram of ``lorentz-hist``:
    ``bin_deg`` (None: the Freedman–Diaconis width) and ``range_iqr`` (the half-range around the
    median in interquartile ranges; inf: every angle)."""

    estimator: str = DEFAULT_ESTIMATOR
    bin_deg: float | None = None
    range_iqr: float = HIST_RANGE_IQR

    def __post_init__(self):
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"`fwhm.estimator` must be one of {', '.join(ESTIMATORS)}, got {self.estimator!r}")
        if self.bin_deg is not None and not (isinstance(self.bin_deg, (int, float)) and 0 < self.bin_deg <= 10):
            raise ValueError(f"`fwhm.bin_deg` must be a number in (0, 10] degrees, got {self.bin_deg!r}")
        if not (isinstance(self.range_iqr, (int, float)) and self.range_iqr >= 1):
            raise ValueError(f"`fwhm.range_iqr` must be a number >= 1 (or .inf), got {self.range_iqr!r}")

    def of(self, estimator: str) -> "FwhmSpec":
        """The same histogram settings with another estimator."""
        return FwhmSpec(estimator, self.bin_deg, self.range_iqr)

    @classmethod
    def from_dict(cls, d: dict | None) -> "FwhmSpec":
        d = {k: float(v) if v == "inf" else v for k, v in (d or {}).items()}  # to_dict's JSON form of .inf
        unknown = set(d) - {"estimator", "bin_deg", "range_iqr"}
        if unknown:
            raise ValueError(f"unknown key `fwhm.{sorted(unknown)[0]}` (known: estimator, bin_deg, range_iqr)")
        return cls(**d)

    def to_dict(self) -> dict:
        return {"estimator": self.estimator, "bin_deg": self.bin_deg,
                "range_iqr": self.range_iqr if math.isfinite(self.range_iqr) else "inf"}


@dataclass(frozen=True)
class Bins:
    """A grid of ``m`` bins of width ``step`` whose first centre is ``lo`` [degree]."""

    lo: float
    step: float
    m: int

    def index(self, x: np.ndarray) -> np.ndarray:
        """Each angle's bin, -1 outside the grid."""
        i = np.floor((np.asarray(x, dtype=np.float64) - self.lo) / self.step + 0.5).astype(np.int64)
        i[(i < 0) | (i >= self.m)] = -1
        return i

    def counts(self, x: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """How many of ``x`` (or how much of their ``weights``) fall in each bin."""
        i = self.index(x)
        keep = i >= 0
        w = None if weights is None else np.asarray(weights, np.float64)[keep]
        return np.bincount(i[keep], weights=w, minlength=self.m).astype(np.float64)

    @property
    def centres(self) -> np.ndarray:
        return self.lo + self.step * np.arange(self.m)


def _quartiles(x: np.ndarray) -> tuple[float, float]:
    q1, med, q3 = np.percentile(x, [25, 50, 75])
    return float(med), float(q3 - q1)


def kde_plan(x: np.ndarray) -> tuple[Bins, float] | None:
    """The binned grid and bandwidth h [degree] of ``half-max`` for the sample ``x``; None where more
    than a quarter of the angles lie on each side of one value (IQR 0: a spike, of width 0)."""
    med, iqr = _quartiles(x)
    return kde_grid(med, iqr, x.size)


def kde_grid(med: float, iqr: float, n: float) -> tuple[Bins, float] | None:
    """``half-max``'s grid and bandwidth for a distribution of median ``med`` and interquartile
    range ``iqr`` [degree] estimated from ``n`` angles (None where the IQR is 0)."""
    if iqr == 0.0:
        return None
    h = KDE_C * iqr * n ** -0.2
    step = h / KDE_BINS_PER_H
    half = 4.0 * iqr + 5.0 * h  # the peak and its half-maximum points for any unimodal shape seen (FWHM <= 4 IQR)
    m = int(math.ceil(2.0 * half / step)) + 1
    return Bins(med - half, step, m), h


def half_max_of_counts(counts: np.ndarray, bins: Bins, h: float) -> np.ndarray:
    """Width at half maximum [degree] of the Gaussian kernel density estimate of each row of
    binned ``counts`` (B, m) with bandwidth ``h``: the outermost points where the estimate is half
    its maximum, linearly interpolated between bins; NaN where the estimate does not fall below
    half its maximum inside the grid."""
    from scipy.ndimage import gaussian_filter1d

    d = np.atleast_2d(gaussian_filter1d(np.asarray(counts, dtype=np.float64), h / bins.step, axis=-1,
                                        mode="constant", truncate=4.0))
    rows = np.arange(d.shape[0])
    half = d.max(axis=1) / 2.0
    above = d >= half[:, None]
    right = d.shape[1] - 1 - np.argmax(above[:, ::-1], axis=1)  # the last bin at or above half
    left = np.argmax(above, axis=1)
    ok = (right < d.shape[1] - 1) & (left > 0)
    right, left = np.minimum(right, d.shape[1] - 2), np.maximum(left, 1)

    def cross(ja, jb):  # d[ja] >= half > d[jb], adjacent bins
        da, db = d[rows, ja], d[rows, jb]
        return bins.lo + bins.step * (ja + (da - half) / (da - db) * (jb - ja))

    width = cross(right, right + 1) - cross(left, left - 1)
    return np.where(ok, width, np.nan)


def half_max_fwhm(theta_deg: np.ndarray) -> float:
    """The width of the angle distribution between the points at half its maximum [degree]
    (``half-max``): the outermost half-maximum points of a Gaussian kernel density estimate with
    bandwidth h = 0.3 · IQR · n^(-1/5), binned at h/4.  0 where the IQR is 0."""
    x = np.asarray(theta_deg, dtype=np.float64)
    if x.size < 2:
        return float("nan")
    plan = kde_plan(x)
    if plan is None:
        return 0.0
    bins, h = plan
    return float(half_max_of_counts(bins.counts(x), bins, h)[0])


def hist_bins(x: np.ndarray, spec: FwhmSpec) -> Bins | None:
    """The histogram of ``lorentz-hist`` for the sample ``x`` (None where the IQR is 0)."""
    med, iqr = _quartiles(x)
    return hist_grid(med, iqr, x.size, spec, span=(float(x.min()), float(x.max())))


def hist_grid(med: float, iqr: float, n: float, spec: FwhmSpec, *, span: tuple[float, float]) -> Bins | None:
    """``lorentz-hist``'s histogram for a distribution of median ``med`` and interquartile range
    ``iqr`` [degree] estimated from ``n`` angles lying within ``span`` (None where the IQR is 0)."""
    if iqr == 0.0:
        return None
    step = float(spec.bin_deg) if spec.bin_deg is not None else 2.0 * iqr * n ** (-1.0 / 3.0)
    if math.isfinite(spec.range_iqr):  # at least ten bins each side, however narrow the angles
        half = max(spec.range_iqr * iqr, HIST_MIN_BINS * step)
        lo, hi = med - half, med + half
    else:
        lo, hi = span
    m = max(int(math.ceil((hi - lo) / step)), 3)
    return Bins(lo + step / 2.0, step, m)


def lorentz_hist_of_counts(counts: np.ndarray, bins: Bins, *, iterations: int = 60) -> np.ndarray:
    """FWHM = 2γ [degree] of the least-squares fit of A / (1 + ((θ − θ0)/γ)²) to each row of
    histogram ``counts`` (B, m) at the bin centres (Levenberg–Marquardt, from the tallest bin and
    the half-maximum width of the bars); NaN where it does not converge."""
    y = np.atleast_2d(np.asarray(counts, dtype=np.float64))
    c = bins.centres
    b = y.shape[0]
    rows = np.arange(b)
    k = y.argmax(axis=1)
    amp = y[rows, k]
    p = np.stack([amp, c[k], np.maximum(np.sum(y >= amp[:, None] / 2, axis=1) * bins.step / 2, bins.step / 2)], axis=1)

    def residual(p, y):
        u = (c[None] - p[:, 1:2]) / p[:, 2:3]
        return p[:, 0:1] / (1.0 + u * u) - y, u

    r, u = residual(p, y)
    cost = np.sum(r * r, axis=1)
    lam = np.full(b, 1e-3)
    done = np.zeros(b, dtype=bool)
    # Each row is fitted on its own: the rows not done yet are taken out, stepped and put back (a row's
    # numbers do not depend on the others').
    for _ in range(iterations):
        act = np.flatnonzero(~done)
        pa, ua, ra, la = p[act], u[act], r[act], lam[act]
        q = 1.0 / (1.0 + ua * ua)
        jac = np.stack([q, pa[:, 0:1] * 2 * ua * q * q / pa[:, 2:3], pa[:, 0:1] * 2 * ua * ua * q * q / pa[:, 2:3]],
                       axis=2)
        jtj = np.einsum("bmi,bmj->bij", jac, jac)
        g = np.einsum("bmi,bm->bi", jac, ra)
        a = jtj + la[:, None, None] * np.eye(3)[None] * np.maximum(np.diagonal(jtj, axis1=1, axis2=2), 1e-300)[:, :, None]
        step = -np.linalg.solve(a, g[:, :, None])[:, :, 0]
        trial = pa + step
        trial[:, 2] = np.abs(trial[:, 2])
        rt, ut = residual(trial, y[act])
        ct = np.sum(rt * rt, axis=1)
        better = ct <= cost[act]
        small = better & (np.abs(step[:, 2]) <= 1e-10 * trial[:, 2]) & (np.abs(step[:, 1]) <= 1e-10 * bins.step)
        up = act[better]
        p[up], r[up], u[up], cost[up] = trial[better], rt[better], ut[better], ct[better]
        lam[act] = la = np.where(better, la / 3.0, la * 4.0)
        done[act] = small | (la > 1e12)
        if done.all():
            break
    return np.where(np.isfinite(p[:, 2]) & (p[:, 2] > 0), 2.0 * p[:, 2], np.nan)


def lorentz_hist_fwhm(theta_deg: np.ndarray, spec: FwhmSpec = FwhmSpec()) -> float:
    """FWHM = 2γ of a Lorentzian fitted by least squares to the histogram of the angles [degree]
    (``lorentz-hist``, the source's estimator): bins of ``spec.bin_deg`` (default Freedman–Diaconis)
    over the median ± ``spec.range_iqr`` interquartile ranges (at least ten bins each side).  0 where the
    IQR is 0."""
    x = np.asarray(theta_deg, dtype=np.float64)
    if x.size < 2:
        return float("nan")
    bins = hist_bins(x, spec)
    if bins is None:
        return 0.0
    return float(lorentz_hist_of_counts(bins.counts(x), bins)[0])


def lorentz_ks(theta_deg: np.ndarray) -> float:
    """The Kolmogorov–Smirnov distance between the angles and the Lorentz distribution fitted to
    them by maximum likelihood: how well "Lorentz" describes the rays (0: exactly; a 1000-ray
    Lorentzian sample gives about 0.03)."""
    x = np.sort(np.asarray(theta_deg, dtype=np.float64))
    if x.size < 2:
        return float("nan")
    loc, g = cauchy_fit(x)
    if not g > 0:
        return float("nan")
    cdf = 0.5 + np.arctan((x - loc) / g) / math.pi
    n = x.size
    return float(max(np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n)))


def fwhm(theta_deg: np.ndarray, spec: FwhmSpec | str = FwhmSpec()) -> float:
    """The FWHM of an angle sample [degree] by estimator ``spec`` (a :class:`FwhmSpec` or an
    estimator's name): ``half-max`` (the default), ``lorentz-hist`` or ``lorentz-mle`` (2γ of the
    Cauchy maximum-likelihood fit)."""
    spec = FwhmSpec(spec) if isinstance(spec, str) else spec
    x = np.asarray(theta_deg, dtype=np.float64)
    if spec.estimator == LORENTZ_MLE:
        return 2.0 * cauchy_fit(x)[1] if x.size else float("nan")
    if spec.estimator == LORENTZ_HIST:
        return lorentz_hist_fwhm(x, spec)
    return half_max_fwhm(x)



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


def deviated_from_angles(theta_r: np.ndarray, theta_l: np.ndarray) -> np.ndarray:
    """1.0 where a ray leaves more than 2.5° from +T, from its two projected angles [degree] (a beam
    along +T): the direction is ∝ (tan θ_R, 1, tan θ_L)."""
    tr, tl = np.tan(np.radians(theta_r)), np.tan(np.radians(theta_l))
    return (np.degrees(np.arccos(1.0 / np.sqrt(1.0 + tr * tr + tl * tl))) > HAZE_ANGLE_DEG).astype(np.float64)


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
    from scipy.special import ndtri  # the normal quantile (scipy.stats' norm.ppf; that import is slow)

    if n < 1 or not math.isfinite(haze_fraction):
        return float("nan"), float("nan")
    z = float(ndtri(0.5 + level / 2.0))
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
