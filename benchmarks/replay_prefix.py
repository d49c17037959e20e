"""Does the code on the path still train what a record says?  Replays a record's first iterations.

    python benchmarks/replay_prefix.py RECORD [RECORD ...] [--iters 1600]

For each record folder (``refgs record``: its ``config.json`` settings and rounded
``history.json``) a new run with the same settings is trained, in a temporary folder, for the
first ``--iters`` iterations with the refgs found on the path, and its per-iteration training
loss (rounded as the record rounds it) and Gaussian count are compared with the record's.
Training is chaotic: any change of the arithmetic on the path (a summation order, a rounding, a
random draw) moves the loss within a few iterations and the densification counts soon after, so
equal histories over the first densification steps and the first FM re-initialisation (500..1600)
say that the recorded run was made by code that computes what this code computes.  Used to show
that campaign records made while unrelated files changed (demo, docs, analysis) came from the same
training code.  Prints one line per record; exit status 1 if any differs.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

#: default number of iterations replayed: past the first densification steps (from 500, every 100)
#: and FM's first re-initialisation with its frozen window (1000..1100)
DEFAULT_ITERS = 1600


class _Enough(Exception):
    """Raised from the training callback once the prefix has been trained."""


def replay(record: Path, iters: int) -> str | None:
    """None when the first ``iters`` iterations agree with the record, else the first difference."""
    from refgs import runs
    from refgs.train.trainer import TrainConfig

    settings = json.loads((record / "config.json").read_text())["settings"]
    history = json.loads((record / "history.json").read_text())
    decimals = json.loads((record / "record.json").read_text())["history_decimals"]["train_loss"]
    got = {}

    def callback(trainer, _stop):
        got[trainer.t] = (round(float(trainer.history["train_loss"][-1]), decimals), trainer.n)
        if trainer.t >= iters:
            raise _Enough

    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            runs.train(TrainConfig.from_dict(settings), Path(tmp) / "run", progress=False,
                       callback=callback)
        except _Enough:
            pass
    for t, loss, n in zip(history["train_t"], history["train_loss"], history["n_gaussians"]):
        if t > iters:
            break
        if got.get(t) != (loss, n):
            return f"iteration {t}: loss {got.get(t, (None,))[0]} vs {loss}, " \
                   f"Gaussians {got.get(t, (None, None))[1]} vs {n}"
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("records", type=Path, nargs="+", help="record folders (results/records/<id>)")
    ap.add_argument("--iters", type=int, default=DEFAULT_ITERS, help="iterations to replay")
    args = ap.parse_args()
    bad = 0
    for rec in args.records:
        diff = replay(rec, args.iters)
        bad += diff is not None
        print(f"{rec.name}: {'same' if diff is None else 'DIFFERS at ' + diff} "
              f"(iterations 1..{args.iters})", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
