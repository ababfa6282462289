"""`run_trainer.py resume RUN [--json]`: see daemon/cli/control.py."""
from daemon.cli.control import make

add_arguments, run = make("resume")
