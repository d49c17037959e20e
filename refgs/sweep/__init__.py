"""Grids of training runs that survive a kill, on a local process pool or a Ray cluster
(docs/sweeps.md).

    options.py     the options of ``refgs train`` (one table for the CLI and for grid files)
    grid.py        grid files (TOML): axes, groups, run names -> GridRun(index, name, cfg)
    state.py       the filesystem's view: run states, run locks, the manifest DIR/sweep.json
    execute.py     one run in this process (``refgs run-one``, a worker, a Ray task)
    executors.py   the sweep: the local process pool and Ray, progress, the closing report
    command.py     ``refgs sweep`` and ``refgs run-one``

The unit is the run directory (refgs.runs): a sweep reads and writes runs only through it.
"""
