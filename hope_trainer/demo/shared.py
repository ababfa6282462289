"""What the demo's steps share: the chain's components, their timeouts, the two ways the demo stops
early (Interrupted, DemoError) and `say`, its one way to print a line."""
from __future__ import annotations

from hope_models.components import COMPONENTS as TABLE
from hope_trainer.console import say as say  # the demo's one way to print a line, written whole

COMPONENTS = tuple(TABLE)  # the chain: every component, in the table's (training) order
DEMO_SEED = 100000  # sim-demos' default; evaluation uses seeds 0..N-1, so the two never overlap
GATE_WAIT_S = 900.0  # a promote child: validation batches and, for the fast_loop, reflex episodes
SERVE_WAIT_S = 60.0  # BrainService notices a pointer within a second; loading takes well under one
CLOSURE_WAIT_S = 5.0  # the loop-closure record is written beside the first answer, on its own thread
PLAIN_EVERY_S = 5.0  # progress lines when the output is not a terminal (a log, CI)


class Interrupted(Exception):
    """Ctrl-C (or SIGTERM) before the summary."""


class DemoError(Exception):
    """The demo cannot go on; the message says why."""
