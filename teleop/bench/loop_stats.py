"""The loop's stamps as figures: hops, percentiles, the loop checked across clocks.

Pure functions of the raw stamps every loop record carries (``Stage``, monotonic ns, a
row per loop): :func:`analyse` takes the traces of a run to its round trip and hops
(:class:`LoopAnalysis`), :func:`across_clocks` checks a loop whose stamps come from two
hosts' clocks, :func:`chain_accounting` counts the loops that never closed, and
:func:`overhead` sets a stack's figures against the transport floor's. Percentiles come
from HDR histograms (``hdrhistogram``: 3 significant digits, so within 0.1 % of the exact
order statistic). Used by ``teleop latency`` (:mod:`teleop.bench.latency`) and the
across-sites measurement (:mod:`teleop.bench.sites`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from teleop.bus.messages import Stage
from teleop.core.clock import NS_PER_S, NS_PER_US

# HDR histogram range and precision: 1 ns .. 60 s, 3 significant digits.
HDR_LOWEST_NS = 1
HDR_HIGHEST_NS = 60 * NS_PER_S
HDR_SIGNIFICANT_DIGITS = 3
# The percentiles every report gives (JSON key -> percentile).
PERCENTILES = {"p50": 50.0, "p90": 90.0, "p99": 99.0, "p999": 99.9}
# the plant's grid locking to the commands): left out of every figure.
WARMUP_S = 1.0
# A floor figure below this (us) is "no such stage" (a relay does not wait): no ratio.
MIN_RATIO_BASE_US = 1.0


@dataclass(frozen=True)
class Hop:
    """One stage-to-stage interval of the loop; ``kind``: transport, compute or wait."""

    name: str
    start: Stage
    end: Stage
    kind: str


HOPS: tuple[Hop, ...] = (
    Hop("haptic_to_controller", Stage.HAPTIC_SAMPLE, Stage.CONTROLLER_RX, "transport"),
    Hop("controller_command", Stage.CONTROLLER_RX, Stage.CONTROLLER_TX, "compute"),
    Hop("controller_to_plant", Stage.CONTROLLER_TX, Stage.PLANT_RX, "transport"),
    Hop("plant_wait", Stage.PLANT_RX, Stage.PLANT_APPLIED, "wait"),
    Hop("plant_step", Stage.PLANT_APPLIED, Stage.PLANT_STATE_TX, "compute"),
    Hop("plant_to_controller", Stage.PLANT_STATE_TX, Stage.CONTROLLER_STATE_RX, "transport"),
    Hop("controller_feedback", Stage.CONTROLLER_STATE_RX, Stage.FEEDBACK_TX, "compute"),
    Hop("controller_to_haptic", Stage.FEEDBACK_TX, Stage.FEEDBACK_RX, "transport"),
    Hop("haptic_render", Stage.FEEDBACK_RX, Stage.FEEDBACK_RENDERED, "wait"),
)
ROUND_TRIP = Hop("round_trip", Stage.HAPTIC_SAMPLE, Stage.FEEDBACK_RENDERED, "total")
LOOP_STAGES = tuple(Stage)  # every stamp of one loop, in loop order


# -- statistics ---------------------------------------------------------------------------


def histogram(values_ns: Iterable[int]) -> Any:
    """An HDR histogram of latencies in ns (values clamped into its range)."""
    from hdrh.histogram import HdrHistogram

    hist = HdrHistogram(HDR_LOWEST_NS, HDR_HIGHEST_NS, HDR_SIGNIFICANT_DIGITS)
    for value in np.clip(np.asarray(values_ns, dtype=np.int64), HDR_LOWEST_NS, HDR_HIGHEST_NS):
        hist.record_value(int(value))
    return hist


@dataclass(frozen=True)
class LatencyStats:
    """count, percentiles (PERCENTILES), max and mean of latencies, in us; the figures are
    None without a sample. ``not_measured``: why a payload-sweep size was not sent.
    JSON keys drop the unit (``p50``, ``max``): the report's key says ``_us``."""

    count: int
    p50_us: float | None = None
    p90_us: float | None = None
    p99_us: float | None = None
    p999_us: float | None = None
    max_us: float | None = None
    mean_us: float | None = None
    not_measured: str | None = None

    def percentile_us(self, key: str) -> float | None:
        """The figure of a PERCENTILES key (``p50``, ...), or ``max``/``mean``."""
        return getattr(self, f"{key}_us")

    def to_json(self) -> dict[str, float | str | None]:
        out: dict[str, float | str | None] = {"count": self.count}
        out |= {key: self.percentile_us(key) for key in (*PERCENTILES, "max", "mean")}
        if self.not_measured is not None:
            out["not_measured"] = self.not_measured
        return out

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> LatencyStats:
        """The record of a JSON figure set; a key it lacks is None (an empty ``{}``: 0 loops)."""
        figures = {f"{key}_us": content.get(key) for key in (*PERCENTILES, "max", "mean")}
        return cls(
            int(content.get("count", 0)), **figures, not_measured=content.get("not_measured")
        )


def stats_us(values_ns: np.ndarray) -> LatencyStats:
    """count, p50, p90, p99, p999, max and mean of latencies given in ns, reported in us.

    Percentiles are the HDR histogram's (the smallest recorded value with at least that
    share of samples at or below it, to 3 significant digits); max and mean are exact.
    """
    values_ns = np.asarray(values_ns, dtype=np.int64)
    if values_ns.size == 0:
        return LatencyStats(0)
    hist = histogram(values_ns)
    percentiles = {
        f"{key}_us": hist.get_value_at_percentile(pct) / NS_PER_US
        for key, pct in PERCENTILES.items()
    }
    return LatencyStats(
        int(values_ns.size),
        **percentiles,
        max_us=float(values_ns.max()) / NS_PER_US,
        mean_us=float(values_ns.mean()) / NS_PER_US,
    )


def complete_loops(traces: np.ndarray) -> np.ndarray:
    """Rows of ``traces`` (n, N_STAGES) that hold every stamp of one loop."""
    traces = np.asarray(traces, dtype=np.int64).reshape(-1, len(Stage))
    return traces[(traces[:, list(LOOP_STAGES)] > 0).all(axis=1)]


def after_warmup(traces: np.ndarray, warmup_s: float = WARMUP_S) -> np.ndarray:
    """Rows whose handle sample is at least ``warmup_s`` after the first one's."""
    if traces.shape[0] == 0:
        return traces
    start_ns = traces[:, Stage.HAPTIC_SAMPLE]
    return traces[start_ns >= start_ns.min() + round(warmup_s * NS_PER_S)]


def hop_ns(traces: np.ndarray, hop: Hop) -> np.ndarray:
    """The hop's durations (ns), one per row."""
    return traces[:, hop.end] - traces[:, hop.start]


def non_monotonic(traces: np.ndarray) -> int:
    """Rows whose stamps decrease somewhere along the loop (must be 0)."""
    stamps = traces[:, list(LOOP_STAGES)]
    return int((np.diff(stamps, axis=1) < 0).any(axis=1).sum())


def warm_loops(*traces: np.ndarray) -> np.ndarray:
    """The complete loops of each run's traces after that run's own warm-up, together."""
    return np.concatenate([after_warmup(complete_loops(t)) for t in traces])


def hops_json(hops_us: Mapping[str, LatencyStats]) -> dict[str, dict[str, float | str | None]]:
    """Each hop's figures as JSON, by hop name."""
    return {name: figures.to_json() for name, figures in hops_us.items()}


def hops_from_json(content: Mapping[str, Any]) -> dict[str, LatencyStats]:
    """Each hop's figures of a JSON object by hop name."""
    return {name: LatencyStats.from_json(figures) for name, figures in content.items()}


@dataclass(frozen=True)
class LoopAnalysis:
    """The round trip and every hop (HOPS, by name) of complete loops, in us, and the
    loops whose stamps go back in time (must be 0)."""

    round_trip_us: LatencyStats
    hops_us: Mapping[str, LatencyStats]
    non_monotonic: int


def analyse(*traces: np.ndarray) -> LoopAnalysis:
    """Round trip and every hop of complete loops (after the warm-up of each run whose
    traces are given), in us."""
    loops = warm_loops(*traces)
    return LoopAnalysis(
        round_trip_us=stats_us(hop_ns(loops, ROUND_TRIP)),
        hops_us={hop.name: stats_us(hop_ns(loops, hop)) for hop in HOPS},
        non_monotonic=non_monotonic(loops),
    )


@dataclass(frozen=True)
class AcrossClocks:
    """The loop split across two sites on two clocks (:func:`across_clocks`): the clocks'
    offset (robot minus operator site, s) and its uncertainty (us), the round trip on the
    operator site's clock, the robot site's part and each way across (us). No loop: every
    figure None."""

    loops: int
    offset_s: float | None = None
    offset_uncertainty_us: float | None = None
    round_trip_us: LatencyStats | None = None
    robot_site_us: LatencyStats | None = None
    operator_to_robot_us: LatencyStats | None = None
    robot_to_operator_us: LatencyStats | None = None

    def to_json(self) -> dict[str, Any]:
        """The JSON object (only ``loops`` when no loop closed)."""
        if not self.loops:
            return {"loops": self.loops}
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.to_json() if isinstance(value, LatencyStats) else value
        return out

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> AcrossClocks:
        """The record of :meth:`to_json`'s keys in ``content`` (other keys are left)."""
        figures = {
            f.name: LatencyStats.from_json(content[f.name])
            for f in fields(cls)
            if f.name.endswith("_us") and f.name in content and f.name != "offset_uncertainty_us"
        }
        return cls(
            loops=content["loops"],
            offset_s=content.get("offset_s"),
            offset_uncertainty_us=content.get("offset_uncertainty_us"),
            **figures,
        )


def across_clocks(*traces: np.ndarray) -> AcrossClocks:
    """The loop split across two sites on two clocks: the operator site's stamps
    (HAPTIC_SAMPLE, FEEDBACK_RX, FEEDBACK_RENDERED) on one, the robot site's
    (CONTROLLER_RX to FEEDBACK_TX) on another. The round trip is on the sampling side's
    clock alone; each way across is found as NTP does: per loop, the clocks' offset
    ``((t1 - t0) + (t2 - t3)) / 2`` (robot minus operator) and the time on the wire
    ``(t3 - t0) - (t2 - t1)``; the offset taken from the loop with the least wire time,
    whose half is its uncertainty (the two ways need not be equal). In us (the offset in
    s) after the warm-up."""
    loops = warm_loops(*traces)
    if loops.shape[0] == 0:
        return AcrossClocks(0)
    t0, t1 = loops[:, Stage.HAPTIC_SAMPLE], loops[:, Stage.CONTROLLER_RX]
    t2, t3 = loops[:, Stage.FEEDBACK_TX], loops[:, Stage.FEEDBACK_RX]
    wire_ns = (t3 - t0) - (t2 - t1)
    best = int(np.argmin(wire_ns))
    # Halved in integers: two stamps hours apart are beyond a float's ns resolution.
    offset_ns = ((t1[best] - t0[best]) + (t2[best] - t3[best])) // 2
    return AcrossClocks(
        loops=int(loops.shape[0]),
        offset_s=offset_ns / NS_PER_S,
        offset_uncertainty_us=float(wire_ns[best]) / 2 / NS_PER_US,
        round_trip_us=stats_us(hop_ns(loops, ROUND_TRIP)),
        robot_site_us=stats_us(t2 - t1),
        operator_to_robot_us=stats_us(t1 - t0 - offset_ns),
        robot_to_operator_us=stats_us(t3 - t2 + offset_ns),
    )


@dataclass(frozen=True)
class ChainAccounting:
    """Handle samples between the first and the last that came back (:func:`chain_accounting`)."""

    samples: int
    returned: int
    missing: int
    shed: int
    unaccounted: int
    duplicates: int

    def to_json(self) -> dict[str, int]:
        return asdict(self)


def chain_accounting(
    samples: np.ndarray, traces: np.ndarray, shed_ns: np.ndarray | None = None
) -> ChainAccounting:
    """Did every handle sample come back exactly once, or was it shed on purpose?

    ``samples`` (n, 2): (seq, HAPTIC_SAMPLE ns) of every published HAPTIC_STATE;
    ``traces``: the rendered feedback traces; ``shed_ns``: HAPTIC_SAMPLE stamps of the
    samples a service shed while behind schedule (its ``.shed.npy`` files). Between the
    first and the last sample that came back, a sample that never did is ``missing``,
    ``shed`` if a service says it dropped it, else ``unaccounted`` (must be 0); one that
    came back twice or more counts in ``duplicates`` (each extra time).
    """
    loops = complete_loops(traces)
    if loops.shape[0] == 0:
        return ChainAccounting(0, 0, 0, 0, 0, 0)
    returned = loops[:, Stage.HAPTIC_SAMPLE]
    unique, counts = np.unique(returned, return_counts=True)
    sample_ns = np.asarray(samples, dtype=np.int64).reshape(-1, 2)[:, 1]
    window = sample_ns[(sample_ns >= unique.min()) & (sample_ns <= unique.max())]
    missing = np.setdiff1d(window, unique)
    shed = np.zeros(0, np.int64) if shed_ns is None else np.asarray(shed_ns).reshape(-1)
    return ChainAccounting(
        samples=int(window.size),
        returned=int(unique.size),
        missing=int(missing.size),
        shed=int(np.isin(missing, shed).sum()),
        unaccounted=int(np.setdiff1d(missing, shed).size),
        duplicates=int((counts - 1).sum()),
    )


@dataclass(frozen=True)
class FloorRatio:
    """A figure's p50 and p99 over the floor's: the ratio (None where the floor's is below
    MIN_RATIO_BASE_US, or either is missing) and the extra us (None if either is missing)."""

    p50_ratio: float | None
    p50_extra_us: float | None
    p99_ratio: float | None
    p99_extra_us: float | None

    @classmethod
    def of(cls, mine: LatencyStats, base: LatencyStats) -> FloorRatio:
        values: dict[str, float | None] = {}
        for key in ("p50", "p99"):
            a, b = mine.percentile_us(key), base.percentile_us(key)
            if a is None or b is None:
                values[f"{key}_ratio"] = values[f"{key}_extra_us"] = None
                continue
            values[f"{key}_ratio"] = a / b if b >= MIN_RATIO_BASE_US else None
            values[f"{key}_extra_us"] = a - b
        return cls(**values)

    def to_json(self) -> dict[str, float | None]:
        return asdict(self)


def overhead(stack: LoopAnalysis, floor: LoopAnalysis) -> dict[str, FloorRatio]:
    """Each hop's and the round trip's (``round_trip``) p50/p99 over the floor's: ratio
    and extra us.

    A ratio is None where the floor's figure is below MIN_RATIO_BASE_US (a wait the bare
    relay does not have).
    """
    result = {"round_trip": FloorRatio.of(stack.round_trip_us, floor.round_trip_us)}
    for name, figures in stack.hops_us.items():
        result[name] = FloorRatio.of(figures, floor.hops_us[name])
    return result
