"""Shared by the benchmarks: results/bench.json holds one section per benchmark."""

import json
from pathlib import Path


def write_section(path: str, name: str, result: dict) -> None:
    """Replace section ``name`` of the JSON file at ``path`` and print the result."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = json.loads(out.read_text()) if out.exists() else {}
    doc[name] = result
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(result, indent=2))
