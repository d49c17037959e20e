"""Checkpoint and resume (docs/spec/training.md TRN-09): a run stopped by Ctrl-C or killed and
continued with ``refgs train --resume`` ends with exactly the parameters, optimiser state and
random streams of the uninterrupted run; checkpoints load with allow_pickle=False."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from refgs.cli import build_parser, config_from_args, main
from refgs.runs import Interrupted, load, resume, train
from refgs.train.checkpoint import load_checkpoint, rng_from_state, rng_state, save_checkpoint

from test_cli import tiny_args, write_tiny_scene

ITERS = 20  # densification at 4, 8, 12 (tiny_args)
CHECKPOINT_EVERY = 5


class SimulatedKill(BaseException):
    """Stands for SIGKILL: nothing after it runs in the trainer."""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


def config(scene, out, iters=ITERS, *extra):
    args = build_parser().parse_args(tiny_args(scene, out, iters, "--checkpoint-every",
                                               str(CHECKPOINT_EVERY), *extra))
    return config_from_args(args)


SNAPSHOTS = {}


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory):
    """The uninterrupted run; SNAPSHOTS[t] = its full state after iteration t (t = 5, 6)."""
    out = tmp_path_factory.mktemp("ref") / "run"

    def snap(trainer, stop):
        if trainer.t in (5, 6):
            SNAPSHOTS[trainer.t] = ({k: np.array(v) for k, v in trainer.state_arrays().items()},
                                    json.loads(json.dumps(trainer.state_meta())))

    train(config(scene, out), out, progress=False, callback=snap)
    return out


def assert_restored_equals_snapshot(run: Path, t: int):
    """Everything loaded from the checkpoint equals the uninterrupted run's state at t."""
    trainer = load(run).trainer
    arrays, meta = SNAPSHOTS[t]
    got = trainer.state_arrays()
    assert sorted(got) == sorted(arrays)
    for k, v in arrays.items():
        if k.startswith("history/iter_"):     # wall and CPU timings
            continue
        assert np.array_equal(got[k], v) and np.asarray(got[k]).dtype == v.dtype, k
    got_meta = trainer.state_meta()
    for k in ("iteration", "rng", "view_stack", "n_gaussians"):
        assert got_meta[k] == meta[k], k


def assert_same_state(run_a: Path, run_b: Path):
    a, meta_a = load_checkpoint(run_a / "checkpoint.npz")
    b, meta_b = load_checkpoint(run_b / "checkpoint.npz")
    assert meta_a["iteration"] == meta_b["iteration"] == ITERS
    state_keys = [k for k in a if k.split("/")[0] in ("param", "adam", "densify")]
    assert sorted(state_keys) == sorted(k for k in b if k.split("/")[0] in ("param", "adam", "densify"))
    for k in state_keys:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
    assert meta_a["rng"] == meta_b["rng"] and meta_a["view_stack"] == meta_b["view_stack"]
    for k in ("train_t", "train_loss", "train_psnr", "n_gaussians", "test_t", "test_psnr"):
        assert np.array_equal(a[f"history/{k}"], b[f"history/{k}"]), k
    assert (run_a / "model.ply").read_bytes() == (run_b / "model.ply").read_bytes()


def test_reference_run_densified(reference):
    arrays, meta = load_checkpoint(reference / "checkpoint.npz")
    n = arrays["history/n_gaussians"]
    # the Gaussian count changes after the checkpoint at 5 (densify at 8 and 12)
    assert n[4] != n[8] != n[12]
    assert meta["iteration"] == ITERS


def kill_at(scene, out, t_kill: int) -> None:
    """Start a run in ``out`` and kill it (an exception, as a crash) after iteration ``t_kill``."""
    def kill(trainer, stop):
        if trainer.t == t_kill:
            raise SimulatedKill

    with pytest.raises(SimulatedKill):
        train(config(scene, out), out, progress=False, callback=kill)


def test_resume_after_kill(scene, reference, tmp_path):
    out = tmp_path / "run"
    kill_at(scene, out, 7)  # after the checkpoint at 5; densification at 8 and 12 follow
    _, meta = load_checkpoint(out / "checkpoint.npz")
    assert meta["iteration"] == 5
    assert not (out / "metrics.json").exists()
    assert_restored_equals_snapshot(out, 5)
    resume(out, progress=False)
    assert_same_state(reference, out)


def test_resume_after_ctrl_c(scene, reference, tmp_path):
    out = tmp_path / "run"

    def ctrl_c(trainer, stop):
        if trainer.t == 6:
            stop.set()

    with pytest.raises(Interrupted) as exc:
        train(config(scene, out), out, progress=False, callback=ctrl_c)
    assert exc.value.iteration == 6
    _, meta = load_checkpoint(out / "checkpoint.npz")
    assert meta["iteration"] == 6
    assert_restored_equals_snapshot(out, 6)
    assert main(["train", "--resume", str(out), "--quiet"]) == 0
    assert_same_state(reference, out)


def test_kill_before_first_checkpoint_leaves_nothing(scene, tmp_path):
    out = tmp_path / "run"
    kill_at(scene, out, 3)
    assert list(tmp_path.iterdir()) == []


def test_resume_finished_run_is_noop(reference):
    before = (reference / "checkpoint.npz").read_bytes()
    resume(reference, progress=False)
    assert (reference / "checkpoint.npz").read_bytes() == before


def test_edited_config_refused(reference, tmp_path, capsys):
    import json
    import shutil

    run = tmp_path / "run"
    shutil.copytree(reference, run)
    cfg = json.loads((run / "config.json").read_text())
    cfg["settings"]["seed"] = 99
    (run / "config.json").write_text(json.dumps(cfg))
    assert main(["train", "--resume", str(run)]) == 2
    assert "settings differ" in capsys.readouterr().err


def test_checkpoint_has_no_pickles(reference):
    with np.load(reference / "checkpoint.npz", allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)
        assert z["meta"].dtype.kind == "U"


def test_rng_state_round_trip(tmp_path):
    rng = np.random.default_rng(12345)
    rng.standard_normal(7)
    save_checkpoint(tmp_path / "c.npz", {"x": np.arange(3)}, {"rng": rng_state(rng)})
    arrays, meta = load_checkpoint(tmp_path / "c.npz")
    again = rng_from_state(meta["rng"])
    assert np.array_equal(again.standard_normal(5), rng.standard_normal(5))
    assert np.array_equal(arrays["x"], np.arange(3))


def _wait_for(predicate, proc, timeout=60.0):
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.02)
    return False


SIGNAL_ITERS = 40
SIGNAL_ARGS = ("--checkpoint-every", "10", "--densify-until", "40", "--densify-interval", "10")


@pytest.fixture(scope="module")
def signal_reference(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("sigref") / "run"
    train(config(scene, out, SIGNAL_ITERS, *SIGNAL_ARGS), out, progress=False)
    return out


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_real_signal_then_resume(scene, signal_reference, tmp_path, sig):
    """A real process: SIGINT (Ctrl-C) checkpoints and exits 130; SIGKILL loses the work since the
    last periodic checkpoint; both resume to the uninterrupted result (densification every 10)."""
    out = tmp_path / "run"
    argv = tiny_args(scene, out, SIGNAL_ITERS, *SIGNAL_ARGS)
    proc = subprocess.Popen([sys.executable, "-m", "refgs", *argv], stderr=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    started = _wait_for(lambda: (out / "checkpoint.npz").exists(), proc)
    if started:
        os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=120)
    if not started:
        pytest.fail(f"run ended before the first checkpoint: rc {proc.returncode}, {err}")
    if sig == signal.SIGINT:
        assert proc.returncode == 130, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "interrupted at iteration" in lines[0] and "--resume" in lines[0]
    else:
        assert proc.returncode == -signal.SIGKILL
    _, meta = load_checkpoint(out / "checkpoint.npz")
    assert 0 < meta["iteration"] < SIGNAL_ITERS, meta["iteration"]
    resume(out, progress=False)
    a, _ = load_checkpoint(signal_reference / "checkpoint.npz")
    b, _ = load_checkpoint(out / "checkpoint.npz")
    for k in a:
        if k.split("/")[0] in ("param", "adam", "densify"):
            assert np.array_equal(a[k], b[k]), (k, meta["iteration"])


def test_checkpoint_holds_the_initial_cloud(scene, tmp_path):
    """TRN-09: the checkpoint keeps the initial point cloud; resume restores init_points.ply."""
    from refgs.data.pointcloud import read_ply

    out = tmp_path / "run"
    kill_at(scene, out, 7)
    arrays, _ = load_checkpoint(out / "checkpoint.npz")
    pts, cols = read_ply(out / "init_points.ply")
    assert arrays["init/points"].shape == pts.shape and len(pts) > 0
    np.testing.assert_allclose(arrays["init/points"], pts, rtol=1e-6)
    np.testing.assert_allclose(arrays["init/colors"], cols, atol=1 / 255)
    (out / "init_points.ply").unlink()
    resume(out, progress=False)
    pts2, _ = read_ply(out / "init_points.ply")
    np.testing.assert_allclose(pts2, pts, rtol=1e-6)


@pytest.mark.skipif(__import__("importlib").util.find_spec("numba") is None,
                    reason="the fast backend needs numba")
@pytest.mark.parametrize("method", ["3dgs", "fm"])
def test_fast_float32_resume_is_bit_identical(scene, tmp_path, method):
    """The training default (float32, TrainConfig.dtype) on the fast backend: a run killed after
    its checkpoint at 5 and resumed ends with the bytes of the uninterrupted run (TRN-09), FM's
    perturbation stream included."""
    extra = ("--backend", "fast", "--method", method)
    full = tmp_path / "full"
    train(config(scene, full, ITERS, *extra), full, progress=False)
    arrays, _ = load_checkpoint(full / "checkpoint.npz")
    assert arrays["param/means"].dtype == np.float32

    def kill(trainer, stop):
        if trainer.t == 7:
            raise SimulatedKill

    out = tmp_path / "run"
    with pytest.raises(SimulatedKill):
        train(config(scene, out, ITERS, *extra), out, progress=False, callback=kill)
    resume(out, progress=False)
    assert_same_state(full, out)
