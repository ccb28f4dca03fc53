"""Command-line plug-in of the evaluation: ``ahrs-service evaluate``."""

from __future__ import annotations

import argparse

from ahrs_service import execution
from ahrs_service.evaluation.broad import ENV_VAR
from ahrs_service.cli import add_offline_options, lazy_command
from ahrs_service.evaluation.dido import ENV_VAR as DIDO_ENV_VAR


def add_subcommands(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``evaluate`` to the ``ahrs-service`` command line."""
    p = subparsers.add_parser(
        "evaluate",
        help="score the estimators on the BROAD recordings (RMSE, L2 index, Friedman/Nemenyi, plots)",
        description=(
            "Runs the estimators (and optionally peer libraries) over the BROAD recordings and "
            "writes results.md, results.json and PNG plots. Data: D. Laidig et al., BROAD, "
            "Data 6(7), 2021, doi:10.3390/data6070072."
        ),
    )
    p.add_argument(
        "--dataset",
        choices=("broad", "dido"),
        default="broad",
        help="broad: handheld recordings with optical truth (default); dido: quadrotor flights "
        "(K. Zhang et al., DIDO, RA-L 2022), recorded stamps, inclination only",
    )
    p.add_argument(
        "--data",
        metavar="DIR",
        default=None,
        help=f"folder of the data set's *.hdf5 files (default: ${ENV_VAR} / ${DIDO_ENV_VAR}, "
        "else ../shared/data/broad or ../shared/data/dido)",
    )
    p.add_argument("--estimators", default="all", metavar="LIST", help="comma-separated names, or all (default)")
    p.add_argument(
        "--peers",
        default="none",
        metavar="LIST",
        help="reference libraries: vqf,imufusion,ahrs (or single peers such as ahrs.ekf), all, or none (default)",
    )
    p.add_argument("--trials", default=None, metavar="PATTERN", help="only trials whose name matches (glob or substring)")
    p.add_argument("--out", default="results/evaluation", metavar="DIR", help="output folder (default ./results/evaluation)")
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME.KEY=VALUE",
        help="tuning parameter for one column, e.g. madgwick.beta=0.05 (repeatable)",
    )
    p.add_argument(
        "--preset",
        action="append",
        default=[],
        metavar="paper|FILE",
        help="paper: every selected paper filter at its source paper's values instead of the tuned defaults; "
        "FILE: a preset file (ahrs-service tune) for its estimator (repeatable; --param overrides)",
    )
    add_offline_options(p, "also score the offline (forward-backward, non-causal) mode of every column, as '<name>+offline'")
    p.add_argument(
        "--drop-pattern",
        action="append",
        default=[],
        metavar="PATTERN",
        help="also score every estimator column with samples dropped: bursts:LO-HIms:PCT%% (e.g. bursts:20-100ms:10%%), "
        "outage:Ss (e.g. outage:2s) or standard (the gap benchmark's seven); comma-separated or repeatable; "
        "gap-free against gapped RMSE on the kept rows, and their ratio, in results.md/json (docs/gaps.md)",
    )
    p.add_argument(
        "--drop-seed",
        type=int,
        default=None,
        metavar="N",
        help="seed of the places where --drop-pattern drops samples (default 0)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary line")
    execution.add_arguments(p)
    p.set_defaults(func=lazy_command("ahrs_service.evaluation.report:main"))


    t = subparsers.add_parser(
        "tune",
        help="search an estimator's parameters with Optuna on BROAD and/or DIDO and write a preset file",
        description=(
            "Optuna (TPE) over the search space declared on the estimator's Params fields (or --space); "
            "every (trial x recording) is one job of the execution layer, grouped into tasks of at least "
            "--task-floor-s; objective: mean RMSE over the "
            "recordings (BROAD total, or inclination without heading; DIDO inclination); with --dataset both "
            "the worse data set relative to its target; leave-one-recording-out validation and "
            "parameter importances reported; the best parameters written as a preset file that "
            "estimators.create(name, preset=PATH) accepts."
        ),
    )
    t.add_argument("estimator", metavar="ESTIMATOR")
    t.add_argument("--dataset", choices=["broad", "dido", "both"], default="broad",
                   help="recordings to tune on: broad (default), dido, or both (objective: the worse data set's "
                   "mean RMSE over its target, BROAD 6 deg / 3 deg inclination, DIDO 5 deg)")
    t.add_argument("--data", metavar="DIR", default=None,
                   help=f"folder of the one data set (default: ${ENV_VAR} / ${DIDO_ENV_VAR}, else ../shared/data/...); "
                   "not with --dataset both")
    t.add_argument("--trials", default=None, metavar="PATTERN", help="only recordings whose name matches")
    t.add_argument("--budget", type=int, default=50, metavar="N", help="Optuna trials (default 50)")
    t.add_argument("--space", action="append", default=[], metavar="NAME=LOW:HIGH[:log]",
                   help="search range of one parameter (repeatable; replaces the declared space)")
    t.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    t.add_argument("--out", default=None, metavar="FILE", help="preset file to write (default ./ESTIMATOR.preset.json)")
    t.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    execution.add_arguments(t)
    t.set_defaults(func=lazy_command("ahrs_service.evaluation.tuning:main"))

