"""``python -m bench``: the benchmark suites (Table 1, roofline, scaling, clips) from the
checkout's root; options as bench/suites.py's (bench/README.md).

``python -m bench --suite e2e [OPTIONS]`` runs the whole-process suite (bench/e2e.py: its
own options and record, bench/results/e2e.json); it runs alone and is not part of ``all``
(about 25 minutes with the Blender anchor)."""
import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent
for folder in (HERE, HERE.parent):       # the bench modules, and the checkout's nrpose
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

ARGS = sys.argv[1:]
if ARGS[:2] == ["--suite", "e2e"] or ARGS[:1] == ["--suite=e2e"]:
    import e2e  # noqa: E402

    sys.exit(e2e.main(ARGS[1 if ARGS[0] == "--suite=e2e" else 2:], prog="python -m bench --suite e2e"))

import suites  # noqa: E402

sys.exit(suites.main(prog="python -m bench"))
