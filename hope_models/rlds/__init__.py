"""Reading, validating and writing Continuon RLDS episodes in every layout the producers write."""
