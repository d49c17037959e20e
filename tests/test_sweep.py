"""refgs sweep / run-one (refgs/sweep, docs/sweeps.md): grid files, run names, failures that stay
with their run, refusal of changed settings, and resume after kill -9 with byte-identical results
(local process pool and Ray)."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from refgs import runs
from refgs.cli import build_parser, config_from_args, main
from refgs.errors import ConfigError
from refgs.sweep.grid import load_grid
from refgs.sweep.state import MANIFEST_FILE

ROOT = Path(__file__).resolve().parents[1]
FERN = ROOT.parent / "shared" / "data" / "fern"
needs_fern = pytest.mark.skipif(not (FERN / "sparse").is_dir(), reason="needs ../shared/data/fern")

#: A tiny run (seconds): fern at 1/8 of images_8, 2 iterations, the reference backend (named:
#: a grid without backend gets the fastest that loads, refgs.backends.default_backend).
TINY = dict(views=3, iters=2, resolution=8, no_lpips=True, checkpoint_every=1, eval_every=0,
            backend="reference")
#: The kill test's runs: 2 methods x 2 seeds, a few seconds each (fern at 1/8 of images_8, 40
#: iterations), a checkpoint every 5 iterations, the fast backend.
KILL_GRID = f"""scene = "{FERN}"
views = 3
iters = 40
checkpoint_every = 5
no_lpips = true
backend = "fast"
resolution = 8
method = ["3dgs", "fm"]
seed = [0, 1]
"""


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return str(v)


def write_grid(path: Path, top: dict, groups: list | None = None) -> Path:
    lines = [f"{k} = {toml_value(v)}" for k, v in top.items()]
    for g in groups or []:
        lines += ["", "[[group]]"] + [f"{k} = {toml_value(v)}" for k, v in g.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def tree_hashes(folder: Path) -> dict:
    """sha256 of every file under ``folder`` (relative path -> hex)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def run_dirs(out: Path) -> list[Path]:
    return sorted(d for d in out.iterdir() if d.is_dir() and not d.name.startswith("."))


def manifest(out: Path) -> dict:
    return json.loads((out / MANIFEST_FILE).read_text())["runs"]


def refgs(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "refgs", *map(str, args)], capture_output=True,
                          text=True, cwd=ROOT, timeout=600, **kw)


# --- grid files ----------------------------------------------------------------------------------
def test_grid_axes_groups_names_and_paths(tmp_path):
    (tmp_path / "data" / "fern").mkdir(parents=True)
    (tmp_path / "exp").mkdir()
    grid = write_grid(tmp_path / "exp" / "g.toml",
                      {"iters": 10, "method": ["3dgs", "fm"], "seed": [0, 1], "fm-gamma": 1.5},
                      [{"scene": "../data/fern", "views": 3}])
    with pytest.raises(ConfigError, match="g.toml: group 1: --fm-.*flat-minima options need"):
        load_grid(grid)                                    # as refgs train: --fm-gamma needs fm
    grid = write_grid(grid, {"iters": 10, "method": ["3dgs", "fm"], "seed": [0, 1]},
                      [{"scene": "../data/fern", "views": 3},
                       {"scene": "../data/fern", "views": [6, 9], "seed": 2, "no_lpips": True}])
    g = load_grid(grid)
    names = [r.name for r in g.runs]
    assert names == ["fern_v3_3dgs_s0", "fern_v3_3dgs_s1", "fern_v3_fm_s0", "fern_v3_fm_s1",
                     "fern_v6_3dgs_s2", "fern_v6_fm_s2", "fern_v9_3dgs_s2", "fern_v9_fm_s2"]
    assert [r.index for r in g.runs] == list(range(8))
    assert all(r.cfg.scene == str(tmp_path / "data" / "fern") for r in g.runs)
    assert [r.cfg.lpips for r in g.runs] == [True] * 4 + [False] * 4
    # names are stable when the grid grows: another seed and another axis value
    grown = write_grid(tmp_path / "exp" / "g2.toml",
                       {"iters": 10, "method": ["3dgs", "fm", "dropgaussian"], "seed": [0, 1, 5]},
                       [{"scene": "../data/fern", "views": 3},
                        {"scene": "../data/fern", "views": [6, 9], "seed": 2, "no_lpips": True}])
    assert set(names) <= {r.name for r in load_grid(grown).runs}
    # the same options through `refgs train` give the same settings hash (the same config)
    args = build_parser().parse_args(["train", "--scene", str(tmp_path / "data" / "fern"),
                                      "--views", "6", "--iters", "10", "--method", "fm",
                                      "--seed", "2", "--no-lpips", "--out", "x"])
    cfg = runs.absolute_paths(config_from_args(args))
    assert runs.settings_hash(cfg.to_dict()) == g.find(name="fern_v6_fm_s2").settings_hash


def test_grid_name_clashes_and_duplicates(tmp_path):
    grid = write_grid(tmp_path / "g.toml", {"scene": "fern", "views": 3},
                      [{"iters": 10}, {"iters": 20}, {"iters": 10}])   # the third = the first
    g = load_grid(grid)
    assert [r.name for r in g.runs] == ["fern_v3_3dgs_iters10_s0", "fern_v3_3dgs_iters20_s0"]
    g = load_grid(write_grid(tmp_path / "h.toml", {"scene": "fern", "views": 3, "iters": 5,
                                                   "fm": [False, True], "method": "dropgaussian",
                                                   "drop-r-max": [0.2, 0.3]}))
    assert [r.name for r in g.runs] == [
        "fern_v3_dropgaussian_drop-r-max0.2_s0", "fern_v3_dropgaussian_drop-r-max0.3_s0",
        "fern_v3_dropgaussian_drop-r-max0.2_fm_s0", "fern_v3_dropgaussian_drop-r-max0.3_fm_s0"]
    assert g.runs[2].cfg.method_params["fm"] is True and g.runs[3].cfg.method_params["r_max"] == 0.3


@pytest.mark.parametrize("text, key", [
    ('scene = "fern"\nviews = 3\niters = 10\nitres = 5\n', "itres"),               # unknown key
    ('scene = "fern"\nviews = 3\niters = "ten"\n', "iters"),                      # bad type
    ('scene = "fern"\nviews = 3\niters = 10\nmethod = ["fm", "nerf"]\n', "method"),  # bad choice
    ('scene = "fern"\nviews = 3\niters = 10\nno_lpips = 1\n', "no_lpips"),        # flag, not bool
    ('scene = "fern"\nviews = 3\niters = 10\nbackend = "cuda"\n', "backend"),     # no backend
    ('scene = "fern"\nviews = 0\niters = 10\n', "--views"),                       # validated
    ('scene = "fern"\nviews = 3\niters = 10\nseed = []\n', "seed"),               # empty axis
    ('scene = "fern"\nviews = 3\niters = 10\nout = "x"\n', "out"),                # not a setting
    ('views = 3\niters = 10\n', "scene"),                                         # missing
    ('scene = "fern"\nviews = 3\niters = 10\n[[group]]\nseeds = 1\n', "seeds"),   # in a group
    ('', "empty grid"),
    ('# nothing\n[[group]]\n', "empty grid"),
    ('scene = "fern\n', "not valid TOML"),
])
def test_grid_errors_are_one_line_naming_key_and_file(tmp_path, capsys, text, key):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_grid(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and key in message, message
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--list"]) == 2
    stderr = capsys.readouterr().err
    assert stderr.count("\n") == 1 and stderr.startswith("refgs: error: ") and key in stderr
    assert not (tmp_path / "out").exists()                 # nothing ran, nothing written


def test_grid_file_missing(tmp_path):
    with pytest.raises(ConfigError, match="grid file not found"):
        load_grid(tmp_path / "none.toml")


def test_committed_grids_parse():
    main_grid = load_grid(ROOT / "experiments" / "paper_main.toml")
    assert len(main_grid.runs) == 36
    assert {(Path(r.cfg.scene).name, r.cfg.views) for r in main_grid.runs} == {
        ("fern", 3), ("desk", 3), ("bonsai", 12), ("cup", 12)}
    assert {r.cfg.method for r in main_grid.runs} == {"3dgs", "dropgaussian", "fm"}
    assert all(r.cfg.iters == 10000 and r.cfg.backend == "fast" and r.cfg.checkpoint_every == 500
               and r.cfg.images == "images_8" for r in main_grid.runs)
    assert main_grid.runs[0].cfg.scene == str(ROOT.parent / "shared" / "data" / "fern")
    views = load_grid(ROOT / "experiments" / "llff_views.toml")
    assert {r.cfg.views for r in views.runs} == {3, 6, 9} and len(views.runs) == 27
    follow = load_grid(ROOT / "experiments" / "paper_followups.toml")
    ablations = {r.name: r.cfg.method_params for r in follow.runs if r.cfg.views == 3}
    assert sorted(ablations) == [f"fern_v3_fm_fm-no-{a}_s{s}" for a in ("reinit", "schedule")
                                 for s in range(3)]
    assert all(not p["reinit"] and p["schedule"] for n, p in ablations.items() if "reinit" in n)
    assert all(p["reinit"] and not p["schedule"] for n, p in ablations.items() if "schedule" in n)
    assert len(follow.runs) == 24 and {r.cfg.views for r in follow.runs} == {3, 6, 9}
    assert all(r.cfg.iters == 10000 and r.cfg.backend == "fast" and r.cfg.images == "images_8"
               for r in follow.runs)


# --- a sweep with a bad scene -------------------------------------------------------------------
@needs_fern
def test_bad_scene_fails_alone_and_changed_settings_are_refused(tmp_path, capsys):
    out = tmp_path / "out"
    grid = write_grid(tmp_path / "g.toml", TINY,
                      [{"scene": str(FERN)}, {"scene": str(tmp_path / "nowhere")}])
    out.mkdir()
    leftover = out / f".fern_v3_3dgs_s0{runs.PARTIAL_TAG}killed"   # as a kill -9 leaves it
    leftover.mkdir()
    (leftover / "checkpoint.npz").write_bytes(b"half")
    r = refgs("sweep", grid, "--out", out, "--workers", "2", "--quiet")
    assert r.returncode == 1, r.stdout + r.stderr
    runs_ = manifest(out)
    assert runs_["fern_v3_3dgs_s0"]["state"] == "done"
    bad = runs_["nowhere_v3_3dgs_s0"]
    assert bad["state"] == "failed" and "\n" not in bad["error"]
    assert "SceneError" in bad["error"] and "nowhere" in bad["error"]
    assert "failed   nowhere_v3_3dgs_s0: SceneError" in r.stdout and "--retry-failed" in r.stdout
    assert not leftover.exists() and [d.name for d in run_dirs(out)] == ["fern_v3_3dgs_s0"]
    done = tree_hashes(out / "fern_v3_3dgs_s0")
    assert "metrics.json" in done and "model.ply" in done

    # again: the done run is skipped, the failed one not retried; --retry-failed retries it
    with pytest.raises(SystemExit) as code:
        main(["sweep", str(grid), "--out", str(out), "--quiet"])
    assert code.value.code == 1 and manifest(out)["nowhere_v3_3dgs_s0"]["attempts"] == 1
    with pytest.raises(SystemExit):
        main(["sweep", str(grid), "--out", str(out), "--quiet", "--retry-failed"])
    assert manifest(out)["nowhere_v3_3dgs_s0"]["attempts"] == 2
    assert main(["run-one", str(grid), "--out", str(out), "--index", "0", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["sweep", str(grid), "--out", str(out), "--list"]) == 0
    assert capsys.readouterr().out.split() == ["0", "fern_v3_3dgs_s0", "done",
                                               "1", "nowhere_v3_3dgs_s0", "failed"]

    # the grid changes a setting of the done run: refused with a message, not overwritten
    write_grid(grid, dict(TINY, iters=3), [{"scene": str(FERN)}])
    assert main(["sweep", str(grid), "--out", str(out), "--dry-run"]) == 0
    assert "refuse: " in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["sweep", str(grid), "--out", str(out), "--quiet"])
    entry = manifest(out)["fern_v3_3dgs_s0"]
    assert entry["state"] == "failed" and "other settings" in entry["error"]
    with pytest.raises(SystemExit) as code:
        main(["run-one", str(grid), "--out", str(out), "--index", "0", "--quiet"])
    assert code.value.code == 1 and "other settings" in capsys.readouterr().err
    assert tree_hashes(out / "fern_v3_3dgs_s0") == done


# --- kill -9 and resume ---------------------------------------------------------------------------
def kill_during(cmd: list, out: Path, env: dict | None = None) -> None:
    """Start ``cmd`` in its own process group and kill -9 the whole group as soon as one run is
    done and another is in its training loop past a checkpoint (published, no model.ply yet)."""
    p = subprocess.Popen(cmd, cwd=ROOT, start_new_session=True, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, env=env)
    try:
        deadline = time.monotonic() + 300
        while p.poll() is None and time.monotonic() < deadline:
            dirs = run_dirs(out) if out.is_dir() else []
            done = [d for d in dirs if (d / runs.METRICS_FILE).is_file()]
            if done and any(not (d / runs.MODEL_FILE).exists() for d in dirs):
                break
            time.sleep(0.02)
        assert p.poll() is None, "the sweep ended before it could be killed"
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The kill grid swept without interruption: one worker with 2 threads."""
    tmp = tmp_path_factory.mktemp("uninterrupted")
    grid = tmp / "kill.toml"
    grid.write_text(KILL_GRID)
    r = refgs("sweep", grid, "--out", tmp / "out", "--workers", "1", "--threads-per-run", "2",
              "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    models = {d.name: tree_hashes(d)["model.ply"] for d in run_dirs(tmp / "out")}
    print("uninterrupted:", {name: h[:16] for name, h in models.items()})
    return models


def check_kill_and_resume(tmp_path, uninterrupted, executor: str):
    grid = tmp_path / "kill.toml"
    grid.write_text(KILL_GRID)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "refgs", "sweep", str(grid), "--out", str(out), "--workers", "2",
           "--executor", executor, "--quiet"]
    kill_during(cmd, out)
    finished = {d.name: tree_hashes(d) for d in run_dirs(out) if (d / runs.METRICS_FILE).is_file()}
    in_flight = [d.name for d in run_dirs(out) if d.name not in finished]
    print(f"{executor}: killed with {sorted(finished)} done and {in_flight} in flight")
    assert finished and in_flight
    r = refgs("sweep", grid, "--out", out, "--workers", "2", "--executor", executor, "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    after = {d.name: tree_hashes(d) for d in run_dirs(out)}
    for name, files in sorted(after.items()):
        resumes = json.loads((out / name / runs.CONFIG_FILE).read_text())["resumes"]
        how = ("finished before the kill" if name in finished else
               f"in flight, resumed at iteration {resumes[0]['from_iteration']}" if resumes else
               "in flight, its last outputs written again" if name in in_flight else
               "not started before the kill")
        print(f"  {name}: model.ply {files['model.ply'][:16]} ({how})")
    assert all(after[name] == files for name, files in finished.items())   # not a byte changed
    assert {name: files["model.ply"] for name, files in after.items()} == uninterrupted
    assert all(e["state"] == "done" for e in manifest(out).values())
    assert not list(out.glob(f".*{runs.PARTIAL_TAG}*"))


@needs_fern
def test_kill9_local_sweep_resumes_to_identical_models(tmp_path, uninterrupted):
    check_kill_and_resume(tmp_path, uninterrupted, "local")


@pytest.mark.slow
@needs_fern
def test_kill9_ray_sweep_resumes_to_identical_models(tmp_path, uninterrupted):
    pytest.importorskip("ray", reason="the ray executor needs ray (pip install 'refgs[ray]')")
    check_kill_and_resume(tmp_path, uninterrupted, "ray")


@pytest.mark.slow
@needs_fern
def test_killed_worker_fails_alone_and_retry_resumes_it(tmp_path, uninterrupted):
    grid = tmp_path / "kill.toml"
    grid.write_text(KILL_GRID)
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "refgs", "sweep", str(grid), "--out", str(out),
                          "--workers", "2", "--quiet"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    victim = None
    while victim is None and p.poll() is None:              # a run past its first checkpoint
        if (out / MANIFEST_FILE).is_file():
            for name, e in manifest(out).items():
                if e["state"] == "running" and (out / name / runs.CHECKPOINT_FILE).is_file():
                    victim = name, e["pid"]
        time.sleep(0.02)
    assert victim is not None, p.communicate()[0]
    os.kill(victim[1], signal.SIGKILL)
    stdout = p.communicate(timeout=600)[0]
    assert p.returncode == 1, stdout
    states = {n: e["state"] for n, e in manifest(out).items()}
    assert states.pop(victim[0]) == "failed" and set(states.values()) == {"done"}
    assert "killed by signal 9" in manifest(out)[victim[0]]["error"]
    r = refgs("sweep", grid, "--out", out, "--retry-failed", "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    assert {d.name: tree_hashes(d)["model.ply"] for d in run_dirs(out)} == uninterrupted
