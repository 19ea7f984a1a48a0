"""``python -m swarmpc`` runs the command line."""

from swarmpc.cli import main

main()
