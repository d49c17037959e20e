"""The run directory as a public API (refgs.runs, docs/spec/training.md TRN-07..TRN-09): train,
load, resume, evaluate and render a run without the command line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from refgs import runs
from refgs.errors import ConfigError
from refgs.train.checkpoint import CheckpointError
from refgs.train.trainer import TrainConfig

from test_cli import write_tiny_scene

ITERS = 8


def tiny_config(scene, **kw) -> TrainConfig:
    """The settings of test_cli.tiny_args, built without argparse."""
    return TrainConfig.with_preset(
        "dropgaussian", {"start": 3, "interval": 4, "until": 14, "grad_threshold": 0.002},
        scene=str(scene), views=3, iters=ITERS, seed=3, images="images", init_points="sfm-all",
        lpips=False, **kw)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "run"
    assert runs.train(tiny_config(scene), out, progress=False) == out
    return out


def test_train_writes_every_run_file(run):
    for name in (runs.CONFIG_FILE, runs.CHECKPOINT_FILE, runs.MODEL_FILE, runs.INIT_FILE,
                 runs.METRICS_FILE, runs.HISTORY_FILE, runs.PLOT_FILE):
        assert (run / name).is_file(), name
    assert sorted(p.name for p in (run / runs.RENDER_DIR / "test").iterdir()) == ["v00.png", "v08.png"]
    config = runs.read_config(run)
    assert config["settings_hash"] == runs.settings_hash(config["settings"])
    assert config["settings"]["backend"] == "reference" and config["settings"]["method"] == "3dgs"


def test_load_gives_the_checkpointed_trainer(run):
    loaded = runs.load(run)
    assert isinstance(loaded, runs.LoadedRun)
    config, cfg, trainer = loaded
    assert cfg.iters == trainer.t == ITERS and config["train_images"] == [
        v.name for v in trainer.train_views]
    assert trainer.backend.dtype == "float32" and trainer.backend.profile == "inria"  # defaults
    metrics = json.loads((run / runs.METRICS_FILE).read_text())
    assert runs.evaluate(trainer, lpips=False)["psnr"] == pytest.approx(metrics["psnr"], abs=1e-12)
    again = runs.load(run, backend="ref32").trainer          # another backend, same renders
    v = trainer.test_views[0]
    assert np.array_equal(again.render_view(v), trainer.render_view(v))


def test_evaluate_and_render_run(run):
    before = json.loads((run / runs.METRICS_FILE).read_text())
    after = runs.evaluate_run(run, progress=False)
    assert after["psnr"] == before["psnr"] and after["n_init_points"] == before["n_init_points"]
    out = runs.render_run(run, "train")
    names = runs.read_config(run)["train_images"]
    assert sorted(p.name for p in (out / "train").iterdir()) == sorted(names) and len(names) == 3


def test_resume_of_a_finished_run_changes_nothing(run):
    model = (run / runs.MODEL_FILE).read_bytes()
    assert runs.resume(run, progress=False) == run
    assert (run / runs.MODEL_FILE).read_bytes() == model


def test_interrupted_then_resumed_equals_uninterrupted(scene, run, tmp_path):
    out = tmp_path / "stopped"

    def stop_at_5(trainer, flag):
        if trainer.t == 5:
            flag.set()

    with pytest.raises(runs.Interrupted) as e:
        runs.train(tiny_config(scene), out, progress=False, callback=stop_at_5)
    assert e.value.iteration == 5 and "refgs train --resume" in str(e.value)
    assert runs.load(out).trainer.t == 5
    runs.resume(out, progress=False)
    assert (out / runs.MODEL_FILE).read_bytes() == (run / runs.MODEL_FILE).read_bytes()
    resumes = runs.read_config(out)["resumes"]
    assert [r["from_iteration"] for r in resumes] == [5]


def test_bad_input_leaves_nothing(scene, tmp_path):
    with pytest.raises(ConfigError, match="--backend: unknown backend 'nope'"):
        runs.train(tiny_config(scene, backend="nope"), tmp_path / "a", progress=False)
    with pytest.raises(ConfigError, match="--backend ref64: renders dtype float64 only"):
        runs.train(tiny_config(scene, backend="ref64"), tmp_path / "b", progress=False)
    with pytest.raises(ConfigError, match="--method"):
        runs.train(tiny_config(scene, method="sam"), tmp_path / "c", progress=False)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ConfigError, match="--out: parent folder"):
        runs.RunDir.create(tmp_path / "missing" / "run")


def test_run_dir_is_published_once(tmp_path):
    rd = runs.RunDir.create(tmp_path / "run")
    assert rd.path.name.startswith(".run" + runs.PARTIAL_TAG) and not rd.published
    (rd / "x.txt").write_text("x")
    rd.publish()
    rd.publish()
    assert rd.published and (tmp_path / "run" / "x.txt").read_text() == "x"
    other = runs.RunDir.create(tmp_path / "late")
    (tmp_path / "late").mkdir()
    with pytest.raises(ConfigError, match="appeared while the run was being built"):
        other.publish()
    other.discard()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["late", "run"]


def test_read_config_errors_name_the_file(tmp_path):
    with pytest.raises(CheckpointError, match="run directory not found"):
        runs.read_config(tmp_path / "none")
    with pytest.raises(CheckpointError, match="config.json: not found"):
        runs.read_config(tmp_path)
    (tmp_path / runs.CONFIG_FILE).write_text("{")
    with pytest.raises(CheckpointError, match="config.json: not valid JSON"):
        runs.read_config(tmp_path)
