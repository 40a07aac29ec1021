"""``python -m jscratch.bench``: see `jscratch.bench.cli`."""

from jscratch.bench.cli import main

if __name__ == "__main__":
    main()
