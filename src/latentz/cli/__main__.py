"""``python -m latentz.cli``: the command line."""

from latentz.cli.main import main

main()
