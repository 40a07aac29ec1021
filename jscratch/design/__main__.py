"""``python -m jscratch.design``: see `jscratch.design.cli`."""

import os
import sys

from jscratch.design.cli import main

if __name__ == "__main__":
    code = main()
    if code == 130:  # interrupted: leave at once, without tearing down the compiler and kernel
        sys.stdout.flush()  # threads still at work (the checkpoint on disk is whole: it is
        sys.stderr.flush()  # written to a temporary file and renamed)
        os._exit(code)
    sys.exit(code)
