"""`python -m jaxmetrics.examples.ppo`: the command line (see `--help`)."""

import sys

from ._cli import main

if __name__ == "__main__":
    sys.exit(main())
