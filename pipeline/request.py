"""What a command that runs a cached Dask graph (``twray study``, ``twray camera``) asks for, beside
its own inputs: where the cache and the results are, the scale and method, whether to only plan
or to run past the confirmation threshold, how progress shows, and what starting the workers costs."""

from __future__ import annotations

from dataclasses import dataclass, field

from .limits import Estimate


@dataclass(frozen=True, kw_only=True)
class GraphRequest:
    cache: str  # absolute, resolved on the client (the workers may run elsewhere)
    results: str
    scale: str = "paper"
    method: str | None = None  # instead of the file's trace.method
    dry_run: bool = False
    yes: bool = False
    progress: str = "off"
    started: Estimate = field(default_factory=Estimate)  # the command and the workers it starts
    workers: int = 0  # the local workers it starts (0: a running scheduler's, unknown here)
