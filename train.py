"""Entry point: ``python train.py [--config configs/X.yaml] [key=value ...]``; see ``--help``."""
from nsplat.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
