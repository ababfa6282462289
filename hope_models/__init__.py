"""HOPE seed model library: RLDS I/O, features and windows, models, trainer, runtime, sim.

Imports nothing from daemon, workers or webapp (dependencies point one way).
"""
__version__ = "0.1.0"
