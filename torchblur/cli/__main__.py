"""``python -m torchblur.cli <command> ...``: the ``torchblur`` command (:func:`torchblur.cli.main`)."""
import sys

from torchblur.cli import main

sys.exit(main())
