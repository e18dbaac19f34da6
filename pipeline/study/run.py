"""Running studies: plan, compute what is missing, widen to a target precision, publish.

The one orchestrator of a study run, whatever calls it (``twray study``,
benchmarks, tests): it plans every study against the cache, computes the
missing stages on a client it opens only when something is missing, traces
further (more rays or more woods) where a ``target_ci`` is not met, and returns the
final plans.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .. import limits
from ..params import ParameterError
from ..request import GraphRequest
from .graph import compute
from .plan import Plan, describe_plan, plan_study, report_table, summary_rows, target_met, widen
from .spec import at_target_cap, load_study

FIT = "use fewer rays, a narrower beam, larger voxels or a thinner sample"  # what to change when a study is too big


@dataclass(frozen=True, kw_only=True)
class StudyRequest(GraphRequest):
    """What ``twray study`` asks for (:func:`run`)."""

    files: tuple
    shard_rays: int = 250
    realisations: int | None = None
    rays: int | None = None
    report: Path | None = None  # also a Markdown table of every study


@dataclass
class StudyOutcome:
    """What :func:`run` did: the final plans (planned only, on a dry run), the datasets written and
    the report, and how long it took."""

    plans: list
    datasets: list
    report: Path | None
    seconds: float
    dry_run: bool = False


def say(line: str) -> None:
    """A line for the user while a run goes (stderr: stdout holds the results)."""
    print(line, file=sys.stderr)


def run(request: StudyRequest, *, open_client, log=say) -> StudyOutcome:
    """Load the study files of ``request``, refuse what could not fit, plan against the cache, and
    (unless a dry run) compute what is missing on the client ``open_client()`` opens, to every
    target, and publish each study's Dataset (and the report table)."""
    from .dataset import write_dataset

    studies = [load_study(f, scale=request.scale, realisations=request.realisations, method=request.method,
                          rays=request.rays) for f in request.files]
    names = [s.name for s in studies]
    if len(set(names)) != len(names):
        raise ParameterError(f"study files must have distinct names, got {names}")
    unused = [s.name for s in studies if "voxel_um" in s.unused]
    if unused:
        log(f"twray study: `voxel_um` is unused in {', '.join(unused)}: method exact traces the model's own "
            "surfaces, no voxels (it applies with --method fast, accurate or paper)")
    # What could never fit is refused before planning (which lists the wood's chunks).
    # A target over woods may trace up to its cap of woods (over rays, study_estimate takes its cap of rays).
    scenes = [sc for st in studies for sc in at_target_cap(st).all_scenes()]
    # The workers' first traces compile the kernels where this checkout has not yet on this machine.
    compiling = limits.compiling({sc.settings.medium_kind for sc in scenes}, request.workers)
    est = request.started + compiling + limits.study_estimate(scenes, shard_rays=request.shard_rays)
    limits.check(est, what="`study`", yes=True, disk_path=request.cache, fit=FIT)
    t0 = time.perf_counter()
    plans = [plan_study(s, request.cache, shard_rays=request.shard_rays) for s in studies]
    todo = [plan.study.realisation(summ.scene_index, summ.realisation)
            for plan in plans for summ in plan.summaries if not summ.cached]
    more = [sc for st in studies for sc in at_target_cap(st).all_scenes() if sc.realisation >= st.realisations]
    est = request.started + limits.study_estimate(todo + more, shard_rays=request.shard_rays)
    if todo or more:
        est = est + compiling
        first = limits.first_run_line("study", compiling, request.workers)
        if first:
            log(first)
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        upto = f" (up to {len(more)} more at the targets' caps of woods)" if more else ""
        log(f"twray study: estimate for the {len(todo)} value{'' if len(todo) == 1 else 's'} to compute{upto}: "
            f"{est.text()}")
    if request.dry_run:
        return StudyOutcome(plans, [], None, time.perf_counter() - t0, dry_run=True)
    limits.check(est, what="`study`", yes=request.yes, disk_path=request.cache, fit=FIT)
    plans = run_studies(plans, request.cache, open_client=open_client, shard_rays=request.shard_rays,
                        progress=request.progress, log=log)
    datasets = [write_dataset(plan, request.results) for plan in plans]
    if request.report is not None:
        from ..cache import atomic_write

        atomic_write(request.report, lambda tmp: tmp.write_text(report_table(plans)))
    return StudyOutcome(plans, datasets, request.report, time.perf_counter() - t0)


def describe(outcome: StudyOutcome) -> list[str]:
    """The lines ``twray study`` prints: a dry run's stages, or each study's Dataset and values."""
    if outcome.dry_run:
        return [line for plan in outcome.plans for line in describe_plan(plan)]
    lines = []
    for plan, out in zip(outcome.plans, outcome.datasets):
        st = plan.study
        target = st.scenes[0].target
        cap = f"max_realisations {target.max_realisations}" if target and target.over == "woods" else (
            f"max_rays {target.max_rays}" if target else "")
        unmet = (f", target_ci NOT met at {cap}" if st.scale == "paper"
                 else f", target_ci not met at the {st.scale} scale's {cap}")
        met = "" if target is None else (
            ", target_ci met" if target_met(target, summary_rows(plan)) else unmet)
        lines.append(f"{out}: {st.title} (scale {st.scale}, {st.scenes[0].rays} rays x {st.realisations} "
                     f"realisation{'' if st.realisations == 1 else 's'}, {st.scenes[0].settings.method}{met})")
        for row in summary_rows(plan):
            traced = "" if st.scale == "paper" else f" ({row['thickness_traced_mm']:g} mm traced)"
            lines.append(f"  {row['label']}{traced}: FWHM_R {row['fwhm_r_deg']:.2f}°, "
                         f"FWHM_L {row['fwhm_l_deg']:.2f}°, haze {100 * row['haze']:.1f} % "
                         f"[{100 * row['haze_ci'][0]:.1f}, {100 * row['haze_ci'][1]:.1f}], "
                         f"{row['n_transmitted']}/{row['n_rays']} transmitted")
    if outcome.report is not None:
        lines.append(f"wrote {outcome.report}")
    return lines + [f"{len(outcome.plans)} studies in {outcome.seconds:.1f} s"]


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
