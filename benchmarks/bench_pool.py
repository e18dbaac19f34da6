"""What a value's pool costs (pipeline.summary.pool: every estimator, 2000 resamples of woods and
of rays) against the woods and rays pooled, for pipeline/limits.py's POOL_CPU_S and
POOL_CPU_S_PER_RAY.  Lorentzian-and-Gaussian angles stand in for rays (the estimators' cost does
not depend on where angles come from).  Prints one line per size and the fitted constants."""

from __future__ import annotations

import time

import numpy as np

from pipeline.summary import reduce_angles


def main():
    rng = np.random.default_rng(0)
    reduce_angles([(rng.standard_cauchy(50), rng.standard_cauchy(50), np.ones(50))] * 2)  # compiled kernels loaded
    rows = []
    for woods, rays in ((3, 200), (5, 1000), (16, 1000), (40, 1000)):
        parts = [(5 * rng.standard_normal(rays) + rng.standard_cauchy(rays), 0.5 * rng.standard_cauchy(rays),
                  (rng.random(rays) < 0.8).astype(float)) for _ in range(woods)]
        c0 = time.process_time()
        reduce_angles(parts, seed=1)
        cpu = time.process_time() - c0
        rows.append((woods * rays, cpu))
        print(f"{woods} woods x {rays} rays: {cpu:.2f} CPU-s")
    n, c = np.array(rows).T
    b, a = np.polyfit(n, c, 1)
    print(f"fit: {a:.2f} CPU-s + {b:.2e} CPU-s a ray")


if __name__ == "__main__":
    main()
