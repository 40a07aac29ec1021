"""``python -m jscratch.design``: see `jscratch.design.cli`."""

import sys

from jscratch.design.cli import main

if __name__ == "__main__":
    sys.exit(main())
