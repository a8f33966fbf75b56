"""`python -m quakescan.cli`, as the console script `quakescan`."""
import sys

from . import main

sys.exit(main())
