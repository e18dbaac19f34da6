"""Running studies: plan, compute what is missing, widen to a target precision, publish.

The one orchestrator of a study run, whatever calls it (``twray study``,
benchmarks, tests): it plans every study against the cache, computes the
missing stages on a client it opens only when something is missing, traces
again with twice the rays where a ``target_ci`` is not met, and returns the
final plans.
"""

from __future__ import annotations

from .graph import compute
from .plan import Plan, plan_study, widen


def run_studies(plans: list[Plan], cache_dir, *, open_client, shard_rays: int, progress: str = "off",
                log=print) -> list[Plan]:
    """Compute ``plans`` (from :func:`~pipeline.study.plan.plan_study`) until every stage is
    cached and every target met; returns the final plans.

    ``open_client()`` returns a context manager yielding a ``distributed.Client``;
    it is entered once, and only if something is to compute.
    """
    import contextlib

    with contextlib.ExitStack() as stack:
        client = None
        while True:
            if not all(p.up_to_date for p in plans):
                if client is None:
                    client = stack.enter_context(open_client())
                compute(plans, client, progress=progress)
                plans = [plan_study(p.study, cache_dir, shard_rays=shard_rays) for p in plans]
            # A study with a `target_ci` is traced again with twice the rays until it is met.
            wider = [widen(p) for p in plans]
            if not any(wider):
                return plans
            for st in wider:
                if st is not None:
                    log(f"twray study: {st.name}: an interval is wider than target_ci; "
                        f"tracing {st.scenes[0].rays} rays")
            plans = [plan_study(w, cache_dir, shard_rays=shard_rays) if w is not None else p
                     for w, p in zip(wider, plans)]
