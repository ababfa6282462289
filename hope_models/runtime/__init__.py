"""Inference-side runtime pieces: the reflex policy (a fast_loop stepped once per control tick)."""
