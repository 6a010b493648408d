"""`python -m openfly_agent.hub ...` (see cli.py)."""

import sys

from openfly_agent.hub.cli import main

if __name__ == "__main__":
    sys.exit(main())
