"""`python -m rangeret.cli`: the `rangeret` command."""

import sys

from rangeret.cli.main import main

sys.exit(main())
