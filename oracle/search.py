"""The search for the deviation set that brings the reference closest to a backend (DEV-02 2).

A set is scored by the *distance* that remains between the reference rendered with it and the
backend, probe by probe -- not by how many checks it makes pass: with ten differences at once no
single deviation makes anything pass, yet each removes its share of the error.

    distance(verdict)     summed over the failing outputs, log10(1 + excess): the excess is the
                          summed error / tolerance of the elements out of tolerance; 0 when the
                          probe agrees, an output's error halved counts 0.3 whatever its size
    s = DistanceSearch(ctx, probes, candidates)
    found = s.run(start)  stepwise: the best of adding a deviation, replacing the members it
                          conflicts with, or (when neither helps) adding a pair, while a move
                          lowers the summed distance by MARGIN; after each move, members whose
                          removal costs less than MARGIN are dropped (backward elimination)
    s.residual(found)     per probe: status and distance under the set

A probe's distance under a set is taken under the members that matter on that probe
(``relevant``: those whose reference fingerprint, alone, differs from the plain reference's
there), so judgements are shared between every set with the same relevant members.  A member
that shows only beside another is found when the result is judged as a whole (``refine``), and
the search goes on from there.
"""
from __future__ import annotations

import itertools

import numpy as np

from refgs.deviations import incompatible

from .compare import RATIO_LIMIT
from .explain import FIXED_SCENES, judge, outcome, reference_fingerprint

#: a move must lower the summed distance by this much (log10 units: one output's error
#: halved, net of every output it moves the other way)
MARGIN = 0.3
#: at most this many moves are made (a guard; the search stops long before)
MAX_MOVES = 60
#: when no single move helps, pairs are formed of this many candidates (those that move the
#: differing probes most): two conventions that only together undo a difference (quaternions
#: read x, y, z, w *and* the rotation transposed) show no gain one at a time
MAX_PAIRED = 10
#: the stepwise search is repeated at most this many times after ``refine`` (a guard)
MAX_REFINE = 4


def distance(verdict) -> float:
    """The probe's distance from the reference: over its failing comparisons (one per output),
    log10(1 + excess), the excess being the summed error / tolerance of the elements out of
    tolerance (oracle/compare.py); a comparison that failed without one (an aggregate gradient
    limit, an invariant, a missing output) counts log10(1 + its ratio), capped at
    compare.RATIO_LIMIT.  0 when the probe agrees."""
    total = 0.0
    for c in verdict.comparisons:
        if c.ok:
            continue
        ex = float(getattr(c, "excess", 0.0) or 0.0)
        total += float(np.log10(1.0 + (ex if ex > 0 else min(float(c.ratio), RATIO_LIMIT))))
    return total


class DistanceSearch:
    """Stepwise selection over deviation sets by summed distance (module docstring).

    ``probes``: oracle.explain.Probe objects (stage probes, witnesses, check scenes); their
    distance without deviations is taken first, and a probe that cannot be judged without
    deviations (too many near-ties) is left out."""

    def __init__(self, ctx, probes, candidates, margin: float = MARGIN):
        self.ctx, self.candidates, self.margin = ctx, list(candidates), margin
        self.cache: dict = {}
        self.trace: list = []
        self.evaluations = 0
        self._rel: dict = {}
        self._extra: dict = {}
        self.base: dict = {}
        self.probes: list = []
        self.add(probes)

    def add(self, probes) -> None:
        """Take more probes (each judged without deviations first; inconclusive ones left out)."""
        for p in probes:
            i = len(self.probes)
            self.probes.append(p)
            st, d = self._judge(i, frozenset())
            if st == "inconclusive":
                self.probes.pop()
                self.cache.pop((i, frozenset()))
                continue
            self.base[i] = d

    # ---- one probe ------------------------------------------------------------------------------

    def relevant(self, i: int, s: frozenset | None = None) -> frozenset:
        """The members of ``s`` that matter on probe ``i`` (module docstring); with ``s`` None,
        the candidates that change its reference alone."""
        if i not in self._rel:
            p = self.probes[i]
            plain = reference_fingerprint(p, frozenset())
            self._rel[i] = frozenset(d for d in self.candidates
                                     if reference_fingerprint(p, frozenset({d})) != plain)
        if s is None:
            return self._rel[i]
        return frozenset(s) & (self._rel[i] | self._extra.get(i, frozenset()))

    def refine(self, s: frozenset) -> bool:
        """Compare, by reference fingerprint, each probe under the whole of ``s`` -- and each
        small-scene probe under every single move from ``s`` whose new member shows on it alone
        -- with the relevant members only;
        where they differ, the members that change the probe's reference beside those become
        relevant there too (a deviation that shows only beside another: a pixel offset on a
        Gaussian that only the missing 1/255 skip lets through, gsplat's tile rule under the
        3-sigma radius).  True when any probe gained one."""
        grown = False
        sets = [(s, range(len(self.probes)))]
        small = [i for i, p in enumerate(self.probes) if p.source in FIXED_SCENES]
        sets += [(t, [i for i in small if self.relevant(i) & (t - s)]) for _, t in self.moves(s)]
        for t, idx in sets:
            for i in idx:
                key = self.relevant(i, t)
                p = self.probes[i]
                if key == t or reference_fingerprint(p, t) == reference_fingerprint(p, key):
                    continue
                here = reference_fingerprint(p, key)
                more = frozenset(m for m in t - key if reference_fingerprint(p, key | {m}) != here)
                self._extra[i] = self._extra.get(i, frozenset()) | (more or (t - key))
                grown = True
        return grown

    def _judge(self, i: int, key: frozenset) -> tuple[str, float]:
        if (i, key) not in self.cache:
            self.evaluations += 1
            v = judge(self.ctx, self.probes[i], key)
            st = outcome(v)[0]
            self.cache[(i, key)] = (st, distance(v) if st == "differ" else 0.0)
        return self.cache[(i, key)]

    def judged(self, i: int, s: frozenset) -> tuple[str, float]:
        """(status, distance) of probe ``i`` under ``s``; a probe the set makes inconclusive
        keeps its distance without deviations (no evidence either way)."""
        st, d = self._judge(i, self.relevant(i, frozenset(s)))
        return (st, self.base[i]) if st == "inconclusive" else (st, d)

    # ---- sets -----------------------------------------------------------------------------------

    def total(self, s: frozenset, only=None) -> float:
        idx = range(len(self.probes)) if only is None else only
        return float(sum(self.judged(i, s)[1] for i in idx))

    def _touching(self, s: frozenset, t: frozenset) -> list:
        return [i for i in range(len(self.probes)) if self.relevant(i, s) != self.relevant(i, t)]

    def gain(self, s: frozenset, t: frozenset) -> float:
        """Distance of ``s`` minus distance of ``t`` over the probes the change touches."""
        idx = self._touching(s, t)
        return self.total(s, idx) - self.total(t, idx)

    @staticmethod
    def with_member(s: frozenset, d: str) -> frozenset | None:
        """``s`` with ``d`` added and the members it conflicts with dropped, or None when the
        result is still incompatible."""
        t = frozenset(m for m in s if incompatible({m, d}) is None) | {d}
        return t if incompatible(t) is None else None

    def moves(self, s: frozenset) -> list[tuple[str, frozenset]]:
        """Additions of a compatible candidate, and replacements of the members a candidate
        conflicts with (dilation 0.1 for no dilation, ...)."""
        out = []
        for d in self.candidates:
            t = None if d in s else self.with_member(s, d)
            if t is not None:
                out.append(("add" if s <= t else "swap", t))
        return out

    def pair_moves(self, s: frozenset) -> list[tuple[str, frozenset]]:
        """Two moves at once, among the MAX_PAIRED candidates whose single move changes the
        probes still differing under ``s`` for the better most (their distance lowered, less
        what it raised there; then how many they touch): two conventions that only together
        undo a difference (quaternions read x, y, z, w *and* the rotation transposed; gsplat's
        radius rule *and* its tile rule) gain nothing one at a time."""
        open_ = [i for i in range(len(self.probes)) if self.judged(i, s)[1] > 0]
        ranked = []
        for _, t in self.moves(s):
            idx = [i for i in open_ if self.relevant(i, s) != self.relevant(i, t)]
            if idx:
                change = sum(self.judged(i, s)[1] - self.judged(i, t)[1] for i in idx)
                ranked.append((-change, -len(idx), sorted(t - s)[0]))
        top = [d for *_, d in sorted(ranked)[:MAX_PAIRED]]
        out = []
        for a, b in itertools.combinations(top, 2):
            t = self.with_member(s, a)
            t = None if t is None else self.with_member(t, b)
            if t is not None and a in t and t != s:
                out.append(("pair", t))
        return out

    def _log(self, move: str, before: frozenset, after: frozenset, gain: float) -> None:
        self.trace.append({"move": move, "added": sorted(after - before), "dropped": sorted(before - after),
                           "gain": round(gain, 3), "distance": round(self.total(after), 3)})

    def eliminate(self, s: frozenset, keep=frozenset()) -> frozenset:
        """Drop, one at a time, the member whose removal costs least, while that is < MARGIN."""
        while s - keep:
            cost, m = min((-self.gain(s, s - {m}), m) for m in sorted(s - keep))
            if cost >= self.margin:
                break
            self._log("drop", s, s - {m}, -cost)
            s = s - {m}
        return s

    def _best(self, s: frozenset, moves):
        """(gain, kind, set) of the move of largest gain, when that gain is at least MARGIN."""
        best = None
        for kind, t in moves:
            g = self.gain(s, t)
            if g >= self.margin and (best is None or (g, sorted(t)) > (best[0], sorted(best[2]))):
                best = (g, kind, t)
        return best

    def run(self, start=frozenset()) -> frozenset:
        """Stepwise selection from ``start`` (module docstring), repeated from its result while
        judging the result as a whole shows a member that matters beside another (``refine``)."""
        s = frozenset(start)
        for _ in range(MAX_REFINE):
            s = self._stepwise(s)
            if not self.refine(s):
                break
        return s

    def _stepwise(self, start: frozenset) -> frozenset:
        s = self.eliminate(frozenset(start))
        for _ in range(MAX_MOVES):
            best = self._best(s, self.moves(s)) or self._best(s, self.pair_moves(s))
            if best is None:
                break
            g, kind, t = best
            self._log(kind, s, t, g)
            s = self.eliminate(t, keep=t - s)
        return s

    def residual(self, s: frozenset) -> list[dict]:
        """Per probe: its source and name, status and distance without deviations and under
        ``s`` (``explained``: it differed and agrees under the set)."""
        out = []
        for i, p in enumerate(self.probes):
            st0, d0 = self.judged(i, frozenset())
            st, d = self.judged(i, s)
            out.append({"source": p.source, "name": p.name, "before": st0, "distance_before": round(d0, 3),
                        "status": st, "distance": round(d, 3),
                        "explained": st0 == "differ" and st == "agree",
                        "broken": st0 == "agree" and st == "differ"})
        return out


__all__ = ["DistanceSearch", "MARGIN", "distance"]
