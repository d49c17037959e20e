"""Peak memory of training at a run's final size (docs/performance.md, "Training").

    NUMBA_NUM_THREADS=1 python benchmarks/train_memory.py RUN_DIR [--from 9400] [--steps 101]

Loads the run's checkpoint (refgs train's own restore), sets the iteration counter to ``--from``
(so that densification and the method's hooks are active), trains ``--steps`` iterations -- 101
from 9400 include a densification step -- and writes one checkpoint to a temporary file, then
prints the Gaussian count and the process's peak resident memory.  The run directory is not
changed.  (Runs record their own ``peak_rss_gb`` in metrics.json; this measures runs made
before that.)
"""
from __future__ import annotations

import argparse
import tempfile
import warnings
from pathlib import Path

from refgs.runs import load
from refgs.train.checkpoint import peak_rss_gb, save_checkpoint


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--from", dest="start", type=int, default=9400)
    ap.add_argument("--steps", type=int, default=101)
    args = ap.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trainer = load(args.run).trainer
    trainer.t = args.start
    for _ in range(args.steps):
        trainer.step()
    with tempfile.TemporaryDirectory() as tmp:
        save_checkpoint(Path(tmp) / "probe.npz", trainer.state_arrays(), trainer.state_meta())
    print(f"{args.run}: {trainer.n} Gaussians after {args.steps} iterations from {args.start}; "
          f"peak RSS {peak_rss_gb():.2f} GB")


if __name__ == "__main__":
    main()
