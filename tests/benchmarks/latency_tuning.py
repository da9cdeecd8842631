"""Benchmark: Zenoh and process settings for 1 kHz round trips on 2 cores (issue 6, item 6).

Each variant runs the transport floor (teleop/bench/relay.py: the loop's four legs between
three Python processes, no work) paced at 1 kHz and back to back, each in a fresh
process so that environment settings (Zenoh's runtime threads) reach every end. Rounds
alternate the variants so that machine noise hits all alike; the report gives, per
variant, the median over rounds of p50 and p99 and their ratio to the default measured
in the same rounds, and writes them to a JSON file.

    .venv/bin/python tests/benchmarks/latency_tuning.py --paced 10 --repeat 3 \
        --json runs/bench/latency_tuning.json

Variants: ``default`` (deploy/zenoh/local.json5 as shipped, the low-latency transport
with SHM), ``lowlatency_off`` (Zenoh's default transport: ``bus.lowlatency``),
``shm_lazy`` (SHM segments mapped on first use instead of at start),
``runtime_1_thread`` (one worker thread in each Zenoh runtime pool, ``ZENOH_RUNTIME``),
``unpinned`` (the relays where the kernel puts them; by default each runs on the CPUs of
the service it stands in for), ``shm_off`` (TCP only).
"""

from __future__ import annotations

import json
import os
import statistics
import sys
from pathlib import Path

from variants import (
    ONE_THREAD_RUNTIME,
    alternate,
    chosen_variants,
    variant_parser,
)

from teleop.bench import latency, loop_stats

VARIANTS: dict[str, dict] = {
    "default": {},
    "lowlatency_off": {"overrides": ["bus.lowlatency=false"]},
    "shm_lazy": {"overrides": ['bus.zenoh_overrides=["transport/shared_memory/mode=\\"lazy\\""]']},
    "runtime_1_thread": {"env": {"ZENOH_RUNTIME": ONE_THREAD_RUNTIME}},
    # The relays run on their services' CPUs by default (cpu.plant, cpu.controller).
    "unpinned": {"overrides": ["cpu.plant=[]", "cpu.controller=[]"]},
    "shm_off": {"overrides": list(latency.SHM_OFF)},
}
# Payload of the sweep point each variant also measures (one eye-view frame, bytes).
FRAME_BYTES = 640 * 480 * 3


def one_variant(name: str, paced_s: float, run_dir: Path, out: Path) -> None:
    """Child process: measure one variant, write its figures to ``out``."""
    variant = VARIANTS[name]
    run = latency.run_floor(
        name,
        None,
        variant.get("overrides", []),
        run_dir,
        paced_s=paced_s,
        back_to_back_count=1000,
        sweep_sizes=(FRAME_BYTES,),
        sweep_count=100,
    )
    figures = {
        "paced": run.paced.round_trip_us.to_json(),
        "back_to_back": run.back_to_back.to_json(),
        "frame": run.sweep[FRAME_BYTES].to_json(),
        "lost": run.sent - run.received,
    }
    out.write_text(json.dumps(figures))


def main() -> int:
    parser = variant_parser(__doc__, VARIANTS, Path("runs/bench/latency_tuning.json"))
    parser.add_argument(
        "--paced", type=float, default=10.0, help="paced seconds per run (more than the warm-up)"
    )
    args = parser.parse_args()
    if args.paced <= loop_stats.WARMUP_S:  # a run all warm-up has no percentiles to report
        parser.error(f"--paced must exceed the {loop_stats.WARMUP_S:g} s warm-up")
    if args.one:
        one_variant(args.one, args.paced, args.run_dir, args.out)
        return 0
    names = chosen_variants(parser, args, VARIANTS)

    def describe(figures: dict) -> str:
        paced, b2b = figures["paced"], figures["back_to_back"]
        return (
            f"paced p50 {paced['p50']:7.0f} us p99 {paced['p99']:7.0f} us | back to back "
            f"p99 {b2b['p99']:6.0f} us | frame p50 {figures['frame']['p50']:6.0f} us | "
            f"lost {figures['lost']}"
        )

    child_args = ["--paced", str(args.paced)]
    results = alternate(__file__, VARIANTS, names, args.repeat, child_args, describe)

    def median(name: str, series: str, key: str) -> float:
        return statistics.median(r[series][key] for r in results[name])

    summary = {
        name: {
            f"{series}_{key}_us": median(name, series, key)
            for series in ("paced", "back_to_back", "frame")
            for key in ("p50", "p99")
        }
        for name in names
    }
    for name in names:
        if "default" in summary:
            for key in ("paced_p50_us", "paced_p99_us", "back_to_back_p99_us", "frame_p50_us"):
                summary[name][f"{key[:-3]}_ratio_to_default"] = (
                    summary[name][key] / summary["default"][key]
                )
    report = {
        "paced_s": args.paced,
        "repeat": args.repeat,
        "loadavg": os.getloadavg(),
        "medians": summary,
        "runs": results,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    for name, figures in summary.items():
        ratio = figures.get("paced_p99_ratio_to_default")
        print(
            f"{name:17s} median paced p50 {figures['paced_p50_us']:6.0f} us, p99 "
            f"{figures['paced_p99_us']:6.0f} us (x{ratio:.2f} of default)"
            if ratio is not None
            else name
        )
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
