"""``python -m bench``: the benchmark suites (Table 1, roofline, scaling, clips) from the
checkout's root; options as bench/suites.py's (bench/README.md)."""
import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent
for folder in (HERE, HERE.parent):       # the bench modules, and the checkout's nrpose
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

import suites  # noqa: E402

sys.exit(suites.main(prog="python -m bench"))
