"""``python -m simt_sim`` is the ``simt-sim`` command."""

from simt_sim.cli import main

raise SystemExit(main())
