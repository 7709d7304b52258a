"""The `bench` verb: one sub-command for each bench of the registry (benchmarks/__init__.py, BENCHES)."""

from __future__ import annotations

import argparse
import importlib

from benchmarks import BENCHES


def add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure accuracy and speed (writes docs/benchmarks.md)",
                       description="Benchmarks on the simulated rig; each prints its table and writes it to "
                                   "docs/benchmarks.md.")
    what = p.add_subparsers(dest="what", metavar="WHAT")
    for name in BENCHES:
        importlib.import_module(f"benchmarks.{name}").add(what)
    p.set_defaults(run=lambda args: p.print_help() or 2)
