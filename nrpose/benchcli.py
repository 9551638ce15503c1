"""``nrpose bench``: the benchmark suites of bench/ (Table 1, roofline, scaling, clips).

    nrpose bench [--suite table1|scaling|clips|roofline|all] [--repeat N] [--quick]
                 [--json OUT.json] [--png PLOT.png] [--data DIR]

The suites live in the project's ``bench/`` folder (next to this package in a
checkout or an editable install); they are not part of the wheel. Wiring into
``nrpose.cli``::

    from .benchcli import add_bench_parser
    add_bench_parser(subparsers)          # sets func=cmd_bench on the sub-parser
"""
from __future__ import annotations

import argparse
import importlib.util
import pathlib
import sys

from .errors import InputError

SUITES = ("table1", "roofline", "scaling", "clips")


def bench_dir() -> pathlib.Path:
    """The project's bench/ folder; InputError when this is not a checkout."""
    d = pathlib.Path(__file__).resolve().parent.parent / "bench"
    if not (d / "suites.py").is_file():
        raise InputError(f"{d}/suites.py not found: `nrpose bench` needs the project checkout "
                         "(the benchmarks are not installed with the package)")
    return d


def _suites_module():
    d = bench_dir()
    if str(d) not in sys.path:
        sys.path.insert(0, str(d))
    name = "nrpose_bench_suites"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, d / "suites.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def add_bench_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``bench`` sub-command (options as in bench/README.md)."""
    root = pathlib.Path(__file__).resolve().parent.parent
    p = subparsers.add_parser("bench", help="benchmark suites: Table 1, roofline, scaling, clips",
                              description="Run the benchmark suites of bench/ and write one JSON "
                                          "document and one PNG (schema in bench/README.md).")
    p.add_argument("--suite", action="append", choices=SUITES + ("all",),
                   help="suite to run (repeatable; default all)")
    p.add_argument("--repeat", type=int, default=5, help="timing rounds (default 5)")
    p.add_argument("--quick", action="store_true", help="tiny sizes, seconds; timings mean nothing")
    p.add_argument("--json", default=str(root / "bench" / "results" / "suites.json"), help="output JSON")
    p.add_argument("--png", default=str(root / "bench" / "results" / "suites.png"), help="output PNG ('' skips)")
    p.add_argument("--data", default=str(root.parent / "shared" / "data"), help="shared data folder")
    p.set_defaults(func=cmd_bench)
    return p


def cmd_bench(args) -> int:
    """Run the chosen suites; write args.json (atomically) and args.png. Returns 0."""
    if args.repeat < 1:
        raise InputError(f"--repeat must be at least 1, got {args.repeat}")
    for opt in ("json", "png"):
        path = getattr(args, opt)
        if path and not pathlib.Path(path).parent.is_dir():
            raise InputError(f"--{opt} {path}: directory {pathlib.Path(path).parent} does not exist")
    return _suites_module().execute(args)
