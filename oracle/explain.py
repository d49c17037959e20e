"""Judging a backend against the reference with named deviations on (docs/spec/deviations.md,
DEV-02): the layer under the diagnosis (oracle/diagnose.py) and the shrinker's deviation
signature (oracle/shrink.py, ORC-06).

    ctx = plain_context(info, timeout=None)      # the backend as the diagnosis calls it
    judge(ctx, Probe(...), deviations)           # -> Verdict against the deviated reference
    explains(deviations, case, backend_output=None, *, backend=None, check=None) -> bool
    sig = Signature(info, check, found)          # a failure's deviation signature

The backend may be in this process or behind an isolated worker (oracle/isolation.py, its
``BackendInfo.session``): a worker that dies or runs out of time during a call makes that call
raise :class:`BackendLost`, which the evaluators report as the backend's failure on that scene,
and the next call starts a fresh worker.  The diagnosis never calls the backend twice with the
same input (outputs are memoised), and never passes it the deviations: they belong to the
reference.
"""
from __future__ import annotations

import dataclasses
import hashlib
import itertools
from dataclasses import dataclass

import numpy as np

import refgs
from refgs.deviations import DEVIATIONS, incompatible

from . import evaluate as ev
from .checks import Check
from .compare import RATIO_LIMIT, problem
from .evaluate import Context, Verdict
from .isolation import OutputReleased, WorkerLost
from .protocol import BackendInfo, Case, describe_backend, load_backend

#: a check's invariant (a property of the reference model, not a comparison with it) is waived
#: only under the deviations that change that property by definition
INVARIANT_WAIVERS = {"final_T": {"blend_at_cutoff", "stop_off"}, "background": {"no_background"}}
#: a worst error/tolerance ratio above this counts as this (structural failures are infinite)
RATIO_CAP = RATIO_LIMIT
#: a signature is searched among subsets of the found set up to this size, then the whole set
SIGNATURE_MAX_SUBSET = 2


class BackendLost(RuntimeError):
    """The backend's worker died or ran out of time during one call (the message says which)."""


def _digest(*values) -> str:
    """A digest of the inputs of one stage call: arrays, cameras, configs (without deviations),
    plain numbers."""
    h = hashlib.sha1()
    for v in values:
        if isinstance(v, refgs.Camera):
            v = (v.world_to_camera, v.K, v.width, v.height)
        elif isinstance(v, refgs.RenderConfig):
            v = (str(v.profile), v.sh_degree, tuple(v.background), bool(v.antialiased), v.opacity_scale)
        _digest_into(h, v)
    return h.hexdigest()


def _digest_into(h, v) -> None:
    if isinstance(v, (tuple, list)):
        h.update(b"(")
        for x in v:
            _digest_into(h, x)
        h.update(b")")
    elif v is None or isinstance(v, (str, bool, int, float, np.integer, np.floating)):
        h.update(repr(v).encode())
    else:
        a = np.ascontiguousarray(v)
        h.update(f"{a.dtype}{a.shape}".encode() + a.tobytes())


class PlainBackend:
    """The backend as the diagnosis calls it: a config's deviations belong to the reference, so
    they are stripped before the backend sees the config; outputs are memoised per input (an
    exception is memoised too and re-raised to every caller, as the backend would raise it).

    ``info``: the BackendInfo (in this process, or a worker's proxy with its ``session``);
    ``timeout``: seconds of backend time per call (None: no limit; isolated backends only)."""

    def __init__(self, info: BackendInfo, timeout: float | None = None):
        self._obj, self._session, self._timeout = info.obj, info.session, timeout
        self._memo: dict = {}
        self._inputs: dict = {}                  # id(render output) -> its (gaussians, camera, config)
        self.stages = {name: self._stage(name, fn) for name, fn in info.stages.items()}

    def _call(self, key, pins, fn):
        if key not in self._memo:
            try:
                if self._session is not None:
                    self._session.begin_check(self._timeout)
                self._memo[key] = ((True, fn()), pins)        # pins keep the ids in the key alive
            except WorkerLost as lost:
                self._memo[key] = ((False, BackendLost(f"{lost.kind}: {lost.reason}")), pins)
            except Exception as exc:
                self._memo[key] = ((False, exc), pins)
        (ok, val), _ = self._memo[key]
        if not ok:
            raise val
        return val

    @staticmethod
    def _key(gaussians, camera, config) -> tuple:
        return ("render", id(gaussians), id(camera), str(config.profile), config.sh_degree,
                tuple(config.background), bool(config.antialiased), id(config.opacity_scale))

    def remember(self, scene: Case, output) -> None:
        """Use ``output`` as the backend's render output for ``scene``."""
        self._memo[self._key(scene.gaussians, scene.camera, scene.config)] = ((True, output), scene)

    def render(self, gaussians, camera, config):
        plain = dataclasses.replace(config, deviations=frozenset())

        def run():
            out = self._obj.render(gaussians, camera, plain)
            self._inputs[id(out)] = (gaussians, camera, plain)
            return out

        return self._call(self._key(gaussians, camera, config), (gaussians, camera, config), run)

    def render_backward(self, out, v_image, **cotangents):
        h = hashlib.sha1(np.ascontiguousarray(v_image).tobytes())
        for k in sorted(cotangents):
            h.update(k.encode() + np.ascontiguousarray(cotangents[k]).tobytes())

        def run():
            try:
                return self._obj.render_backward(out, v_image, **cotangents)
            except OutputReleased:                 # the worker no longer holds it: render again
                fresh = self._obj.render(*self._inputs[id(out)])
                return self._obj.render_backward(fresh, v_image, **cotangents)

        return self._call(("backward", id(out), h.hexdigest()), out, run)

    def _stage(self, name: str, fn):
        def call(*args):
            plain = [dataclasses.replace(a, deviations=frozenset())
                     if isinstance(a, refgs.RenderConfig) else a for a in args]
            return self._call(("stage", name, _digest(*plain)), None, lambda: fn(*plain))
        return call


def backend_info(backend) -> BackendInfo:
    """``backend`` (a ``module:object`` spec or registry name, a BackendInfo, or a backend
    object) as a BackendInfo."""
    if isinstance(backend, BackendInfo):
        return backend
    if isinstance(backend, str):
        return load_backend(backend)
    return describe_backend(backend, getattr(backend, "name", "") or type(backend).__name__)


def plain_context(backend, timeout: float | None = None) -> Context:
    """A Context whose backend (render, render_backward and stage functions) ignores
    ``RenderConfig.deviations`` and memoises its outputs (:class:`PlainBackend`)."""
    info = backend_info(backend)
    plain = PlainBackend(info, timeout)
    return Context(dataclasses.replace(info, obj=plain, stages=plain.stages))


def with_deviations(scene: Case, deviations) -> Case:
    """``scene`` whose reference renders with ``deviations`` on (the same Gaussians and camera)."""
    cfg = dataclasses.replace(scene.config, deviations=frozenset(deviations))
    return Case(scene.gaussians, scene.camera, cfg, scene.seed, scene.label)


@dataclass(eq=False)
class Probe:
    """One scene the search judges: from a check (``check`` set) or a deviation's witness."""

    source: str                      # "check", "shrunk", "run", "witness", "shrink"
    name: str                        # the check's or the deviation's name
    scene: Case                      # rounded to the backend's dtype
    check: Check | None = None
    backward: bool = False           # witnesses: judged through render_backward
    rounding: str = "float64"        # the dtype the scene was rounded to


def judge(ctx: Context, probe: Probe, deviations) -> Verdict:
    """The backend against the reference under ``deviations`` on the probe's scene: the check's
    own evaluation (its invariants waived only under the deviations of INVARIANT_WAIVERS), or for
    a witness the render outputs (forward) or gradients for image, alpha and depth cotangents."""
    scene = with_deviations(probe.scene, deviations)
    try:
        if probe.check is not None:
            v = probe.check.evaluate(ctx, scene)
        elif probe.backward:
            v = ev.backward(ctx, scene, kinds=("image", "alpha", "depth"))
        else:
            v = ev.forward(ctx, scene)
    except Exception as exc:          # the reference under this set cannot render the scene
        return Verdict([problem("reference", f"the reference with {sorted(deviations)} raised "
                                             f"{type(exc).__name__}: {exc}")])
    waived = {out for out, devs in INVARIANT_WAIVERS.items() if devs & set(deviations)}
    v.comparisons = [c for c in v.comparisons if c.output not in waived]
    return v


def outcome(v: Verdict) -> tuple[str, float]:
    """("agree" | "differ" | "inconclusive", worst error / tolerance capped at RATIO_CAP)."""
    if v.inconclusive:
        return "inconclusive", 0.0
    w = v.worst
    ratio = 0.0 if w is None else float(min(w.ratio, RATIO_CAP))
    return ("agree" if v.ok else "differ"), ratio


#: the reference outputs that identify a probe's judgement
FINGERPRINT_OUTPUTS = ("image", "alpha", "depth", "n_contrib", "radii", "visible", "means2d",
                       "depths", "conics", "colors", "opacities")
#: probe sources whose scene depends only on the probe's name, profile and rounding
FIXED_SCENES = ("witness", "stage")
#: reference fingerprints of witness and stage probes, shared by every diagnosis in this process
_WITNESS_FINGERPRINTS: dict = {}


def reference_fingerprint(probe: Probe, deviations) -> str:
    """A digest of the reference's outputs on the probe under ``deviations`` and, for a probe
    judged through gradients, of its gradients for one fixed random cotangent."""
    kind = probe.check.kind if probe.check is not None else ("backward" if probe.backward else "forward")
    if probe.source not in FIXED_SCENES:
        return fingerprint(probe.scene, frozenset(deviations), kind)
    # a witness or stage probe's scene is a function of (name, profile, rounding): the same in
    # every diagnosis
    key = (probe.name, str(probe.scene.config.profile), probe.scene.label, kind,
           frozenset(deviations), probe.rounding)
    if key not in _WITNESS_FINGERPRINTS:
        _WITNESS_FINGERPRINTS[key] = fingerprint(probe.scene, frozenset(deviations), kind)
    return _WITNESS_FINGERPRINTS[key]


def fingerprint(case: Case, deviations: frozenset, kind: str) -> str:
    """Digest of the reference's render outputs on ``case`` under ``deviations`` (and, for kind
    "backward" or "hard", of its gradients for one fixed random cotangent)."""
    scene = with_deviations(case, deviations)
    h = hashlib.sha1()
    try:
        ref = ev.reference(scene)
        for k in FINGERPRINT_OUTPUTS:
            h.update(np.ascontiguousarray(getattr(ref, k)).tobytes())
        if kind in ("backward", "hard") and len(ref.gaussians):
            rng = np.random.default_rng(0)
            g = refgs.render_backward(ref, rng.normal(size=ref.image.shape),
                                      rng.normal(size=ref.alpha.shape), rng.normal(size=ref.alpha.shape))
            for v in g.to_dict().values():
                h.update(np.ascontiguousarray(v).tobytes())
    except Exception as exc:
        h.update(f"{type(exc).__name__}: {exc}".encode())
    return h.hexdigest()


def explains(deviations, case: Case, backend_output=None, *, backend=None, check: Check | None = None) -> bool:
    """True iff the reference with ``deviations`` on agrees with the backend on ``case``, judged
    as :func:`judge` does (``check``'s evaluation, or the render outputs when None).

    ``backend_output``: the backend's render output for the case (then the case's profile and
    the output's dtype are the backend's); ``backend`` (spec, BackendInfo or object): needed for
    gradients and stage checks.  A shrinker keeps a failure's deviation signature by accepting a
    smaller case only while ``not explains((), c, out) and explains(found, c, out)``
    (:class:`Signature`)."""
    if backend is None:
        if backend_output is None:
            raise ValueError("explains: expected backend_output or backend, got neither")
        backend = _Recorded(backend_output, str(case.config.profile))
    ctx = plain_context(backend)
    scene = case.rounded(ctx.dtype)
    if backend_output is not None:
        ctx.backend.obj.remember(scene, backend_output)
    probe = Probe("check" if check else "case", check.name if check else "render", scene, check)
    return outcome(judge(ctx, probe, frozenset(deviations)))[0] == "agree"


class _Recorded:
    """A backend that only knows one render output (what :func:`explains` judges)."""

    has_backward = False

    def __init__(self, output, profile: str):
        self.output, self.profile, self.name = output, profile, "recorded output"
        self.dtype = str(np.asarray(output["image"] if isinstance(output, dict) else output.image).dtype)

    def render(self, gaussians, camera, config):
        return self.output


def subsets(found) -> list[frozenset]:
    """Compatible subsets of ``found`` to try as a signature, fewest members first (in catalogue
    order), up to SIGNATURE_MAX_SUBSET members, then ``found`` itself."""
    names = [n for n in DEVIATIONS if n in set(found)]
    out = [frozenset(c) for k in range(1, min(SIGNATURE_MAX_SUBSET, len(names)) + 1)
           for c in itertools.combinations(names, k) if incompatible(c) is None]
    if frozenset(names) not in out:
        out.append(frozenset(names))
    return out


class Signature:
    """The deviation signature of one check's failure, kept while a case shrinks (ORC-06, DEV-02).

    ``start(case)`` finds the smallest subset S of ``found`` under which the reference agrees with
    the backend on the failing ``case`` (None: no subset explains it; no signature to keep).
    ``keeps(case)`` is the shrinker's extra acceptance rule: the case still fails without
    deviations and S still explains it -- ``not explains((), c) and explains(S, c)`` --; S then
    narrows to a smaller subset when one explains the smaller case too (a deviation that stopped
    showing leaves the signature and cannot come back), so the minimal case shows its own
    deviations and no other.  The backend is called once per case (a :class:`PlainBackend`)."""

    def __init__(self, backend, check: Check, found, timeout: float | None = None):
        self.ctx = plain_context(backend, timeout)
        self.check, self.found = check, frozenset(found)
        self.current: frozenset | None = None
        self.evaluations = 0
        self._last = None                        # (case as given, the case rounded)

    def _rounded(self, case: Case) -> Case:
        if self._last is None or self._last[0] is not case:
            self._last = (case, case.rounded(self.ctx.dtype))
        return self._last[1]

    def _agrees(self, case: Case, deviations) -> bool:
        self.evaluations += 1
        probe = Probe("shrink", self.check.name, self._rounded(case), self.check)
        return outcome(judge(self.ctx, probe, frozenset(deviations)))[0] == "agree"

    def evaluate(self, case: Case) -> Verdict:
        """The check's verdict on ``case`` without deviations (through the memoised backend)."""
        return judge(self.ctx, Probe("shrink", self.check.name, self._rounded(case), self.check), ())

    def start(self, case: Case) -> frozenset | None:
        self.current = None
        if not self.found or self._agrees(case, ()):
            return None
        self.current = next((s for s in subsets(self.found) if self._agrees(case, s)), None)
        return self.current

    def keeps(self, case: Case, verdict: Verdict | None = None) -> bool:
        if self.current is None:
            return True
        if verdict is not None and verdict.ok or verdict is None and self._agrees(case, ()):
            return False
        if not self._agrees(case, self.current):
            return False
        for s in subsets(self.current):
            if len(s) < len(self.current) and self._agrees(case, s):
                self.current = s
                break
        return True


__all__ = ["BackendLost", "INVARIANT_WAIVERS", "PlainBackend", "Probe", "RATIO_CAP", "Signature",
           "backend_info", "explains", "fingerprint", "judge", "outcome", "plain_context",
           "reference_fingerprint", "subsets", "with_deviations"]
