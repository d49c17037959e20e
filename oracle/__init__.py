"""oracle: conformance testing of any 3DGS backend against refgs (the executable spec).

    python -m oracle check --backend module:object [--clause RAS-05] [--max-examples 20]
                           [--seed 0] [--report DIR] [--timeout 300] [--memory-limit 8192]
    python -m oracle list-clauses
    python -m oracle replay DIR/failures/<check>.npz --backend module:object
    python -m oracle check --backend NAME --diagnose    # + the named deviations that explain failures
    python -m oracle diagnose --backend NAME            # the diagnosis alone (docs/spec/deviations.md)
    python -m oracle matrix [--backend NAME ...]        # one column per backend (docs/conformance.md)

A backend is any importable object with ``render(gaussians, camera, config)`` and the capability
attributes ``profile`` and ``dtype`` (oracle/protocol.py; template: oracle/adapters/template.py).
Every check cites the spec clauses it tests (oracle/checks.py); the oracle's own rules are
docs/spec/oracle.md (ORC-xx); the user guide is docs/oracle.md.

The backend runs in a worker process (isolation, worker, wire): a hang, a crash or runaway
memory is a verdict, never the end of the run.

Modules: protocol (backend, Case), clauses (spec headings), tolerances (the one table), ties
(near-tie analysis), compare (assertion helpers), strategies and hard_cases (cases), evaluate
and checks (what is compared), isolation / worker / wire (the backend's process), runner,
blame (which clauses a failure is evidence against), known (known differences), shrink, report,
html and pictures (the page), calibrate, explain / diagnose / triage (which named deviations
explain the failures), matrix, adapters/, meta/ (planted-bug, hostile and deviant backends).
Importing the oracle needs the core dependencies only (numpy, scipy, hypothesis; matplotlib for
the pictures).
"""
__version__ = "0.1.0"
