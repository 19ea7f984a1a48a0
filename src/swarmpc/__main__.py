"""``python -m swarmpc`` runs the command line."""

from swarmpc._launch import main

main()
