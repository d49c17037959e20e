"""The written spec is well-formed: clause ids, cross-references to tests, and renderable math.

docs/spec/README.md fixes the clause format: a level-4 heading ``#### ABC-12: Title``, ids unique
across docs/spec/, each clause ending with a ``Checked by:`` line that names tests as
``tests/<file>.py`` or ``tests/<file>.py::<test_function>``.  This module checks that, plus:

* every clause id of the renderer's clause list (CNV, COV, PRJ, SH, RAS, PRF, API, HARD) is declared;
* docs/spec/README.md links every spec file;
* every ``tests/...`` file named by a ``Checked by:`` line in docs/spec/ or docs/derivations/
  exists, and a named test function is defined in it;
* the CNV and HARD clauses name the tests that carry their number (test_cnv01_..., test_hard01_...);
* math is GitHub-renderable: ``$``/``$$`` balanced, no custom macros, no inline math starting or
  ending with a space, ``\\lt`` rather than ``<`` before a letter, ``\\lbrace`` rather than ``\\{``.

Pure text processing; runs in well under a second.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPEC_DIR = ROOT / "docs" / "spec"
DERIV_DIR = ROOT / "docs" / "derivations"
SPEC_FILES = sorted(SPEC_DIR.glob("*.md"))
DOC_FILES = SPEC_FILES + sorted(DERIV_DIR.glob("*.md"))
#: pages whose math is checked: the spec, the derivations, and the two reader-facing pages
MATH_FILES = DOC_FILES + [p for p in (ROOT / "docs" / "index.md", ROOT / "docs" / "glossary.md") if p.is_file()]

#: The heading pattern of the brief (levels 2-5); a clause must in addition be level 4 (the
#: oracle's ``oracle/clauses.py`` reads level-4 headings only).
CLAUSE_RE = re.compile(r"^#{2,5} ([A-Z]{2,4}-\d{2}):")
STRICT_CLAUSE_RE = re.compile(r"^#### ([A-Z]{2,4}-\d{2}): \S.*$")
#: Anything that looks like an attempt at a clause heading (to catch ``### CNV-1 Title`` etc.).
LOOSE_CLAUSE_RE = re.compile(r"^#{1,6}\s*[A-Z]{2,4}-\d+\b")
HEADING_RE = re.compile(r"^#{1,6} ")
CHECKED_BY_RE = re.compile(r"^Checked by:\s*(.+)$")
TEST_REF_RE = re.compile(r"(tests/[\w/]+\.py)(?:::([\w:]+))?")


def _ids(prefix: str, n: int) -> list[str]:
    return [f"{prefix}-{i:02d}" for i in range(1, n + 1)]


#: The renderer's clause list (the project's common brief; docs/spec/README.md).  Later issues add
#: FM/TRN/DAT/MET clauses; those are declared by their authors and not required here.
REQUIRED_IDS = (_ids("CNV", 11) + _ids("COV", 2) + _ids("PRJ", 8) + _ids("SH", 4)
                + _ids("RAS", 10) + _ids("PRF", 8) + _ids("API", 6) + _ids("HARD", 13))

#: Test files that "Checked by:" lines may name before they exist.  Keep this short: each entry is
#: a file another author is writing now; remove the entry when the file lands (a stale entry fails
#: ``test_pending_allow_list_is_not_stale``), and the list should end up empty.
PENDING_TEST_FILES: set[str] = set()

#: Macro definitions GitHub's math renderer does not keep across blocks (and we do not use).
FORBIDDEN_MACROS = ("\\newcommand", "\\renewcommand", "\\def\\", "\\DeclareMathOperator", "\\require")


def _read(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


def _without_code(lines: list[str]) -> list[str]:
    """Lines with fenced code blocks blanked and inline code spans removed."""
    out, fenced = [], False
    for line in lines:
        if line.lstrip().startswith("```"):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else re.sub(r"`[^`]*`", "", line))
    return out


def _clauses() -> list[tuple[str, Path, int]]:
    """(id, file, 0-based line) of every clause heading in docs/spec, in file order."""
    found = []
    for path in SPEC_FILES:
        for i, line in enumerate(_without_code(_read(path))):
            m = CLAUSE_RE.match(line)
            if m:
                found.append((m.group(1), path, i))
    return found


def _sections(path: Path) -> dict[str, list[str]]:
    """Clause id -> the lines of its section (up to the next heading of any level)."""
    lines = _without_code(_read(path))
    sections, current = {}, None
    for line in lines:
        m = CLAUSE_RE.match(line)
        if m:
            current = m.group(1)
            sections[current] = []
        elif HEADING_RE.match(line):
            current = None
        elif current is not None:
            sections[current].append(line)
    return sections


def _checked_by_refs(path: Path) -> list[tuple[int, str, str | None]]:
    """(1-based line, test file, test name or None) for each tests/ reference on a Checked-by line."""
    refs = []
    for i, line in enumerate(_read(path), start=1):
        m = CHECKED_BY_RE.match(line.strip())
        if m:
            for ref in TEST_REF_RE.finditer(m.group(1)):
                refs.append((i, ref.group(1), ref.group(2)))
    return refs


# ------------------------------------------------------------------------------------------------
# clause ids
# ------------------------------------------------------------------------------------------------

def test_spec_files_present():
    names = {p.name for p in SPEC_FILES}
    assert {"README.md", "conventions.md", "stages.md", "profiles.md", "hard_cases.md"} <= names


def test_readme_indexes_every_spec_file():
    readme = (SPEC_DIR / "README.md").read_text(encoding="utf-8")
    unlisted = [p.name for p in SPEC_FILES if p.name != "README.md" and f"]({p.name})" not in readme]
    assert not unlisted, f"docs/spec/README.md does not link these spec files: {unlisted}"


def test_clause_headings_well_formed():
    bad = []
    for path in SPEC_FILES:
        for i, line in enumerate(_without_code(_read(path)), start=1):
            if LOOSE_CLAUSE_RE.match(line) and not STRICT_CLAUSE_RE.match(line):
                bad.append(f"{path.name}:{i}: {line!r} (expected '#### ABC-12: Title')")
    assert not bad, "malformed clause headings:\n" + "\n".join(bad)


def test_clause_ids_unique():
    seen, dup = {}, []
    for cid, path, i in _clauses():
        if cid in seen:
            dup.append(f"{cid} at {path.name}:{i + 1} and {seen[cid]}")
        seen[cid] = f"{path.name}:{i + 1}"
    assert not dup, "clause ids declared twice:\n" + "\n".join(dup)


def test_required_clauses_declared():
    declared = {cid for cid, _, _ in _clauses()}
    missing = [cid for cid in REQUIRED_IDS if cid not in declared]
    assert not missing, f"clauses required by the renderer's clause list but not declared: {missing}"


def test_every_clause_has_checked_by():
    missing = []
    for path in SPEC_FILES:
        for cid, body in _sections(path).items():
            if not any(CHECKED_BY_RE.match(line.strip()) for line in body):
                missing.append(f"{cid} ({path.name})")
    assert not missing, f"clauses without a 'Checked by:' line: {missing}"


@pytest.mark.parametrize("prefix,width", [("CNV", 11), ("HARD", 13)])
def test_numbered_clauses_name_their_test(prefix, width):
    """CNV-07 is checked by a test_cnv07_* function, HARD-07 by test_hard07_* (the lead's names)."""
    sections = {}
    for path in SPEC_FILES:
        sections.update(_sections(path))
    wrong = []
    for cid in _ids(prefix, width):
        want = f"test_{prefix.lower()}{cid[-2:]}_"
        refs = [name or "" for line in sections.get(cid, []) if CHECKED_BY_RE.match(line.strip())
                for _, name in TEST_REF_RE.findall(line)]
        if not any(r.split("::")[-1].startswith(want) for r in refs):
            wrong.append(f"{cid}: no reference to a {want}* test (found {refs})")
    assert not wrong, "\n".join(wrong)


# ------------------------------------------------------------------------------------------------
# references to tests
# ------------------------------------------------------------------------------------------------

def test_checked_by_references_exist():
    problems = []
    for path in DOC_FILES:
        for line, file, name in _checked_by_refs(path):
            target = ROOT / file
            where = f"{path.relative_to(ROOT)}:{line}"
            if not target.is_file():
                if file not in PENDING_TEST_FILES:
                    problems.append(f"{where}: {file} does not exist")
                continue
            if name:
                func = name.split("::")[-1]
                if not re.search(rf"^\s*(async\s+)?def {re.escape(func)}\(", target.read_text(encoding="utf-8"),
                                 re.MULTILINE):
                    problems.append(f"{where}: {file} defines no function {func}")
    assert not problems, "\n".join(problems)


def test_pending_allow_list_is_not_stale():
    stale = sorted(f for f in PENDING_TEST_FILES if (ROOT / f).is_file())
    assert not stale, f"these files exist now; remove them from PENDING_TEST_FILES: {stale}"


def test_pending_references_reported():
    """Lists (as a skip reason, visible with ``pytest -rs``) the references still waiting for files."""
    pending = sorted({f for p in DOC_FILES for _, f, _ in _checked_by_refs(p)
                      if f in PENDING_TEST_FILES and not (ROOT / f).is_file()})
    if pending:
        pytest.skip(f"Checked-by references to test files not written yet: {pending}")


def test_derivation_pages_name_the_fd_tests():
    renderer = {"covariance.md", "projection.md", "sh.md", "compositing.md"}
    pages = [p for p in sorted(DERIV_DIR.glob("*.md")) if p.name in renderer]
    assert {p.name for p in pages} == renderer
    for page in pages:
        files = {f for _, f, _ in _checked_by_refs(page)}
        assert "tests/test_backward_fd.py" in files, f"{page.name}: no 'Checked by:' naming tests/test_backward_fd.py"


# ------------------------------------------------------------------------------------------------
# math that GitHub renders
# ------------------------------------------------------------------------------------------------

def _math_problems(path: Path) -> list[str]:
    text = "\n".join(_without_code(_read(path)))
    problems = []
    for macro in FORBIDDEN_MACROS:
        if macro in text:
            problems.append(f"custom macro {macro!r}")
    if text.count("$$") % 2:
        problems.append("unbalanced $$")
        return problems
    display = re.findall(r"\$\$(.*?)\$\$", text, flags=re.DOTALL)
    rest = re.sub(r"\$\$.*?\$\$", " ", text, flags=re.DOTALL)
    for n, para in enumerate(re.split(r"\n\s*\n", rest)):
        if para.count("$") % 2:
            problems.append(f"unbalanced $ in paragraph {n}: {para.strip()[:80]!r}")
    inline = re.findall(r"\$([^$]+)\$", rest)
    for m in inline:
        if m != m.strip():
            problems.append(f"inline math with leading/trailing space: ${m}$")
    for m in inline + display:
        if re.search(r"<[A-Za-z/!?]", m):   # would open an HTML tag before math rendering
            problems.append(f"'<' before a letter in math (use \\lt): {m.strip()[:60]!r}")
        if "\\{" in m or "\\}" in m:
            problems.append(f"\\{{ or \\}} in math (use \\lbrace, \\rbrace): {m.strip()[:60]!r}")
    return problems


@pytest.mark.parametrize("path", MATH_FILES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_math_renders_on_github(path):
    problems = _math_problems(path)
    assert not problems, f"{path.relative_to(ROOT)}:\n" + "\n".join(problems)
