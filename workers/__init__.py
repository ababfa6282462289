"""The Celery app and the one training task (see docs/architecture.md)."""
