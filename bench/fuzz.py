"""The long fuzz run of the ``nrpose`` command line (the CI run is tests/test_fuzz.py).

    python bench/fuzz.py --cases 100000 --workers 2 --out bench/results/fuzz.json \\
        --repro /tmp/nrpose-fuzz-repro [--minutes 25] [--seed 0] [--shared]

Runs cases ``0..N-1`` of ``--seed`` (tests/fuzzing: seeds of every input kind, mutated
bytes, tokens, JSON structure, headers, options and paths; one forked child per case with a
limit of 20 s of CPU (60 s of wall time as a backstop) and a 3 GiB address-space limit) over
``--workers`` processes, stopping early after ``--minutes``. ``--shared`` adds the assets of ../shared/data as extra seeds.

Writes a JSON summary (every 30 s and at the end): ``cases``, ``violations``,
``by_outcome``, ``totals`` (command × input kind × outcome: ``accepted``, ``rejected`` and
``partial`` keep the contract, the others are the classes of tests/fuzzing/runner.py), and
``defects``: one record per distinct (command, class, where) with its count, the last
traceback frame, the stderr tail, argv and the reproducer folder (replay with
``python -m tests.fuzzing.runner FOLDER`` from the repository root). Prints a line per
violation and, at the end, the table of cases by command and input kind (cases, accepted,
rejected, partial, each violation class; ``python -m tests.fuzzing.report SUMMARY.json`` prints
it again with the defects grouped by root cause); exit status 1 when any case broke the contract.
``--commands bake,fit-skin`` runs only those commands (in their usual shares).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzzing.campaign import run  # noqa: E402
from tests.fuzzing.cases import COMMANDS  # noqa: E402
from tests.fuzzing.report import totals_table  # noqa: E402
from tests.fuzzing.runner import GOOD  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", type=int, default=100_000)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--minutes", type=float, default=None, help="stop after this long")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="bench/results/fuzz.json")
    p.add_argument("--repro", default=None, help="folder for one reproducer per distinct defect")
    p.add_argument("--shared", action="store_true", help="also mutate the assets of ../shared/data")
    p.add_argument("--commands", help="only these commands, comma-separated, in their usual shares "
                                      f"(default: all, {', '.join(COMMANDS)})")
    args = p.parse_args(argv)
    commands = None
    if args.commands:
        names = args.commands.split(",")
        unknown = [c for c in names if c not in COMMANDS]
        if unknown:
            p.error(f"--commands: unknown {', '.join(unknown)}; choose from {', '.join(COMMANDS)}")
        commands = {c: COMMANDS[c] for c in names}

    def progress(collector, o):
        if o.outcome not in GOOD and collector.defects[o.key]["count"] == 1:
            print(f"[{collector.count}] {o.outcome:<18} {o.template:<18} {o.input_kind:<14} {o.where[:90]}",
                  flush=True)
        elif collector.count % 500 == 0:
            print(f"[{collector.count}] {collector.violations} violations, {len(collector.defects)} distinct",
                  flush=True)

    s = run(args.seed, args.cases, args.workers, args.minutes, args.repro, args.out, args.shared, progress, commands)
    print(f"\n{s['cases']} cases in {s['elapsed_s']:.0f} s ({s['cases_per_s']:.1f}/s, {args.workers} workers): "
          f"{s['violations']} violations, {s['distinct']} distinct defects")
    for outcome, n in sorted(s["by_outcome"].items(), key=lambda kv: -kv[1]):
        print(f"  {outcome:<20} {n:>7}")
    print("\n" + totals_table(s) + "\n")
    print(f"summary: {args.out}; the report (totals and defects by root cause): "
          f"python -m tests.fuzzing.report {args.out}")
    return 1 if s["violations"] else 0


if __name__ == "__main__":
    sys.exit(main())
