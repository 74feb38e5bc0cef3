"""``python -m latentz.cli``: the command line."""

from latentz.cli.main import main

if __name__ == "__main__":
    main()
