"""The paper end to end (`orchestration.experiment_paper`, `ddvs experiment paper`): the report's table carries the
numbers of each run's summary, and a shortened real run (estimation from rendered frames on the free-flying camera; the
real service on the SAPIEN arm) writes summaries, figures and the report, then resumes without re-running."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from orchestration.experiment_paper import PaperSettings, markdown_table, write_report

ROW = {
    "experiment": "arm_ddvs", "plant": "SAPIEN UR5, planar poster", "law": "ddvs", "geometry": "estimated",
    "converged": True, "images": 535, "first_below_threshold": 412, "paper_images": 309, "translation_error_mm": 1.9786,
    "rotation_error_deg": 0.16417, "retreat_mm": 0.0, "coupling": 0.1234, "coupling_near_equilibrium": math.nan,
    "stopped": "converged", "figures": ["plots/velocities.png"],
}


def test_settings_reject_unknown_experiments():
    with pytest.raises(ValueError, match="experiments"):
        PaperSettings(experiments=("arm_pbvs",))


def test_table_and_report_carry_the_numbers(tmp_path):
    table = markdown_table({"arm_ddvs": ROW})
    assert "| arm_ddvs | ddvs | estimated | yes | 535 | 412 | 309 | 1.98 | 0.164 | 0.0 | 0.123 | — |" in table
    report = write_report({"arm_ddvs": ROW}, tmp_path).read_text()
    assert table in report
    assert "![arm_ddvs velocities](arm_ddvs/plots/velocities.png)" in report
    assert "- arm_ddvs: converged" in report
    assert json.loads((tmp_path / "paper.json").read_text())["arm_ddvs"]["images"] == 535


@pytest.mark.slow
def test_shortened_paper_run_writes_the_report_and_resumes(tmp_path: Path):
    from ddvs.cli import main

    chosen = ("synthetic_ddvs", "arm_dvs")
    args = ["experiment", "paper", "--out", str(tmp_path), "--max-images", "4", "--only", *chosen]
    assert main(args) == 1  # nothing can converge in 4 images: the command says so
    rows = json.loads((tmp_path / "paper.json").read_text())
    assert list(rows) == list(chosen)
    report = (tmp_path / "report.md").read_text()
    for name in chosen:
        row = rows[name]
        assert row == json.loads((tmp_path / name / "summary.json").read_text())
        assert row["converged"] is False and 4 <= row["images"] <= 8  # the arm counts status sequence numbers
        assert row["geometry"].startswith("estimated")
        assert row["translation_error_mm"] > 150.0  # still near the paper's start (0.2 m / 0.27 m away)
        assert 0.0 <= row["coupling"] <= 1.0 and row["retreat_mm"] >= 0.0
        line = next(x for x in report.splitlines() if x.startswith(f"| {name} |"))
        assert row["first_below_threshold"] is None
        assert f"| {row['images']} | — | {row['paper_images']} | {row['translation_error_mm']:.2f} |" in line
        for figure in row["figures"]:
            assert (tmp_path / name / figure).stat().st_size > 5_000, figure
    assert rows["synthetic_ddvs"]["paper_images"] == 762 and rows["arm_dvs"]["paper_images"] == 417
    assert {Path(f).name for f in rows["arm_dvs"]["figures"]} >= {"velocities.png", "trajectory.png"}

    # Resumed: the summaries exist, so nothing runs again (the arm recording would otherwise be replaced).
    stamps = {name: (tmp_path / name / "summary.json").stat().st_mtime_ns for name in chosen}
    assert main(args) == 1
    assert stamps == {name: (tmp_path / name / "summary.json").stat().st_mtime_ns for name in chosen}
