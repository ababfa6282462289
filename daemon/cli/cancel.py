"""`run_trainer.py cancel RUN [--json]`: see daemon/cli/control.py."""
from daemon.cli.control import make

add_arguments, run = make("cancel")
