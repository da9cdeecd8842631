"""What the settings benchmarks share (latency_tuning.py, latency_stack_variants.py).

Each variant runs in a fresh child process (the benchmark script itself, called with
``--one NAME``), so environment settings such as ``ZENOH_RUNTIME`` reach every process
it starts; rounds alternate the variants so that machine noise hits all alike. Run the
scripts by path (``.venv/bin/python tests/benchmarks/<script>.py``): this module is
imported from the script's own folder.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

# One worker per Zenoh runtime pool (RON syntax of the ZENOH_RUNTIME variable).
ONE_THREAD_RUNTIME = (
    "(app: (worker_threads: 1), acc: (worker_threads: 1), tx: (worker_threads: 1), "
    "rx: (worker_threads: 1), net: (worker_threads: 1))"
)


def _run_in_child(
    script: str, name: str, args: Sequence[str], env: Mapping[str, str], run_dir: Path
) -> dict[str, Any]:
    """Run ``script --one name *args`` with ``env`` added; the figures it wrote (JSON)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    out = run_dir / "figures.json"
    subprocess.run(
        [sys.executable, script, "--one", name, *args, "--out", str(out),
         "--run-dir", str(run_dir)],
        check=True, env={**os.environ, **env}, stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
    )  # fmt: skip
    return json.loads(out.read_text())


def round_order(names: Sequence[str], round_index: int) -> list[str]:
    """The variants in the order round ``round_index`` runs them (rotated by one per
    round, see :func:`alternate`)."""
    shift = round_index % len(names) if names else 0
    return [*names[shift:], *names[:shift]]


def alternate(
    script: str,
    variants: Mapping[str, Mapping[str, Any]],
    names: Sequence[str],
    repeat: int,
    child_args: Sequence[str],
    describe: Callable[[dict[str, Any]], str],
) -> dict[str, list[dict[str, Any]]]:
    """``repeat`` rounds, each running every variant of ``names`` once, each in a child
    ``script --one NAME *child_args`` with the variant's ``env`` added, and printing
    ``describe(figures)``; the figures of each variant, round by round.

    The order rotates from round to round (round r starts at variant r), so every
    variant runs in every position alike over len(names) rounds: on a shared host the
    second run of a pair can measure slower than the same code run first."""
    results: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory(prefix=f"{Path(script).stem}-") as tmp:
        for round_index in range(repeat):
            for name in round_order(names, round_index):
                run_dir = Path(tmp) / f"{name}-{round_index}"
                env = variants[name].get("env", {})
                figures = _run_in_child(script, name, child_args, env, run_dir)
                results[name].append(figures)
                print(f"round {round_index} {name:18s} {describe(figures)}", flush=True)
    return results


def variant_parser(
    doc: str, variants: Mapping[str, Any], default_json: Path
) -> argparse.ArgumentParser:
    """The options both benchmarks share (add their own duration option to it)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3, help="rounds over all variants")
    parser.add_argument("--variants", default=",".join(variants), help="comma-separated")
    parser.add_argument("--json", type=Path, default=default_json)
    parser.add_argument("--one", help=argparse.SUPPRESS)  # the child process: one variant
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)
    return parser


def chosen_variants(
    parser: argparse.ArgumentParser, args: argparse.Namespace, variants: Mapping[str, Any]
) -> list[str]:
    """The ``--variants`` asked for; an unknown one is a usage error."""
    names = args.variants.split(",")
    unknown = sorted(set(names) - set(variants))
    if unknown:
        parser.error(f"unknown variants {unknown}; known: {', '.join(variants)}")
    return names
