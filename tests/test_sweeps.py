"""Trials on Ray (`orchestration.trials`, `orchestration.ray_trials`, docs/sweeps.md): the status line, failures kept
apart from the records, a journal in key order whatever order the trials end in, and real domain sweeps — on a
two-node Ray cluster on this host (Ray's `cluster_utils`), with a worker killed mid-sweep, stopped with Ctrl-C — whose
journals equal the sequential sweep's, byte for byte, once resumed."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import psutil
import pytest

from orchestration.experiment_domain import DomainSettings, run_domain
from orchestration.journal import run_journalled
from orchestration.progress import status_line
from orchestration.trials import TrialsFailed, run_trials
from orchestration.workers import SEQUENTIAL, Workers

ROOT = Path(__file__).resolve().parents[1]
# A small sweep: 16 trials of a few seconds each (too short to converge: each runs its 30 images; longer closed loops
# drift apart by the rounding of Taichi's sums over 2 threads against 1). So many that a Ctrl-C sent on the first
# journalled trial lands before the last one ends, on a quiet host too.
TRIALS = 8
SWEEP = DomainSettings(targets=("planar",), laws=("ddvs",), sizes=(0.5, 3.0), trials=TRIALS, max_images=30,
                       noise=1.0, seed=7)
SWEEP_ARGS = ["experiment", "domain", "--target", "planar", "--law", "ddvs", "--trials", str(TRIALS), "--sizes", "0.5",
              "3", "--max-images", "30", "--noise", "1", "--seed", "7"]
N_TRIALS = 2 * TRIALS
STORE = 80 * 1024**2  # each Ray node's object store (bytes)


def test_status_line_counts_failures_and_estimates_the_time_left():
    assert status_line(0, 0, 40, 3.0) == "[0/40] 0 failed, elapsed 0:03, left ?"
    assert status_line(10, 2, 40, 125.0) == "[10/40] 2 failed, elapsed 2:05, left 6:15"
    assert status_line(1, 0, 700, 10.0) == "[1/700] 0 failed, elapsed 0:10, left 1:56:30"


def test_workers_refuse_nonsense():
    with pytest.raises(ValueError, match="at least 1"):
        Workers(count=0)
    with pytest.raises(ValueError, match="no --cluster"):
        Workers(count=1, cluster="127.0.0.1:6379")


@pytest.mark.parametrize(("options", "reason"), [(["--workers", "0"], "at least 1"),
                                                 (["--workers", "1", "--cluster", "auto"], "no --cluster")])
def test_the_command_refuses_nonsense_workers_before_any_trial(tmp_path, capsys, options, reason):
    from ddvs.cli import main

    assert main([*SWEEP_ARGS, *options, "--out", str(tmp_path / "out")]) == 2
    assert reason in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@dataclass
class Square:
    n: int
    square: int


def _square(n: int) -> Square:
    if n == 3:
        raise ValueError("three is refused")
    return Square(n, n * n)


def test_a_failed_trial_is_reported_after_the_others_are_journalled(tmp_path):
    journal = tmp_path / "squares.jsonl"
    with pytest.raises(TrialsFailed) as failed:
        run_journalled(range(6), _square, Square, lambda s: s.n, journal)
    assert list(failed.value.failures) == [3]
    assert "three is refused" in str(failed.value) and "run the same command again" in str(failed.value)
    assert [json.loads(line)["n"] for line in journal.read_text().splitlines()] == [0, 1, 2, 4, 5]


def test_the_journal_ends_in_key_order_with_other_keys_first(tmp_path):
    """Lines written in another order (as trials on many workers end) and a key this run does not ask for: the
    journal ends with that key's line first, as it was, then this run's keys in their order."""
    journal = tmp_path / "squares.jsonl"
    journal.write_text('{"n": 9, "square": 81}\n{"n": 4, "square": 16}\n{"n": 1, "square": 1}\n')
    records = run_journalled([0, 1, 2, 4], _square, Square, lambda s: s.n, journal)
    assert records == [Square(0, 0), Square(1, 1), Square(2, 4), Square(4, 16)]
    assert [json.loads(line)["n"] for line in journal.read_text().splitlines()] == [9, 0, 1, 2, 4]


def test_one_trial_without_a_cluster_runs_here_without_ray():
    got: list[tuple[int, Square]] = []
    run_trials([2], _square, Workers(), lambda key, record: got.append((key, record)))
    assert got == [(2, Square(2, 4))]


@pytest.fixture(scope="module")
def sequential_journal(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The journal of `SWEEP` run one trial after another in this process."""
    out = tmp_path_factory.mktemp("sequential")
    run_domain(SWEEP, out, workers=SEQUENTIAL)
    return (out / "trials.jsonl").read_text()


def _worker_nodes(session_dir: Path) -> set[str]:
    """The node ids of the Ray workers of a session that ran a trial (their log shows Taichi starting)."""
    logs = session_dir / "logs"
    nodes = set()
    for out in logs.glob("worker-*.out"):
        if "Starting on arch" in out.read_text():
            pid = out.stem.rsplit("-", 1)[1]
            core_log = next(logs.glob(f"python-core-worker-*_{pid}.log")).read_text()
            nodes.add(re.search(r"node_id=(\w+)", core_log).group(1))  # type: ignore[union-attr]
    return nodes


@pytest.mark.slow
def test_a_sweep_on_a_two_node_cluster_journals_what_the_sequential_sweep_does(tmp_path, sequential_journal):
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "object_store_memory": STORE, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1, object_store_memory=STORE)
        cluster.wait_for_nodes()
        # Ray puts its nodes on this host's own address (it refuses 127.0.0.1 as one); Linux carries traffic to it
        # on the loopback interface.
        host = cluster.address.rsplit(":", 1)[0]
        assert host in {a.address for addrs in psutil.net_if_addrs().values() for a in addrs}
        trials = run_domain(SWEEP, tmp_path, workers=Workers(cluster=cluster.address))
        session = Path(cluster.head_node.get_session_dir_path())
        assert len(_worker_nodes(session)) == 2  # both nodes ran trials
    finally:
        cluster.shutdown()
    assert (tmp_path / "trials.jsonl").read_text() == sequential_journal
    assert [(t.size, t.trial) for t in trials] == [(s, k) for k in range(TRIALS) for s in (0.5, 3.0)]


@pytest.fixture
def sweep_cli(tmp_path: Path) -> Iterator[subprocess.Popen[str]]:
    """`ddvs experiment domain` of `SWEEP` on a local Ray of 2 workers, into `tmp_path`, in a process group of its own
    with Ctrl-C's default action (as a terminal's foreground job: Ctrl-C signals the whole group; a test run started
    in the background, where SIGINT is ignored and the command would inherit that, made the sweep run to its end);
    the group is killed if still running."""
    proc = subprocess.Popen([sys.executable, "-m", "ddvs", *SWEEP_ARGS, "--workers", "2", "--out", str(tmp_path)],
                            cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    yield proc
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()


def _wait_for_records(journal: Path, proc: subprocess.Popen[str], timeout_s: float = 300.0) -> int:
    """The number of lines in `journal` once it has one (the sweep has finished a trial)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        if journal.exists() and journal.read_text():
            return len(journal.read_text().splitlines())
        time.sleep(0.2)
    raise AssertionError(f"no trial journalled (sweep exited {proc.poll()})")


def _resume(out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ddvs", *SWEEP_ARGS, "--workers", "2", "--out", str(out)], cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_a_killed_worker_loses_no_finished_trial_and_the_resumed_sweep_completes(tmp_path, sweep_cli,
                                                                                  sequential_journal):
    journal = tmp_path / "trials.jsonl"
    _wait_for_records(journal, sweep_cli)
    driver = psutil.Process(sweep_cli.pid)
    busy = []
    while not busy and sweep_cli.poll() is None:
        busy = [p for p in driver.children(recursive=True) if p.cmdline()[:1] == ["ray::trial"]]
    assert busy, "no worker running a trial"
    busy[0].kill()
    _, err = sweep_cli.communicate(timeout=600)
    assert sweep_cli.returncode == 1, err
    assert "1 trial(s) failed" in err and "run the same command again" in err
    lines = journal.read_text().splitlines()
    assert len(lines) == N_TRIALS - 1 and set(lines) < set(sequential_journal.splitlines())  # the others, as sequential

    resumed = _resume(tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert f"1 trial(s) to run, {N_TRIALS - 1} already journalled" in resumed.stderr
    assert journal.read_text() == sequential_journal


@pytest.mark.slow
def test_ctrl_c_stops_the_sweep_keeping_the_finished_trials(tmp_path, sweep_cli, sequential_journal):
    journal = tmp_path / "trials.jsonl"
    _wait_for_records(journal, sweep_cli)
    ray_processes = psutil.Process(sweep_cli.pid).children(recursive=True)
    os.killpg(sweep_cli.pid, signal.SIGINT)  # Ctrl-C: the driver, Ray's processes and its workers
    _, err = sweep_cli.communicate(timeout=120)
    assert sweep_cli.returncode == 130, err
    assert "stopped: the finished trials are kept" in err
    _, alive = psutil.wait_procs(ray_processes, timeout=30)
    assert not alive, f"Ray processes left running: {alive}"
    lines = journal.read_text().splitlines()
    assert 1 <= len(lines) < N_TRIALS
    assert lines == [line for line in sequential_journal.splitlines() if line in lines]  # in the sweep's order

    resumed = _resume(tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert journal.read_text() == sequential_journal


@pytest.mark.slow
def test_the_robustness_matrix_on_ray_journals_what_it_does_sequentially(tmp_path):
    """Records with per-image traces (lists of floats and states) come back from the workers unchanged: the matrix of
    three conditions (image transforms, dropped frames, latency) on a local Ray of 2 workers journals the same file
    as one run after another."""
    from orchestration.experiment_robustness import RobustnessSettings, run_matrix

    settings = RobustnessSettings(conditions=("hard_combination", "drop_10pct", "latency_2"), max_images=12)
    sequential = run_matrix(settings, tmp_path / "sequential", workers=SEQUENTIAL)
    on_ray = run_matrix(settings, tmp_path / "ray", workers=Workers(count=2))
    assert len(on_ray) == len(sequential) == 3 and all(len(run.error_norms) == run.images > 0 for run in on_ray)
    assert (tmp_path / "ray" / "runs.jsonl").read_bytes() == (tmp_path / "sequential" / "runs.jsonl").read_bytes()
