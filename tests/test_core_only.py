"""`import refgs`, the CLI and the oracle work with the core dependencies alone (issue 2 item 1).

Optional packages (numba, torch, gsplat, jupyter) are blocked with an import hook in a subprocess;
the commands must still run.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OPTIONAL = ("numba", "torch", "gsplat", "jupytext", "nbclient", "llvmlite")

BLOCKER = textwrap.dedent(f"""
    import sys, importlib.abc
    class _Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in {OPTIONAL!r}:
                raise ImportError('blocked optional dependency: ' + name)
    sys.meta_path.insert(0, _Block())
""")


def run_blocked(code: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCKER + textwrap.dedent(code)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def test_import_refgs_and_render_without_optional_packages():
    r = run_blocked("""
        import numpy as np, refgs
        from refgs.synthetic import benchmark_scene
        g, cam = benchmark_scene(50, 32, 24)
        out = refgs.render(g, cam)
        refgs.render_backward(out, np.ones_like(out.image))
        assert not any(m.split('.')[0] in ('numba', 'torch', 'gsplat') for m in sys.modules)
        print('ok')
    """)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout


def test_cli_help_without_optional_packages():
    r = run_blocked("""
        import sys
        from refgs.cli import main
        for cmd in (['train', '--help'], ['eval', '--help']):
            try:
                main(cmd)
            except SystemExit as e:
                assert e.code == 0, e.code
        print('ok')
    """)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout


def test_oracle_check_without_optional_packages():
    r = run_blocked("""
        import sys
        from oracle.__main__ import main
        code = main(['check', '--backend', 'oracle.adapters.refgs_backend:refgs_float64',
                     '--max-examples', '2', '--clause', 'CNV-08'])
        print('exit', code)
        sys.exit(code or 0)
    """)
    assert r.returncode == 0, r.stdout + r.stderr


def test_train_and_eval_run_without_optional_packages(tmp_path):
    """A real (tiny) ``refgs train`` and ``refgs eval`` with numba/torch/gsplat/jupyter blocked."""
    from test_cli import tiny_args, write_tiny_scene

    scene = write_tiny_scene(tmp_path / "scene")
    out = tmp_path / "run"
    args = [str(a) for a in tiny_args(scene, out, 6)]
    r = run_blocked(f"""
        import sys, json
        from refgs.cli import main
        assert main({args!r}) == 0
        assert main(['eval', {str(out)!r}, '--no-lpips', '--quiet']) == 0
        assert not any(m.split('.')[0] in ('numba', 'torch', 'gsplat') for m in sys.modules)
        print('psnr', json.load(open({str(out / 'metrics.json')!r}))['psnr'])
    """)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "psnr" in r.stdout


def test_bench_without_optional_packages(tmp_path):
    """``refgs bench`` runs the reference alone and lists the optional backends as n/a."""
    r = run_blocked(f"""
        import json
        from refgs.cli import main
        assert main(['bench', '--n', '60', '--size', '24x16', '--repeats', '1', '--no-plots',
                     '--out', {str(tmp_path)!r}]) == 0
        doc = json.load(open({str(tmp_path / 'bench.json')!r}))
        print(sorted(doc['results'][0]['backends']), sorted(doc['unavailable']))
    """)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "['ref32', 'ref64'] ['fast32', 'fast32g', 'fast64', 'gsplat', 'torch32', 'torch64']" in r.stdout, r.stdout
