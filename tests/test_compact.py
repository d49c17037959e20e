"""The compact strategy (docs/spec/training.md TRN-14) and the test points before resets (TRN-07).

* contributions through the backward equal the forward's per-Gaussian weight sums (one Gaussian
  coloured at a time) and count the fragments;
* the budget admits at most its room, best gradients first, ties at the cut left out;
* contribution pruning moves parameters, optimiser state, statistics and method state together;
* the resolution schedule downsamples images and intrinsics consistently (a projected mean at
  1/f resolution is the full-resolution one over f);
* a compact run is deterministic and resumes bit for bit; bad settings are one-line errors;
* the paper's settings leave ``compact`` out of config.json, so their hash is unchanged.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import refgs
from refgs import runs
from refgs.backends import get_backend
from refgs.constants import SH_C0
from refgs.errors import ConfigError
from refgs.synthetic import benchmark_scene
from refgs.train.adam import Adam
from refgs.train.contribution import contributions
from refgs.train.densify import DensifyConfig, DensifyStats, budget_threshold, densify_and_prune, prune_rows
from refgs.train.strategy import CompactConfig, downsample_view, parse_resolution_schedule
from refgs.train.trainer import TrainConfig, View
from refgs.types import Gaussians, RenderConfig

from test_cli import write_tiny_scene

ITERS = 12


def test_contribution_is_the_sum_of_blending_weights():
    """TRN-14: the backward's reading equals, per Gaussian, the red channel of a render where only
    that Gaussian has colour 1 (all others 0): sum_p alpha_i T_i."""
    g, cam = benchmark_scene(25, 48, 40, seed=2)
    c = contributions(get_backend("reference", "inria", "float64"), g, [cam, cam])
    direct = []
    for i in range(len(g)):
        sh = np.full((len(g), 1, 3), -0.5 / SH_C0)
        sh[i] = 0.5 / SH_C0
        one = Gaussians(means=g.means, log_scales=g.log_scales, quats=g.quats,
                        opacity_logits=g.opacity_logits, sh=sh)
        direct.append(refgs.render(one, cam, RenderConfig(sh_degree=0)).image[..., 0].sum())
    np.testing.assert_allclose(c.weight, 2 * np.array(direct), rtol=1e-12, atol=1e-12)
    out = refgs.render(g, cam, RenderConfig())
    assert list(c.fragments) == [int(out.n_contrib.sum())] * 2 and list(c.pixels) == [48 * 40] * 2
    assert c.weight.min() >= 0 and c.weight.sum() > 0


def test_carried_by_counts_the_largest_first():
    from refgs.train.contribution import Contribution
    c = Contribution(weight=np.array([0.0, 5.0, 90.0, 4.0, 1.0]), fragments=np.zeros(1), pixels=np.ones(1))
    assert c.carried_by((0.9, 0.95, 0.98, 1.0)) == {0.9: 1, 0.95: 2, 0.98: 3, 1.0: 4}


def test_budget_threshold_admits_the_best_up_to_the_room():
    g = np.array([0.1, 0.5, 0.5, 0.2, 0.9, 0.0])
    assert budget_threshold(g, 0.15, 10) == 0.15                  # room enough: the threshold
    assert np.sum(g >= budget_threshold(g, 0.15, 1)) == 1         # only 0.9
    assert np.sum(g >= budget_threshold(g, 0.15, 2)) == 1         # the tie at 0.5 is left out
    assert np.sum(g >= budget_threshold(g, 0.15, 3)) == 3
    assert budget_threshold(g, 0.15, 0) == np.inf


def _state(n, seed=0):
    rng = np.random.default_rng(seed)
    params = {"means": rng.normal(size=(n, 3)), "log_scales": np.log(rng.uniform(0.001, 0.05, (n, 3))),
              "quats": rng.normal(size=(n, 4)), "opacity_logits": rng.normal(size=n),
              "sh": rng.normal(size=(n, 4, 3))}
    adam = Adam(params)
    for k in adam.m:
        adam.m[k] = rng.normal(size=params[k].shape)
        adam.v[k] = rng.uniform(size=params[k].shape)
    stats = DensifyStats(n)
    stats.grad_accum = rng.uniform(0, 0.002, n) * 3
    stats.denom = np.full(n, 3.0)
    stats.max_radii = rng.uniform(0, 10, n)
    return params, adam, stats


def test_densify_budget_caps_the_new_rows_and_none_changes_nothing():
    cfg = DensifyConfig(grad_threshold=0.0005)
    results = {}
    for max_new in ("absent", None, 7):
        params, adam, stats = _state(200)
        kw = {} if max_new == "absent" else {"max_new": max_new}
        remap = densify_and_prune(params, stats, adam, cfg, 1.0, False, np.random.default_rng(1), **kw)
        results[max_new] = (params, remap)
    for k in results["absent"][0]:
        assert np.array_equal(results["absent"][0][k], results[None][0][k])
    capped = results[7][1]
    assert capped.n_cloned + capped.n_split <= 7 < results[None][1].n_cloned + results[None][1].n_split


def test_prune_rows_moves_every_row_state_together():
    params, adam, stats = _state(10)
    before = {k: v.copy() for k, v in params.items()}
    m_before = {k: v.copy() for k, v in adam.m.items()}
    g_before = stats.grad_accum.copy()
    keep = np.array([1, 0, 1, 1, 0, 0, 1, 1, 1, 0], bool)
    remap = prune_rows(params, stats, adam, keep)
    assert remap.n_pruned == 4 and list(remap.parent) == [0, 2, 3, 6, 7, 8]
    for k in params:
        assert np.array_equal(params[k], before[k][keep]) and np.array_equal(adam.m[k], m_before[k][keep])
    assert np.array_equal(stats.grad_accum, g_before[keep]) and len(stats.denom) == 6


@pytest.mark.parametrize("factor", [2, 3])
def test_downsampled_view_projects_to_the_scaled_pixel(factor):
    """TRN-14 / CNV-08: the intrinsics over f put a mean at 1/f of its full-resolution pixel
    position; the image is the block mean (cropped to a multiple of f)."""
    g, cam = benchmark_scene(40, 64, 50, seed=4)
    img = np.random.default_rng(0).random((50, 64, 3))
    low = downsample_view(View("v", cam, img), factor)
    h, w = 50 // factor, 64 // factor
    assert (low.camera.width, low.camera.height) == (w, h) and low.image.shape == (h, w, 3)
    np.testing.assert_allclose(low.image[1, 2], img[factor:2 * factor, 2 * factor:3 * factor].mean(axis=(0, 1)))
    full = refgs.render(g, cam, RenderConfig())
    small = refgs.render(g, low.camera, RenderConfig())
    vis = full.visible & small.visible
    np.testing.assert_allclose(small.means2d[vis], full.means2d[vis] / factor, rtol=1e-12, atol=1e-9)


def test_compact_settings_are_checked():
    assert CompactConfig().validate() == CompactConfig()
    for bad, flag in [({"budget": 0}, "--budget"), ({"prune_fraction": 1.0}, "--prune-fraction"),
                      ({"final_prune_fraction": -0.1}, "--final-prune-fraction"),
                      ({"prune_every": 0}, "--prune-every"),
                      ({"resolution_schedule": ((0.2, 2),)}, "--resolution-schedule"),
                      ({"resolution_schedule": ((0.0, 2), (0.0, 1))}, "--resolution-schedule"),
                      ({"resolution_schedule": ((0.0, 1.5),)}, "--resolution-schedule")]:
        with pytest.raises(ConfigError, match=flag):
            CompactConfig(**bad).validate()
    with pytest.raises(ConfigError, match="--resolution-schedule"):
        parse_resolution_schedule("0-4")
    sched = CompactConfig(resolution_schedule=parse_resolution_schedule("0:4,0.3:2,0.7:1"))
    assert [sched.factor_at(t, 100) for t in (1, 30, 31, 70, 71, 100)] == [4, 4, 2, 2, 1, 1]
    assert CompactConfig.from_dict(sched.to_dict()) == sched


def test_test_points_fall_before_the_resets():
    """TRN-07: the iteration before each multiple of E, and not past T."""
    assert [t for t in range(1, 31) if runs.is_test_point(t, 10, 30)] == [9, 19]   # and T after
    assert [t for t in range(1, 36) if runs.is_test_point(t, 10, 35)] == [9, 19, 29]
    assert not any(runs.is_test_point(t, 0, 30) for t in range(1, 31))


# --- a compact run end to end ----------------------------------------------------------------
def compact_config(scene, **kw) -> TrainConfig:
    """A tiny run with every compact part active: budget, soft pruning at 8, hard pruning at 10
    (densification ends there), resolution 2 then 1."""
    return TrainConfig.with_preset(
        "dropgaussian", {"start": 3, "interval": 4, "until": 10, "grad_threshold": 0.002},
        scene=str(scene), views=3, iters=ITERS, seed=3, images="images", init_points="sfm-all",
        lpips=False, method="fm", backend="reference", compact=CompactConfig(
            budget=60, prune_fraction=0.1, prune_every=8, final_prune_fraction=0.2,
            resolution_schedule=((0.0, 2), (0.5, 1))), **kw)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


@pytest.fixture(scope="module")
def compact_run(scene, tmp_path_factory):
    seen = {}

    def watch(trainer, _flag):
        seen[trainer.t] = (trainer.n, trainer.strategy.training_view(
            trainer, trainer.train_views[0], trainer.t).camera.width)

    out = tmp_path_factory.mktemp("runs") / "compact"
    runs.train(compact_config(scene), out, progress=False, callback=watch)
    return out, seen


def test_compact_run_prunes_caps_and_schedules(compact_run):
    out, seen = compact_run
    cfg = runs.read_config(out)
    assert cfg["settings"]["compact"]["budget"] == 60
    width = cfg["image_size"][0]
    assert seen[1][1] == width // 2 and seen[ITERS][1] == width
    assert max(n for n, _ in seen.values()) <= 60
    # soft pruning at 8 removes floor(0.1 n), hard pruning at 10 floor(0.2 n)
    assert seen[8][0] < seen[7][0] and seen[10][0] == seen[9][0] - int(0.2 * seen[9][0])


def test_compact_run_is_deterministic_and_resumes_bit_for_bit(scene, compact_run, tmp_path):
    out, _ = compact_run
    again = tmp_path / "again"
    runs.train(compact_config(scene), again, progress=False)
    assert (again / runs.MODEL_FILE).read_bytes() == (out / runs.MODEL_FILE).read_bytes()
    stopped = tmp_path / "stopped"

    def stop_at_9(trainer, flag):
        if trainer.t == 9:
            flag.set()

    with pytest.raises(runs.Interrupted):
        runs.train(compact_config(scene), stopped, progress=False, callback=stop_at_9)
    runs.resume(stopped, progress=False)
    assert (stopped / runs.MODEL_FILE).read_bytes() == (out / runs.MODEL_FILE).read_bytes()


def test_paper_settings_leave_compact_out(scene):
    """The default protocol's settings dict (and so its hash) has no compact key (TRN-14)."""
    d = compact_config(scene, ).to_dict()
    assert "compact" in d
    paper = TrainConfig.from_dict({k: v for k, v in d.items() if k != "compact"})
    assert paper.compact is None and "compact" not in paper.to_dict()
    assert TrainConfig.from_dict(d).compact == compact_config(scene).compact


def test_history_counts_fragments_and_reads_old_checkpoints(compact_run):
    """TRN-07/TRN-14: one fragment count per iteration; a checkpoint from before the count loads
    with -1 (not measured) for its iterations."""
    import json
    out, _ = compact_run
    h = json.loads((out / runs.HISTORY_FILE).read_text())
    assert len(h["fragments"]) == ITERS and min(h["fragments"]) > 0
    trainer = runs.load(out).trainer
    arrays, meta = trainer.state_arrays(), trainer.state_meta()
    del arrays["history/fragments"]
    trainer.load_state(arrays, meta)
    assert trainer.history["fragments"] == [-1] * ITERS


def test_compactness_report_of_a_run(compact_run, tmp_path):
    """docs/compact.md's measurement: `refgs compactness` writes the table, JSON and plot; the
    counts carrying 90 / 99 / 99.9 % rise and stay within the model."""
    import json

    from refgs.cli import main
    out, _ = compact_run
    assert main(["compactness", str(out), "--out", str(tmp_path / "c"), "--quiet"]) == 0
    row = json.loads((tmp_path / "c" / "compactness.json").read_text())["runs"][0]
    counts = [row["carried_by"][k] for k in ("0.9", "0.99", "0.999")]
    assert 1 <= counts[0] <= counts[1] <= counts[2] <= row["gaussians"]
    assert min(row["fragments_per_view"]) > 0 and row["phases"][0]["from"] == 1
    assert row["curve"]["share"][-1] == pytest.approx(1.0)
    assert "| compact |" in (tmp_path / "c" / "compactness.md").read_text()
    assert (tmp_path / "c" / "compactness.png").stat().st_size > 0


def test_compact_runs_have_a_label_of_their_own():
    """A report tells compact runs from the paper's by their method label (refgs.analysis.tables)."""
    from refgs.analysis.tables import method_label
    from refgs.train.strategy import compact_label
    assert compact_label(None) == "" and method_label({"method": "fm"}) == "fm"
    settings = {"method": "fm", "compact": CompactConfig(
        budget=4000, resolution_schedule=((0.0, 2), (0.5, 1))).to_dict()}
    assert method_label(settings) == "fm+compact(budget=4000,resolution_schedule=0:2/0.5:1)"
    assert method_label({"method": "3dgs", "compact": CompactConfig().to_dict()}) == "3dgs+compact"


def test_compact_flags_on_the_command_line(scene, tmp_path, capsys):
    """`refgs train --compact` takes the preset, given flags override it; bad values are one
    line naming the flag (TRN-11, TRN-14)."""
    import json

    from refgs.train.strategy import COMPACT_PRESET
    from test_cli import assert_one_line_error, run_cli, tiny_args

    out = tmp_path / "c"
    rc, _, err = run_cli(tiny_args(scene, out, 10, "--compact", "--budget", "50"), capsys)
    assert rc == 0, err
    settings = json.loads((out / runs.CONFIG_FILE).read_text())["settings"]
    preset = CompactConfig(**COMPACT_PRESET["compact"])
    assert settings["compact"] == dataclasses.replace(preset, budget=50).to_dict()
    assert settings["sh_degree"] == COMPACT_PRESET["sh_degree"]
    assert settings["densify"]["until"] == 14            # tiny_args' --densify-until wins
    for flag, value in (("--prune-fraction", "1.5"), ("--budget", "0"),
                        ("--resolution-schedule", "0:x")):
        rc, _, err = run_cli(tiny_args(scene, tmp_path / flag.strip("-"), 10, flag, value), capsys)
        assert_one_line_error(rc, err, flag)
        assert not (tmp_path / flag.strip("-")).exists()
