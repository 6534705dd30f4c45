"""``python -m jaxtalk`` runs the command line."""

from jaxtalk.cli import main

main()
