"""``python -m camhealth.iopc --config configs/iopc.yaml`` (see :mod:`camhealth.iopc.cli`)."""

from camhealth.iopc.cli import main

if __name__ == "__main__":
    main()
