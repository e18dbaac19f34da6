"""A study's missing stages as one Dask graph, and running it on a ``distributed`` client."""

from __future__ import annotations

from dataclasses import dataclass, field

from .plan import Micro, Plan
from .tasks import generate_chunks, pool_value, summarize_scene, trace_shard

COLUMN_BATCH = 16  # chunks per microstructure task


@dataclass
class Graph:
    """The Dask tasks computing the missing stages of some plans."""

    micro: list  # delayed chunk counts
    summaries: list  # delayed {"pool": ..., "chunks_generated": ...}, one per value
    n_trace: int
    n_summaries: int = 0
    labels: dict = field(default_factory=dict)  # task key: what it computes, for the user's line
    weights: dict = field(default_factory=dict)  # trace task key: its estimated CPU-seconds, for the time left


def wood_of(scene, shard) -> str:
    """What a shard's trace builds and keeps per wood (chunks, distortion tiles, vessels): its wood
    chunk store for a voxel method, else the wood's (or lattice's) parameters and seed; the same for
    every value and study that share the wood."""
    from ..cache import cache_key

    if shard.micro is not None:
        return shard.micro
    what = scene.reference.to_dict() if scene.reference is not None else scene.wood.key_dict()
    return cache_key({"wood": what, "seed": scene.seed})


def build_graph(plans: list[Plan]) -> Graph:
    """Dask delayed objects computing every missing stage of ``plans``."""
    import dask

    from ..limits import shard_estimate

    # Task arguments enter the graph once each, by name, and untraversed: dask would
    # otherwise walk every dataclass field of every argument of every task.
    def constant(obj, name):
        return dask.delayed(obj, name=name, traverse=False)

    # Studies that share a wood (say study 1 and study 2) share its chunk tasks.
    todo: dict[str, set] = {}
    woods: dict[str, Micro] = {}
    labels: dict[str, str] = {}
    for plan in plans:
        for m in plan.micros.values():
            todo.setdefault(m.key, set()).update(m.todo)
            woods.setdefault(m.key, m)
    micro_tasks: dict[str, list] = {}
    micro_args: dict[str, object] = {}
    for key, m in woods.items():
        chunks = sorted(todo[key])
        micro_args[key] = arg = constant(m.slim(), f"wood-{key[:12]}")
        for i in range(0, len(chunks), COLUMN_BATCH):
            labels[f"micro-{key[:12]}-{i // COLUMN_BATCH}"] = f"wood chunks of {m.path}"
        labels[f"wood-{key[:12]}"] = f"wood chunks of {m.path}"
        micro_tasks[key] = [
            dask.delayed(generate_chunks, pure=False)(
                arg, chunks[i:i + COLUMN_BATCH], dask_key_name=f"micro-{key[:12]}-{i // COLUMN_BATCH}")
            for i in range(0, len(chunks), COLUMN_BATCH)]
    summaries = []
    pools = []
    weights: dict[str, float] = {}
    wood_rank: dict[str, int] = {}
    n_trace = 0
    for plan in plans:
        done = {}
        for summ in plan.summaries:
            if summ.cached:
                continue
            sc = plan.study.realisation(summ.scene_index, summ.realisation)
            scene = constant(sc, f"scene-{summ.key[:12]}")
            what = f"{plan.study.name} {plan.study.label(summ.scene_index)} realisation {summ.realisation}"
            # A worker that dies may be holding a task's arguments: they are named after its scene too.
            for name in ("summary", "scene", "summ", "shards"):
                labels[f"{name}-{summ.key[:12]}"] = f"{what}, summary"
            traced = []
            for shard in plan.shards_of(summ):
                if not shard.cached:
                    n_trace += 1
                    wood = shard.micro
                    for name in ("rays", "shard"):
                        labels[f"{name}-{shard.key[:12]}"] = f"{what}, rays {shard.lo}-{shard.hi}"
                    weights[f"rays-{shard.key[:12]}"] = shard_estimate(sc, shard.hi - shard.lo).cpu_s
                    # Wood by wood: a worker keeps a wood's distortion tiles while it traces that wood's
                    # shards, of every value and study that share the wood, instead of building them again.
                    rank = wood_rank.setdefault(wood_of(sc, shard), len(wood_rank))
                    with dask.annotate(priority=-rank):
                        traced.append(dask.delayed(trace_shard, pure=False)(
                            micro_args.get(wood), scene, constant(shard, f"shard-{shard.key[:12]}"),
                            *micro_tasks.get(wood, ()), dask_key_name=f"rays-{shard.key[:12]}"))
            shards = constant(plan.shards_of(summ), f"shards-{summ.key[:12]}")
            done[summ.key] = dask.delayed(summarize_scene, pure=False)(
                scene, constant(summ, f"summ-{summ.key[:12]}"), shards, *traced,
                dask_key_name=f"summary-{summ.key[:12]}")
            summaries.append(done[summ.key])
        for pool in plan.pools:
            if pool.cached:
                continue
            mine = plan.summaries_of(pool)
            for name in ("pool", "pool-shards", "scene0", "poolarg"):
                labels[f"{name}-{pool.key[:12]}"] = f"{plan.study.name} {plan.study.label(pool.scene_index)}, pooling"
            shards = constant([plan.shards_of(s) for s in mine], f"pool-shards-{pool.key[:12]}")
            pools.append(dask.delayed(pool_value, pure=False)(
                constant(plan.study.realisation(pool.scene_index, 0), f"scene0-{pool.key[:12]}"), constant(pool, f"poolarg-{pool.key[:12]}"), shards,
                *[done[s.key] for s in mine if s.key in done], dask_key_name=f"pool-{pool.key[:12]}"))
    micro = [t for ts in micro_tasks.values() for t in ts]
    return Graph(micro, pools, n_trace, len(summaries), labels, weights)


def compute(plans: list[Plan], client, *, progress: str = "off") -> dict:
    """Run the missing stages of ``plans`` on a ``distributed.Client`` (``progress``: "bar",
    "lines" or "off", see :mod:`pipeline.progress`).

    Returns counts of what ran: tasks per stage and wood chunks generated.
    """
    graph = build_graph(plans)
    report = {"micro_tasks": len(graph.micro), "trace_tasks": graph.n_trace,
              "summary_tasks": graph.n_summaries, "pool_tasks": len(graph.summaries), "chunks_generated": 0}
    if not graph.micro and not graph.summaries:
        return report
    from ..progress import graph_keys
    from ..runlog import gather_graph

    futures = client.compute(graph.micro + graph.summaries)
    results = gather_graph(client, futures, graph_keys(graph.micro + graph.summaries), "twray study", progress,
                           graph.labels, graph.weights)
    n = len(graph.micro)
    report["chunks_generated"] = int(sum(results[:n]) + sum(r["chunks_generated"] for r in results[n:]))
    return report
