"""Convergence-domain sweep (`orchestration.experiment_domain`, `ddvs experiment domain`): the random starts have the
requested size and see the target, the table counts outcomes, a resumed sweep reuses only compatible trials, and a
tiny real sweep (rendered frames, real estimators) writes its table, journal and plot."""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import pytest

from ddvs_service.lie import pose_inv, so3_log
from orchestration.experiment_domain import (
    CAMERA,
    OUTCOMES,
    UNIT_R_DEG,
    UNIT_T_M,
    DomainSettings,
    Trial,
    initial_pose,
    markdown_table,
    run_domain,
    success_table,
    trial_start,
)


@pytest.mark.parametrize("size", [0.5, 2.0, 4.0])
def test_initial_pose_has_the_size_and_sees_the_target(size):
    for k in range(5):
        T = initial_pose(size, np.random.default_rng([0, k]))
        assert np.linalg.norm(T[:3, 3]) == pytest.approx(size * UNIT_T_M, rel=1e-12)
        assert np.degrees(np.linalg.norm(so3_log(T[:3, :3]))) == pytest.approx(size * UNIT_R_DEG, rel=1e-9)
        X = (pose_inv(T) @ np.array([0.0, 0.0, 1.0, 1.0]))[:3]
        u, v = (CAMERA.K @ (X / X[2]))[:2]
        assert X[2] > 0 and 0 <= u < CAMERA.width and 0 <= v < CAMERA.height


def test_trial_starts_are_reproducible_and_vary_with_trial_size_and_seed():
    settings = DomainSettings(seed=3)
    (a, seed_a), (b, seed_b) = trial_start(settings, 2.0, 1), trial_start(DomainSettings(seed=3, sizes=(2.0,)), 2.0, 1)
    np.testing.assert_array_equal(a, b)  # independent of the other sizes swept
    assert seed_a == seed_b
    others = [trial_start(settings, 2.0, 2), trial_start(DomainSettings(seed=4), 2.0, 1), trial_start(settings, 3.0, 1)]
    for T, seed in others:
        assert not np.allclose(a[:3, 3] / np.linalg.norm(a[:3, 3]), T[:3, 3] / np.linalg.norm(T[:3, 3]))
        assert seed != seed_a


def test_settings_reject_unknown_names_and_bad_values():
    with pytest.raises(ValueError, match="targets"):
        DomainSettings(targets=("cube",))
    with pytest.raises(ValueError, match="laws"):
        DomainSettings(laws=("pbvs",))
    with pytest.raises(ValueError, match="sizes"):
        DomainSettings(sizes=(0.0,))
    with pytest.raises(ValueError, match="noise"):
        DomainSettings(noise=-1.0)


def _trial(law: str, size: float, k: int, outcome: str, images: int) -> Trial:
    return Trial("planar", law, size, k, size * UNIT_T_M, size * UNIT_R_DEG, outcome, images, 1e-3, 0.0, 0.0, "")


def test_success_table_counts_each_outcome():
    trials = [_trial("ddvs", 1.0, 0, "success", 100), _trial("ddvs", 1.0, 1, "success", 200),
              _trial("ddvs", 1.0, 2, "lost", 5), _trial("dvs", 1.0, 0, "budget", 400)]
    rows = {(r["law"], r["size"]): r for r in success_table(trials)}
    ddvs, dvs = rows[("ddvs", 1.0)], rows[("dvs", 1.0)]
    assert (ddvs["trials"], ddvs["success"], ddvs["lost"], ddvs["rate"], ddvs["mean_images"]) == (3, 2, 1, 2 / 3, 150)
    assert (dvs["budget"], dvs["rate"]) == (1, 0.0) and np.isnan(dvs["mean_images"])
    assert sum(ddvs[o] for o in OUTCOMES) == ddvs["trials"]
    table = markdown_table(success_table(trials))
    assert "| planar | ddvs | 1 | 0.050 | 15 | 3 | 2 | 67% | 1 | 0 | 0 | 0 | 150 |" in table


def test_resume_refuses_other_physics(tmp_path):
    (tmp_path / "settings.json").write_text(json.dumps({**asdict(DomainSettings()), "noise": 2.0}))
    with pytest.raises(ValueError, match="noise"):
        run_domain(DomainSettings(), tmp_path)


@pytest.mark.slow
def test_tiny_sweep_through_the_cli_writes_table_journal_and_plot(tmp_path):
    from ddvs.cli import main

    args = ["experiment", "domain", "--target", "planar", "--law", "ddvs", "--trials", "2", "--sizes", "0.5", "3",
            "--max-images", "20", "--noise", "1", "--illumination", "--seed", "7", "--out", str(tmp_path)]
    assert main(args) == 0
    journal = [json.loads(line) for line in (tmp_path / "trials.jsonl").read_text().splitlines()]
    assert len(journal) == 4
    assert {(t["size"], t["trial"]) for t in journal} == {(0.5, 0), (0.5, 1), (3.0, 0), (3.0, 1)}
    for t in journal:
        assert t["outcome"] in OUTCOMES
        assert 1 <= t["images"] <= 20
        assert t["initial_translation_m"] == pytest.approx(t["size"] * UNIT_T_M)
    small = [t for t in journal if t["size"] == 0.5]
    assert all(t["outcome"] == "budget" and t["images"] == 20 for t in small)  # 2 s simulated: too short to converge
    report = json.loads((tmp_path / "domain.json").read_text())
    assert report["settings"]["noise"] == 1.0 and report["settings"]["illumination"] is True
    assert [(r["size"], r["trials"]) for r in report["rows"]] == [(0.5, 2), (3.0, 2)]
    markdown = (tmp_path / "domain.md").read_text()
    assert "| planar | ddvs | 0.5 | 0.025 | 8 | 2 | 0 | 0% | 0 | 0 | 2 | 0 | nan |" in markdown
    assert (tmp_path / "domain.png").stat().st_size > 10_000

    # Resumed with one more trial: the four journalled trials are reused, only the new ones run.
    settings = DomainSettings(targets=("planar",), laws=("ddvs",), sizes=(3.0,), trials=3, noise=1.0,
                              illumination=True, seed=7, max_images=20)
    trials = run_domain(settings, tmp_path)
    assert len(trials) == 3
    assert len((tmp_path / "trials.jsonl").read_text().splitlines()) == 5
    assert trials[0] == next(Trial(**t) for t in journal if (t["size"], t["trial"]) == (3.0, 0))
