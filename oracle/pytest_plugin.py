"""The oracle as a pytest plugin: one pytest item per check, in a backend author's own CI (ORC-08).

    pytest --oracle-backend mypkg.mymodule:backend [--oracle-profile inria|gsplat]
           [--oracle-max-examples N] [--oracle-seed S] [--oracle-clause ID ...]
           [--oracle-report DIR] [--oracle-timeout S] [--oracle-memory-limit MIB]
           [--oracle-known-differences FILE.toml] [--junitxml reports/oracle.xml]

Installed with refgs (entry point ``pytest11``: ``oracle``); ``pytest -p oracle.pytest_plugin``
loads it where entry points are off.  Without ``--oracle-backend`` it only declares its options:
it imports nothing beyond this module and changes nothing in the run.

With it, the session collects one item per check of oracle/checks.py, named
``oracle::<check>[<clause ids>]`` (``oracle::forward_pixel_centres[CNV-08]``; ``-k CNV-08``
selects by clause), besides whatever else pytest collects.  The items run as
``python -m oracle check`` runs its checks: the backend in one worker process (oracle/isolation.py,
ORC-11) started at the first item and replaced when it dies, each check a hypothesis property
with its failing example shrunk and written as a reproducer.  An item passes on ``pass``, is
skipped on ``n/a`` / ``not provided`` with the reason, is an expected failure on ``known``, and
fails on ``fail``, ``error``, ``crash`` or ``timeout`` with the report's failure block (blamed
clauses, smallest scene, reproducer, replay command); JUnit XML carries each item's status and
clauses as properties.  At the end the report folder (``index.html``, ``report.json``,
``report.txt``, ``failures/``) is written beside the JUnit XML (``<xml folder>/oracle-report``),
else to ``--oracle-report`` (default ``oracle-report``).  A backend that cannot be loaded stops
the session with one line and exit status 2, as ``python -m oracle check`` does.
"""
from __future__ import annotations

import textwrap
import time
from pathlib import Path

import pytest

#: The folder name of the report when it goes beside the JUnit XML.
REPORT_BESIDE_XML = "oracle-report"
#: The node id of the collector holding the oracle's items (their class name in JUnit XML).
COLLECTOR = "oracle"
#: Exit status when the backend cannot be loaded (python -m oracle check: a usage error).
EXIT_USAGE = 2


def pytest_addoption(parser) -> None:
    g = parser.getgroup("oracle", "the oracle: conformance of a 3DGS backend (docs/oracle.md)")
    g.addoption("--oracle-backend", metavar="MODULE:OBJECT",
                help="run the oracle's checks against this backend (module:object or a registry "
                     "name), one pytest item per check")
    g.addoption("--oracle-profile", choices=("inria", "gsplat"),
                help="judge the backend in this profile instead of the one it declares (for a "
                     "renderer whose render follows config.profile)")
    g.addoption("--oracle-max-examples", type=int, metavar="N",
                help="hypothesis examples per check (default: as python -m oracle check)")
    g.addoption("--oracle-seed", type=int, metavar="S",
                help="hypothesis seed (default: as python -m oracle check)")
    g.addoption("--oracle-clause", action="append", default=[], metavar="ID",
                help="only checks citing these clause ids or prefixes (repeatable, or a comma list)")
    g.addoption("--oracle-report", metavar="DIR",
                help=f"report folder (default: {REPORT_BESIDE_XML}/ beside --junitxml, else "
                     f"./{REPORT_BESIDE_XML})")
    g.addoption("--oracle-timeout", type=float, metavar="S",
                help="seconds of backend time one check may use (default: as python -m oracle "
                     "check; 0: no limit)")
    g.addoption("--oracle-memory-limit", type=int, metavar="MIB",
                help="data memory of the backend's worker in MiB (default: as python -m oracle "
                     "check; 0: no limit)")
    g.addoption("--oracle-known-differences", metavar="FILE",
                help="TOML file of [[difference]] tables: failures reported as known")
    g.addoption("--oracle-no-shrink", action="store_true",
                help="report the first failing example as found")


def pytest_configure(config) -> None:
    spec = config.getoption("oracle_backend")
    if not spec:
        return
    if getattr(config.option, "numprocesses", None):
        raise pytest.UsageError("--oracle-backend: run without -n (the checks share one backend "
                                "worker, and the report is written by one process)")
    config.pluginmanager.register(OracleRun(config, spec), "oracle-run")


def report_folder(config) -> Path:
    """``--oracle-report``, else ``oracle-report`` beside the JUnit XML, else in the folder
    pytest was started from."""
    given = config.getoption("oracle_report")
    if given:
        return Path(given)
    xml = getattr(config.option, "xmlpath", None)
    base = Path(xml).parent if xml else Path(config.invocation_params.dir)
    return base / REPORT_BESIDE_XML


class CheckFailed(Exception):
    """A check ended in fail, error, crash or timeout; ``result`` is its runner.CheckResult."""

    def __init__(self, result):
        super().__init__(result.status)
        self.result = result


class OracleItem(pytest.Item):
    """One check of oracle/checks.py against the session's backend."""

    def __init__(self, *, check, run, **kw):
        super().__init__(**kw)
        self.check, self.run = check, run
        for cid in check.clauses:
            self.keywords[cid] = True

    def runtest(self) -> None:
        r = self.run.run_check(self.check)
        self.user_properties += [("clauses", ",".join(self.check.clauses)), ("status", r.status)]
        if r.failure and r.failure.get("reproducer"):
            self.user_properties.append(("reproducer", r.failure["reproducer"]))
        if r.status == "pass":
            return
        if r.status in ("n/a", "not provided"):
            pytest.skip(f"{r.status}: {r.reason}")
        if r.status == "known":
            pytest.xfail("known difference: " + "; ".join(e["reason"] for e in r.known))
        raise CheckFailed(r)

    def repr_failure(self, excinfo, style=None):
        if isinstance(excinfo.value, CheckFailed):
            from .report import failure_lines
            return textwrap.dedent("\n".join(failure_lines(excinfo.value.result)))
        return super().repr_failure(excinfo, style)

    def reportinfo(self):
        return self.path, None, f"{COLLECTOR}::{self.name}"


class OracleCollector(pytest.Collector):
    """The parent of the oracle's items (node id ``oracle``)."""

    def collect(self):
        return self.items

    def make_items(self, checks, run) -> list[OracleItem]:
        self.items = [OracleItem.from_parent(self, name=f"{c.name}[{','.join(c.clauses)}]",
                                             check=c, run=run) for c in checks]
        return self.items


class OracleRun:
    """The session's oracle run: its settings, the backend's worker, the results so far."""

    def __init__(self, config, spec: str):
        from .runner import Settings
        from .isolation import DEFAULT_MEMORY_LIMIT_MIB, DEFAULT_TIMEOUT

        self.config, self.spec = config, spec
        opt = config.getoption
        n = opt("oracle_max_examples")
        if n is not None and n < 1:
            raise pytest.UsageError(f"--oracle-max-examples: expected a positive integer, got {n}")
        timeout = opt("oracle_timeout")
        timeout = DEFAULT_TIMEOUT if timeout is None else timeout
        memory = opt("oracle_memory_limit")
        memory = DEFAULT_MEMORY_LIMIT_MIB if memory is None else memory
        if timeout < 0 or memory < 0:
            raise pytest.UsageError("--oracle-timeout and --oracle-memory-limit: expected 0 (no "
                                    "limit) or a positive number")
        try:
            known, clauses = self._selection()
        except ValueError as exc:
            raise pytest.UsageError(str(exc)) from None
        defaults = Settings()
        self.folder = report_folder(config)
        self.settings = Settings(
            max_examples=defaults.max_examples if n is None else n,
            seed=defaults.seed if opt("oracle_seed") is None else opt("oracle_seed"),
            shrink=not opt("oracle_no_shrink"),
            report_dir=str(self.folder), clauses=clauses, timeout=timeout or None,
            memory_limit_mib=memory, known_differences=known)
        self.backend = None
        self.results: list = []
        self.started = None
        self.t0 = None

    def _selection(self):
        from .checks import cited_clauses
        from .clauses import expand_selection
        from .known import load_file
        wanted = self.config.getoption("oracle_clause")
        clauses = tuple(sorted(expand_selection(wanted, cited_clauses()))) if wanted else ()
        path = self.config.getoption("oracle_known_differences")
        return (load_file(path) if path else ()), clauses

    # --- collection ------------------------------------------------------------------------------
    @pytest.hookimpl(tryfirst=True)          # before -k / -m deselect among the items
    def pytest_collection_modifyitems(self, session, config, items) -> None:
        from .checks import checks_for
        checks = checks_for(self.settings.clauses or None)
        collector = OracleCollector.from_parent(session, name=COLLECTOR, nodeid=COLLECTOR)
        items.extend(collector.make_items(checks, self))

    # --- running ---------------------------------------------------------------------------------
    def open(self):
        """The backend, in its worker, started on first use (exit status 2 if it cannot load)."""
        if self.backend is None:
            import dataclasses
            from datetime import datetime, timezone
            from .isolation import open_backend
            from .protocol import BackendError
            try:
                backend = open_backend(self.spec, self.settings.memory_limit_mib)
            except (BackendError, ValueError) as exc:
                pytest.exit(f"oracle: error: {exc}", returncode=EXIT_USAGE)
            profile = self.config.getoption("oracle_profile")
            if profile and profile != backend.profile:
                backend = dataclasses.replace(backend, profile=profile, supports_antialiased=(
                    backend.supports_antialiased and profile == "gsplat"))
            self.backend = backend
            self.started = datetime.now(timezone.utc).isoformat(timespec="seconds")
            self.t0 = time.perf_counter()
        return self.backend

    def run_check(self, check):
        """Run one check as ``python -m oracle check`` would; its runner.CheckResult."""
        from .runner import run
        try:
            (r,) = run(self.open(), self.settings, checks=[check]).results
        except ValueError as exc:                 # a known difference naming no such check
            pytest.exit(f"oracle: error: {exc}", returncode=EXIT_USAGE)
        self.results.append(r)
        return r

    def pytest_sessionfinish(self, session, exitstatus) -> None:
        if self.backend is None:
            return
        try:
            if self.results:
                from .clauses import load_clauses
                from .runner import RunResult, write_reports
                result = RunResult(self.backend, self.settings, self.results, load_clauses(),
                                   self.started, time.perf_counter() - self.t0)
                self.page = write_reports(result, self.folder)[2]
        finally:
            self.backend.session.close()

    def pytest_terminal_summary(self, terminalreporter) -> None:
        page = getattr(self, "page", None)
        if page is not None:
            failed = sum(1 for r in self.results if r.status in ("fail", "error", "crash", "timeout"))
            terminalreporter.write_line(f"oracle: {len(self.results)} checks against {self.spec}, "
                                        f"{failed} failing; report: {page}")
