"""benchmarks/retrace.py: the paired old -> new differences that judge a tracer version change."""

import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import retrace  # noqa: E402


def _dataset(haze_per_wood: np.ndarray) -> xr.Dataset:
    """A study Dataset's haze at two values of ΔRI over len(woods) woods (seeds 1..R)."""
    r = haze_per_wood.shape[1]
    return xr.Dataset({"haze": (("delta_ri",), haze_per_wood.mean(axis=1)),
                       "haze_per_realisation": (("delta_ri", "realisation"), haze_per_wood)},
                      coords={"delta_ri": [0.002, 0.01], "realisation": np.arange(r),
                              "seed_of_realisation": ("realisation", np.arange(1, r + 1))})


def test_a_change_alike_in_every_wood_is_flagged_not_resolved_and_a_spread_one_is_judged_by_its_interval():
    old = np.array([[0.0150, 0.0170, 0.0160], [0.10, 0.12, 0.11]])
    # ΔRI 0.002: one ray in 4000 across the cut in each wood alike (zero spread: a t interval of width 0);
    # ΔRI 0.01: every wood up by about a point, with a spread.
    new = old + np.array([[-0.00025] * 3, [0.0100, 0.0110, 0.0090]])
    rows = retrace.paired(_dataset(old), _dataset(new), "haze")
    alike, spread = rows
    assert alike["alike"] and not alike["resolved"] and alike["p"] != alike["p"]
    assert alike["diff"] == pytest.approx(-0.025)  # points of haze
    assert not spread["alike"] and spread["resolved"] and 0.0 < spread["p"] < 0.05
    assert spread["diff"] == pytest.approx(1.0) and 0.0 < spread["half"] < 1.0
    text = retrace.markdown({"study": {"haze": rows}})
    assert "1 of 2 paired differences resolved" in text and "1 moved by the same amount in every wood" in text
    assert "alike in every wood (no spread)" in text


def test_woods_are_paired_by_seed_not_by_position():
    old = _dataset(np.array([[0.01, 0.02, 0.03], [0.1, 0.2, 0.3]]))
    new = old.isel(realisation=[2, 0, 1])  # the same woods, in another order: nothing moved
    new = new.assign_coords(realisation=np.arange(3))
    rows = retrace.paired(old, new, "haze")
    assert all(r["diff"] == 0.0 and not r["resolved"] and not r["alike"] for r in rows)
