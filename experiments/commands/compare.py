"""``iarcs compare``: is the change between two sets of ``iarcs evaluate`` reports real, or sampling noise?

    iarcs compare --base base_s0.json base_s1.json --run stage1_s0.json stage1_s1.json [--out change.json]

Pairs the k-th ``--run`` report with the k-th ``--base`` report (the same floors and sampling seed, with and
without an adapter), pools all pairs, and prints each metric's pooled values, relative change and a 90%
floor-level bootstrap interval of the change (:mod:`iarcs_env.compare`).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("compare", help="change between evaluate reports, with a bootstrap interval",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--base", nargs="+", required=True, metavar="REPORT",
                   help="`iarcs evaluate` reports of the reference samples (one per sampling seed)")
    p.add_argument("--run", nargs="+", required=True, metavar="REPORT",
                   help="reports of the compared samples, in the same order as --base")
    p.add_argument("--boot", type=int, default=2000, help="bootstrap resamples (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default 0)")
    p.add_argument("--out", help="also write the result as .json")
    p.set_defaults(func=cmd_compare)


def _read(path: str) -> dict:
    from experiments.cli import CLIError

    if not Path(path).exists():
        raise CLIError(f"report {path} does not exist (write it with `iarcs evaluate --out`)")
    try:
        report = json.loads(Path(path).read_text())
    except json.JSONDecodeError as e:
        raise CLIError(f"report {path} is not JSON ({e}); pass the .json that `iarcs evaluate --out` wrote") from None
    if not isinstance(report, dict) or "per_scene" not in report:
        raise CLIError(f"{path} is not an `iarcs evaluate` report (no per_scene results)")
    return report


def _finite(row: dict) -> dict:
    """NaN (a change from a base rate of 0) as JSON null."""
    return {k: None if isinstance(v, float) and v != v else v for k, v in row.items()}


def cmd_compare(args) -> int:
    from experiments.cli import CLIError
    from iarcs_env.compare import changes_table, compare_reports

    if args.boot < 100:
        raise CLIError(f"--boot must be at least 100 for a 90% interval, got {args.boot}")
    base, run = [_read(p) for p in args.base], [_read(p) for p in args.run]
    changes = compare_reports(base, run, n_boot=args.boot, seed=args.seed)
    n_scenes = sum(len(r["per_scene"]) for r in base)
    print(changes_table(changes, n_scenes, len(base)))
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"base": args.base, "run": args.run, "boot": args.boot, "seed": args.seed,
                                   "changes": [_finite(asdict(c)) for c in changes]}, indent=1))
        print(f"\nwritten: {out}")
    return 0
