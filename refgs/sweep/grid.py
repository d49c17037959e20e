"""Grid files: a TOML file of ``refgs train`` options whose list values are the axes of a grid.

    load_grid(path) -> Grid       every run of the grid, in a stable order, with its TrainConfig

A key is a ``refgs train`` option by its long name (``iters``, ``fm-gamma`` or ``fm_gamma``,
``no_lpips`` ...; refgs.sweep.options); a flag takes ``true`` / ``false``.  A list value is an
axis: the runs are the cartesian product of the axes (the last axis varies fastest).  Each
``[[group]]`` table adds keys to, or overrides keys of, the top-level ones and gives its own
product; the runs of the groups follow one another.  A relative ``scene`` (or ``init-points``
PLY) is relative to the grid file.  An optional ``[report]`` table declares the grid's report
(refgs.analysis.report_spec); it makes no runs.

Each run's options are parsed by the parser of ``refgs train`` and turned into a TrainConfig by
the same builder (``config_from_args``), so a grid accepts exactly the options of ``refgs train``.
Every problem -- an unknown key, a bad value, an empty axis, a missing scene -- is a ConfigError of
one line naming the file and the key, raised before anything runs.

A run's name (its folder in the sweep's output) is made from its own values: the scene folder's
name, ``v<views>``, the method, the value of every key that is an axis somewhere in the file
(keys in alphabetical order; a true flag by its key), then ``s<seed>``, e.g. ``fern_v3_fm_s0``,
``fern_v3_fm_fm-gamma1_s0``.  Adding values to an axis, or runs to the file, leaves the names of
the other runs unchanged.  Runs that would share a name get the keys in which they differ added
(and, failing that, a hash of their settings); runs with identical settings are one run.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ..backends import available_backends
from ..errors import ConfigError
from ..methods import METHOD_NAMES
from ..runs import absolute_paths, settings_hash
from ..train.trainer import TrainConfig
from .options import RUN_CONTROL_FLAGS, add_train_options, config_from_args

#: The key of the grid's group tables (``[[group]]``).
GROUP_KEY = "group"
#: The key of the grid's optional report table (``[report]``, read by refgs.analysis.report_spec).
REPORT_KEY = "report"
#: Keys whose relative paths are relative to the grid file (a PLY for --init-points).
PATH_KEYS = ("scene", "init_points")
#: Keys always in a run's name, in order (the seed goes last: ``fern_v3_fm_s0``).
NAME_KEYS = ("scene", "views", "method")
#: Characters allowed in a name token; others become '-'.
NAME_UNSAFE = re.compile(r"[^A-Za-z0-9.+-]+")
#: Hex digits of the settings hash added to names that no key tells apart.
NAME_HASH_DIGITS = 8


class OptionParser(argparse.ArgumentParser):
    """The ``refgs train`` parser for grid values: errors raise ConfigError instead of exiting,
    no abbreviations, and it remembers its options (argument groups are itself: groups only
    organise help)."""

    def __init__(self):
        super().__init__(prog="refgs train", add_help=False, allow_abbrev=False)
        self.options: dict[str, argparse.Action] = {}

    def add_argument(self, *args, **kwargs):
        action = super().add_argument(*args, **kwargs)
        for flag in action.option_strings:
            if flag.startswith("--"):
                self.options[key_of(flag[2:])] = action
        return action

    def add_argument_group(self, *args, **kwargs):
        # argparse makes its own groups in __init__, before ``options`` exists
        return self if hasattr(self, "options") else super().add_argument_group(*args, **kwargs)

    def error(self, message):
        raise ConfigError(re.sub(r"^argument [^:]+: ", "", message))


def key_of(name: str) -> str:
    """A grid key or long option name in its canonical form (``fm-gamma`` -> ``fm_gamma``)."""
    return name.replace("-", "_")


@dataclass(frozen=True)
class GridRun:
    """One run of a grid: its position, its name, its options (canonical key -> value, paths
    absolute) and its TrainConfig (absolute paths, validated) with that config's settings hash
    (the one its config.json records, refgs.runs.settings_hash)."""

    index: int
    name: str
    options: dict
    cfg: TrainConfig
    settings_hash: str


@dataclass(frozen=True)
class Grid:
    path: Path
    runs: tuple

    def find(self, index: int | None = None, name: str | None = None) -> GridRun:
        """The run with this index or name; ConfigError naming the flag when there is none."""
        if name is not None:
            for run in self.runs:
                if run.name == name:
                    return run
            raise ConfigError(f"--name: {self.path} has no run named {name!r} (see refgs sweep "
                              f"{self.path} --out DIR --list)")
        if index is None or not 0 <= index < len(self.runs):
            raise ConfigError(f"--index: expected 0..{len(self.runs) - 1} for the "
                              f"{len(self.runs)} runs of {self.path}, got {index}")
        return self.runs[index]


def _read_toml(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"{path}: grid file not found")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None


def _tokens(parser: OptionParser, key: str, value) -> list[str]:
    """The command-line tokens of one option value; ConfigError (without the file) if bad."""
    action = parser.options[key]
    flag = action.option_strings[-1]
    if action.nargs == 0:
        if not isinstance(value, bool):
            raise ConfigError(f"a flag: expected true or false, got {value!r}")
        return [flag] if value else []
    if isinstance(value, bool) or isinstance(value, (dict, list)):
        raise ConfigError(f"expected a value for {flag}, got {value!r}")
    tokens = [flag, str(value)]
    parser.parse_args(tokens)                       # its type and choices
    return tokens


def _check_table(path: Path, where: str, table: dict, parser: OptionParser) -> dict:
    """The table's keys in canonical form, every value checked; paths made absolute."""
    out = {}
    for raw, value in table.items():
        key = key_of(raw)
        at = f"{path}: {where}{raw}"
        if key in (GROUP_KEY, REPORT_KEY) and not where:
            continue
        if key in RUN_CONTROL_FLAGS:
            raise ConfigError(f"{at}: not allowed in a grid (the sweep sets where and how runs go)")
        if key not in parser.options:
            raise ConfigError(f"{at}: unknown key (expected a refgs train option by its long name, "
                              f"e.g. iters, method, seed, views, scene, fm_gamma)")
        if key in out:
            raise ConfigError(f"{at}: given twice (as {raw!r} and another spelling)")
        values = value if isinstance(value, list) else [value]
        if not values:
            raise ConfigError(f"{at}: empty list (an axis needs at least one value)")
        for v in values:
            try:
                _tokens(parser, key, v)
            except ConfigError as exc:
                raise ConfigError(f"{at}: {exc}") from None
            if key in PATH_KEYS and not isinstance(v, str):
                raise ConfigError(f"{at}: expected a path (a string), got {v!r}")
            if key == "backend" and v not in available_backends() and ":" not in v:
                raise ConfigError(f"{at}: expected one of {', '.join(available_backends())} or "
                                  f"module:object, got {v!r}")
        if key in PATH_KEYS:
            values = [v if key == "init_points" and not v.lower().endswith(".ply")
                      else os.path.normpath(path.parent.absolute() / v) for v in values]
        out[key] = values if isinstance(value, list) else values[0]
    return out


def _token(key: str, value) -> str:
    if isinstance(value, bool):
        return key.replace("_", "-") if value else ""
    if key in PATH_KEYS:
        value = Path(str(value)).stem if key == "init_points" else Path(str(value)).name
    if isinstance(value, float):
        value = f"{value:g}"
    text = NAME_UNSAFE.sub("-", str(value)).strip("-.")
    return text if key in PATH_KEYS + ("method",) else key.replace("_", "-") + text


def run_name(options: dict, defaults: dict, axes: set, extra: tuple = ()) -> str:
    """The run's name from its options (``defaults`` for the keys it does not give; ``axes``
    the keys that are lists somewhere in the grid; ``extra`` more keys to show)."""
    get = lambda k: options.get(k, defaults.get(k))  # noqa: E731
    parts = [_token("scene", get("scene")), f"v{get('views')}", _token("method", get("method"))]
    for key in sorted((axes | set(extra)) - set(NAME_KEYS) - {"seed"}):
        if key in options:
            parts.append(_token(key, options[key]))
    parts.append(f"s{get('seed')}")
    return "_".join(p for p in parts if p)


def _expand(table: dict) -> list[dict]:
    """The product of the table's axes: scene, views and method vary slowest, then the other
    axes in the file's order, then the seed (fastest)."""
    order = {k: i for i, k in enumerate(NAME_KEYS)}
    axes = sorted((k for k, v in table.items() if isinstance(v, list)),
                  key=lambda k: order.get(k, len(NAME_KEYS) + (k == "seed")))
    return [dict(table, **dict(zip(axes, combo)))
            for combo in itertools.product(*(table[k] for k in axes))]


def _config(path: Path, parser: OptionParser, options: dict, where: str):
    argv = [t for k, v in options.items() for t in _tokens(parser, k, v)]
    args = parser.parse_args(argv)
    for key in ("scene", "views", "iters"):
        if getattr(args, key) is None:
            raise ConfigError(f"{path}: {where}{key}: required (every run needs scene, views and "
                              f"iters)")
    args.out = "-"
    try:
        cfg = absolute_paths(config_from_args(args)).validate(METHOD_NAMES)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {where}{exc}") from None
    return cfg


def train_argv(path: Path, table: dict, where: str) -> list[str]:
    """The ``refgs train`` tokens of one table of single option values (a grid without axes,
    e.g. a report's pinned run), checked as a grid's are; ConfigError naming ``path`` and
    ``where`` + the key."""
    parser = OptionParser()
    add_train_options(parser)
    options = _check_table(path, where, table, parser)
    axes = [k for k, v in options.items() if isinstance(v, list)]
    if axes:
        raise ConfigError(f"{path}: {where}{axes[0]}: expected one value, not a list")
    _config(path, parser, options, where)
    return [t for k, v in options.items() for t in _tokens(parser, k, v)]


def load_grid(path: str | os.PathLike) -> Grid:
    """Every run of the grid file ``path`` (see the module docstring); ConfigError naming the
    file and the key on any problem."""
    path = Path(path).absolute()
    data = _read_toml(path)
    parser = OptionParser()
    add_train_options(parser)
    defaults = {k: a.default for k, a in parser.options.items()}
    top = _check_table(path, "", data, parser)
    groups = data.get(GROUP_KEY, [{}])
    if not isinstance(groups, list) or not all(isinstance(g, dict) for g in groups):
        raise ConfigError(f"{path}: {GROUP_KEY}: expected [[group]] tables")
    if not groups or (not top and not any(groups)):
        raise ConfigError(f"{path}: empty grid (no options, no runs)")
    tables = []
    for i, group in enumerate(groups):
        where = f"group {i + 1}: " if GROUP_KEY in data else ""
        tables.append((where, dict(top, **_check_table(path, where, group, parser))))
    axes = {k for _, t in tables for k, v in t.items() if isinstance(v, list)}
    found: list[tuple[str, dict, TrainConfig, str]] = []
    seen = set()
    for where, table in tables:
        for options in _expand(table):
            cfg = _config(path, parser, options, where)
            digest = settings_hash(cfg.to_dict())
            if digest not in seen:
                seen.add(digest)
                found.append((run_name(options, defaults, axes), options, cfg, digest))
    if not found:
        raise ConfigError(f"{path}: empty grid (no runs)")
    names = [n for n, *_ in found]
    for name in set(names):
        clash = [i for i, n in enumerate(names) if n == name]
        if len(clash) > 1:
            opts = [found[i][1] for i in clash]
            keys = {k for o in opts for k in o
                    if len({json.dumps(p.get(k, defaults.get(k))) for p in opts}) > 1}
            for i in clash:
                names[i] = run_name(found[i][1], defaults, axes, tuple(keys))
            if len({names[i] for i in clash}) < len(clash):
                for i in clash:
                    names[i] += "-" + found[i][3][:NAME_HASH_DIGITS]
    runs = tuple(GridRun(i, n, opts, cfg, digest)
                 for i, (n, (_, opts, cfg, digest)) in enumerate(zip(names, found)))
    return Grid(path, runs)


__all__ = ["load_grid", "train_argv", "Grid", "GridRun", "OptionParser", "run_name", "key_of",
           "GROUP_KEY", "REPORT_KEY"]
