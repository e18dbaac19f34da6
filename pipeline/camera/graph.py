"""The missing images of a camera file as one Dask graph on a ``distributed.Client``: one task
per block of sensor rows, the tasks of all images together."""

from __future__ import annotations

from .plan import ROWS_PER_TASK, Entry, plan_blocks
from .tasks import assemble, load_block, render_block


def compute(entries: list[Entry], client, cache_dir, *, rows_per_task: int = ROWS_PER_TASK,
            progress: str = "off") -> dict:
    """Render every image of ``entries`` that is not cached, on a ``distributed.Client``: the
    row blocks an earlier run finished are read, the others rendered.

    Returns counts: images assembled, row blocks rendered and read, camera rays traced."""
    import dask

    tasks = []
    report = {"images": 0, "row_tasks": 0, "rows_cached": 0, "rays": 0}
    labels = {}
    for e in entries:
        if e.cached:
            continue
        labels[f"camera-image-{e.key[:12]}"] = labels[f"camera-config-{e.key[:12]}"] = f"camera image {e.config.name}"
        cfg = dask.delayed(e.config, name=f"camera-config-{e.key[:12]}", traverse=False)
        blocks = []
        plan = plan_blocks(e, cache_dir, rows_per_task)
        for b in plan:
            name = f"camera-rows-{e.key[:12]}-{b.lo}"
            labels[name] = f"camera image {e.config.name}, rows {b.lo}-{b.hi}"
            if b.cached:
                blocks.append(dask.delayed(load_block, pure=False)(str(b.path), b.key, b.lo, b.hi, dask_key_name=name))
                report["rows_cached"] += 1
            else:
                blocks.append(dask.delayed(render_block, pure=False)(cfg, b.lo, b.hi, str(cache_dir), str(b.path),
                                                                     dask_key_name=name))
                report["row_tasks"] += 1
                report["rays"] += (b.hi - b.lo) * e.config.camera.pixels[1] * e.config.camera.samples
        tasks.append(dask.delayed(assemble, pure=False)(
            cfg, str(e.path), [str(b.path) for b in plan], *blocks, dask_key_name=f"camera-image-{e.key[:12]}"))
    report["images"] = len(tasks)
    if not tasks:
        return report
    from ..progress import graph_keys
    from ..runlog import gather_graph

    futures = client.compute(tasks)
    gather_graph(client, futures, graph_keys(tasks), "twray camera", progress, labels)
    return report
