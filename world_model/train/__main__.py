"""``python -m world_model.train``: the training command line (:mod:`world_model.train.cli`)."""

import sys

from world_model.train.cli import main

if __name__ == "__main__":
    sys.exit(main())
