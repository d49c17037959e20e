"""The DEV-01.1 benchmark: render + render_backward of one seeded scene, and the stored outputs of
the code before the deviation catalogue existed, made on a named float environment (TRN-13).

``reference_outputs()`` is the benchmark (both profiles, both dtypes, a non-black background and
seeded image, alpha and depth cotangents); ``digest()`` its sha256. The stored file
``tests/data/dev01_reference_c577de3.npz`` holds the outputs of refgs at commit c577de3 (before
``RenderConfig.deviations``) with the float environment that made them, and is rebuilt with::

    python tests/dev01_reference.py --code c577de3 --out tests/data/dev01_reference_c577de3.npz

which checks that commit out into a temporary git worktree, runs ``reference_outputs`` there in a
subprocess (``--dump``) and stores the arrays with this machine's ``float_environment()``.
The outputs only use ``refgs.render``, ``render_backward``, ``RenderConfig`` and
``refgs.synthetic.benchmark_scene``, which every commit since c577de3 has.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: the stored outputs of the code before the catalogue (see the module docstring)
STORED = ROOT / "tests" / "data" / "dev01_reference_c577de3.npz"
#: the output fields of RenderOutput in the order the digest hashes them
OUTPUT_FIELDS = ("image", "alpha", "depth", "n_contrib", "final_T", "radii", "means2d", "conics",
                 "cov2d", "colors", "opacities", "visible")
PROFILES = ("inria", "gsplat")
DTYPES = (np.float64, np.float32)


def reference_outputs(config_extra=None) -> dict[str, np.ndarray]:
    """``{"<profile>/<dtype>/<field>": array}`` of render + render_backward of
    ``benchmark_scene(300, 96, 72, seed=3)``; gradients as ``.../grad_<name>``. Insertion order is
    the digest's order."""
    import refgs
    from refgs import RenderConfig
    from refgs.synthetic import benchmark_scene

    res = {}
    for profile in PROFILES:
        for dtype in DTYPES:
            g, cam = benchmark_scene(300, 96, 72, seed=3, dtype=dtype)
            cfg = RenderConfig(profile=profile, background=(0.25, 0.5, 1.0), **(config_extra or {}))
            out = refgs.render(g, cam, cfg)
            rng = np.random.default_rng(7)
            gr = refgs.render_backward(out, rng.normal(size=out.image.shape),
                                       rng.normal(size=out.alpha.shape), rng.normal(size=out.alpha.shape))
            tag = f"{profile}/{np.dtype(dtype).name}"
            for f in OUTPUT_FIELDS:
                res[f"{tag}/{f}"] = np.asarray(getattr(out, f))
            for k, v in gr.to_dict().items():
                res[f"{tag}/grad_{k}"] = np.asarray(v)
    return res


def digest(outputs: dict[str, np.ndarray]) -> str:
    """sha256 of the arrays' bytes in insertion order (the pinned digests' definition)."""
    h = hashlib.sha256()
    for a in outputs.values():
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def load_stored(path: Path = STORED) -> tuple[dict[str, np.ndarray], dict]:
    """The stored outputs and their metadata (code, float environment, CPU)."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        return {k: z[k] for k in z.files if k != "meta"}, meta


def _write(code: str, out: Path) -> None:
    from refgs.io.atomic import atomic_path
    from refgs.train.checkpoint import cpu_name, float_environment

    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), code],
                       check=True, capture_output=True)
        try:
            dump = Path(tmp) / "dump.npz"
            env = dict(os.environ, PYTHONPATH=str(tree))
            subprocess.run([sys.executable, __file__, "--dump", str(dump)], env=env, check=True)
            with np.load(dump, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                           check=True, capture_output=True)
    meta = {"code": code, "float_environment": float_environment(), "cpu": cpu_name(),
            "digest": digest(arrays)}
    with atomic_path(out) as tmp_out:
        with open(tmp_out, "wb") as fh:
            np.savez_compressed(fh, meta=np.array(json.dumps(meta)), **arrays)
    print(f"wrote {out}: {len(arrays)} arrays, digest {meta['digest']}, {meta['float_environment']}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--code", default="c577de3", help="the commit whose outputs are stored")
    ap.add_argument("--out", type=Path, default=STORED)
    ap.add_argument("--dump", type=Path, help=argparse.SUPPRESS)   # inside the worktree's process
    args = ap.parse_args(argv)
    if args.dump:
        np.savez(args.dump, **reference_outputs())
        return 0
    _write(args.code, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
