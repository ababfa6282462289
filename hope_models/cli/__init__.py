"""Sub-commands of run_trainer.py that need only hope_models."""
