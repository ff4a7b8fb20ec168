"""``python -m camhealth.iopc --config configs/iopc.yaml`` (see :mod:`camhealth.iopc.cli`)."""

import sys

from camhealth._cli import run_cli
from camhealth.iopc.cli import main

if __name__ == "__main__":
    sys.exit(run_cli(main, "python -m camhealth.iopc"))
