"""The run registry: the SQLite engine and tables, the run state machine, what a run request may
say, the Celery broker both sides use (task name, URL, JSON only, the embedded transport), and the
report/control protocol a worker's child speaks about its run.

The daemon (which dispatches runs) and the workers (which train them) both stand on this layer;
neither imports the other. Torch-free.
"""
