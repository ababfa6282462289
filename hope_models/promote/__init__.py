"""Promotion: the gate a candidate checkpoint must pass (gate.py, needs torch) and the pointer
files that say which checkpoint each component serves (pointers.py, torch-free).

Import the submodules directly; this package imports nothing, so the webapp and the daemon can
read pointers without paying for torch.
"""
