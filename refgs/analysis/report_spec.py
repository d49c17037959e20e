"""The ``[report]`` table of a grid file: what the grid's report holds (docs/sweeps.md, "The
report of a grid"; FM-13, FM-15, FM-16).

    load_report(path) -> Report       the grid's runs (its cells) and its [report] table, checked

A grid file (refgs.sweep.grid) may carry one ``[report]`` table.  It names the report's title and
markers, the metrics, the method names, the comparisons (method minus baseline, paired by seed),
the parts of the report (each a table of means and one of paired differences), the quoted
reference numbers (``[[report.quote]]``: a paper's table, its caption, the scene it has a
counterpart in), the optional tables beside the paper, of flatness over training seeds and of
cost, the training code whose records count (``[[report.code]]``: source hashes) and the short
pinned run that checks a new code hash (``[report.equivalence]``).  Which runs count is the
grid's business: a record counts when it was made by the grid (``refgs run-one GRID``), its cell
(scene folder, views, method label, seed) is one of the grid's and it has the settings the grid
file names (refgs.analysis.report).  ``include`` names other grids (beside this one) whose records
the parts may use, with their quotes and names.

Every problem is a ConfigError of one line naming the file and the key.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path, PurePath

from ..errors import ConfigError
from ..sweep.grid import REPORT_KEY, load_grid, train_argv
from .tables import method_label

#: (metrics.json key, column title, decimals shown): the paper's three metrics, the default.
DEFAULT_METRICS = (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("lpips_vgg", "LPIPS-VGG", 3))
#: The layouts of a part's table of means: one row per scene, views and method label, or per
#: method name and views with the quoted numbers beside.
LAYOUTS = ("scene", "method")
#: The intro of a report that gives none; placeholders: {grid}, {scenes}, {seeds}, {settings}.
DEFAULT_INTRO = ("The grid `{grid}`: {scenes}; seeds {seeds}; {settings}. Only records made by "
                 "this grid count (their `config.json` command is `refgs run-one {grid} ...`). "
                 "Mean ± sample standard deviation over the seeds, n the number of seeds.")
#: The closing sentence of the cost table that gives no note.
DEFAULT_COST_NOTE = ("Setup and each run's final evaluation (about a minute) are not counted "
                     "(refgs/analysis/cost.py).")
#: The worker command of a grid run: ``refgs run-one GRID --out DIR --name NAME``.
RUN_ONE = "run-one"
#: The settings that make a record's cell (scene, views, method label, seed).
CELL_KEYS = ("scene", "views", "method", "method_params", "seed")
#: The flatness curves that count: those of ``refgs flatness --settings flatness``.
FLATNESS_SETTINGS = "flatness"


@dataclass(frozen=True)
class Metric:
    key: str
    title: str
    decimals: int


@dataclass(frozen=True)
class Quote:
    """Numbers quoted from a reference table: ``values[method]`` per report metric, a mean over
    ``over`` (e.g. "LLFF 3-view, mean of 8 scenes"), with our counterpart scene and views."""

    source: str
    over: str
    scene: str
    views: int
    values: dict


@dataclass(frozen=True)
class Part:
    """A table of means over ``groups`` x ``methods`` and one of paired differences."""

    caption: str | None
    groups: tuple
    methods: tuple
    names: dict
    comparisons: tuple
    pooled: bool
    layout: str
    explain: bool


@dataclass(frozen=True)
class Report:
    grid: Path
    title: str
    marker: str
    intro: str
    metrics: tuple
    names: dict
    comparisons: tuple
    parts: tuple
    quotes: tuple
    code: tuple
    includes: tuple
    paper_note: str | None
    flatness_groups: tuple | None
    cost_note: str | None
    equivalence: tuple | None
    #: {(scene folder name, views, method label, seed): {setting: value the grid names}}
    cells: dict
    groups: tuple
    methods: tuple
    seeds: tuple
    settings: dict

    @property
    def name(self) -> str:
        """The grid as the records' commands end: ``experiments/my_study.toml``."""
        return f"{self.grid.parent.name}/{self.grid.name}"

    def all_quotes(self) -> tuple:
        return self.quotes + tuple(q for r in self.includes for q in r.all_quotes())

    def display(self, label: str) -> str:
        return self.names.get(label, label)


class Table:
    """A TOML table read key by key: ``take`` checks each type, ``done`` refuses the rest."""

    def __init__(self, path: Path, where: str, data):
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: {where}: expected a table")
        self.path, self.where, self.data, self.used = path, where, data, set()

    def at(self, key: str) -> str:
        return f"{self.path}: {self.where}.{key}"

    def take(self, key: str, kind, default=None, required=False):
        self.used.add(key)
        if key not in self.data:
            if required:
                raise ConfigError(f"{self.at(key)}: required")
            return default
        value = self.data[key]
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            raise ConfigError(f"{self.at(key)}: expected {getattr(kind, '__name__', kind)}, "
                              f"got {value!r}")
        return value

    def done(self) -> None:
        extra = sorted(set(self.data) - self.used)
        if extra:
            raise ConfigError(f"{self.at(extra[0])}: unknown key")


def pairs(t: Table, key: str, default=()) -> tuple:
    """A list of [method, baseline] (or [scene, views]) pairs."""
    value = t.take(key, list, None)
    if value is None:
        return tuple(default)
    if not all(isinstance(p, list) and len(p) == 2 for p in value):
        raise ConfigError(f"{t.at(key)}: expected a list of two-element lists, got {value!r}")
    return tuple(tuple(p) for p in value)


def read_metrics(t: Table) -> tuple:
    value = t.take("metrics", list, None)
    if value is None:
        return tuple(Metric(*m) for m in DEFAULT_METRICS)
    out = []
    for k, entry in enumerate(value):
        m = Table(t.path, f"{t.where}.metrics[{k}]", entry)
        out.append(Metric(m.take("key", str, required=True), m.take("title", str, required=True),
                          m.take("decimals", int, required=True)))
        m.done()
    return tuple(out)


def read_quote(path: Path, k: int, entry, metrics: tuple) -> Quote:
    q = Table(path, f"{REPORT_KEY}.quote[{k}]", entry)
    values = q.take("values", dict, required=True)
    for method, v in values.items():
        if (not isinstance(v, list) or len(v) != len(metrics)
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
            raise ConfigError(f"{q.at('values')}.{method}: expected {len(metrics)} numbers "
                              f"({', '.join(m.title for m in metrics)}), got {v!r}")
    quote = Quote(q.take("source", str, required=True), q.take("over", str, required=True),
                  q.take("scene", str, required=True), q.take("views", int, required=True),
                  {m: tuple(float(x) for x in v) for m, v in values.items()})
    q.done()
    return quote


def read_part(path: Path, k: int, entry, defaults: dict) -> Part:
    p = Table(path, f"{REPORT_KEY}.part[{k}]", entry)
    layout = p.take("layout", str, "scene")
    if layout not in LAYOUTS:
        raise ConfigError(f"{p.at('layout')}: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
    part = Part(p.take("caption", str), pairs(p, "groups", defaults["groups"]),
                tuple(p.take("methods", list, defaults["methods"])), p.take("names", dict, {}),
                pairs(p, "comparisons", defaults["comparisons"]), p.take("pooled", bool, False),
                layout, p.take("explain", bool, True))
    p.done()
    return part


def grid_cells(path: Path) -> tuple[dict, tuple, tuple, tuple, dict]:
    """(cells, (scene, views) groups, method labels, seeds, settings shared by every run) of the
    grid; a cell's settings are those the grid file names (besides the cell's own keys)."""
    grid = load_grid(path)
    cells = {}
    for run in grid.runs:
        s = run.cfg.to_dict()
        cell = (Path(s["scene"]).name, int(s["views"]), method_label(s), int(s["seed"]))
        cells[cell] = {k: s[k] for k in run.options if k in s and k not in CELL_KEYS}
    settings = [run.cfg.to_dict() for run in grid.runs]
    every = {k: v for k, v in settings[0].items() if all(s.get(k) == v for s in settings)}
    groups = tuple(dict.fromkeys(c[:2] for c in cells))
    methods = tuple(dict.fromkeys(c[2] for c in cells))
    seeds = tuple(sorted({c[3] for c in cells}))
    return cells, groups, methods, seeds, every


def read_code(path: Path, data) -> tuple:
    if not isinstance(data, list):
        raise ConfigError(f"{path}: {REPORT_KEY}.code: expected [[report.code]] tables")
    out = []
    for k, entry in enumerate(data):
        c = Table(path, f"{REPORT_KEY}.code[{k}]", entry)
        out.append(c.take("hash", str, required=True))
        c.take("how", str, required=True)
        c.take("date", str)
        c.done()
    return tuple(out)


def read_equivalence(path: Path, data) -> tuple:
    """(train argv of the pinned run, [(float environment key, digest, code)]) of
    ``[report.equivalence]``."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: {REPORT_KEY}.equivalence: expected a table")
    options = {k: v for k, v in data.items() if k != "pin"}
    argv = train_argv(path, options, f"{REPORT_KEY}.equivalence.")
    pins = []
    for k, entry in enumerate(data.get("pin", [])):
        p = Table(path, f"{REPORT_KEY}.equivalence.pin[{k}]", entry)
        pins.append((p.take("float_environment", str, required=True), p.take("digest", str, required=True),
                     p.take("code", str, required=True)))
        p.take("date", str)
        p.done()
    return tuple(argv), tuple(pins)


def read_toml(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"{path}: grid file not found")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None


def has_report(path: Path) -> bool:
    return REPORT_KEY in read_toml(path)


def load_report(path, _seen: tuple = ()) -> Report:
    """The grid ``path``'s cells and [report] table (module docstring); ConfigError naming the
    file and the key on any problem, or when the grid has no [report] table."""
    path = Path(path).absolute()
    if path in _seen:
        raise ConfigError(f"{path}: {REPORT_KEY}.include: includes itself")
    data = read_toml(path)
    if REPORT_KEY not in data:
        raise ConfigError(f"{path}: no [{REPORT_KEY}] table (docs/sweeps.md: the report of a grid)")
    t = Table(path, REPORT_KEY, data[REPORT_KEY])
    cells, groups, methods, seeds, every = grid_cells(path)
    includes = tuple(load_report(path.parent / name, _seen + (path,))
                     for name in t.take("include", list, []))
    metrics = read_metrics(t)
    names = {k: v for r in includes for k, v in r.names.items()}
    names.update(t.take("names", dict, {}))
    comparisons = pairs(t, "comparisons")
    defaults = {"groups": groups, "methods": methods, "comparisons": comparisons}
    parts = tuple(read_part(path, k, e, defaults) for k, e in enumerate(t.take("part", list, [])))
    if not parts:
        parts = (Part(None, groups, methods, {}, comparisons, t.take("pooled", bool, False),
                      "scene", True),)
    else:
        t.take("pooled", bool)
    quotes = tuple(read_quote(path, k, e, metrics) for k, e in enumerate(t.take("quote", list, [])))
    paper = Table(path, f"{REPORT_KEY}.paper", t.take("paper", dict, None) or {})
    flatness = Table(path, f"{REPORT_KEY}.flatness", t.take("flatness", dict, None) or {})
    cost = Table(path, f"{REPORT_KEY}.cost", t.take("cost", dict, None) or {})
    report = Report(
        path, t.take("title", str, required=True), t.take("marker", str, path.stem),
        t.take("intro", str, DEFAULT_INTRO), metrics, names, comparisons, parts, quotes,
        read_code(path, t.take("code", list, [])), includes,
        paper.take("note", str, "") if "paper" in t.data else None,
        pairs(flatness, "groups", groups) if "flatness" in t.data else None,
        cost.take("note", str, DEFAULT_COST_NOTE) if "cost" in t.data else None,
        read_equivalence(path, t.take("equivalence", dict)) if "equivalence" in t.data else None,
        cells, groups, methods, seeds, every)
    for table in (t, paper, flatness, cost):
        table.done()
    check_quotes(report)
    return report


def check_quotes(report: Report) -> None:
    """Two quotes of one (scene, views, method) must agree (ConfigError naming the grid)."""
    seen = {}
    for q in report.all_quotes():
        for method, values in q.values.items():
            key = (q.scene, q.views, method)
            if seen.setdefault(key, values) != values:
                raise ConfigError(f"{report.grid}: {REPORT_KEY}.quote: two quotes of {q.scene} "
                                  f"{q.views}-view {method} disagree ({seen[key]} and {values})")


def made_by(config: dict, report: Report) -> bool:
    """Whether a record's config.json command is ``refgs run-one .../<grid folder>/<grid file>
    ...`` (what ``refgs sweep`` and ``refgs run-one`` write, refgs.sweep.execute)."""
    cmd = config.get("command")
    if not isinstance(cmd, list) or len(cmd) < 3 or cmd[1] != RUN_ONE:
        return False
    return PurePath(str(cmd[2])).parts[-2:] == (report.grid.parent.name, report.grid.name)


def quoted(report: Report, scene: str, views: int, method: str):
    """The quoted values of a (scene, views, method), None when no quote has them."""
    for q in report.all_quotes():
        if (q.scene, q.views) == (scene, views) and method in q.values:
            return q.values[method]
    return None


__all__ = ["load_report", "has_report", "made_by", "quoted", "Report", "Part", "Quote", "Metric",
           "DEFAULT_METRICS", "DEFAULT_INTRO", "FLATNESS_SETTINGS", "LAYOUTS"]
