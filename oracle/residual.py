"""What is left once the named deviations are on: where the outputs first part (DEV-03).

The stage probes (oracle/stage_probes.py) form a ladder; under the deviation set found, a probe
that still differs while the probe it extends agrees is where the outputs *first part*: its new
ingredient -- a rotation, an off-axis mean, a second Gaussian behind the first -- is what the
backend computes in a way no named deviation describes.  A backend's stage functions, when it
has them, are direct evidence: a stage check that still differs names its stage.

    loc = localise(stage_rows, check_rows)     # rows of DistanceSearch.residual, stage probes'
                                               # fields added (stage_rows) / checks' (check_rows)
    loc["first"]       the earliest stage (COV, PRJ, SH, RAS) where the outputs part, or None;
                       the first-parting probes are placed at the fewest stages that explain
                       them (``parting_stages``)
    loc["by_stage"]    stage -> [{probe, clauses, sentence, ...}], pipeline order
    loc["unlocalised"] checks still differing that no stage probe or stage function places
    draw_probe(ctx, probe, deviations, path)   the probe's picture: expected, got, |difference|
"""
from __future__ import annotations

import itertools
from pathlib import Path

from .explain import judge
from .stage_probes import STAGE_NAMES, STAGE_ORDER, STAGE_PROBES

#: the catalogue's stage of each stage function (oracle/checks.py stage_<name>)
STAGE_OF_FUNCTION = {"covariance": "COV", "projection": "PRJ", "sh": "SH", "composite": "RAS"}


def _stage_rank(stage: str) -> int:
    return STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER)


def first_parting(stage_rows: list[dict]) -> list[dict]:
    """The stage-probe rows that differ while their base agrees (or that are the root)."""
    differing = {r["name"] for r in stage_rows if r["status"] == "differ"}
    return [r for r in stage_rows if r["status"] == "differ"
            and STAGE_PROBES[r["name"]].base not in differing]


def parting_stages(rows: list[dict]) -> dict:
    """Where the fewest defects would sit to make every one of ``rows`` (the first-parting stage
    probes) differ: the smallest set H of stages such that each row could show a defect of some
    stage in H (StageProbe.could_be) and each stage in H is the designed-for stage of a row it
    covers; among sets of one size, the one that places most rows at their own stage, then the
    earliest.  Returns {probe name: its stage in H}, in ladder order."""
    probes = [STAGE_PROBES[r["name"]] for r in rows]
    best = None
    for k in range(1, len(STAGE_ORDER) + 1):
        for h in itertools.combinations(STAGE_ORDER, k):
            place = {}
            for p in probes:
                fits = [st for st in h if st in p.could_be]
                if not fits:
                    break
                place[p.name] = p.stage if p.stage in fits else fits[0]
            else:
                if all(any(p.stage == st and place[p.name] == st for p in probes) for st in h):
                    own = sum(place[p.name] == p.stage for p in probes)
                    rank = (-own, [_stage_rank(st) for st in h])
                    if best is None or rank < best[0]:
                        best = (rank, place)
        if best is not None:
            return best[1]
    return {p.name: p.stage for p in probes}


def sentence(row: dict, stage: str | None = None) -> str:
    """One sentence for a stage probe that still differs, placed at ``stage`` (default: the
    stage it is designed for)."""
    p = STAGE_PROBES[row["name"]]
    stage = stage or p.stage
    base = f"; its base probe `{p.base}` agrees" if p.base else ""
    what = p.claim if stage == p.stage else (
        f"{p.adds} differs, as a defect of this stage would make it (the probe is designed for "
        f"the {STAGE_NAMES[p.stage]}, whose own probes agree)")
    return (f"{STAGE_NAMES[stage]}: {what}, in a way the catalogue does not name "
            f"(stage probe `{p.name}`, {', '.join(p.clauses)}{base}; distance {row['distance']:.2f})")


def localise(stage_rows: list[dict], check_rows: list[dict]) -> dict:
    """Where the outputs first part under the set found (module docstring).  ``stage_rows``:
    residual rows of the stage probes; ``check_rows``: residual rows of check scenes, each with
    ``check`` and ``kind`` (a Check's), still differing or not."""
    by_stage: dict = {}
    parting = first_parting(stage_rows)
    place = parting_stages(parting)
    for r in parting:
        p = STAGE_PROBES[r["name"]]
        by_stage.setdefault(place[p.name], []).append(
            {"probe": p.name, "clauses": list(p.clauses), "evidence": "stage probe",
             "sentence": sentence(r, place[p.name]), "distance": r["distance"]})
    left = [r for r in check_rows if r["status"] == "differ"]
    for r in left:
        fn = r["check"][len("stage_"):] if r["kind"] == "stage" else None
        if fn in STAGE_OF_FUNCTION:
            st = STAGE_OF_FUNCTION[fn]
            entry = {"probe": r["check"], "clauses": [], "evidence": "stage function",
                     "sentence": f"{STAGE_NAMES[st]}: the backend's stage function `{fn}` differs "
                                 f"from refgs' in a way the catalogue does not name (check "
                                 f"{r['check']}; distance {r['distance']:.2f})",
                     "distance": r["distance"]}
            if all(e["probe"] != entry["probe"] for e in by_stage.get(st, [])):
                by_stage.setdefault(st, []).append(entry)
    stages = sorted(by_stage, key=_stage_rank)
    first = stages[0] if stages else None
    unlocalised = sorted({r["check"] for r in left} - {e["probe"] for v in by_stage.values() for e in v})
    return {"first": first,
            "stages": stages,
            "by_stage": {s: by_stage[s] for s in stages},
            "unlocalised": [] if stages else unlocalised,
            "also_differing": unlocalised if stages else []}


def summary(loc: dict) -> str:
    """One line: where the outputs first part, or that nothing is left."""
    if loc["first"] is None:
        if loc["unlocalised"]:
            return (f"left unexplained: {', '.join(loc['unlocalised'])}; no stage probe isolates "
                    f"the difference (every stage probe agrees under the set)")
        return "nothing is left: every probe agrees under the set"
    others = [s for s in loc["stages"] if s != loc["first"]]
    more = f"; also at {', '.join(STAGE_NAMES[s] for s in others)}" if others else ""
    return f"outputs first part at the {STAGE_NAMES[loc['first']]}{more}"


def draw_probe(ctx, probe, deviations, path: Path, note: str = "") -> Path | None:
    """The probe's picture under ``deviations``: the reference with them (expected), the backend
    (got) and |got - expected|, image and alpha (oracle/pictures.py); None without a render."""
    from .pictures import image_figure

    ctx.capture = {}
    try:
        judge(ctx, probe, frozenset(deviations))
        fwd = ctx.capture.get("forward", {})
    finally:
        ctx.capture = None
    if "ref" not in fwd:
        return None
    return image_figure(fwd["ref"], fwd.get("got"), path, note)


__all__ = ["STAGE_OF_FUNCTION", "draw_probe", "first_parting", "localise", "sentence", "summary"]
