"""Promotion: the gate a candidate checkpoint must pass (gate.py, needs torch) and the torch reflex
policy its sim check drives (reflex_policy.py). The pointer files that say which checkpoint each
component serves are hope_models/promoted.py, below this package, because the runtime reads them.

Import the submodules directly; this package imports nothing, so importing it costs no torch.
"""
