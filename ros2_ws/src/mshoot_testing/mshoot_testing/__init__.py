"""
mshoot_testing: test support, not a production package.

Fault injection at the controller's seams (:mod:`mshoot_testing.faults`) and an
in-process closed loop to poke at (:mod:`mshoot_testing.harness`), used by the
test suite and the soak benchmark (``bench/soak.py``). Nothing in
``mshoot_core`` or ``mshoot_nodes`` imports it.
"""
