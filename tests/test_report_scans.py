"""The grey-level scans' section of results/accuracy.md and REPORT.md (pipeline/report_scans.py)."""

import json
from pathlib import Path

from pipeline.report_scans import section_of

RESULTS = Path(__file__).resolve().parent.parent / "results"


def test_the_scans_section_is_read_from_what_bench_iso_wrote_and_the_committed_pages_are_current(tmp_path):
    assert section_of(tmp_path) == []  # nothing measured: no section
    text = "\n".join(section_of(RESULTS))
    many = json.loads((RESULTS / "iso_25woods.json").read_text())["configs"][0]
    assert {e["method"] for e in many["table"]} == {"iso", "iso smoothed 0.5 µm", "accurate"}
    for e in many["table"]:  # the 25-wood aim, each method's row with its interval
        assert e["woods"] == 25
        assert (f"| {e['method']} | {e['fwhm_r'][0]:+.1f} ± {e['fwhm_r'][1]:.1f} | "
                f"{e['fwhm_l'][0]:+.1f} ± {e['fwhm_l'][1]:.1f} | {e['haze'][0]:+.2f} ± {e['haze'][1]:.2f} |") in text
    # Both pages print the section as the files now hold it (regenerated with them).
    assert text in (RESULTS / "accuracy.md").read_text()
    assert text in (RESULTS / "REPORT.md").read_text()
