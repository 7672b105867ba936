"""The published numbers in `results/` agree with the runs committed beside them: every
report's tables are rebuilt from the copied config.json / metrics files and compared byte for
byte (`ccfit publish` wrote them; a hand edit or a stale table fails here)."""

from __future__ import annotations

from pathlib import Path

import pytest

from ccfit.report import write_report

RESULTS = Path(__file__).resolve().parents[1] / "results"
REPORTS = sorted(p for p in RESULTS.rglob("report") if p.is_dir())


def test_results_hold_published_reports():
    assert REPORTS, f"no published report under {RESULTS}"


@pytest.mark.parametrize("report", REPORTS, ids=lambda p: str(p.parent.relative_to(RESULTS)))
def test_committed_tables_match_the_metrics_beside_them(report, tmp_path):
    write_report([report.parent], tmp_path)
    committed = sorted(p.name for p in report.glob("table_*"))
    assert committed, f"{report} has no tables"
    for name in committed:
        assert (tmp_path / name).read_text() == (report / name).read_text(), name
