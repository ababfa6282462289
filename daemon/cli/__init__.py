"""The service-side sub-commands of run_trainer.py (daemon, enqueue, status, watch, ...): each
module has add_arguments(parser) and run(args) -> int, and none imports torch."""
