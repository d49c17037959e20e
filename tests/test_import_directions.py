"""The import directions of docs/architecture.md, checked on the source with ``ast``.

Every ``import`` of every module in refgs/ and oracle/ counts -- at module level or inside a
function, absolute or relative, and ``importlib.import_module("...")`` with a constant name --
and the rules are:

- no import cycles among the modules of refgs/ and oracle/;
- the spec (covariance, projection, sh, rasterize, render, constants, types, activations)
  imports nothing from data, train, methods, fast, analysis, runs or the oracle;
- refgs.train never imports refgs.fast, and refgs.fast never imports refgs.train;
- the oracle never imports refgs.train, refgs.runs or refgs.methods; refgs never imports oracle;
- nothing imports refgs.cli (only the entry point refgs/__main__.py);
- no ``from X import _private`` across modules.

``check_imports`` is the checker; the last test plants each violation in a module tree written
to a temporary folder and shows that it is caught.
"""
from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("refgs", "oracle")
SPEC = ("refgs.covariance", "refgs.projection", "refgs.sh", "refgs.rasterize", "refgs.render",
        "refgs.constants", "refgs.types", "refgs.activations")
ABOVE_SPEC = ("refgs.data", "refgs.train", "refgs.methods", "refgs.fast", "refgs.analysis",
              "refgs.runs", "oracle")
#: (importers, forbidden targets, why), prefixes matched on whole dotted components.
RULES = (
    (SPEC, ABOVE_SPEC, "the spec stands alone"),
    (("refgs.train",), ("refgs.fast",), "the trainer reaches a renderer only through the backend "
                                        "its caller passes"),
    (("refgs.fast",), ("refgs.train",), "a backend knows no trainer"),
    (("oracle",), ("refgs.train", "refgs.runs", "refgs.methods"), "the oracle judges renderers, "
                                                                  "not trainers"),
    (("refgs",), ("oracle",), "refgs never imports its judge"),
    (("refgs", "oracle"), ("refgs.cli",), "nothing imports the CLI"),
)
#: Modules allowed to break the CLI rule: the ``python -m refgs`` entry point.
ENTRY_POINTS = ("refgs.__main__",)


def _within(module: str, prefixes) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of PACKAGES under ``root``."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, known: dict) -> list[tuple[str, int, str | None]]:
    """(imported module, line, imported name or None) for every import in the module ``name``:
    a name imported from a module is attributed to that module, a submodule to itself."""
    is_pkg = path.name == "__init__.py"
    package = name.split(".") if is_pkg else name.split(".")[:-1]
    found = []

    def target(dotted: str) -> str | None:
        parts = dotted.split(".")
        while parts and ".".join(parts) not in known:
            parts.pop()
        return ".".join(parts) if parts else None

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.append((target(alias.name), node.lineno, None))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1]
                                + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in known:
                    found.append((sub, node.lineno, None))
                else:
                    found.append((target(base), node.lineno, alias.name))
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and ((isinstance(node.func, ast.Attribute) and node.func.attr == "import_module")
                   or (isinstance(node.func, ast.Name) and node.func.id in ("import_module", "__import__")))):
            found.append((target(node.args[0].value), node.lineno, None))
    return [(t, line, n) for t, line, n in found if t is not None and t != name]


def _cycles(graph: dict[str, set]) -> list[list[str]]:
    """One cycle (a list of modules, first = last) per strongly connected component (Tarjan)."""
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(set(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    cycles = []
    for comp in comps:                      # a shortest way back to the first module (BFS)
        start = min(comp)
        prev, frontier = {start: None}, [start]
        while frontier and start not in [w for v in frontier for w in graph[v]]:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & comp):
                    if w not in prev:
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        last = next(v for v in frontier if start in graph[v])
        path = [last]
        while prev[path[-1]] is not None:
            path.append(prev[path[-1]])
        cycles.append([start] + path[::-1][1:] + [start] if len(path) > 1 else [start, last, start])
    return cycles


def check_imports(root: Path = ROOT) -> list[str]:
    """Every violation of the module docstring's rules in the tree under ``root``, one line each
    (``file:line: message``); empty when the tree keeps them."""
    known = _modules(root)
    graph: dict[str, set] = {m: set() for m in known}
    where: dict[tuple, str] = {}
    problems = []
    for name, path in known.items():
        rel = path.relative_to(root)
        for target, line, imported in _imports(name, path, known):
            graph[name].add(target)
            where.setdefault((name, target), f"{rel}:{line}")
            for importers, forbidden, why in RULES:
                if (_within(name, importers) and _within(target, forbidden)
                        and not (target == "refgs.cli" and name in ENTRY_POINTS)):
                    problems.append(f"{rel}:{line}: {name} imports {target} ({why})")
            if imported and imported.startswith("_") and not imported.endswith("__"):
                problems.append(f"{rel}:{line}: {name} imports the private name {imported!r} "
                                f"from {target}")
    for cycle in _cycles(graph):
        steps = ", ".join(where[(a, b)] for a, b in zip(cycle, cycle[1:]))
        problems.append(f"import cycle: {' -> '.join(cycle)} ({steps})")
    return problems


def test_the_source_keeps_the_import_directions():
    problems = check_imports(ROOT)
    assert not problems, "\n".join(problems)


def test_the_checker_sees_the_real_tree():
    known = _modules(ROOT)
    assert {"refgs.render", "refgs.runs", "refgs.backends", "refgs.cli", "oracle.protocol",
            "refgs.train.trainer", "refgs.fast.render"} <= set(known)
    edges = {t for t, _, _ in _imports("refgs.runs", known["refgs.runs"], known)}
    assert {"refgs.backends", "refgs.train.trainer", "refgs.data", "refgs.data.pointcloud"} <= edges


def test_import_refgs_loads_the_spec_alone():
    """At run time too: ``import refgs`` and the oracle's protocol load no room above the spec
    (refgs.sap_offsets is imported on first use)."""
    code = ("import sys, refgs, oracle.protocol\n"
            "print(sorted(m for m in sys.modules if m.split('.')[:2] in [['refgs', r] for r in "
            "('train', 'methods', 'runs', 'data', 'fast', 'analysis', 'cli', 'backends')]))\n"
            "assert callable(refgs.sap_offsets) and 'refgs.methods.flat_minima' in sys.modules")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


PLANTED = {
    "refgs/__init__.py": "",
    "refgs/covariance.py": "from .train import trainer\n",
    "refgs/render.py": "def f():\n    import oracle.checks\n",
    "refgs/cli.py": "",
    "refgs/__main__.py": "from .cli import main\n",
    "refgs/runs.py": "from . import cli\n",
    "refgs/train/__init__.py": "",
    "refgs/train/trainer.py": "def step():\n    from ..fast.kernels import kernel\n",
    "refgs/fast/__init__.py": "",
    "refgs/fast/kernels.py": ("from ..covariance import _private_helper\n\n"
                              "def kernel():\n    from refgs.train import trainer\n"),
    "refgs/analysis/__init__.py": "",
    "refgs/analysis/bench.py": "import importlib\nimportlib.import_module('refgs.cli')\n",
    "oracle/__init__.py": "",
    "oracle/checks.py": "from refgs.runs import load\nfrom refgs import __version__\n",
}


def test_planted_violations_are_caught(tmp_path):
    for rel, text in PLANTED.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(textwrap.dedent(text))
    problems = check_imports(tmp_path)
    text = "\n".join(problems)
    print(text)
    expected = [
        "refgs/covariance.py:1: refgs.covariance imports refgs.train.trainer (the spec stands alone)",
        "refgs/render.py:2: refgs.render imports oracle.checks (the spec stands alone)",
        "refgs/render.py:2: refgs.render imports oracle.checks (refgs never imports its judge)",
        "refgs/train/trainer.py:2: refgs.train.trainer imports refgs.fast.kernels (the trainer",
        "refgs/fast/kernels.py:4: refgs.fast.kernels imports refgs.train.trainer (a backend knows "
        "no trainer)",
        "refgs/fast/kernels.py:1: refgs.fast.kernels imports the private name '_private_helper' "
        "from refgs.covariance",
        "oracle/checks.py:1: oracle.checks imports refgs.runs (the oracle judges renderers",
        "refgs/runs.py:1: refgs.runs imports refgs.cli (nothing imports the CLI)",
        "refgs/analysis/bench.py:2: refgs.analysis.bench imports refgs.cli (nothing imports the CLI)",
        "import cycle: refgs.covariance -> refgs.train.trainer -> refgs.fast.kernels -> "
        "refgs.covariance (refgs/covariance.py:1, refgs/train/trainer.py:2, "
        "refgs/fast/kernels.py:1)",
    ]
    for line in expected:
        assert any(p.startswith(line) for p in problems), f"not caught: {line}\n{text}"
    # allowed: the entry point imports the CLI, a dunder name, the oracle importing refgs' root
    assert not any(p.startswith("refgs/__main__.py") for p in problems)
    assert not any("__version__" in p or "oracle.checks imports refgs " in p for p in problems)
    assert len(problems) == len(expected), text   # one report per cycle, nothing else
