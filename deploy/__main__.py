"""python -m deploy: the robot side's command line (deploy/cli.py)."""
import sys

from deploy.cli import main

sys.exit(main())
