"""Feature specs, the memory-mapped dataset cache, time-based windows and the resumable sampler."""
