"""Estimators across sample gaps: every estimator on BROAD and DIDO under the drop patterns.

    python benchmarks/gaps.py [--quick] [--estimators all] [--patterns standard] [--dataset both]
                              [--seed 0] [--workers N] [--raw-steps] [--markdown] [--json FILE]

Per data set (DIDO flights, then BROAD), for each recording, estimator and pattern (``ahrs_service/evaluation/gaps.py``, docs/gaps.md):
the rows the pattern drops are removed, the estimator runs on the kept rows with their own
times (``estimators.run(..., timestamps=t[keep])``; BROAD's t = arange(N) / rate), and the
gapped run and the gap-free run are scored on the same rows (the recording's scored rows that
are kept) with ``evaluate``'s metric: total RMSE where heading is observed with a
magnetometer, else inclination. Printed:

* estimator × pattern: the mean over the recordings of the ratio gapped / gap-free RMSE, and
  the worst gapped RMSE (``!`` marks an estimator that scores above 10° with gaps on a
  recording where it scores at most 5° without);
* after the outage: per recording and estimator, the seconds until the gapped estimate is back
  within 2° of the gap-free one for good (``never``: not by the end of the recording);
* the issue's targets, met or missed, per data set (exit code 1 when one is missed on the
  DIDO flights, whose figures they are).

``--quick`` runs only the patterns the targets name (bursts:20-100ms:10%, bursts:20-400ms:10%,
outage:2s). Jobs are one (recording × estimator) each on the execution layer
(``--workers``, default one per core); a first pass compiles each estimator's kernels once
(numba's cache), which takes minutes after the kernels' sources changed.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ahrs_service import estimators  # noqa: E402
from ahrs_service.evaluation import broad, dido, gaps  # noqa: E402
from ahrs_service.execution import add_arguments, open_runner  # noqa: E402

#: the patterns the issue's targets name: what --quick runs
QUICK_PATTERNS = (*gaps.RATIO_TARGETS, "outage:2s")

def short(pattern: str) -> str:
    """A pattern's short column head."""
    p = gaps.parse(pattern)
    if p.kind == "outage":
        return f"outage {p.outage_s:g}s"
    return f"{p.burst_min_s * 1e3:g}-{p.burst_max_s * 1e3:g}ms {p.fraction * 100:g}%"


def _f(x: float | None, fmt: str) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _recovery(x: float | None) -> str:
    if x is None:
        return "–"
    return "never" if math.isinf(x) else f"{x:.1f}"


def render(head: list[str], rows: list[list[str]], markdown: bool) -> str:
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
        return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    fmt = lambda r: "  ".join(str(x).ljust(w) if i == 0 else str(x).rjust(w) for i, (x, w) in enumerate(zip(r, widths)))  # noqa: E731
    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(r) for r in rows])


def ratio_table(summaries: dict, names: list[str], patterns: list[str], markdown: bool) -> str:
    head = ["estimator"] + [short(p) for p in patterns]
    rows = []
    for name in names:
        row = [name]
        for p in patterns:
            s = summaries.get((name, p))
            if s is None:
                row.append("–")
                continue
            mark = "!" if s.bounded_misses else ""
            row.append(f"{_f(s.mean_ratio, '.2f')}x {_f(s.worst_gapped, '.1f')}{mark}")
        rows.append(row)
    return render(head, rows, markdown)


def recovery_table(scores: list[gaps.GapScore], names: list[str], pattern: str, markdown: bool) -> str:
    recordings = list(dict.fromkeys(s.trial for s in scores if s.pattern == pattern))
    by = {(s.trial, s.estimator): s for s in scores if s.pattern == pattern}
    head = ["recording (s after)"] + names
    rows = []
    for r in recordings:
        after = next((s.observed_after_s for s in scores if s.trial == r and s.pattern == pattern), None)
        rows.append([f"{r[:40]} ({_f(after, '.0f')})"] + [_recovery(by[(r, n)].recovery_s) if (r, n) in by else "–"
                                                          for n in names])
    return render(head, rows, markdown)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the patterns the targets name: " + ", ".join(QUICK_PATTERNS).replace("%", "%%"))
    ap.add_argument("--estimators", default="all", help="comma-separated names or all (default)")
    ap.add_argument("--patterns", default=None, help="comma-separated drop patterns, or standard (default: standard; "
                    "--quick: the targets' patterns)")
    ap.add_argument("--dataset", choices=("broad", "dido", "both"), default="both", help="recordings (default both)")
    ap.add_argument("--trials", default=None, metavar="PATTERN", help="only recordings whose name matches")
    ap.add_argument("--broad", default=None, metavar="DIR", help="BROAD folder (default $AHRS_BROAD_DIR or ../shared/data/broad)")
    ap.add_argument("--dido", default=None, metavar="DIR", help="DIDO folder (default $AHRS_DIDO_DIR or ../shared/data/dido)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the drop places (default 0)")
    ap.add_argument("--raw-steps", action="store_true",
                    help="integrate the kept rows' raw time steps (recover_clock=False) in both runs, "
                    "instead of the sensor clock recovered from the stamps")
    ap.add_argument("--markdown", action="store_true", help="print Markdown tables")
    ap.add_argument("--json", default=None, metavar="FILE", help="also write every score to FILE")
    add_arguments(ap)
    args = ap.parse_args(argv)
    try:
        patterns = [p.label for p in gaps.parse_list(args.patterns or (",".join(QUICK_PATTERNS) if args.quick else gaps.STANDARD))]
        names = estimators.names() if args.estimators == "all" else [s.strip() for s in args.estimators.split(",") if s.strip()]
        for n in names:
            estimators.get(n)
        if args.seed < 0:
            raise ValueError(f"--seed {args.seed}: must be 0 or more")
    except (ValueError, ImportError) as exc:
        ap.error(str(exc))
    folders = {"broad": args.broad, "dido": args.dido}
    recordings = []
    for ds in (("broad", "dido") if args.dataset == "both" else (args.dataset,)):
        source = gaps.DATASETS[ds]
        try:
            folder = str(source.check_dir(folders[ds] or source.default_dir()).resolve())
        except FileNotFoundError as exc:
            print(f"skipping {ds}: {exc}", file=sys.stderr)
            continue
        recordings += [(ds, folder, r) for r in source.list_trials(folder, args.trials)]
    if not recordings:
        ap.error("no recording found (see the folder options)")

    jobs = [gaps.GapJob(ds, folder, r, n, tuple(patterns), args.seed, (), not args.raw_steps)
            for ds, folder, r in recordings for n in names]
    t0 = time.perf_counter()
    with open_runner(args.workers, args.scheduler) as runner:
        started = time.perf_counter()
        runner.map(gaps.warm_up, names, desc="compile")
        compiled = time.perf_counter()
        results = runner.map(gaps.run_gap_job, jobs, progress=sys.stderr.isatty(), desc="gaps",
                             place_by=gaps.recording_of, prepare=gaps.prepare_recording)
        done = time.perf_counter()
    scores = [s for job_scores in results for s in job_scores]
    dataset_of = {r: ds for ds, _, r in recordings}

    n_broad = sum(ds == "broad" for ds, _, _ in recordings)
    print(f"{len(names)} estimators x {len(recordings)} recordings ({n_broad} BROAD, {len(recordings) - n_broad} DIDO) "
          f"x {len(patterns)} patterns, seed {args.seed}, "
          f"{'raw steps' if args.raw_steps else 'sensor clock recovered from the stamps'}; "
          f"{runner.info.mode} runner, {runner.info.workers} worker(s); Python {platform.python_version()}")
    print(f"wall {done - t0:.0f} s: cluster start {started - t0:.0f} s, compile/load kernels {compiled - started:.0f} s, "
          f"jobs {done - compiled:.0f} s")
    met = True
    # the issue's targets are figures of flights: checked on DIDO; BROAD's handheld motion
    # (rates to 25 rad/s, changing by 10 rad/s within a burst) is shown beside them
    for ds, title in (("dido", "DIDO quadrotor flights"), ("broad", "BROAD handheld recordings")):
        ds_scores = [s for s in scores if dataset_of.get(s.trial) == ds]
        if not ds_scores:
            continue
        summaries = gaps.summarize(ds_scores)
        print()
        print(f"{title}: mean ratio gapped / gap-free RMSE over the recordings, worst gapped RMSE (deg); "
              "! = above 10 deg with gaps on a recording at most 5 deg without")
        print(ratio_table(summaries, names, patterns, args.markdown))
        for p in patterns:
            if gaps.parse(p).kind == "outage":
                print()
                print(f"{title}, after {p}: seconds until within {gaps.RECOVERY_TOLERANCE_DEG:g} deg of the gap-free "
                      "estimate for good (total angle with heading observed, else inclination); in brackets: "
                      "seconds of recording after the outage")
                print(recovery_table(ds_scores, names, p, args.markdown))
        print()
        print(f"targets on the {title}:")
        for c in gaps.check_targets(summaries):
            print(f"  {'met   ' if c.met else 'MISSED'} {c.name}" + ("" if c.met else ": " + "; ".join(c.misses)))
            met = met and (c.met or ds != "dido")
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"patterns": patterns, "seed": args.seed, "raw_steps": args.raw_steps,
             "scores": [_clean(s.as_dict()) for s in scores]}, indent=1) + "\n", encoding="utf-8")
    return 0 if met else 1


def _clean(v):
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    return v


if __name__ == "__main__":
    sys.exit(main())
