"""The `refgs` command line: bad input gives one line, no traceback, no run directory
(docs/spec/training.md TRN-09, TRN-10); train / eval / render on a tiny scene."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import refgs
from refgs.cli import main
from refgs.train.checkpoint import FLOAT_ENV_FIELDS

DATA = Path(os.environ.get("REFGS_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
FERN = DATA / "fern"

#: Tiny scene: 9 views of 32 x 24 pixels (views 0 and 8 are test views with holdout 8).
TINY_W, TINY_H, TINY_VIEWS, TINY_POINTS = 32, 24, 9, 40


def _qvec(R):
    from scipy.spatial.transform import Rotation
    x, y, z, w = (float(v) for v in Rotation.from_matrix(R).as_quat())
    return w, x, y, z


def write_tiny_scene(root: Path, seed: int = 0, camera_model: str = "PINHOLE") -> Path:
    """A COLMAP text model + PNGs rendered by refgs from TINY_POINTS random Gaussians."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    n = TINY_POINTS
    means = rng.uniform(-1, 1, (n, 3)) * [1.0, 0.8, 0.3]
    colors = rng.uniform(0.1, 0.9, (n, 3))
    sh = np.zeros((n, 16, 3))
    sh[:, 0] = (colors - 0.5) / 0.28209479177387814
    g = refgs.Gaussians(means, np.full((n, 3), np.log(0.2)), np.tile([1.0, 0, 0, 0], (n, 1)),
                        np.full(n, 1.5), sh)
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    fx = 30.0
    params = {"PINHOLE": f"{fx} {fx} {TINY_W / 2} {TINY_H / 2}",
              "OPENCV_FISHEYE": f"{fx} {fx} {TINY_W / 2} {TINY_H / 2} 0.01 0 0 0"}[camera_model]
    images = []
    for k in range(TINY_VIEWS):
        a = np.radians(-30 + 60 * k / (TINY_VIEWS - 1))
        eye = [4 * np.sin(a), 0.3 * np.cos(3 * a), -4 * np.cos(a)]
        cam = refgs.Camera.look_at(eye, [0, 0, 0], fx=fx, width=TINY_W, height=TINY_H)
        img = np.clip(refgs.render(g, cam).image, 0, 1)
        Image.fromarray(np.rint(img * 255).astype(np.uint8)).save(root / "images" / f"v{k:02d}.png")
        w, x, y, z = _qvec(cam.world_to_camera[:3, :3])
        t = [float(v) for v in cam.world_to_camera[:3, 3]]
        images += [f"{k + 1} {w!r} {x!r} {y!r} {z!r} {t[0]!r} {t[1]!r} {t[2]!r} 1 v{k:02d}.png", ""]
    (root / "sparse/0/cameras.txt").write_text(f"1 {camera_model} {TINY_W} {TINY_H} {params}\n")
    (root / "sparse/0/images.txt").write_text("\n".join(images) + "\n")
    rgb = np.rint(colors * 255).astype(int)
    (root / "sparse/0/points3D.txt").write_text("".join(
        f"{i + 1} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0.5\n"
        for i, (p, c) in enumerate(zip(means.tolist(), rgb.tolist()))))
    return root


def tiny_args(scene: Path, out: Path, iters: int = 20, *extra) -> list:
    """Arguments of a fast run: densify at 4, 8, 12, no LPIPS, no progress bar."""
    return ["train", "--scene", str(scene), "--images", "images", "--views", "3",
            "--iters", str(iters), "--out", str(out), "--init-points", "sfm-all", "--seed", "3",
            "--densify-from", "3", "--densify-interval", "4", "--densify-until", "14",
            "--densify-grad-threshold", "0.002", "--no-lpips", "--quiet", *extra]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


def run_cli(argv, capsys) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def assert_one_line_error(rc, err, *needles):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith("refgs: error: "), err
    assert "Traceback" not in err
    for needle in needles:
        assert str(needle) in lines[0], (needle, lines[0])


def listing(folder: Path) -> list:
    return sorted(p.name for p in folder.iterdir())


# --- bad input: one line, exit 2, nothing left behind -----------------------------------------
def test_missing_scene_folder(tmp_path, capsys):
    rc, _, err = run_cli(tiny_args(tmp_path / "nowhere", tmp_path / "run"), capsys)
    assert_one_line_error(rc, err, tmp_path / "nowhere", "not found")
    assert listing(tmp_path) == []


@pytest.mark.skipif(not FERN.is_dir(), reason="needs shared/data/fern")
@pytest.mark.parametrize("victim", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_model_file(tmp_path, capsys, victim):
    scene = tmp_path / "fern"
    shutil.copytree(FERN / "sparse" / "0", scene / "sparse" / "0")
    (scene / "images_8").symlink_to((FERN / "images_8").resolve())
    path = scene / "sparse" / "0" / victim
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2 + 3])
    out = tmp_path / "runs"
    out.mkdir()
    rc, _, err = run_cli(["train", "--scene", scene, "--views", "3", "--iters", "5",
                          "--out", out / "r", "--quiet"], capsys)
    assert_one_line_error(rc, err, path)
    assert listing(out) == []


def test_empty_image_folder(tmp_path, capsys, tiny_scene):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene / "sparse", scene / "sparse")
    (scene / "images").mkdir()
    rc, _, err = run_cli(tiny_args(scene, tmp_path / "run"), capsys)
    assert_one_line_error(rc, err, scene / "images", "no image files")
    assert listing(tmp_path) == ["scene"]


def test_unsupported_camera_model(tmp_path, capsys):
    scene = write_tiny_scene(tmp_path / "scene", camera_model="OPENCV_FISHEYE")
    rc, _, err = run_cli(tiny_args(scene, tmp_path / "run"), capsys)
    assert_one_line_error(rc, err, "cameras.txt", "OPENCV_FISHEYE")
    assert listing(tmp_path) == ["scene"]


def test_too_many_views(tmp_path, capsys, tiny_scene):
    args = tiny_args(tiny_scene, tmp_path / "run")
    args[args.index("--views") + 1] = "8"
    rc, _, err = run_cli(args, capsys)
    assert_one_line_error(rc, err, "--views", "8")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("flag,value", [("--iters", "0"), ("--checkpoint-every", "-1"),
                                        ("--init-points", "cloud.xyz"), ("--backend", "cuda"),
                                        ("--backend", "ref64"), ("--backend", "no_such_mod:obj")])
def test_bad_flag_values(tmp_path, capsys, tiny_scene, flag, value):
    args = tiny_args(tiny_scene, tmp_path / "run")
    if flag in args:
        args[args.index(flag) + 1] = value
    else:
        args += [flag, value]
    rc, _, err = run_cli(args, capsys)
    assert_one_line_error(rc, err, flag)
    assert listing(tmp_path) == []


def test_init_ply_missing(tmp_path, capsys, tiny_scene):
    args = tiny_args(tiny_scene, tmp_path / "run")
    args[args.index("--init-points") + 1] = str(tmp_path / "cloud.ply")
    rc, _, err = run_cli(args, capsys)
    assert_one_line_error(rc, err, tmp_path / "cloud.ply")
    assert listing(tmp_path) == []


def test_argparse_errors_are_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["train", "--views", "three"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and len(err.strip().splitlines()) == 1 and "--views" in err


def test_resume_errors(tmp_path, capsys):
    rc, _, err = run_cli(["train", "--resume", tmp_path / "none"], capsys)
    assert_one_line_error(rc, err, tmp_path / "none")
    rc, _, err = run_cli(["train", "--resume", tmp_path, "--iters", "3"], capsys)
    assert_one_line_error(rc, err, "--iters")


def test_subprocess_entry_point_one_line(tmp_path):
    """The installed entry point path (python -m refgs) prints no traceback either."""
    res = subprocess.run([sys.executable, "-m", "refgs", "train", "--scene", str(tmp_path / "x"),
                          "--views", "3", "--iters", "2", "--out", str(tmp_path / "r")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("refgs: error:"), res.stderr
    assert "Traceback" not in res.stderr


# --- a whole run, then eval / render / corrupt files -----------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "run"
    assert main(tiny_args(tiny_scene, out, 20, "--eval-every", "10")) == 0
    return out


def test_run_directory_contents(tiny_run):
    names = set(listing(tiny_run))
    assert {"config.json", "checkpoint.npz", "metrics.json", "history.json", "model.ply",
            "init_points.ply", "psnr.png", "renders"} <= names
    assert listing(tiny_run / "renders" / "test") == ["v00.png", "v08.png"]
    assert not [n for n in listing(tiny_run.parent) if n.startswith(".")]  # no partial dir left
    cfg = json.loads((tiny_run / "config.json").read_text())
    assert cfg["train_images"] == ["v01.png", "v04.png", "v07.png"]  # linspace(0, 6, 3) of 7
    assert cfg["test_images"] == ["v00.png", "v08.png"]
    assert cfg["settings"]["iters"] == 20 and cfg["settings"]["densify"]["interval"] == 4
    assert cfg["n_init_points"] == TINY_POINTS
    for key in ("git_hash", "packages", "cpu", "cpu_count", "float_environment"):
        assert key in cfg["provenance"]
    # TRN-13: the float environment says what the run's bytes can be compared with
    env = cfg["provenance"]["float_environment"]
    assert set(env) == set(FLOAT_ENV_FIELDS) and env["numpy"] == np.__version__
    from numpy._core._multiarray_umath import __cpu_baseline__, __cpu_dispatch__, __cpu_features__
    assert env["numpy_simd"] in (*__cpu_dispatch__, *__cpu_baseline__)
    assert __cpu_features__[env["numpy_simd"]]                  # a level this CPU runs
    m = json.loads((tiny_run / "metrics.json").read_text())
    for key in ("psnr", "ssim", "ssim_skimage", "lpips_vgg", "lpips_vgg_official", "lpips_alex",
                "n_gaussians", "n_init_points", "iterations", "train_seconds", "peak_rss_gb", "per_view"):
        assert key in m
    assert m["iterations"] == 20 and m["n_init_points"] == TINY_POINTS
    assert 0.01 < m["peak_rss_gb"] < 64
    assert len(m["per_view"]) == 2 and 5 < m["psnr"] < 60
    h = json.loads((tiny_run / "history.json").read_text())
    assert h["test_t"] == [9, 20] and len(h["train_psnr"]) == 20   # before each multiple, and T (TRN-07)
    g = refgs.io.read_gaussians_ply(tiny_run / "model.ply")
    assert len(g) == m["n_gaussians"]


def test_eval_reproduces_metrics(tiny_run, capsys):
    before = json.loads((tiny_run / "metrics.json").read_text())
    rc, out, err = run_cli(["eval", tiny_run, "--no-lpips"], capsys)
    assert rc == 0, err
    after = json.loads((tiny_run / "metrics.json").read_text())
    assert after["psnr"] == before["psnr"] and after["per_view"] == before["per_view"]
    assert "mean" in out


def test_render_command(tiny_run, capsys):
    rc, _, err = run_cli(["render", tiny_run, "--split", "train"], capsys)
    assert rc == 0, err
    assert listing(tiny_run / "renders" / "train") == ["v01.png", "v04.png", "v07.png"]


def test_out_exists(tiny_run, tiny_scene, capsys):
    rc, _, err = run_cli(tiny_args(tiny_scene, tiny_run), capsys)
    assert_one_line_error(rc, err, "--out", tiny_run)


def test_corrupt_model_and_checkpoint(tiny_run, tmp_path, capsys):
    bad = tmp_path / "model.ply"
    data = (tiny_run / "model.ply").read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    rc, _, err = run_cli(["eval", tiny_run, "--model", bad, "--quiet"], capsys)
    assert_one_line_error(rc, err, bad)
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    ck = run / "checkpoint.npz"
    ck.write_bytes(ck.read_bytes()[:1000])
    rc, _, err = run_cli(["train", "--resume", run], capsys)
    assert_one_line_error(rc, err, ck)


@pytest.mark.parametrize("extra", [
    ("--dtype", "float64", "--background", "white", "--loss-form", "blend", "--no-clamp"),
    ("--densify-preset", "original", "--background", "random", "--profile", "gsplat"),
])
def test_other_settings_run(tiny_scene, tmp_path, capsys, extra):
    out = tmp_path / "run"
    rc, _, err = run_cli(tiny_args(tiny_scene, out, 8, *extra), capsys)
    assert rc == 0, err
    arrays = np.load(out / "checkpoint.npz", allow_pickle=False)
    dtype = np.float64 if "float64" in extra else np.float32
    assert arrays["param/means"].dtype == dtype and arrays["adam/m/sh"].dtype == dtype
    settings = json.loads((out / "config.json").read_text())["settings"]
    for flag, value in zip(extra[::2], extra[1::2]):
        key = {"--dtype": "dtype", "--background": "background", "--loss-form": "loss_form",
               "--densify-preset": "densify_preset", "--profile": "profile"}.get(flag)
        if key:
            assert settings[key] == value
    if "original" in extra:
        assert settings["densify"]["until"] == 14          # given on the command line
        assert settings["densify"]["size_prune"] is True   # from the preset


def test_init_points_from_ply(tiny_scene, tmp_path, capsys):
    from refgs.data.pointcloud import write_ply

    rng = np.random.default_rng(0)
    cloud = write_ply(tmp_path / "cloud.ply", rng.uniform(-1, 1, (25, 3)), rng.uniform(0, 1, (25, 3)))
    args = tiny_args(tiny_scene, tmp_path / "run", 4)
    args[args.index("--init-points") + 1] = str(cloud)
    rc, _, err = run_cli(args, capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "run" / "config.json").read_text())["n_init_points"] == 25


def test_bench_on_a_saved_run(tiny_run, tmp_path, capsys):
    """``refgs bench --fern-run RUN``: the run's model.ply on its first test view (issue 7)."""
    pytest.importorskip("numba")
    rc, out, _ = run_cli(["bench", "--n", "--repeats", "1", "--backends",
                          "ref64", "fast32", "--fern-run", tiny_run, "--out", tmp_path, "--no-plots"],
                         capsys)
    assert rc == 0, out
    doc = json.loads((tmp_path / "bench.json").read_text())
    (run,) = doc["results"]                      # --n with no value: the run only
    assert "run at iteration 20 (v00.png)" in run["scene"] and run["error_reference"] == "ref64"
    assert run["backends"]["fast32"]["image_max_abs"] < 1e-5
