"""``python -m pipeline``: the command line (:mod:`pipeline.cli`)."""

from .cli import main

if __name__ == "__main__":
    main(prog_name="pipeline")
