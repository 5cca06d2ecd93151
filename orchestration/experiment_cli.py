"""`ddvs experiment synthetic`: the paper's synthetic experiment (see `orchestration.experiment_synthetic`);
`ddvs experiment paper` (both experiments and the report, `orchestration.experiment_paper`), `ddvs experiment
domain` (convergence domain, `orchestration.experiment_domain`) and `ddvs experiment robustness` (the servo under a
real camera's conditions, `orchestration.experiment_robustness`).

Each runs its trials on Ray (`orchestration.trials`, docs/sweeps.md): a local Ray started for the run on every core
by default, `--cluster ADDRESS` a running cluster, `--workers N` at most N trials at once, `--workers 1` one after
another in this process. A trial that fails is reported at the end (exit status 1) and runs again on the next run;
Ctrl-C stops the run, keeping the finished trials (exit status 130).

Prints a human-readable summary, or one JSON line with `--json` (law, geometry source, converged, why it stopped,
images to convergence, the paper's count, final translation (m) and rotation (deg) errors, retreat (m), coupling
measures), and saves plots of v(t) and of the 3-D trajectory into `--out` (default reports/synthetic).
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

from orchestration.trials import TrialsFailed, run_trials
from orchestration.workers import ClusterUnreachable, Workers

# The geometry sources offered on the command line; keep in step with experiment_synthetic.GEOMETRY_SOURCES
# (listed here so that `ddvs --help` does not import numpy and the plant).
GEOMETRIES = ("exact", "estimated")


def add_worker_arguments(parser: argparse.ArgumentParser) -> None:
    """`--workers N` and `--cluster ADDRESS` (`orchestration.workers.Workers`)."""
    parser.add_argument("--workers", type=int, metavar="N",
                        help="trials at once at most (default: every core of a local Ray started for the run, or "
                             "every CPU of --cluster); 1: one after another in this process, without Ray")
    parser.add_argument("--cluster", metavar="ADDRESS",
                        help="run the trials on this running Ray cluster (HOST:PORT of its head, or 'auto' on one "
                             "of its nodes; docs/sweeps.md)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    sp = sub.add_parser("synthetic", help="servo to the reference pose in front of the horse saddle (paper IV-A)")
    sp.add_argument("--law", choices=("dvs", "ddvs"), required=True, help="dvs: reduced error (13); ddvs: (16)")
    sp.add_argument("--geometry", choices=GEOMETRIES, default="exact",
                    help="source of G, e, rho*: exact (ground truth, default) or estimated (general tracker on "
                         "rendered images)")
    sp.add_argument("--texture", help="texture image of the saddle for rendered frames (default: Oxford graf)")
    sp.add_argument("--t", nargs=3, type=float, metavar=("TX", "TY", "TZ"), help="initial translation (m)")
    sp.add_argument("--r", nargs=3, type=float, metavar=("RX", "RY", "RZ"), help="initial rotation vector (rad)")
    sp.add_argument("--threshold", type=float, default=1e-3, help="stop threshold on the error norm (default 1e-3)")
    sp.add_argument("--gain", type=float, default=0.4, help="control gain λ for every axis (1/s, default 0.4)")
    sp.add_argument("--max-images", type=int, default=20000, help="image budget (default 20000)")
    sp.add_argument("--scaling", choices=("sl3", "euclidean"), default="sl3", help="scale gauge of G (default sl3)")
    sp.add_argument("--json", action="store_true", help="print one JSON line instead of text")
    sp.add_argument("--out", type=Path, default=Path("reports/synthetic"), help="directory for the plots")
    sp.add_argument("--no-plots", action="store_true", help="do not save plots")
    add_worker_arguments(sp)

    pp = sub.add_parser("paper", help="both paper experiments (synthetic saddle, arm) with both laws, and the report")
    pp.add_argument("--out", type=Path, default=Path("reports/paper"), help="report directory (default reports/paper)")
    pp.add_argument("--only", nargs="+", choices=("synthetic_dvs", "synthetic_ddvs", "arm_dvs", "arm_ddvs"),
                    help="run only these experiments (default: all four)")
    pp.add_argument("--max-images", type=int, help="image budget of every run (default 3000 synthetic, 2000 arm)")
    pp.add_argument("--force", action="store_true", help="re-run experiments whose summary exists")
    add_worker_arguments(pp)

    dp = sub.add_parser("domain", help="success rate over random initial displacements of growing size")
    dp.add_argument("--target", choices=("planar", "saddle"), help="one target (default both)")
    dp.add_argument("--law", choices=("dvs", "ddvs"), help="one law (default both)")
    dp.add_argument("--scene", choices=("finite", "distractors", "tiled"), default="finite",
                    help="finite poster on grey (default), on a second texture, or the texture tiled everywhere")
    dp.add_argument("--trials", type=int, default=10, help="trials per size (default 10)")
    dp.add_argument("--sizes", type=float, nargs="+", default=[1.0, 2.0, 3.0, 4.0, 5.0],
                    help="displacement sizes, units of 0.05 m and 15 degrees (default 1 2 3 4 5)")
    dp.add_argument("--illumination", action="store_true", help="vary the lighting over time")
    dp.add_argument("--noise", type=float, default=0.0, help="sensor noise standard deviation (grey levels)")
    dp.add_argument("--seed", type=int, default=0, help="seed of the random starts and the noise (default 0)")
    dp.add_argument("--max-images", type=int, default=400, help="image budget per trial (default 400)")
    dp.add_argument("--dt", type=float, default=0.1, help="sampling period (s, default 0.1)")
    dp.add_argument("--out", type=Path, default=Path("reports/domain"), help="output directory (resumable)")
    add_worker_arguments(dp)

    rp = sub.add_parser("robustness", help="the servo under coarse intrinsics, light changes, occluders, noise, blur, "
                                           "JPEG, latency and frame loss (free-flying camera or SAPIEN arm)")
    rp.add_argument("--plant", choices=("freeflyer", "arm"), default="freeflyer",
                    help="freeflyer (default; every condition) or arm (the SAPIEN UR5, planar target: coarse "
                         "intrinsics, a dimming light, an occluding plate, latency, dropped frames; see "
                         "orchestration/experiment_robustness_arm.py)")
    rp.add_argument("--scene", type=Path, help="arm only: scene file (default configs/arm/ur5_poster.json; "
                                               "configs/arm/ur5_poster_graf.json: the free-flyer's texture)")
    rp.add_argument("--targets", nargs="+", choices=("planar", "saddle"), default=["planar"],
                    help="targets (default planar)")
    rp.add_argument("--laws", nargs="+", choices=("dvs", "ddvs"), default=["ddvs"], help="laws (default ddvs)")
    rp.add_argument("--starts", nargs="+", default=["paper"],
                    help="'paper' and/or domain-sweep starts 's<size>k<trial>', e.g. s3k0 s4k1 (default paper)")
    rp.add_argument("--conditions", nargs="+", help="conditions to run (default all; see "
                                                    "orchestration/experiment_robustness.py CONDITIONS)")
    rp.add_argument("--max-images", type=int, default=1500, help="image budget per run (default 1500)")
    rp.add_argument("--overrides", help="service configuration changes as JSON, e.g. "
                                        "'{\"registration\": {\"robust\": \"huber\"}}'")
    rp.add_argument("--out", type=Path, help="output directory (resumable; default reports/robustness, "
                                             "reports/robustness/arm for the arm)")
    add_worker_arguments(rp)


def run(args: argparse.Namespace) -> int:
    try:
        Workers(args.workers, args.cluster)  # refused here, before any trial, with the reason
    except ValueError as error:
        print(f"ddvs experiment {args.experiment}: {error}", file=sys.stderr)
        return 2
    try:
        return run_experiment(args)
    except (TrialsFailed, ClusterUnreachable) as failed:
        print(failed, file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stopped: the finished trials are kept; run the same command again to run the others",
              file=sys.stderr)
        return 130


def run_experiment(args: argparse.Namespace) -> int:
    if args.experiment == "robustness" and args.plant == "arm":
        from orchestration.experiment_robustness_arm import run_arm_robustness_command

        args.out = args.out or Path("reports/robustness/arm")
        return run_arm_robustness_command(args)
    if args.experiment == "robustness":
        from orchestration.experiment_robustness import run_robustness_command

        if args.scene is not None:
            raise SystemExit("--scene is for the arm plant (--plant arm); the free-flyer's targets are --targets")

        args.out = args.out or Path("reports/robustness")
        return run_robustness_command(args)
    if args.experiment == "paper":
        from orchestration.experiment_paper import run_paper_command

        return run_paper_command(args)
    if args.experiment == "domain":
        from orchestration.experiment_domain import run_domain_command

        return run_domain_command(args)
    from orchestration.experiment_synthetic import (
        PAPER_R,
        PAPER_T,
        ExperimentResult,
        SyntheticSetup,
        run_synthetic,
        save_plots,
    )

    setup = SyntheticSetup(
        t=tuple(args.t) if args.t else PAPER_T,
        r=tuple(args.r) if args.r else PAPER_R,
        gain=args.gain,
        threshold=args.threshold,
        max_images=args.max_images,
        scaling=args.scaling,
        **({"texture": args.texture} if args.texture else {}),
    )
    results: list[ExperimentResult] = []
    run_trials([args.law], partial(run_synthetic, setup=setup, geometry=args.geometry),
               Workers(args.workers, args.cluster), lambda _, result: results.append(result))
    result = results[0]
    summary: dict[str, object] = dict(result.summary())  # a list of plot paths joins the scalars
    if not args.no_plots:
        summary["plots"] = [str(p) for p in save_plots(result, args.out, setup)]
    if args.json:
        print(json.dumps(summary))
    else:
        for key, value in summary.items():
            print(f"{key:>26}: {value}")
    return 0 if result.converged else 1
