"""``refgs train`` without ``--backend`` trains on the fastest backend that loads here and says so
(refgs.backends.default_backend: fast when numba imports, else the reference); the run records
the name, so a record made with either default means what it says."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from refgs.backends import TRAIN_PREFERENCE, default_backend
from refgs.cli import build_parser, config_from_args, main

ROOT = Path(__file__).resolve().parents[1]
FERN = ROOT.parent / "shared" / "data" / "fern"
#: what this machine should pick
EXPECTED = "fast" if importlib.util.find_spec("numba") is not None else "reference"


def test_default_backend_is_the_fastest_that_loads():
    assert TRAIN_PREFERENCE[0] == "fast" and TRAIN_PREFERENCE[-1] == "reference"
    assert default_backend() == EXPECTED


def test_an_explicit_backend_is_kept():
    argv = ["train", "--scene", "s", "--views", "3", "--iters", "2", "--out", "o"]
    assert config_from_args(build_parser().parse_args(argv)).backend == EXPECTED
    ref = config_from_args(build_parser().parse_args(argv + ["--backend", "reference"]))
    assert ref.backend == "reference"


@pytest.mark.skipif(not (FERN / "sparse").is_dir(), reason="needs ../shared/data/fern")
def test_train_without_backend_prints_and_records_it(tmp_path, capsys):
    run = tmp_path / "run"
    rc = main(["train", "--scene", str(FERN), "--views", "3", "--iters", "2", "--resolution", "8",
               "--no-lpips", "--eval-every", "0", "--checkpoint-every", "0", "--out", str(run)])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert f"backend: {EXPECTED} (the fastest that loads here" in out, out
    settings = json.loads((run / "config.json").read_text())["settings"]
    assert settings["backend"] == EXPECTED
