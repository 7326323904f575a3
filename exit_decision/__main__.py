"""``python -m exit_decision``: the ``exit-decision`` command line (``exit_decision.cli``)."""
from exit_decision.cli import main

raise SystemExit(main())
