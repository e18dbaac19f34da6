"""What a value's pool costs (pipeline.summary.pool: every estimator, 2000 resamples of woods and
of rays) against the woods and rays pooled, for pipeline/limits.py's pool_cpu_s.  Lorentzian-and-
Gaussian angles stand in for rays (the estimators' cost does not depend on where angles come from).

One wood: every estimator's interval over its rays, a + b · rays.  Several: the fits to resamples
of woods dominate, and a resample drawn twice is fitted once, so the cost follows the fraction f of
the 2000 resamples that are distinct (limits.distinct_resamples): a + a_f · f + rays · (b + b_f · f).
Prints one line per size and the fitted constants."""

from __future__ import annotations

import time

import numpy as np

from pipeline.limits import distinct_resamples
from pipeline.summary import N_BOOT, reduce_angles

SIZES = ((1, 250), (1, 1000), (1, 4000), (3, 1000), (5, 200), (5, 1000), (5, 4000), (8, 1000), (16, 250),
         (16, 1000), (40, 250), (40, 1000))


def main():
    rng = np.random.default_rng(0)
    reduce_angles([(rng.standard_cauchy(50), rng.standard_cauchy(50), np.ones(50))] * 2)  # compiled kernels loaded
    one, many = [], []
    for woods, rays in SIZES:
        parts = [(5 * rng.standard_normal(rays) + rng.standard_cauchy(rays), 0.5 * rng.standard_cauchy(rays),
                  (rng.random(rays) < 0.8).astype(float)) for _ in range(woods)]
        c0 = time.process_time()
        reduce_angles(parts, seed=1)
        cpu = time.process_time() - c0
        n, f = woods * rays, distinct_resamples(woods) / N_BOOT
        (one if woods == 1 else many).append((n, f, cpu))
        print(f"{woods} woods x {rays} rays (f = {f:.3f}): {cpu:.2f} CPU-s", flush=True)
    n, _, c = np.array(one).T
    b, a = np.polyfit(n, c, 1)
    print(f"one wood: {a:.2f} CPU-s + {b:.2e} CPU-s a ray")
    n, f, c = np.array(many).T
    (a, af, b, bf), *_ = np.linalg.lstsq(np.stack([np.ones_like(n), f, n, n * f], axis=1), c, rcond=None)
    print(f"several: {a:.2f} + {af:.2f} f CPU-s + ({b:.2e} + {bf:.2e} f) CPU-s a ray")


if __name__ == "__main__":
    main()
