"""oracle: conformance testing of any 3DGS backend against refgs (the executable spec).

    python -m oracle check --backend module:object [--clause RAS-05] [--max-examples 20]
                           [--seed 0] [--report DIR]
    python -m oracle list-clauses
    python -m oracle replay DIR/failures/<check>.npz --backend module:object

A backend is any importable object with ``render(gaussians, camera, config)`` and the capability
attributes ``profile`` and ``dtype`` (oracle/protocol.py; template: oracle/adapters/template.py).
Every check cites the spec clauses it tests (oracle/checks.py); the oracle's own rules are
docs/spec/oracle.md (ORC-xx); the user guide is docs/oracle.md.

Modules: protocol (backend, Scene), clauses (spec headings), tolerances (the one table), ties
(near-tie analysis), compare (assertion helpers), strategies and hard_cases (scenes), evaluate
and checks (what is compared), runner, shrink, report, adapters/, meta/ (planted-bug backends).
Importing the oracle needs the core dependencies only (numpy, scipy, hypothesis).
"""
__version__ = "0.1.0"
