"""``slam2d eval ...`` subcommands."""
from __future__ import annotations


def add_eval_parser(sub):
    p = sub.add_parser("eval", help="evaluate a trajectory (relations metric, ATE/RPE, loop closures)")
    p.set_defaults(eval_command=None)
    return p


def run_eval(args) -> int:
    from slam2d.errors import UsageError

    raise UsageError("eval: choose a metric (relations, ate, loops)")
