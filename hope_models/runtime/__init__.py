"""The torch-free serving side: BrainService (brain_service.py) and the NumPy fast_loop it runs
(fast_loop_numpy.py; what it accepts as a checkpoint: fast_loop_checkpoint.py)."""
