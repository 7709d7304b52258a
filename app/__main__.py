import sys

from app.cli import main

if __name__ == "__main__":  # not when the engine process (spawned) imports this module again
    sys.exit(main())
