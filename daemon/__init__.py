"""The supervisor: run registry, queue policy, monitors, event push, recovery (see docs/architecture.md)."""
