"""Backends for testing the oracle itself (ORC-10): refgs with one planted defect each.

See oracle/meta/planted.py; tests/test_oracle_meta.py runs the oracle on every one of them and
requires the clause of its defect to fail, and runs it on refgs (float64 and float32) requiring
every clause to pass.  The diagnosis' own meta-tests (DEV-02, DEV-03): refgs with named
deviations on (deviant.py), many at once and with defects the catalogue does not name
(many.py, offcatalogue.py).
"""
