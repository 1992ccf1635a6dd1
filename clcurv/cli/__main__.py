"""``python -m clcurv.cli``: the ``clcurv`` command."""
import sys

from clcurv.cli.main import main

sys.exit(main())
