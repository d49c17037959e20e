"""The ``refgs`` command: argument parsing and dispatch only (docs/spec/training.md).

    refgs train --scene DIR --views N --iters N --out DIR [--images images_8] [--resolution R]
                [--method 3dgs] [--seed S] [--backend fast|reference|module:object]
                [--init-points train-views|sfm-all|PATH.ply]
                [--checkpoint-every K] [--eval-every K] [--strict] [--dtype float64|float32] ...
    refgs train --resume RUN_DIR
    refgs eval RUN_DIR [--model PATH.ply] [--no-lpips]
    refgs render RUN_DIR [--split test|train|all]
    refgs demo [--out DIR] [--iters N] [--backend fast|reference] [--seed S]
    refgs bench [--n N ...] [--size WxH ...] [--backends ...] [--fern-run RUN] [--out DIR]
    refgs flatness RUN_DIR ... [--gammas G ...] [--seeds S] [--settings flatness|training]
    refgs table RUN_DIR ... [--metrics psnr ssim lpips_vgg] [--baseline LABEL] [--out DIR]
    refgs figures RUN_DIR ... [--flatness DIR ...] [--out figures]
    refgs record RUN_DIR ... [--out results/records]
    refgs compactness RUN_DIR ... [--out DIR]   (contributions and fragments, docs/compact.md)
    refgs report GRID.toml ... [--records results/records] [--update docs/results.md] [--check-equivalence]
    refgs frontier GRID.toml [--records results/records] [--out PNG]   (quality against cost, docs/compact.md)
    refgs sweep GRID.toml --out DIR [--executor local|ray] [--workers N] [--list] ...
    refgs run-one GRID.toml --out DIR --index I

The work is done by refgs.runs (train, resume, evaluate, render), by the analysis modules
(refgs.analysis.*, the demo among them) and by the sweep (refgs.sweep.command), which add their own subcommands; the
options of ``refgs train`` are defined in refgs.sweep.options, shared with grid files.  Bad input
(missing folder, corrupt model, empty image folder, unsupported camera, --views too large, ...)
ends with ONE line ``refgs: error: ...`` on stderr naming the file or flag, exit status 2, and no
run directory left behind (TRN-09).  Ctrl-C / SIGTERM during training writes a checkpoint and exits with status 130;
``refgs train --resume RUN_DIR`` continues it exactly.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from . import runs
from .errors import ConfigError, RefgsError
from .sweep.options import NEW_RUN_FLAGS, add_train_options, config_from_args

#: Exit statuses: bad input, interrupted (128 + SIGINT), other failure.
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_FAILURE = 1


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``refgs: error: ...``, exit 2) instead of usage + error."""

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def _add_train(sub) -> None:
    t = sub.add_parser("train", help="train a new run, or continue one with --resume")
    add_train_options(t)          # refgs.sweep.options: one table for the CLI and grid files
    t.set_defaults(handler=_train_command)


def build_parser() -> argparse.ArgumentParser:
    """The parser of every ``refgs`` subcommand; ``args.handler(args, argv)`` runs one."""
    from .analysis import (bench, compactness, demo, figures, flatness, frontier, records, report,
                           tables)
    from .sweep import command as sweep

    p = _Parser(prog="refgs", description="refgs: the numpy 3DGS specification - training CLI")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_train(sub)

    e = sub.add_parser("eval", help="evaluate a finished run on its test views")
    e.add_argument("run_dir")
    e.add_argument("--model", help="evaluate this 3DGS PLY instead of the run's parameters")
    e.add_argument("--no-lpips", action="store_true")
    e.add_argument("--quiet", action="store_true")
    e.set_defaults(handler=lambda a, _: runs.evaluate_run(a.run_dir, a.model,
                                                          False if a.no_lpips else None, not a.quiet))

    r = sub.add_parser("render", help="render a run's views to PNG")
    r.add_argument("run_dir")
    r.add_argument("--split", default="test", choices=("test", "train", "all"))
    r.set_defaults(handler=lambda a, _: print(runs.render_run(a.run_dir, a.split)))

    m = sub.add_parser("demo", help="3DGS against FM on 3 views of the packaged demo scene: "
                                    "table and comparison picture")
    m.add_argument("--out", help="output folder (default refgs-demo-<time>)")
    m.add_argument("--iters", type=int, default=None,
                   help=f"default {demo.DEMO_ITERS} (fast backend), {demo.DEMO_ITERS_REFERENCE} "
                        "(reference)")
    m.add_argument("--backend", default=None, help="default: fast when numba is installed")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--quiet", action="store_true")
    m.set_defaults(handler=lambda a, _: demo.run_demo(a.out, a.iters, a.backend, a.seed,
                                                      progress=not a.quiet))

    for name, module in (("bench", bench), ("compactness", compactness), ("flatness", flatness),
                         ("table", tables),
                         ("figures", figures), ("frontier", frontier), ("record", records),
                         ("report", report),
                         ("sweep", sweep)):
        module.add_parser(sub)
        sub.choices[name].set_defaults(handler=lambda a, _, run=module.run: run(a))
    return p


def _train_command(args, argv) -> Path:
    if args.resume:
        given = [f for f in NEW_RUN_FLAGS if getattr(args, f) is not None]
        if given:
            raise ConfigError(f"--resume: takes its settings from the run's {runs.CONFIG_FILE}; "
                              f"do not also give --{given[0]}")
        run_dir = runs.resume(args.resume, progress=not args.quiet)
    else:
        cfg = config_from_args(args)
        if args.backend is None and not args.quiet:
            print(f"backend: {cfg.backend} (the fastest that loads here; --backend reference "
                  f"for the numpy reference)")
        run_dir = runs.train(cfg, args.out, progress=not args.quiet, command=["refgs", *argv])
    if not args.quiet:
        print(f"run directory: {run_dir}")
    return run_dir


def _one_line(message) -> str:
    return " ".join(str(message).split())


def main(argv: list | None = None) -> int:
    """Entry point ``refgs`` (console script refgs.cli:main); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    old_show = warnings.showwarning
    warnings.showwarning = lambda msg, cat, *a, **k: print(
        f"refgs: warning: {_one_line(msg)}", file=sys.stderr)
    try:
        args.handler(args, argv)
        return 0
    except RefgsError as exc:
        print(f"refgs: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except runs.Interrupted as exc:
        print(f"refgs: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("refgs: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:
        print(f"refgs: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        warnings.showwarning = old_show


__all__ = ["main", "build_parser", "config_from_args", "EXIT_BAD_INPUT", "EXIT_INTERRUPTED",
           "EXIT_FAILURE"]
