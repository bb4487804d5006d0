"""`python -m glaciar`: the command line (:mod:`glaciar.cli`)."""
import sys

from .cli import main

sys.exit(main())
