"""``refgs sweep`` and ``refgs run-one``: grids of training runs (docs/sweeps.md).

    refgs sweep GRID.toml --out DIR [--executor local|ray] [--workers N] [--threads-per-run K]
                [--dry-run] [--retry-failed] [--list] [--quiet] [--ray-timeout S]
    refgs run-one GRID.toml --out DIR (--index I | --name NAME) [--quiet]

``sweep`` runs every run of the grid that is not done (refgs.sweep.executors) and exits with
status 1, listing them, when some failed or did not finish; run it again to continue.
``--list`` prints the runs (index, name, state) and ``--dry-run`` what a sweep would do with each;
neither writes anything.  ``run-one`` runs one run of the grid in this process (a SLURM array
task, a Snakemake rule): status 0 when it is done, 1 when it failed, 130 when interrupted.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .execute import execute_run, watch_parent
from .executors import DEFAULT_RAY_TIMEOUT_S, DEFAULT_THREADS, EXECUTORS, plan, report, sweep
from .grid import load_grid

#: Exit status when runs failed or did not finish (refgs.cli: 1 = failure, 2 = bad input).
EXIT_RUNS_FAILED = 1


def add_parser(sub) -> None:
    s = sub.add_parser("sweep", help="a grid of training runs (TOML) on a process pool or Ray")
    s.add_argument("grid", help="grid file (TOML): refgs train options, lists are axes")
    s.add_argument("--out", required=True, help="output folder: one run directory per run")
    s.add_argument("--executor", default="local", choices=EXECUTORS)
    s.add_argument("--workers", type=int, help="runs at a time (default: cores / threads)")
    s.add_argument("--threads-per-run", type=int, default=DEFAULT_THREADS, metavar="K",
                   help=f"threads of each run (numba, OpenMP; default {DEFAULT_THREADS})")
    s.add_argument("--dry-run", action="store_true", help="say what would be done, do nothing")
    s.add_argument("--retry-failed", action="store_true", help="run failed runs again")
    s.add_argument("--list", action="store_true", help="the runs: index, name, state")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--ray-timeout", type=float, default=DEFAULT_RAY_TIMEOUT_S, metavar="S",
                   help=f"seconds to wait for the Ray cluster at RAY_ADDRESS (default "
                        f"{DEFAULT_RAY_TIMEOUT_S:g})")
    s.set_defaults(handler=lambda a, _: run(a))
    o = sub.add_parser("run-one", help="one run of a grid (a SLURM array task, a Snakemake rule)")
    o.add_argument("grid")
    o.add_argument("--out", required=True)
    which = o.add_mutually_exclusive_group(required=True)
    which.add_argument("--index", type=int, help="the run's index (refgs sweep --list)")
    which.add_argument("--name", help="the run's name")
    o.add_argument("--quiet", action="store_true", help="no progress bar or table")
    o.add_argument("--parent-pid", type=int, help=argparse.SUPPRESS)
    o.set_defaults(handler=lambda a, _: run(a))


def run(args) -> dict:
    """Dispatch ``refgs sweep`` / ``refgs run-one``; SystemExit(1) when runs failed."""
    grid = load_grid(args.grid)
    out = Path(args.out).absolute()
    if args.command == "run-one":
        if args.parent_pid:
            watch_parent(args.parent_pid)
        outcome = execute_run(grid, out, grid.find(args.index, args.name), progress=not args.quiet)
        if outcome["state"] != "done":
            print(f"refgs: error: {outcome['name']}: {outcome['error']}", file=sys.stderr)
            raise SystemExit(EXIT_RUNS_FAILED)
        if not args.quiet:
            print(f"{outcome['name']}: done ({out / outcome['name']})")
        return outcome
    if args.list or args.dry_run:
        for r, state, what in plan(grid, out, args.retry_failed):
            print(f"{r.index:>4}  {r.name}  {what if args.dry_run else state}")
        return {}
    data = sweep(grid, out, args.executor, args.workers, args.threads_per_run,
                 args.retry_failed, progress=not args.quiet, ray_timeout=args.ray_timeout)
    lines = report(data, out, grid.path)
    print("\n".join(lines))
    if any(e["state"] != "done" for e in data["runs"].values()):
        raise SystemExit(EXIT_RUNS_FAILED)
    return data


__all__ = ["add_parser", "run", "EXIT_RUNS_FAILED"]
