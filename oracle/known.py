"""Known differences: failures a backend's author declares, reported as ``known`` (ORC-02).

A backend may carry ``known_differences`` (oracle/protocol.py) and ``python -m oracle check``
may be given a TOML file (``--known-differences FILE``) of the same entries::

    [[difference]]
    check = "forward_coverage"
    clause = "PRF-04"                      # optional: only this clause's failures
    reason = "we use the 3-sigma radius of the original 3DGS in the gsplat profile"
    link = "https://github.com/me/renderer/issues/12"   # optional

A failing check whose every blamed clause (oracle/blame.py) is covered by an entry for that
check (an entry without ``clause`` covers all of them) is reported ``known`` with the reasons;
tolerances stay as they are.  A check that an entry names but that passes is a failure: the
difference no longer happens, and the entry must go.  Crashes, timeouts and errors are never
known: they are not differences of the rendering model.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from .protocol import KNOWN_KEYS


def load_file(path) -> tuple[dict, ...]:
    """The ``[[difference]]`` entries of a TOML file; ValueError naming the file and the entry."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"--known-differences {path}: not a readable TOML file ({exc})") from None
    entries = data.get("difference", [])
    if not isinstance(entries, list) or set(data) - {"difference"}:
        raise ValueError(f"--known-differences {path}: expected only [[difference]] tables, "
                         f"got keys {sorted(data)}")
    out = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not e.get("check") or not e.get("reason") or set(e) - set(KNOWN_KEYS):
            raise ValueError(f"--known-differences {path}: difference {i + 1} must have 'check' and "
                             f"'reason' (and optionally 'clause', 'link'), got {e!r}")
        out.append({k: str(e[k]) for k in KNOWN_KEYS if k in e})
    return tuple(out)


def validate(entries, checks) -> None:
    """ValueError naming the entry when it names no check, or a clause its check does not cite."""
    by_name = {c.name: c for c in checks}
    for e in entries:
        check = by_name.get(e["check"])
        if check is None:
            raise ValueError(f"known difference {e!r}: no check is named {e['check']!r} "
                             f"(see `python -m oracle list-clauses`)")
        if e.get("clause") and e["clause"] not in check.clauses:
            raise ValueError(f"known difference {e!r}: {e['check']} cites {', '.join(check.clauses)}, "
                             f"not {e['clause']}")


def apply(result, entries) -> None:
    """Turn ``result`` (a runner.CheckResult) into ``known``, or into a failure when a declared
    difference no longer happens (module docstring)."""
    mine = [e for e in entries if e["check"] == result.check.name]
    if not mine:
        return
    result.known = mine
    blamed = set((result.blame or {}).get("blamed", {}))
    covered = None if any(not e.get("clause") for e in mine) else {e["clause"] for e in mine}
    if result.status == "fail":
        if covered is None or blamed <= covered:
            result.status = "known"
            for cid in blamed:
                result.clause_status[cid] = "known"
        return
    if result.status == "pass":
        reasons = "; ".join(e["reason"] for e in mine)
        result.status = "fail"
        result.failure = {"message": f"declared known difference no longer happens ({reasons}): the "
                                     f"check passed, so remove it from known_differences",
                          "scene": None}
        for cid in (covered or {result.check.clauses[0]}):
            result.clause_status[cid] = "fail"
