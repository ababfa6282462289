"""`python -m hope_trainer ...`: the same as the `hope-trainer` console script."""
import sys

from hope_trainer.cli import main

if __name__ == "__main__":
    sys.exit(main())
