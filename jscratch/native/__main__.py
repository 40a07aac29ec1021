"""``python -m jscratch.native``: what the native kernel is, where it lives, whether it is in use
(`jscratch.native.main`)."""

import sys

from jscratch.native import main

if __name__ == "__main__":
    sys.exit(main())
