"""Which clauses a failure is evidence against, and the mechanism a shrink must keep (ORC-12).

A check cites several clauses (oracle/checks.py); a failure of one example is evidence against
some of them only.  A clause is blamed by a failing comparison when

1. the comparison's *evidence* -- ``forward`` (render outputs), ``backward`` (gradients),
   ``stage`` (a stage function), ``errors`` (API-03's expected ValueError) -- is one the clause
   can be shown by (:data:`EVIDENCE`: COV-02, PRJ-07, SH-04, RAS-07, RAS-08, RAS-10, PRF-07 and
   API-05 only through gradients; the forward clauses through render outputs or stage functions);
2. the failing case *exercises* the clause (:func:`exercised`: the background and opacity-scale
   part of API-02 needs a background or an opacity_scale, the SH clauses a degree >= 1 or more
   coefficients than degree 0 reads, PRF-02 a clamped Gaussian, PRJ-08 antialiasing, ...);
3. and the problem is of the clause's sort: CNV-11 (dtypes) is blamed only by a wrong dtype, and
   a wrong dtype only blames CNV-11 (or, where the check does not cite it, the output containers
   API-04 / API-05).

When no cited clause qualifies only because of the evidence kind (a render that raises in a
gradient check), the check's first clause (the one its cases were designed for) takes the
failure.  When rule 2 or 3 excludes every clause (a value failure in ``forward_dtype`` is no
evidence against CNV-11; a failure that stays once the shrinker removed the opacity_scale is none
against API-02) the failure is *unattributed*: the check still fails, and the report says that
no clause it cites is shown to be violated.  Every other cited clause is *spared*, with the
reason.  A crash or a timeout is evidence against no clause in particular: every cited clause
takes it.

The *mechanism* of a failure (:func:`mechanism`) is what the shrinker (oracle/shrink.py) must keep
while it makes a failing case smaller: which outputs failed and how (an exception by its type and
the line it came from), and each Gaussian's depth-culling, frustum-clamp and visibility flags.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import refgs
from refgs.render import resolve_profile

#: problem kinds of oracle/compare.py that say the output is malformed rather than wrong
STRUCTURAL = ("missing", "shape", "malformed", "nonfinite")
_FWD = frozenset({"forward", "stage"})
_BWD = frozenset({"backward"})
_ALL = frozenset({"forward", "stage", "backward"})
#: clause -> the evidence that can show it (default: forward outputs and stage functions)
EVIDENCE: dict[str, frozenset] = {
    **{c: _BWD for c in ("COV-02", "PRJ-07", "SH-04", "RAS-07", "RAS-08", "RAS-10", "PRF-07", "API-05")},
    **{c: _ALL for c in ("CNV-10", "CNV-11", "PRJ-08", "API-02", "SH-01")},
    "CNV-05": _ALL | {"errors"}, "API-03": frozenset({"errors"}), "RAS-09": frozenset({"reference"}),
}


def evidence_of(cid: str) -> frozenset:
    """The evidence kinds that can show clause ``cid`` (a HARD clause: all of them)."""
    if cid.startswith("HARD-"):
        return _ALL
    return EVIDENCE.get(cid, _FWD)


@dataclass(frozen=True)
class Facts:
    """What a case contains, from the float64 reference (per Gaussian: in front of the near
    plane, frustum-clamped in x / y, visible, some colour channel clamped at 0)."""

    n: int
    in_depth: np.ndarray
    clamped_x: np.ndarray
    clamped_y: np.ndarray
    visible: np.ndarray
    near: np.ndarray
    colour_clamped: np.ndarray
    over_cap: np.ndarray
    sh_degree: int
    sh_coeffs: int
    background: bool
    opacity_scale: bool
    antialiased: bool

    def flags(self) -> np.ndarray:
        """(N, 4) bool: in depth, clamped in x, clamped in y, visible (the shrink invariant)."""
        return np.stack([self.in_depth, self.clamped_x, self.clamped_y, self.visible], -1) \
            if self.n else np.zeros((0, 4), bool)


def facts(case, ref: refgs.RenderOutput | None = None) -> Facts:
    """The :class:`Facts` of ``case`` (``ref``: its reference render, computed when None)."""
    ref = refgs.render(case.gaussians, case.camera, case.config) if ref is None else ref
    g, cfg = case.gaussians, case.config
    profile = resolve_profile(cfg)
    n = len(g)
    deg = cfg.active_sh_degree(g.sh.shape[1])
    if n:
        proj = ref.cache["proj"]
        tz = np.asarray(proj["depths"], np.float64)
        in_depth = (tz > profile.near) if profile.near_inclusive else (tz >= profile.near)
        in_depth &= tz <= profile.far
        front = in_depth
        cx, cy = proj["clamped_x"] & front, proj["clamped_y"] & front
        d = np.asarray(g.means, np.float64) - case.camera.center
        dirs = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
        basis, _ = refgs.sh_basis(deg, dirs)
        rgb = np.einsum("nk,nkc->nc", basis, g.sh[:, :(deg + 1) ** 2, :]) + refgs.constants.SH_COLOR_OFFSET
        colour = np.any(rgb < 0, axis=-1) & ref.visible
        over_cap = (np.asarray(ref.opacities, np.float64) > profile.alpha_max) & ref.visible
        near = tz <= 3.0 * profile.near
    else:
        in_depth = cx = cy = colour = over_cap = near = np.zeros(0, bool)
    return Facts(n=n, in_depth=in_depth, clamped_x=cx, clamped_y=cy, visible=np.asarray(ref.visible, bool),
                 near=near, colour_clamped=colour, over_cap=over_cap, sh_degree=int(deg),
                 sh_coeffs=int(g.sh.shape[1]), background=bool(np.any(np.asarray(cfg.background) != 0)),
                 opacity_scale=cfg.opacity_scale is not None, antialiased=bool(cfg.antialiased))


def exercised(cid: str, f: Facts, evidence: str) -> str | None:
    """None when case facts ``f`` exercise clause ``cid`` for this ``evidence``, else why not."""
    if cid == "API-02" and not (f.background or f.opacity_scale or f.antialiased):
        return "the case has no background, no opacity_scale and no antialiasing"
    if cid == "SH-01" and f.sh_coeffs <= 1 and f.sh_degree == 0:
        return "the case has SH degree 0 and one coefficient"
    if cid in ("SH-03", "CNV-09") and f.sh_degree == 0:
        return "the case has SH degree 0 (no view dependence)"
    if cid == "CNV-10" and evidence == "backward" and not f.colour_clamped.any():
        return "no visible Gaussian has a colour channel clamped at 0"
    if cid in ("PRF-02", "HARD-01") and not (f.clamped_x | f.clamped_y).any():
        return "no Gaussian is clamped by the frustum"
    if cid in ("PRJ-02", "PRF-01") and not f.near.any():
        return "no Gaussian is near the near plane"
    if cid == "PRJ-08" and not f.antialiased:
        return "the case is not antialiased"
    if cid in ("RAS-10", "PRF-07", "PRF-05") and not f.over_cap.any():
        return "no visible Gaussian's opacity reaches the alpha cap"
    if cid == "RAS-02" and int(f.visible.sum()) < 2:
        return "fewer than two visible Gaussians: nothing to sort"
    if cid == "API-06" and f.visible.any():
        return "some Gaussian is visible: neither empty nor all culled"
    return None


def _sort_ok(cid: str, comparison, cited) -> str | None:
    """None when a comparison of this problem sort may blame ``cid`` (rule 3), else why not."""
    kind = getattr(comparison, "kind", "value")
    if cid == "CNV-11" and kind != "dtype":
        return "only a wrong dtype fails CNV-11, and every output had the declared dtype"
    if kind == "dtype" and cid != "CNV-11" and ("CNV-11" in cited or cid not in ("API-04", "API-05")):
        return "a wrong dtype is evidence against CNV-11 (or the output containers) only"
    return None


def blame(clauses, verdict, f: Facts | None) -> tuple[dict, dict]:
    """``(blamed, spared)``: clause -> why, for a failing ``verdict`` of a check citing
    ``clauses`` (designed-for first) on a case with facts ``f`` (None: no case, e.g. no example
    could be judged; every clause is blamed).  ``blamed`` is empty when the failure is
    unattributed (module docstring)."""
    bad = [c for c in verdict.comparisons if not c.ok] if verdict is not None else []
    if f is None or not bad:
        return {cid: "the check failed without a case to attribute" for cid in clauses}, {}
    blamed, spared, excluded = {}, {}, set()
    for c in bad:
        ev = getattr(c, "evidence", "") or "forward"
        for cid in clauses:
            if ev not in evidence_of(cid):
                spared.setdefault(cid, f"{cid} is shown by {'/'.join(sorted(evidence_of(cid)))} "
                                       f"evidence; the failure is {ev} evidence")
                continue
            why = _sort_ok(cid, c, clauses) or exercised(cid, f, ev)
            if why is not None:
                excluded.add(cid)
                spared.setdefault(cid, why)
                continue
            blamed.setdefault(cid, f"{c.output} ({ev} evidence, {getattr(c, 'kind', 'value')})")
    if not blamed and clauses[0] not in excluded:
        blamed[clauses[0]] = (f"the designed-for clause takes the failure: no cited clause is shown "
                              f"by {'/'.join(sorted({getattr(c, 'evidence', '') or 'forward' for c in bad}))} "
                              f"evidence on this case")
    return blamed, {k: v for k, v in spared.items() if k not in blamed}


def failure_keys(verdict) -> set:
    """What failed and how: (output, problem kind[, exception type and line])."""
    keys = set()
    for c in verdict.comparisons:
        if not c.ok:
            keys.add((c.output, getattr(c, "kind", "value"), getattr(c, "origin", "")))
    return keys


def mechanism(verdict, f: Facts) -> dict:
    """The mechanism of a failure (module docstring), for oracle/shrink.py."""
    return {"keys": failure_keys(verdict), "flags": f.flags()}
