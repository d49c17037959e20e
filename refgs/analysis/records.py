"""``refgs record``: the small, committable summary of finished runs (``results/records/<run>/``).

    refgs record RUN_DIR [RUN_DIR ...] [--out results/records]

A run directory holds checkpoints and renders (hundreds of MB) and lives on one machine; a record
holds what the tables and the trajectory figures need, small enough to commit:

- ``config.json`` and ``metrics.json``, copied byte for byte;
- ``history.json``, every iteration of the run's history with floats rounded to
  ``RECORD_DECIMALS`` (compact JSON; about 0.4 MB for 10k iterations);
- ``record.json``, where the record came from (source folder, time, the rounding).

A folder written by ``refgs flatness --out`` is recorded as its ``flatness.json`` and
``flatness.csv``.  ``refgs table`` and ``refgs figures`` take record folders wherever they take run
directories (figures: trajectories, Gaussian counts and flatness curves; no renders, as a record
has no images or checkpoint).  Every file is written atomically.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from ..errors import ConfigError
from ..io.atomic import atomic_write_bytes, atomic_write_text
from ..runs import CONFIG_FILE, HISTORY_FILE, METRICS_FILE
from .flatness import FLATNESS_CSV, FLATNESS_JSON

DEFAULT_OUT = "results/records"
#: decimals kept per history field (what a plot or a table can show; our choice): loss to 1e-6,
#: PSNR to 1e-3 dB, seconds to 0.1 ms.  Fields not listed (iterations, Gaussian counts) are kept.
RECORD_DECIMALS = {"train_loss": 6, "train_psnr": 3, "test_psnr": 3, "iter_seconds": 4,
                   "iter_cpu_seconds": 4}
#: The run files a record copies byte for byte (besides the rounded HISTORY_FILE).
RUN_FILES = (CONFIG_FILE, METRICS_FILE)
FLATNESS_FILES = (FLATNESS_JSON, FLATNESS_CSV)
RECORD_FILE = "record.json"


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None


def rounded_history(history: dict) -> dict:
    """The history with the floats of RECORD_DECIMALS' fields rounded (lists of equal length)."""
    out = {}
    for key, values in history.items():
        if not isinstance(values, list):
            raise ConfigError(f"history field {key!r}: expected a list, got {type(values).__name__}")
        d = RECORD_DECIMALS.get(key)
        out[key] = [round(float(v), d) for v in values] if d is not None else values
    return out


def _collect(src: Path) -> tuple[str, dict, dict | None]:
    """(kind, {file name: bytes}, rounded history or None) of one source; ConfigError naming the
    file when it is neither a finished run nor a flatness output."""
    if not src.is_dir():
        raise ConfigError(f"{src}: not a folder (expected a finished refgs run or a refgs "
                          "flatness output)")
    if (src / FLATNESS_FILES[0]).is_file() and not (src / RUN_FILES[0]).is_file():
        _read_json(src / FLATNESS_FILES[0])                  # refuse a broken file
        return "flatness", {n: (src / n).read_bytes() for n in FLATNESS_FILES
                            if (src / n).is_file()}, None
    missing = [n for n in (*RUN_FILES, HISTORY_FILE) if not (src / n).is_file()]
    if missing:
        raise ConfigError(f"{src / missing[0]}: not found (is {src} a finished refgs run? "
                          f"finish it with refgs train --resume {src})")
    for name in RUN_FILES:
        _read_json(src / name)
    return ("run", {n: (src / n).read_bytes() for n in RUN_FILES},
            rounded_history(_read_json(src / HISTORY_FILE)))


def _write(src: Path, kind: str, data: dict, history: dict | None, out_root: Path) -> Path:
    dest = out_root / src.name
    dest.mkdir(parents=True, exist_ok=True)
    for name, blob in data.items():
        atomic_write_bytes(dest / name, blob)
    if history is not None:
        atomic_write_text(dest / HISTORY_FILE, json.dumps(history, separators=(",", ":")) + "\n")
    meta = {"kind": kind, "source": str(src), "recorded": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "files": sorted(data) + ([HISTORY_FILE] if history is not None else []),
            "history_decimals": RECORD_DECIMALS if history is not None else None}
    atomic_write_text(dest / RECORD_FILE, json.dumps(meta, indent=2) + "\n")
    return dest


def record_runs(srcs, out_root: str | Path = DEFAULT_OUT) -> list[Path]:
    """Write the records of finished runs (or flatness folders) to ``out_root/<folder name>``;
    returns the record folders.  Every source is read and checked before anything is written
    (ConfigError naming the file otherwise)."""
    srcs = [Path(s).absolute() for s in srcs]
    names = [s.name for s in srcs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"refgs record: two sources named {dup[0]!r} would share one record folder")
    collected = [_collect(s) for s in srcs]
    return [_write(s, *c, Path(out_root)) for s, c in zip(srcs, collected)]


def add_parser(sub) -> None:
    r = sub.add_parser("record", help="copy the small files of finished runs (config, metrics, "
                                      "history rounded) into a committable folder")
    r.add_argument("run_dirs", nargs="+", help="finished run directories or refgs flatness outputs")
    r.add_argument("--out", default=DEFAULT_OUT, help=f"records folder (default {DEFAULT_OUT})")
    r.add_argument("--quiet", action="store_true")


def run(args) -> list[Path]:
    written = record_runs(args.run_dirs, args.out)
    if not args.quiet:
        for p in written:
            print(p)
    return written


__all__ = ["record_runs", "rounded_history", "RECORD_DECIMALS", "DEFAULT_OUT"]
