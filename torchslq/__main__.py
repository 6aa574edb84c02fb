"""``python -m torchslq``: the ``torchslq`` command (:mod:`torchslq.cli`)."""

from .cli import main

raise SystemExit(main())
