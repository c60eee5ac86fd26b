"""``python -m nsplat.data fetch|prepare ...``: the ``nsplat data`` command (:mod:`nsplat.data.commands`)."""
import sys

from nsplat.data.commands import main

if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:], prog="python -m nsplat.data"))
