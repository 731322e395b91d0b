"""``python -m canbrake ...``: the same as the ``canbrake`` console script."""
import sys

from canbrake.cli import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
