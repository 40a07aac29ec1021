"""``python -m jscratch.bench``: see `jscratch.bench.cli`."""

import sys

from jscratch.bench.cli import main

if __name__ == "__main__":
    sys.exit(main())
