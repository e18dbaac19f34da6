"""Running studies: plan, compute what is missing, widen to a target precision, publish.

The one orchestrator of a study run, whatever calls it (``twray study``,
benchmarks, tests): it plans every study against the cache, computes the
missing stages on a client it opens only when something is missing, traces
further (more rays or more woods) where a ``target_ci`` is not met, and returns the
final plans.
"""

from __future__ import annotations

from .graph import compute
from .plan import Plan, plan_study, summary_rows, target_met, widen


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
            # A study with a `target_ci` is traced further (more rays or more woods) until it is met.
            wider = [widen(p) for p in plans]
            if not any(wider):
                _say_unmet(plans, log)
                return plans
            for st in wider:
                if st is not None:
                    what = (f"{st.realisations} woods" if st.scenes[0].target.over == "woods"
                            else f"{st.scenes[0].rays} rays")
                    log(f"twray study: {st.name}: an interval is wider than target_ci; tracing {what}")
            plans = [plan_study(w, cache_dir, shard_rays=shard_rays) if w is not None else p
                     for w, p in zip(wider, plans)]


def _say_unmet(plans: list[Plan], log) -> None:
    """One line for the studies whose target is not met at their cap (grouped by the cap)."""
    unmet: dict[str, list[str]] = {}
    for p in plans:
        target = p.study.scenes[0].target
        if target is None or target_met(target, summary_rows(p)):
            continue
        woods = target.over == "woods"
        cap = f"{target.max_realisations} woods" if woods else f"{target.max_rays} rays"
        fix = (f"raise `target_ci.max_{'realisations' if woods else 'rays'}`" if p.study.scale == "paper"
               else "--scale paper traces to the target")
        unmet.setdefault(f"at the cap of {cap} ({p.study.scale} scale): {fix}", []).append(p.study.name)
    for why, names in unmet.items():
        log(f"twray study: {', '.join(names)}: {'an interval is' if len(names) == 1 else 'intervals are'} still "
            f"wider than target_ci {why}")
