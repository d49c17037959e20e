"""Spec clauses, read from the headings of docs/spec/*.md (ORC-09).

A clause is declared by a level-4 markdown heading of exactly the form ``#### ABC-12: Title``
(docs/spec/README.md).  The oracle cites clause ids in every check (oracle/checks.py); this
module finds what the spec declares so that the meta-test can require that every renderer clause
has a check and that every check cites a declared clause.

    load_clauses(spec_dir=None) -> dict[id, Clause]   (in file order)
    clause_sort_key("RAS-10")   -> ("RAS", 10)        (numeric order within a prefix)
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

#: the heading grammar of docs/spec/README.md: level 4, 2-4 capitals, hyphen, two digits, colon
CLAUSE_HEADING = re.compile(r"^####\s+([A-Z]{2,4}-\d{2}):\s*(.+?)\s*$")

#: prefixes of the renderer's clauses: every one of them must be covered by a check (ORC-09).
#: Method and training clauses (FM, TRN, DAT, MET) and the oracle's own (ORC) are not renderer
#: behaviour and are not checked through a backend.
RENDERER_PREFIXES = ("CNV", "COV", "PRJ", "SH", "RAS", "PRF", "API", "HARD")

#: environment variable that points the oracle at another spec folder (tests use it)
SPEC_DIR_ENV = "REFGS_SPEC_DIR"


@dataclass(frozen=True)
class Clause:
    """One declared clause: id ``ABC-12``, its title, the file and 1-based line declaring it."""

    id: str
    title: str
    file: str
    line: int

    @property
    def prefix(self) -> str:
        return self.id.split("-")[0]

    def cite(self) -> str:
        """``[RAS-05: Transmittance stop; ...]`` for failure messages."""
        return f"[{self.id}: {self.title}]"


def default_spec_dir() -> Path:
    """``$REFGS_SPEC_DIR``, else the spec beside this module: ``oracle/spec``, a link to
    docs/spec in a checkout and a copy of it in an installed wheel (pyproject package-data)."""
    env = os.environ.get(SPEC_DIR_ENV)
    if env:
        return Path(env)
    return Path(__file__).resolve().parent / "spec"


def load_clauses(spec_dir: str | os.PathLike | None = None) -> dict[str, Clause]:
    """Every clause declared in ``spec_dir/*.md``, keyed by id, in file then line order.

    Headings inside fenced code blocks (examples of the format) declare nothing.
    Raises ValueError naming both places if an id is declared twice (ids are unique across the
    spec, docs/spec/README.md).  A missing folder gives an empty dict: the meta-test then reports
    every check's citation as unknown, which is the right failure.
    """
    folder = Path(spec_dir) if spec_dir is not None else default_spec_dir()
    found: dict[str, Clause] = {}
    if not folder.is_dir():
        return found
    for path in sorted(folder.glob("*.md")):
        fenced = False
        for lineno, text in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            if text.lstrip().startswith("```"):
                fenced = not fenced          # a heading inside a code block is an example
                continue
            m = None if fenced else CLAUSE_HEADING.match(text)
            if not m:
                continue
            cid, title = m.group(1), m.group(2)
            if cid in found:
                prev = found[cid]
                raise ValueError(f"{path}:{lineno}: clause {cid} already declared at "
                                 f"{prev.file}:{prev.line}")
            found[cid] = Clause(cid, title, path.name, lineno)
    return found


def clause_sort_key(cid: str) -> tuple[str, int]:
    """Sort key giving CNV-02 before CNV-10 and prefixes in RENDERER_PREFIXES order."""
    prefix, _, num = cid.partition("-")
    rank = RENDERER_PREFIXES.index(prefix) if prefix in RENDERER_PREFIXES else len(RENDERER_PREFIXES)
    return (f"{rank:02d}{prefix}", int(num) if num.isdigit() else 0)


def renderer_clauses(clauses: dict[str, Clause]) -> list[str]:
    """Ids with a renderer prefix, sorted (what ORC-09 requires a check for)."""
    return sorted((c for c in clauses if c.split("-")[0] in RENDERER_PREFIXES), key=clause_sort_key)


def expand_selection(selection, known) -> set[str]:
    """Turn ``--clause`` values (ids, prefixes like ``RAS``, comma lists) into a set of ids.

    Raises ValueError naming the value when it matches no known id or prefix.
    """
    out: set[str] = set()
    known = list(known)
    for raw in selection:
        for item in (s.strip() for s in str(raw).split(",")):
            if not item:
                continue
            item = item.upper()
            hits = [c for c in known if c == item or c.split("-")[0] == item]
            if not hits:
                raise ValueError(f"--clause: {item!r} matches no clause id or prefix the checks cite "
                                 f"(see `python -m oracle list-clauses`)")
            out.update(hits)
    return out
