"""The paper's synthetic experiment with exact geometry: both laws converge from the paper's initial displacement,
reach < 0.01 mm / 0.001° at a 1e-6 threshold, without retreat worth the name; the decoupled law converges faster and
its translation stops depending on the rotation near the equilibrium. The CLI prints one JSON line and saves plots."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from ddvs.cli import main
from orchestration.experiment_cli import GEOMETRIES
from orchestration.experiment_synthetic import GEOMETRY_SOURCES, SyntheticSetup, run_synthetic


@pytest.fixture(scope="module")
def runs() -> dict:
    return {
        (law, threshold): run_synthetic(law, replace(SyntheticSetup(), threshold=threshold))
        for law in ("dvs", "ddvs")
        for threshold in (1e-3, 1e-6)
    }


@pytest.mark.parametrize("law", ["dvs", "ddvs"])
def test_both_laws_converge_from_the_paper_displacement(runs: dict, law: str) -> None:
    coarse, fine = runs[(law, 1e-3)], runs[(law, 1e-6)]
    assert coarse.converged and fine.converged
    assert coarse.error_norms[-1] < 1e-3 <= coarse.error_norms[-2]
    assert coarse.translation_error_m < 3e-3 and coarse.rotation_error_deg < 0.1  # ~1 mm at the 1e-3 threshold
    assert fine.translation_error_m < 1e-5 and fine.rotation_error_deg < 1e-3
    assert coarse.retreat_m < 0.01  # "without nearly any camera retreat"


def test_decoupled_law_is_faster_and_decoupled_near_the_equilibrium(runs: dict) -> None:
    dvs, ddvs = runs[("dvs", 1e-3)], runs[("ddvs", 1e-3)]
    assert ddvs.images < dvs.images
    assert ddvs.coupling < dvs.coupling
    assert ddvs.coupling_near_equilibrium < 0.1 < dvs.coupling_near_equilibrium
    assert ddvs.path_excess < dvs.path_excess


def test_cli_prints_one_json_line_and_saves_plots(runs: dict, tmp_path, capsys) -> None:
    rc = main(["experiment", "synthetic", "--law", "ddvs", "--geometry", "exact", "--json", "--out", str(tmp_path)])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip())
    assert summary["converged"] and summary["images"] == runs[("ddvs", 1e-3)].images and summary["paper_images"] == 762
    for key in ("translation_error_m", "rotation_error_deg", "retreat_m", "coupling", "path_excess"):
        assert key in summary
    for path in summary["plots"]:
        assert (tmp_path / path.split("/")[-1]).stat().st_size > 10_000


def test_cli_takes_another_displacement_and_lists_every_geometry_source(tmp_path, capsys) -> None:
    args = ["experiment", "synthetic", "--law", "dvs", "--t", "0.05", "0", "0", "--r", "0", "0", "0.2", "--json"]
    assert main([*args, "--no-plots"]) == 0
    assert json.loads(capsys.readouterr().out)["images"] < 1000
    assert set(GEOMETRIES) == set(GEOMETRY_SOURCES)
