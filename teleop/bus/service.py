"""The one service lifecycle: open -> run -> close, shared by every process.

A service module in ``services/`` is three lines: it hands its class to
:func:`service_main`, which parses the common command line, loads the typed config,
turns SIGINT/SIGTERM into a stop event, and runs ``open -> run(stop) -> close``.
``close`` is safe to call twice and writes the service's summary to
``<run_dir>/<name>.summary.json`` (atomically), which ``teleop run`` collects
(:func:`read_summary`). Meanwhile the process writes its summary so far every
``SUMMARY_PERIOD_S`` to a file of its own (``<name>.<pid>.incarnation.json``), so the
counts of a process killed with SIGKILL, which never closes, are not lost: the next
summary written at close, or the launcher, takes them in as an earlier incarnation.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import json
import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, ClassVar

import zenoh
import zenoh.ext
from zenoh.shm import ShmProvider

from teleop.bus import graph
from teleop.bus.access import participant_zids, strangers
from teleop.bus.messages import DropCounter
from teleop.bus.session import (
    NewestSubscriber,
    Publisher,
    RecordCallback,
    ServicesMissing,
    close_session,
    declare_alive,
    declare_protocol,
    session_config,
    subscribe_events,
    subscribe_stream,
    wait_alive,
)
from teleop.bus.topics import Topics
from teleop.core.clock import NS_PER_S
from teleop.core.config import Config, ConfigError, ModelError, load_config
from teleop.core.rundir import incarnation_path, incarnation_paths, summary_path

logger = logging.getLogger(__name__)

# While waiting for peers, wake this often to notice a stop request (s).
STOP_POLL_S = 0.25
# After waiting this long for peers, say which ones are missing (once; s).
PEER_WAIT_LOG_S = 5.0
# A stop signal repeated this long after the first prints every thread's stack to the log
# (the launcher repeats it every few seconds while a service is still there).
STOP_AGAIN_DUMP_S = 4.0
# A service declares itself ready after this long even if some peer of its stack is
# still not seen (a pair of peers that never linked: an error in the log and the
# summary, rather than a run that never starts; s).
PEER_LINK_WAIT_S = 15.0
# Exit code of a service whose config or model is unusable (supervisord will not retry
# it forever: startretries bounds it, and the log says why).
EXIT_CONFIG = 2
# Exit code of a service that failed on an unexpected error (its traceback is logged).
EXIT_FAILED = 1
# A running service writes its summary so far this often (s): what a SIGKILL can lose.
SUMMARY_PERIOD_S = 2.0


@dataclass(frozen=True)
class ServiceOptions:
    """Per-process settings that are not part of the shared config."""

    run_dir: Path | None = None
    # Hold the run's bus endpoint (the listener) instead of connecting to it.
    listen: bool = False
    # Services that must be ready (their ready tokens present) before the work starts.
    await_services: tuple[str, ...] = ()
    # The other services of this stack: this one declares itself ready once it sees
    # them all alive, i.e. once its own links to them are up (become_ready).
    peers: tuple[str, ...] = ()
    # Run until stopped instead of for run.duration_s (``teleop up``).
    continuous: bool = False
    # The plant in lockstep: sim instants (ns) at which it waits for the launcher's
    # release (fault injection, teleop.sim.pacing.LockstepHolds).
    hold_at_ns: tuple[int, ...] = ()


class Service:
    """Base of every service: a Zenoh session, a liveliness token, drop counters."""

    name: ClassVar[str] = "service"
    # The service whose CPUs and scheduling this process takes (empty: its own name's):
    # a stand-in, such as a relay of the latency floor, runs where the real one runs.
    scheduling_as: ClassVar[str] = ""

    def __init__(self, config: Config, options: ServiceOptions | None = None) -> None:
        self.config = config
        self.options = options or ServiceOptions()
        self.topics = Topics(config.robot.robot_id)
        # The robots this process works: its own (a per-robot service), or every robot of
        # the run (a station's service: its tokens under each robot's keys, so each
        # robot's services see one of each). Robot 0's first: ``topics``.
        robot_ids = (config.robot.robot_id,)
        if self.name not in graph.PER_ROBOT:
            robot_ids = config.robot_ids()
        self.robot_topics = tuple(Topics(rid) for rid in robot_ids)
        # The robots under whose keys this service's peers (the processes of its own
        # stack or site) declare their tokens: on a robot site of a run of several robots,
        # that site's robot only (the other robots' processes run on other sites).
        here = config.site_robot_ids()
        self.peer_topics = tuple(t for t in self.robot_topics if t.robot_id in here)
        # A lockstep run across sites needs every record of the streams nothing sends
        # again, through a router's restart: those streams with recovery (graph.Stream).
        self.recovery = bool(config.site.name) and config.run.mode == "lockstep"
        self.drops = DropCounter()
        self.session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._newest: dict[str, NewestSubscriber] = {}  # streams taken newest-only, by name
        self._closed = False
        self._summary_stop = threading.Event()
        self._summary_thread: threading.Thread | None = None
        self.running_summaries = 0  # summaries so far written while running
        # CPU time (s) this process had used when it declared itself ready: its start-up
        # (imports, models, session, links), apart from what its work costs per second.
        self.cpu_s_ready: float | None = None
        self.running_summary_failures = 0  # of which summary() raised (skipped)
        # CPU time (ms) the costliest one took, the first apart: about how long it held
        # the GIL the service's own threads need.
        self.running_summary_cpu_max_ms = 0.0
        self.unlinked_peers: list[str] = []  # peers never seen (become_ready gave up)
        # Sessions linked to this one that are no participant of the run (Zenoh ids):
        # someone holding a run's certificate (or password) under an id of its own. The
        # access list gives them no right; they are counted, and logged once each.
        self.unknown_peers: list[str] = []
        self._participants: frozenset[str] = frozenset()  # the run's Zenoh ids
        self._strangers_lock = threading.Lock()  # transport events and the summaries
        # Peers become_ready gave up on that linked after all: name -> seconds after the
        # start of the wait (on a starved machine start-up can outlast PEER_LINK_WAIT_S).
        self.peers_linked_late: dict[str, float] = {}
        # Realtime privileges asked for and whether the kernel granted them (service_main
        # fills it in): {"sched_fifo": ..., "cpu_pinning": ...}, each "granted ...",
        # "refused: <why>" or "not requested".
        self.privileges: dict[str, str] = {}

    @property
    def instance(self) -> str:
        """The process's own name: its summary's and its participant's
        (graph.instance_name; read when needed, as a service may name itself in its own
        constructor, a site's router)."""
        config = self.config
        return graph.instance_name(self.name, config.robot.robot_id, config.run.robots)

    # -- lifecycle ---------------------------------------------------------------------
    def open(self) -> None:
        """Open the session; subclasses declare their publishers and subscribers after."""
        self.session = zenoh.open(self.zenoh_config())
        if self.config.bus.credentials_file:
            self._participants = participant_zids(Path(self.config.bus.credentials_file))
            # Every link as it opens, however short its stay (the running summaries'
            # check alone would miss a session gone before the next one); those open
            # already, from the session's list. (The listener's own history panics in
            # zenoh-python 1.x when a TLS link exists: "no reactor running".)
            self.keep(self.session.info.declare_transport_events_listener(self._on_transport))
            self.check_peers()

    def _on_transport(self, event: zenoh.TransportEvent) -> None:
        if event.kind == zenoh.SampleKind.PUT:
            self._note_strangers([event.transport.zid])

    def zenoh_config(self) -> zenoh.Config:
        """This service's session config: a peer of the run's mesh (a site's router
        says otherwise)."""
        return session_config(self.config.bus, listen=self.options.listen)

    def announce(self) -> None:
        """Declare this service alive, and the protocol version it speaks: call once its
        subscribers are in place."""
        assert self.session is not None
        for topics in self.robot_topics:
            self.keep(declare_protocol(self.session, topics))
            self.keep(declare_alive(self.session, topics, self.name))

    def subscribe_stream(
        self, stream_name: str, callback: RecordCallback, topics: Topics | None = None
    ) -> zenoh.Subscriber | NewestSubscriber:
        """Subscribe this service to the graph's stream ``stream_name`` (its key and record
        kind) of robot ``topics`` (default: :attr:`topics`) as the graph says it takes it
        in this run's mode: every record in order, or only the newest
        (:class:`NewestSubscriber`, its skips in the summary's ``skipped``). Kept:
        close() undeclares it."""
        assert self.session is not None
        run = self.config.run
        topics = topics or self.topics
        sub = subscribe_stream(
            self.session,
            topics,
            stream_name,
            callback,
            self.drops,
            consumer=self.name,
            mode=run.mode,
            scenario=run.scenario,
            recovery=self.recovery,
        )
        if isinstance(sub, NewestSubscriber):
            own = topics.robot_id == self.topics.robot_id
            self._newest[stream_name if own else f"{stream_name}@{topics.robot_id}"] = sub
        return self.keep(sub)

    def subscribe_events(
        self, stream_name: str, callback: RecordCallback, topics: Topics | None = None
    ) -> zenoh.Subscriber | zenoh.ext.AdvancedSubscriber:
        """Subscribe this service to one service's RUN_EVENT stream of robot ``topics``
        (default: :attr:`topics`): only the events that service owns, with this run's
        recovery (:func:`teleop.bus.session.subscribe_events`). Kept."""
        assert self.session is not None
        topics = topics or self.topics
        return self.keep(
            subscribe_events(
                self.session, topics, stream_name, callback, self.drops, recovery=self.recovery
            )
        )

    def publish_stream(
        self, stream_name: str, topics: Topics | None = None, *, shm: ShmProvider | None = None
    ) -> Publisher:
        """A publisher of the graph's stream ``stream_name`` on robot ``topics`` (default:
        :attr:`topics`), with this run's recovery where the graph marks the stream
        recovered (:meth:`Publisher.for_stream`). Kept."""
        assert self.session is not None
        topics = topics or self.topics
        return self.keep(
            Publisher.for_stream(self.session, topics, stream_name, shm=shm, recovery=self.recovery)
        )

    def keep(self, entity: Any) -> Any:
        """Remember a Zenoh entity so close() undeclares it; returns it."""
        self._entities.append(entity)
        return entity

    def run(self, stop: threading.Event) -> None:
        raise NotImplementedError

    def summary(self) -> dict[str, Any]:
        """What this service reports at close; subclasses extend it.

        ``cpu_s``: CPU time (user + system, all threads) this process used so far: what
        the service costs the machine, unlike wall-clock figures not inflated by others.
        """
        drops = self.drops.by_key()
        return {
            "service": self.name,
            "dropped_messages": self.drops.total,
            # every rejected record, by record kind and reason (DecodeError / Reason), and
            # the first of each: what it was (a version drop: its version and ours)
            "dropped_by_reason": dict(drops.counts),
            "dropped_first": dict(drops.first),
            "cpu_s": time.process_time(),
            "cpu_s_ready": self.cpu_s_ready,
            # per stream taken newest-only (realtime): records taken, and skipped because
            # a newer one came first (this service was behind)
            "newest_only": {
                name: {"taken": sub.taken, "skipped": sub.skipped}
                for name, sub in self._newest.items()
            },
            "unlinked_peers": list(self.unlinked_peers),
            "unknown_peers": list(self.unknown_peers),
            "peers_linked_late": dict(self.peers_linked_late),
            "privileges": self.privileges,
            "running_summaries": self.running_summaries,
            "running_summary_cpu_max_ms": round(self.running_summary_cpu_max_ms, 3),
        }

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._stop_running_summaries()
            self.write_summary()
        finally:
            close_session(self.session, *reversed(self._entities))
            self._entities.clear()

    def __enter__(self) -> Service:
        try:
            self.open()
        except BaseException:
            # What open() made (a session, its threads) must go, or the process would
            # neither exit nor stop on a signal after the error. Its summary may not be
            # writable from a half-made service: the open() error is the one to report.
            with contextlib.suppress(Exception):
                self.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- helpers -----------------------------------------------------------------------
    def become_ready(self, stop: threading.Event) -> bool:
        """Wait until every peer of the stack is alive as seen from here, then declare
        this service ready; False if stopped first.

        Why: peers link to each other directly, each pair on its own schedule after they
        find each other, and a put sent before a pair's link is up is lost. The plant
        starts the run only once every service is ready (``await_services``), so
        nothing the run sends is lost on a link still being made (a lockstep run can end
        within a second: a link made late would miss all of it).
        """
        assert self.session is not None
        started_ns = time.monotonic_ns()
        missing = self._wait_tokens(
            stop, self.options.peers, self.peer_topics, ready=False, limit_s=PEER_LINK_WAIT_S
        )
        if missing and stop.is_set():
            return False
        if missing:
            self.unlinked_peers = list(missing)
            logger.error(
                "no link to %s after %g s: going on without (what this service sends "
                "them is lost until they link; see the summary's unlinked_peers)",
                ", ".join(missing),
                PEER_LINK_WAIT_S,
            )
            for topics in self.peer_topics:
                self.keep(self._watch_late_links(started_ns, topics))
        self.cpu_s_ready = time.process_time()
        for topics in self.robot_topics:
            self.keep(declare_alive(self.session, topics, self.name, ready=True))
        return True

    def _watch_late_links(self, started_ns: int, topics: Topics) -> Any:
        """A liveliness subscriber (under robot ``topics``' keys) that moves each peer of
        ``unlinked_peers`` to ``peers_linked_late`` when its token comes after all (over
        this session's own link to it: from then on what this service sends reaches it)."""
        assert self.session is not None

        def on_token(sample: zenoh.Sample) -> None:
            name = self._peer_label(topics.service_of(str(sample.key_expr)), topics)
            if sample.kind != zenoh.SampleKind.PUT or name not in self.unlinked_peers:
                return
            late_s = (time.monotonic_ns() - started_ns) / NS_PER_S
            self.unlinked_peers.remove(name)
            self.peers_linked_late[name] = round(late_s, 3)
            logger.warning("linked to %s after all, %.1f s after the wait began", name, late_s)

        return self.session.liveliness().declare_subscriber(
            topics.alive_all, on_token, history=True
        )

    def wait_for_peers(self, stop: threading.Event) -> bool:
        """Wait (event driven) until ``options.await_services`` are ready; False if
        stopped first."""
        return not self._wait_tokens(
            stop, self.options.await_services, self.robot_topics, ready=True
        )

    def _wait_tokens(
        self,
        stop: threading.Event,
        services: tuple[str, ...],
        robots: tuple[Topics, ...],
        *,
        ready: bool,
        limit_s: float | None = None,
    ) -> tuple[str, ...]:
        """Wait until ``services``' tokens are all present under the keys of every robot
        of ``robots``, until stopped, or for ``limit_s`` (None: no limit); the
        services still missing then (empty: none; under several robots, a service is
        named once per robot it is missing for, as ``service@robot``)."""
        assert self.session is not None
        missing: tuple[str, ...] = ()
        waited_s = 0.0
        warned = False
        for topics in robots:
            robot_missing = tuple(services)
            while robot_missing and not stop.is_set() and (limit_s is None or waited_s < limit_s):
                try:
                    wait_alive(self.session, topics, services, STOP_POLL_S, ready=ready)
                    robot_missing = ()
                except ServicesMissing as exc:
                    robot_missing = exc.missing
                    waited_s += STOP_POLL_S
                    if waited_s >= PEER_WAIT_LOG_S and not warned:  # what it waits for
                        warned = True
                        logger.warning("still waiting (robot %s): %s", topics.robot_id, exc)
            missing += tuple(self._peer_label(name, topics) for name in robot_missing)
        return missing

    def _peer_label(self, service: str, topics: Topics) -> str:
        """How a peer is named in ``unlinked_peers`` and the like: its service, and
        under several robots the robot whose keys it is missing from
        (``service@robot``)."""
        return f"{service}@{topics.robot_id}" if len(self.robot_topics) > 1 else service

    def write_summary(self) -> None:
        """``<run_dir>/<name>.summary.json``, atomically: this process's summary, and
        under ``earlier_incarnations`` those of the processes of this service that came
        before it in this run: the ones that closed (the file's) and the ones killed
        before they could (their running summaries, whose files are then removed). A
        restarted service: nothing it counted is lost, but what a killed process counted
        after its last running summary."""
        if self.options.run_dir is None:
            return
        run_dir, pid = self.options.run_dir, os.getpid()
        path = summary_path(run_dir, self.instance)
        path.parent.mkdir(parents=True, exist_ok=True)
        summary = {**self.summary(), "pid": pid}
        running = incarnation_paths(run_dir, self.instance)
        earlier = earlier_incarnations(path, pid, running)
        if earlier:
            summary["earlier_incarnations"] = earlier
        _write_json(path, summary)
        for taken_in in running:
            taken_in.unlink(missing_ok=True)

    def check_peers(self) -> list[str]:
        """The Zenoh ids linked to this session that are no participant of the run, newly
        seen ones logged (once each) and added to :attr:`unknown_peers`; run with each
        running summary."""
        if not self._participants or self.session is None or self.session.is_closed():
            return []
        return self._note_strangers(self.session.info.peers_zid())

    def _note_strangers(self, linked: Iterable[object]) -> list[str]:
        """Of the Zenoh ids ``linked``, those no participant of the run and not yet
        noted: logged, added to :attr:`unknown_peers`, announced (on_strangers)."""
        new = []
        with self._strangers_lock:
            for zid in strangers(linked, self._participants):
                if zid not in self.unknown_peers:
                    self.unknown_peers.append(zid)
                    new.append(zid)
        for zid in new:
            logger.warning(
                "a session that is no participant of this run linked (Zenoh id %s): "
                "it holds a run certificate or password; the access list gives it "
                "nothing", zid,
            )  # fmt: skip
        if new:
            self.on_strangers(new)
        return new

    def on_strangers(self, zids: list[str]) -> None:
        """Sessions that are no participant of the run newly linked to this one (already
        logged and counted); a service that owns an event stream announces them."""

    # -- running summaries -------------------------------------------------------------
    def start_running_summaries(self, period_s: float = SUMMARY_PERIOD_S) -> None:
        """Write the summary so far every ``period_s`` from a thread of its own, until
        close (no run directory: nothing to do)."""
        if self.options.run_dir is None or self._summary_thread is not None:
            return
        self._summary_thread = threading.Thread(
            target=self._running_summaries, args=(period_s,), name="summary", daemon=True
        )
        self._summary_thread.start()

    def _running_summaries(self, period_s: float) -> None:
        # The first at once: it pays the one-off costs (imports, caches: tens of ms of
        # the GIL) while the service starts, before any loop of the run does.
        self.write_running_summary()
        while not self._summary_stop.wait(period_s):
            self.write_running_summary()

    def _stop_running_summaries(self) -> None:
        self._summary_stop.set()
        if self._summary_thread is not None:
            self._summary_thread.join()

    def write_running_summary(self) -> None:
        """This process's summary so far to its incarnation file, atomically. The
        counters are read while the service's threads go on: one that changes mid-read
        (summary() raises) skips this period, logged once."""
        if self.options.run_dir is None:
            return
        pid = os.getpid()
        start_ns = time.thread_time_ns()
        self.check_peers()
        try:
            summary = {**self.summary(), "pid": pid, "running": True}
        except Exception:
            self.running_summary_failures += 1
            if self.running_summary_failures == 1:
                logger.warning("running summary skipped (read mid-change)", exc_info=True)
            return
        try:
            _write_json(incarnation_path(self.options.run_dir, self.instance, pid), summary)
        except OSError as exc:
            logger.warning("running summary not written: %s", exc)
            return
        self.running_summaries += 1
        cpu_ms = (time.thread_time_ns() - start_ns) / 1e6
        if self.running_summaries > 1:  # the first one pays one-off imports and caches
            self.running_summary_cpu_max_ms = max(self.running_summary_cpu_max_ms, cpu_ms)


def _write_json(path: Path, content: dict[str, Any]) -> None:
    """``content`` as JSON into ``path``, atomically (a reader sees the old or the new)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(content, indent=2) + "\n")
    os.replace(tmp, path)


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        content = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return content if isinstance(content, dict) else None


def earlier_incarnations(
    path: Path, pid: int, running: list[Path] | None = None
) -> list[dict[str, Any]]:
    """The summaries of the processes of a service other than ``pid``, oldest first: those
    in its summary file ``path`` (the file's own earlier incarnations, and the file itself
    if another process wrote it), then the running summaries ``running`` (oldest write
    first) of processes not among them (killed before they closed)."""
    earlier: list[dict[str, Any]] = []
    previous = _read_json(path)
    if previous is not None:
        earlier = list(previous.pop("earlier_incarnations", []))
        if previous.get("pid") != pid:
            earlier.append(previous)
    return _taken_in(earlier, {pid}, running or [])


def _taken_in(
    earlier: list[dict[str, Any]], pids: set[Any], running: list[Path]
) -> list[dict[str, Any]]:
    """``earlier`` and, after it, the running summaries of processes neither in it nor in
    ``pids``."""
    known = {incarnation.get("pid") for incarnation in earlier} | pids
    out = list(earlier)
    for running_path in running:
        incarnation = _read_json(running_path)
        if incarnation is not None and incarnation.get("pid") not in known:
            out.append(incarnation)
            known.add(incarnation.get("pid"))
    return out


def read_summary(run_dir: Path, service: str) -> dict[str, Any] | None:
    """What the processes of ``service`` reported in this run: the summary the last one
    wrote at close, with every earlier process's (killed ones' running summaries
    included) under ``earlier_incarnations``; if none closed (the last was killed, or
    stopped while starting), the newest running summary (``"running": true``), the others
    earlier. None: no process of it wrote anything."""
    running = incarnation_paths(run_dir, service)
    top = _read_json(summary_path(run_dir, service))
    if top is None:
        readable = [(path, _read_json(path)) for path in running]
        readable = [(path, content) for path, content in readable if content is not None]
        if not readable:
            return None
        newest_path, top = readable[-1]
        running = [path for path in running if path != newest_path]
    earlier = _taken_in(list(top.pop("earlier_incarnations", [])), {top.get("pid")}, running)
    if earlier:
        top["earlier_incarnations"] = earlier
    return top


def lower_priority_to(nice: int) -> None:
    """Run this thread (and the threads it starts later) at niceness ``nice`` at least:
    lowered to it if it runs above it, left alone if it already runs at or below it (a
    launcher may start the process niced; ``os.nice`` would add the two up)."""
    if nice > os.getpriority(os.PRIO_PROCESS, 0):
        os.setpriority(os.PRIO_PROCESS, 0, nice)


# A privilege's outcome in Service.privileges when it was not asked for.
NOT_REQUESTED = "not requested"
REFUSED = "refused"


def pin_to_cpus(cpus: tuple[int, ...]) -> str:
    """Run this process on the given CPUs (those that exist); no-op when none is given.
    Returns the outcome for the summary: "granted [...]", "refused: <why>" or
    NOT_REQUESTED."""
    if not cpus:
        return NOT_REQUESTED
    available = os.sched_getaffinity(0)
    wanted = set(cpus) & available
    if not wanted:
        logger.warning("cpu affinity %s: no such CPU here (have %s), not pinned", cpus, available)
        return f"{REFUSED}: CPU(s) {list(cpus)} not available (have {sorted(available)})"
    try:
        os.sched_setaffinity(0, wanted)
    except OSError as exc:
        logger.warning("cpu affinity %s refused (%s): not pinned", sorted(wanted), exc)
        return f"{REFUSED}: {exc}"
    logger.info("pinned to CPU(s) %s", sorted(wanted))
    return f"granted {sorted(wanted)}"


@contextlib.contextmanager
def fifo_scheduling(priority: int) -> Iterator[str]:
    """Within the block, run the calling thread, and every thread it starts (Zenoh's
    included, so open the session inside), under SCHED_FIFO at ``priority``; yields
    the outcome for the summary ("granted ...", "refused: <why>" or NOT_REQUESTED). The
    calling thread's old policy is back after the block.

    No-op for 0. Without CAP_SYS_NICE the kernel refuses: a warning says so and the
    thread stays normally scheduled.
    """
    if priority <= 0:
        yield NOT_REQUESTED
        return
    old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        logger.warning("SCHED_FIFO priority %d refused (%s): normal scheduling", priority, exc)
        yield f"{REFUSED}: {exc.strerror or exc} (needs CAP_SYS_NICE or RLIMIT_RTPRIO)"
        return
    logger.info("SCHED_FIFO priority %d", priority)
    try:
        yield f"granted (priority {priority})"
    finally:
        os.sched_setscheduler(0, old_policy, old_param)


def build_service_parser(name: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=f"teleop-{name}",
        description=f"zenoh-teleop {name} service (normally started by `teleop run` or "
        "`teleop up` under supervisord).",
    )
    parser.add_argument("--config", type=Path, default=None, help="TOML config file")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--run-dir", type=Path, default=None, help="where to write the summary")
    parser.add_argument("--listen", action="store_true", help="hold the bus endpoint")
    parser.add_argument(
        "--await",
        dest="await_services",
        default="",
        help="comma-separated services that must be ready before the work starts",
    )
    parser.add_argument(
        "--peers",
        default="",
        help="comma-separated other services of the stack: declare this one ready once "
        "it sees them all alive",
    )
    parser.add_argument("--continuous", action="store_true", help="run until stopped")
    parser.add_argument(
        "--hold-at",
        dest="hold_at_ns",
        type=sim_instants_ns,
        default=(),
        metavar="T[,T...]",
        help="the plant in lockstep: sim seconds at which it waits for the launcher's "
        "release before stepping on (where `teleop run` injects a fault)",
    )
    return parser


def sim_instants_ns(text: str) -> tuple[int, ...]:
    """``--hold-at``'s comma-separated sim seconds, as ns (argparse's type: a bad one is
    a usage error that says which)."""
    instants = []
    for part in (p.strip() for p in text.split(",")):
        try:
            seconds = float(part)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{part!r} is not a number of seconds") from None
        if not math.isfinite(seconds) or seconds < 0:
            raise argparse.ArgumentTypeError(f"{part!r}: sim seconds, finite and >= 0")
        instants.append(round(seconds * NS_PER_S))
    return tuple(instants)


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def stop_on_signals(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set ``stop``, from a thread of their own (call from the main
    thread, once per process).

    Python runs a signal's handler in the main thread between two bytecodes, which may
    be inside ``stop.wait()`` while that thread holds the Event's lock: ``stop.set()``
    in the handler then waits forever for its own thread (the signal module's warning on
    handlers and threading primitives: the process hangs so until supervisord kills it,
    its summary unwritten). So the handler does nothing: the
    interpreter's C-level handler writes the signal's number to a pipe
    (``signal.set_wakeup_fd``), and the thread reading it logs and sets ``stop``. It
    does so even while the main thread is stuck in native code. A stop signal that
    comes again, :data:`STOP_AGAIN_DUMP_S` or more after the first, while the process
    is still there prints every thread's stack to the log: where a slow stop is.
    """
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    for signum in STOP_SIGNALS:
        signal.signal(signum, _no_op_handler)

    def watch() -> None:
        first_ns = 0
        while True:
            for signum in os.read(read_fd, 64):
                if signum not in STOP_SIGNALS:
                    continue
                name = signal.Signals(signum).name
                now_ns = time.monotonic_ns()
                if not first_ns:
                    first_ns = now_ns
                    logger.info("signal %s: stopping", name)
                    stop.set()
                    continue
                waited_s = (now_ns - first_ns) / NS_PER_S
                logger.info("signal %s again, %.1f s after the first: stopping", name, waited_s)
                if waited_s >= STOP_AGAIN_DUMP_S:
                    faulthandler.dump_traceback(all_threads=True)

    threading.Thread(target=watch, name="signals", daemon=True).start()


def _no_op_handler(signum: int, frame: FrameType | None) -> None:
    """A Python-level handler must be installed for the wakeup fd to hear the signal;
    the work is the ``signals`` thread's (:func:`stop_on_signals`)."""


def service_main(service_class: type[Service], argv: list[str] | None = None) -> int:
    """Entry point of a service process: parse, build, run until stopped, close."""
    logging.basicConfig(
        level=logging.INFO,
        format=f"%(asctime)s {service_class.name} %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    # `kill -USR1 <pid>` prints every thread's stack to the log, even while the main
    # thread is stuck in native code (where a Python signal handler cannot run).
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    args = build_service_parser(service_class.name).parse_args(argv)
    try:
        config = load_config(args.config, args.overrides)
    except ConfigError as exc:
        logger.error("config: %s", exc)
        return EXIT_CONFIG
    options = ServiceOptions(
        run_dir=args.run_dir,
        listen=args.listen,
        await_services=tuple(s for s in args.await_services.split(",") if s),
        peers=tuple(s for s in args.peers.split(",") if s),
        continuous=args.continuous,
        hold_at_ns=args.hold_at_ns,
    )
    scheduled_as = service_class.scheduling_as or service_class.name
    pinning = pin_to_cpus(config.cpu.for_service(scheduled_as, config.run.mode))
    fifo_priority = config.cpu.fifo_priority_for(scheduled_as, config.run.mode)
    if not fifo_priority and os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
        # A restart that did its imports under the restart priority
        # (teleop.run.restart_priority): this service's own scheduling from here, before
        # it starts a thread (Zenoh's would keep the realtime policy for good).
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    stop = threading.Event()
    stop_on_signals(stop)
    try:
        with fifo_scheduling(fifo_priority) as fifo, service_class(config, options) as service:
            service.privileges.update(sched_fifo=fifo, cpu_pinning=pinning)
            service.start_running_summaries()
            if service.become_ready(stop):
                logger.info("running (robot %s)", config.robot.robot_id)
                service.run(stop)
    except (ConfigError, ModelError) as exc:
        logger.error("%s", exc)
        return EXIT_CONFIG
    except Exception:
        # Logged whole (the launcher quotes the log's tail), then a plain exit: the
        # session is closed by now (Service.__enter__/__exit__), nothing keeps us alive.
        logger.exception("%s failed", service_class.name)
        return EXIT_FAILED
    logger.info("stopped")
    # The stop signal may come twice (the launcher and supervisord both send it); what
    # comes after this is the interpreter's exit.
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    return 0
