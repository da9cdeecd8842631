"""How the stack runs on its hosts: CPU affinity and scheduling (``cpu``), the Zenoh bus
(``bus``), the sites of a two-host run (``site``), and the Rerun recorder (``recorder``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from teleop.core.config.base import DEPLOY_DIR, REPO_ROOT, require


@dataclass(frozen=True)
class CpuConfig:
    """CPU affinity of the services (CPU numbers; empty = let the kernel choose).

    The default is laid out for the 2-core target: the plant alone on CPU 0 (warm
    caches, no migrations, nothing waking up on its core), controller, recorder and eye
    view on CPU 1; haptic, HMD and operator free. Pinned, the realtime plant keeps time
    closer and overruns less than unpinned; lockstep speed is the same either way.
    CPUs the machine does not have are ignored (a warning says so); on a machine with
    more cores give each loop its own.
    """

    plant: tuple[int, ...] = (0,)
    controller: tuple[int, ...] = (1,)
    haptic: tuple[int, ...] = ()
    hmd: tuple[int, ...] = ()
    operator: tuple[int, ...] = ()
    recorder: tuple[int, ...] = (1,)
    eyeview: tuple[int, ...] = (1,)
    # Lockstep: the recorder shares the plant's CPU instead. With the lockstep delay the
    # controller is the busier of the two (the plant waits for it part of each cycle).
    recorder_lockstep: tuple[int, ...] = (0,)
    # Realtime runs: SCHED_FIFO priority (1-99) of the bilateral loop's processes; 0 =
    # normal scheduling. A FIFO thread that wakes runs at once, ahead of every normal
    # process (recorder, eye view, HMD, operator, anything else on the host), so a
    # message waits for a core only while another loop service is working: on a 2-core
    # machine the round trip's p99 and the samples shed while behind fall several-fold
    # (tests/benchmarks/latency_stack_variants.py measures it). The loops are event
    # driven (no busy wait), and the kernel's RT throttling (sched_rt_runtime_us) keeps
    # 5 % of each CPU for normal tasks in any case. Not in lockstep: there plant and
    # controller run flat out and would starve the recorder. Needs CAP_SYS_NICE (root
    # has it); without it a warning says so and the service runs normally scheduled.
    fifo_priority: int = 40
    # Which processes get it: the loop services, and the operator that feeds them (its
    # hand; 100 light decisions a second). Normally scheduled, or below the loops, the
    # operator waits behind them, and on 2 cores they can keep both busy: its hand
    # inputs then come late (haptic.hand_input_stale_s), and a recorder or eye view
    # restarting (seconds of imports) takes the CPU it needs.
    fifo_services: tuple[str, ...] = ("plant", "controller", "haptic", "operator")
    # A restart of one of fifo_services (killed, crashed) runs its start-up (imports,
    # model loading: seconds of CPU) under SCHED_FIFO at this priority, in both timing
    # modes: below the loops, above every normally scheduled process. Realtime loops
    # leave a small share of 2 cores to everything else, and a normally scheduled
    # restart shares it with whatever else runs on the host (teleop.run.restart_priority).
    # 0: restarts start normally scheduled. Must be below fifo_priority when that is set.
    restart_fifo_priority: int = 1
    # Realtime runs: one spinner per CPU (teleop/run/idle_poll.py: SCHED_IDLE in a CPU
    # cgroup marked idle) so the idle CPUs poll instead of halting. On a KVM guest a
    # halted vCPU leaves its host core (cold caches, a hypervisor exit on every wake-up);
    # polling shortens the round trip and the services' own CPU time. Anything else that
    # wants a CPU preempts its spinner at once; the cost is CPUs that read 100 % busy
    # while the stack runs. The floor's relay chain polls alike.
    idle_poll: bool = True
    # Which CPUs poll (empty: every CPU the launching process may use). On a machine
    # with more cores than the stack needs, list the loop services' CPUs only.
    idle_poll_cpus: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        names = ("plant", "controller", "haptic", "hmd", "operator", "recorder", "eyeview",
                 "recorder_lockstep", "idle_poll_cpus")  # fmt: skip
        for name in names:
            require(all(c >= 0 for c in getattr(self, name)), f"cpu.{name}: CPU numbers >= 0")
        require(0 <= self.fifo_priority <= 99, "cpu.fifo_priority in [0, 99]")
        require(
            0 <= self.restart_fifo_priority <= 99
            and (not self.fifo_priority or self.restart_fifo_priority < self.fifo_priority),
            "cpu.restart_fifo_priority in [0, 99] and below cpu.fifo_priority",
        )

    def for_service(self, service: str, mode: str) -> tuple[int, ...]:
        """The CPUs of ``service`` in timing ``mode`` (empty: the kernel's choice)."""
        if service == "recorder" and mode == "lockstep":
            return self.recorder_lockstep
        return tuple(getattr(self, service, ()))

    def polls_idle(self, mode: str) -> bool:
        """Whether a stack in timing ``mode`` keeps its idle CPUs polling."""
        return self.idle_poll and mode == "realtime"

    def fifo_priority_for(self, service: str, mode: str) -> int:
        """SCHED_FIFO priority of ``service`` in timing ``mode``; 0: normal scheduling."""
        if mode != "realtime" or service not in self.fifo_services:
            return 0
        return self.fifo_priority


@dataclass(frozen=True)
class BusConfig:
    """How services reach each other over Zenoh."""

    # Zenoh json5 config: a file name inside deploy/zenoh/, or a path.
    zenoh_config: str = "local.json5"
    # Where the run's first service listens and every other connects (loopback only).
    endpoint: str = "tcp/127.0.0.1:7447"
    shm: bool = True
    shm_pool_bytes: int = 16 * 1024 * 1024
    # With shm: Zenoh's low-latency unicast transport (a put writes to the link itself,
    # no TX pipeline thread to hand it to; it has no QoS, so no priorities, and cannot
    # fragment: every payload over the SHM threshold then goes through shared memory,
    # which never falls back to the socket; without shm the default transport is kept,
    # as TCP must fragment an eye-view frame). It shortens the round trip by about a
    # third (tests/benchmarks/latency_stack_variants.py). With it, two peers that connect
    # to each other at once may never link: local.json5 lets only one of a pair connect
    # (gossip autoconnect_strategy "greater-zid"), and the launchers link the services
    # by an explicit mesh (see gossip below). Service.become_ready reports a pair that
    # never links (unlinked_peers).
    lowlatency: bool = True
    # How the peers of a run find each other. With gossip (the default), every process
    # connects to the run's listener (``endpoint``) and learns the others from it, then
    # links to them itself. A launcher instead gives every service the whole mesh
    # (teleop.run.stack.peer_mesh): its own listening endpoint and those of the peers it
    # connects to, with gossip off. Why: with the low-latency transport, a Zenoh 1.10.2
    # receive thread that handles gossip's link states holds the routing lock while it
    # blocks on a send, and a session declaring a subscriber meanwhile waits for that
    # lock for ever (a known class of upstream deadlocks under peer churn, zenoh issue
    # 2581): at start-up a service stuck in declare_subscriber, never alive, deaf to
    # SIGINT, in a few stacks of a hundred; none with the mesh.
    gossip: bool = True
    # This process's own listening endpoint when it is not the run's listener; empty:
    # an ephemeral loopback port (the peers learn it through gossip).
    peer_listen_endpoint: str = ""
    # Peers this process connects to besides ``endpoint`` (the launcher's mesh).
    peer_connect_endpoints: tuple[str, ...] = ()
    # Zenoh config entries set over the file, last: "path=json5", e.g.
    # 'transport/shared_memory/mode="lazy"' (the tuning benchmark tries variants this way).
    zenoh_overrides: tuple[str, ...] = ()
    # Launchers (teleop run / up / latency) give every process of a run its own user,
    # password and Zenoh id and an access-control list from the graph
    # (teleop/bus/access.py): only this run's processes can link, each may publish only
    # what the graph lets it. false: an open bus (any local process can join).
    secure: bool = True
    # With secure: the launchers make a certificate authority for the run and one
    # certificate per process (teleop/bus/tls.py) and link the run over tls/ endpoints
    # only, mutual TLS: both ends of every link are authenticated, each process's file
    # holds its own key only, and the access-control list knows a process by its
    # certificate's name and its session's Zenoh id together. Encrypts the bus; shared
    # memory and the low-latency transport work over TLS links as over TCP. false:
    # user/password authentication, where every service's file names the run's password
    # dictionary (see teleop/bus/access.py). Ignored without secure. Cost: see
    # docs/protocol.md, "TLS cost".
    tls: bool = True
    # This process's credentials file (written by its launcher; empty: no authentication).
    credentials_file: str = ""
    # Records per message on the observers' copies of the fast streams (recorder, eye
    # view; topics.plant_state_batch, ...): one message instead of 10 saves the recorder ~9
    # wake-ups per 10 ms at 1 kHz. Fewer when a message would reach the shared-memory
    # threshold (teleop.bus.session.batch_records: 6 plant states of 483 B).
    observer_batch_records: int = 10

    def __post_init__(self) -> None:
        require("/" in self.endpoint, "bus.endpoint like tcp/127.0.0.1:7447")
        require(
            all("/" in e for e in (*self.peer_connect_endpoints, self.peer_listen_endpoint or "/")),
            "bus.peer_listen_endpoint and bus.peer_connect_endpoints like tcp/127.0.0.1:7448",
        )
        require(self.observer_batch_records >= 1, "bus.observer_batch_records >= 1")
        require(
            all("=" in entry for entry in self.zenoh_overrides),
            "bus.zenoh_overrides: entries like path=json5value",
        )
        require(self.shm_pool_bytes >= 1 << 16, "bus.shm_pool_bytes >= 65536")

    @property
    def mutual_tls(self) -> bool:
        """Whether a launcher's run links over mutual TLS (``tls`` on a ``secure`` bus)."""
        return self.secure and self.tls

    @property
    def zenoh_config_path(self) -> Path:
        candidate = Path(self.zenoh_config)
        if candidate.is_absolute():
            return candidate
        if (DEPLOY_DIR / "zenoh" / candidate).exists():
            return DEPLOY_DIR / "zenoh" / candidate
        return REPO_ROOT / candidate


# The two sites of a run split across hosts (docs/sites.md): the robot's (plant,
# controller, recorder, eye view) and the operator's (haptic device, HMD, operator).
ROBOT_SITE = "robot"
OPERATOR_SITE = "operator"
SITES = (ROBOT_SITE, OPERATOR_SITE)
# Longest round trip a lockstep run emulates (ms): ten times a transatlantic link's.
MAX_EMULATED_ROUND_TRIP_MS = 2000.0


@dataclass(frozen=True)
class SiteConfig:
    """Which site of a two-host run this process belongs to, and how the two sites'
    routers link (docs/sites.md). Empty ``name``: the whole stack on one host."""

    name: str = ""  # "" (one host), "robot" or "operator"
    # A run of several robots (run.robots): the robot a robot site runs, when not the
    # first. The first robot's site ("") is the hub: it makes the run's identities, runs
    # the recorder, and its router is the one every other site's router connects to.
    robot: str = ""
    # The hub's router listens here for the other sites' routers: tls/ADDR:PORT with an
    # address of this host the others can reach.
    listen: str = ""
    # The operator site's router, and another robot's site's, connect here: the hub's
    # ``listen``.
    connect: str = ""
    # A round trip between the two sites emulated in sim time (ms; lockstep runs with the
    # scripted operator): what one site sends, the other takes this much simulated time
    # later, half each way (an odd number of ticks: the extra one on the way back). The
    # controller then sees the handle, and the handle feels the force, as they were then;
    # the operator sees the scene that much later too. What a distance does to the
    # bilateral loop, on any machine (docs/sites.md); a real network's delay is emulated
    # between two sites' routers by teleop.bench.netem.
    emulated_round_trip_ms: float = 0.0

    def __post_init__(self) -> None:
        require(self.name in ("", *SITES), f"site.name: empty or one of {', '.join(SITES)}")
        require(
            0.0 <= self.emulated_round_trip_ms <= MAX_EMULATED_ROUND_TRIP_MS,
            f"site.emulated_round_trip_ms in [0, {MAX_EMULATED_ROUND_TRIP_MS:g}]",
        )
        for key, endpoint in (("listen", self.listen), ("connect", self.connect)):
            require(
                not endpoint or endpoint.startswith("tls/"),
                f"site.{key}: tls/ADDRESS:PORT (sites link over mutual TLS only)",
            )
        hub = self.name == ROBOT_SITE and not self.robot
        require(not self.robot or self.name == ROBOT_SITE, "site.robot: a robot site's only")
        require(not self.listen or hub, "site.listen: the first robot's site's only")
        require(not self.connect or not hub, "site.connect: the operator site's or another robot's")


@dataclass(frozen=True)
class RecorderConfig:
    """The Rerun recorder service."""

    # Recording file; empty = <run dir>/recording.rrd.
    rrd_path: str = ""
    # Also open the native Rerun viewer (never in tests or CI).
    spawn: bool = False
    # Also stream to this Rerun gRPC server (``rerun+http://127.0.0.1:PORT/proxy``); empty:
    # none. ``teleop run --web`` starts a web viewer and sets it.
    grpc_url: str = ""
    # Draw the scene in 3D from the MuJoCo model (arm, gripper, table, bin, cube, obstacles).
    scene3d: bool = True
    # Rate of the 3D arm pose (Hz of sim time): the plant state is 1 kHz, a view needs less.
    scene_rate_hz: float = 30.0
    # A ghost pose of the arm (stroboscopic view, paper Fig. 7) every this much sim time (s).
    ghost_period_s: float = 3.0
    # Loop rates are counted over windows of this much of the producer's clock (s).
    rate_window_s: float = 1.0
    # Buffered samples are sent to Rerun in columns this often (s). Each flush costs about
    # the same whatever it carries (a send per entity), so fewer flushes cost less CPU.
    flush_period_s: float = 0.5
    # The same while a live viewer watches (``spawn`` or ``grpc_url``): its plots move on
    # at every flush.
    live_flush_period_s: float = 0.1
    # A segment's file is closed, its footer written, once it holds this much (MB), and
    # the recording goes on in the next (teleop.viz.recording_file): Rerun keeps a
    # file's chunk index, about as large as the file, in memory until its footer, so
    # this bounds the recorder's memory whatever the run's length.
    segment_mb: float = 16.0
    # The recording's segments on disk at most (MB; 0: every one kept): past it the
    # oldest closed segments are deleted, never the one being written, so a stack kept
    # up for a day holds its newest hours. At least two segments.
    keep_mb: float = 0.0
    # Scheduling niceness (0 normal .. 19 lowest): a logger must not delay the loops,
    # which on 2 cores share their CPUs with it (docs/faults.md on restart priorities).
    nice: int = 10

    @property
    def flush_every_s(self) -> float:
        """How often the buffered samples go out: ``live_flush_period_s`` while a live
        viewer watches, ``flush_period_s`` for the file alone."""
        live = self.spawn or bool(self.grpc_url)
        return self.live_flush_period_s if live else self.flush_period_s

    def __post_init__(self) -> None:
        require(0 < self.flush_period_s <= 5, "recorder.flush_period_s in (0, 5]")
        require(0 < self.live_flush_period_s <= 5, "recorder.live_flush_period_s in (0, 5]")
        require(0 <= self.nice <= 19, "recorder.nice in [0, 19]")
        require(0 < self.segment_mb <= 4096, "recorder.segment_mb in (0, 4096]")
        require(
            self.keep_mb == 0 or self.keep_mb >= 2 * self.segment_mb,
            "recorder.keep_mb: 0 (keep every segment) or at least two segments "
            f"(2 x recorder.segment_mb = {2 * self.segment_mb:g})",
        )
        require(self.scene_rate_hz > 0, "recorder.scene_rate_hz > 0")
        require(self.ghost_period_s > 0, "recorder.ghost_period_s > 0")
        require(self.rate_window_s > 0, "recorder.rate_window_s > 0")
        require(
            not self.grpc_url or self.grpc_url.startswith(("rerun://", "rerun+http")),
            "recorder.grpc_url: empty or a rerun:// / rerun+http(s):// URL",
        )
