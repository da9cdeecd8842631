"""Benchmark: Zenoh and process settings for 1 kHz round trips on 2 cores (issue 6, item 6).

Each variant runs the transport floor (teleop/relay.py: the loop's four legs between
three Python processes, no work) paced at 1 kHz and back to back, each in a fresh
process so that environment settings (Zenoh's runtime threads) reach every end. Rounds
alternate the variants so that machine noise hits all alike; the report gives, per
variant, the median over rounds of p50 and p99 and their ratio to the default measured
in the same rounds, and writes them to a JSON file.

    .venv/bin/python tests/benchmarks/latency_tuning.py --paced 10 --repeat 3 \
        --json runs/bench/latency_tuning.json

Variants: ``default`` (deploy/zenoh/local.json5 as shipped, with SHM and the
low-latency transport: ``bus.lowlatency``), ``lowlatency_off`` (Zenoh's default
transport, with QoS), ``shm_lazy`` (SHM segments mapped on first use instead of at
start), ``runtime_1_thread`` (one worker thread in each Zenoh runtime pool,
``ZENOH_RUNTIME``), ``pinned`` (origin and plant relay on CPU 0, controller relay on
CPU 1), ``shm_off`` (TCP only).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

# One worker per Zenoh runtime pool (RON syntax of the ZENOH_RUNTIME variable).
ONE_THREAD_RUNTIME = (
    "(app: (worker_threads: 1), acc: (worker_threads: 1), tx: (worker_threads: 1), "
    "rx: (worker_threads: 1), net: (worker_threads: 1))"
)
VARIANTS: dict[str, dict] = {
    "default": {},
    "lowlatency_off": {"overrides": ["bus.lowlatency=false"]},
    "shm_lazy": {"overrides": ['bus.zenoh_overrides=["transport/shared_memory/mode=\\"lazy\\""]']},
    "runtime_1_thread": {"env": {"ZENOH_RUNTIME": ONE_THREAD_RUNTIME}},
    "pinned": {"origin_cpus": [0], "relay_cpus": {"relay_controller": [1], "relay_plant": [0]}},
    "shm_off": {"overrides": ["bus.shm=false", 'bus.zenoh_config="local-noshm.json5"']},
}
# Payload of the sweep point each variant also measures (one eye-view frame, bytes).
FRAME_BYTES = 640 * 480 * 3


def one_variant(name: str, paced_s: float, run_dir: Path, out: Path) -> None:
    """Child process: measure one variant, write its figures to ``out``."""
    from teleop import latency

    variant = VARIANTS[name]
    if variant.get("origin_cpus"):
        os.sched_setaffinity(0, set(variant["origin_cpus"]))
    run = latency.run_floor(
        name,
        None,
        variant.get("overrides", []),
        run_dir,
        paced_s=paced_s,
        back_to_back_count=1000,
        sweep_sizes=(FRAME_BYTES,),
        sweep_count=100,
        relay_cpus=variant.get("relay_cpus"),
    )
    figures = {
        "paced": run.paced["round_trip_us"],
        "back_to_back": run.back_to_back,
        "frame": run.sweep[FRAME_BYTES],
        "lost": run.sent - run.received,
    }
    out.write_text(json.dumps(figures))


def run_variant(name: str, paced_s: float, run_dir: Path) -> dict:
    out = run_dir / "figures.json"
    env = {**os.environ, **VARIANTS[name].get("env", {})}
    subprocess.run(
        [sys.executable, __file__, "--one", name, "--paced", str(paced_s), "--out", str(out),
         "--run-dir", str(run_dir)],
        check=True, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    return json.loads(out.read_text())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--paced", type=float, default=10.0, help="paced seconds per run")
    parser.add_argument("--repeat", type=int, default=3, help="rounds over all variants")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/latency_tuning.json"))
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        one_variant(args.one, args.paced, args.run_dir, args.out)
        return 0
    names = args.variants.split(",")
    results: dict[str, list[dict]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory(prefix="tune-") as tmp:
        for round_index in range(args.repeat):
            for name in names:
                figures = run_variant(name, args.paced, Path(tmp) / f"{name}-{round_index}")
                results[name].append(figures)
                paced, b2b = figures["paced"], figures["back_to_back"]
                print(
                    f"round {round_index} {name:17s} paced p50 {paced['p50']:7.0f} us "
                    f"p99 {paced['p99']:7.0f} us | back to back p99 {b2b['p99']:6.0f} us | "
                    f"frame p50 {figures['frame']['p50']:6.0f} us | lost {figures['lost']}"
                )

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
