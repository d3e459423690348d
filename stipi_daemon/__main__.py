"""``python -m stipi_daemon`` runs the command-line interface."""

from stipi_daemon.cli import main

raise SystemExit(main())
