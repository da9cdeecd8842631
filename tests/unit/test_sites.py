"""A run across hosts, without a bus: which site runs what, who may forward what, and
the robot site's bundles of identities for the other sites (teleop.run.sites)."""

from __future__ import annotations

import json
import os
import stat

import pytest
from cryptography import x509

from services.router import RouterService
from teleop.bus import graph
from teleop.bus.access import (
    OBSERVER,
    OPERATOR_OBSERVER,
    Credentials,
    access_control,
    participant_robots,
    rights,
)
from teleop.cli import EXIT_USAGE, main
from teleop.core.config import OPERATOR_SITE, ROBOT_SITE, ConfigError, load_config
from teleop.run.sites import (
    BUNDLE_FORMAT,
    OPERATOR_BUNDLE_FILE,
    SiteError,
    check_site,
    join_site,
    robot_bundle_file,
    write_site_bundles,
)
from teleop.run.stack import Launch, StackServices, run_credentials

SITE_LISTEN = "tls/10.213.0.1:7447"
GRASP = ['run.scenario="grasp"', "eyeview.enabled=true"]


def robot_config(*extra: str):
    return load_config(
        None, [*GRASP, f'site.name="{ROBOT_SITE}"', f'site.listen="{SITE_LISTEN}"', *extra]
    )


def test_every_service_has_one_site_and_the_sites_split_the_teleoperation_loop():
    assert {graph.site_of(s.name) for s in graph.SERVICES} == {ROBOT_SITE, OPERATOR_SITE}
    assert graph.site_of("haptic") == graph.site_of("operator") == OPERATOR_SITE
    assert graph.site_of("plant") == graph.site_of("controller") == ROBOT_SITE
    for site in (ROBOT_SITE, OPERATOR_SITE):
        assert graph.site_of(graph.router_name(site)) == site


def test_each_site_starts_its_own_services_and_router_and_knows_the_others():
    robot = StackServices.of(robot_config(), [])
    operator = StackServices.of(
        load_config(None, [*GRASP, 'site.name="operator"', 'site.connect="tls/10.0.0.1:1"']), []
    )
    assert robot.started == ("robot_router", "plant", "controller", "recorder", "eyeview")
    assert robot.remote == ("haptic", "hmd", "operator")
    assert operator.started == ("operator_router", "haptic", "hmd", "operator")
    assert operator.remote == ("plant", "controller", "recorder", "eyeview")
    assert robot.scenario == operator.scenario
    # The plant holds the robot site's endpoint; the operator site's router holds its own.
    assert robot.listener(Launch.UP) == "plant"
    assert operator.listener(Launch.UP) == "operator_router"
    one_host = StackServices.of(load_config(None, GRASP), [])
    assert one_host.remote == () and one_host.router == ""


@pytest.mark.parametrize(
    "overrides, message",
    [
        (['site.name="moon"'], "site.name"),
        (['site.name="robot"', 'site.listen="tcp/10.0.0.1:7447"'], "tls/"),
        (['site.name="operator"', 'site.listen="tls/10.0.0.1:7447"'], "first robot's site's"),
        (['site.name="robot"', 'site.connect="tls/10.0.0.1:7447"'], "operator site's or"),
        (['site.name="operator"', 'site.robot="arm1"'], "a robot site's only"),
        (['site.name="robot"', 'site.robot="arm1"', 'site.listen="tls/10.0.0.1:1"'], "first"),
    ],
)
def test_a_site_setting_that_cannot_work_is_refused(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, overrides)


def test_sites_link_over_mutual_tls_only_and_need_their_endpoints():
    with pytest.raises(SiteError, match="mutual TLS"):
        check_site(robot_config("bus.tls=false"))
    with pytest.raises(SiteError, match="--site-listen"):
        check_site(load_config(None, [*GRASP, 'site.name="robot"']))
    with pytest.raises(SiteError, match="--connect"):
        check_site(load_config(None, [*GRASP, 'site.name="operator"']))
    with pytest.raises(SiteError, match="path-following has no operator site"):
        check_site(robot_config('run.scenario="path-following"'))
    check_site(robot_config())


def test_a_router_may_forward_every_stream_and_a_peer_only_its_own():
    every = sorted(s.key for s in graph.STREAMS)
    for router in graph.ROUTERS:
        produces, consumes = rights(router)
        assert sorted(produces) == sorted(consumes) == every
    produces, _ = rights("haptic")
    assert "cmd/joint_velocity" not in produces
    assert rights(OPERATOR_OBSERVER)[0] == []


def test_only_a_recovered_streams_producer_answers_for_its_records():
    """The access list's part in recovery (graph.Stream.recovered): the plant keeps its
    events' cache (heartbeats, the cache's queryable and replies out, queries in); the
    haptic service, a consumer, may ask for them and hear the answers, never answer;
    a stream without recovery has no such rights."""
    names = ["plant", "haptic", "controller"]
    acl = access_control({n: Credentials.generate(n) for n in names}, ("arm0",))
    rules = {rule["id"]: rule for rule in acl["rules"]}
    events, states = "teleop/arm0/events/plant", "teleop/arm0/state/plant"
    keeps = rules["plant-keeps"]
    assert keeps["flows"] == ["ingress"] and "reply" in keeps["messages"]
    assert f"{events}/@adv/pub/**" in keeps["key_exprs"] and events in keeps["key_exprs"]
    assert not any(key.startswith(states) for key in keeps["key_exprs"])
    assert f"{events}/@adv/**" in rules["plant-is-asked"]["key_exprs"]
    asks = rules["haptic-asks"]
    assert asks["flows"] == ["ingress"] and "reply" not in asks["messages"]
    assert f"{events}/@adv/**" in asks["key_exprs"]
    answered = rules["haptic-is-answered"]
    assert answered["flows"] == ["egress"] and f"{events}/@adv/pub/**" in answered["key_exprs"]
    replied_by_haptic = [
        r for r in acl["rules"]
        if r["id"].startswith("haptic-") and "reply" in r["messages"] and "ingress" in r["flows"]
    ]  # fmt: skip
    assert replied_by_haptic == []
    assert "controller-keeps" not in rules  # it produces no recovered stream


def _certificate(path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_the_robot_router_is_certified_at_its_site_address_the_others_on_loopback(tmp_path):
    files = run_credentials(robot_config(), tmp_path, ["plant", "haptic"])
    assert files is not None
    assert {"robot_router", "operator_router", OPERATOR_OBSERVER} <= set(files)

    def addresses(name: str) -> set[str]:
        tls = json.loads(files[name].read_text())["tls"]
        names = _certificate(tls_path := tmp_path / "auth" / f"{name}.cert.pem")
        assert tls["connect_certificate"] == str(tls_path)
        san = names.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        return {str(v) for v in san.get_values_for_type(x509.IPAddress)}

    assert addresses("robot_router") == {"127.0.0.1", "10.213.0.1"}
    assert addresses("operator_router") == addresses("haptic") == {"127.0.0.1"}


def test_the_operator_site_takes_its_identities_and_the_runs_settings_from_the_bundle(tmp_path):
    config = robot_config()
    robot_dir, operator_dir = tmp_path / "robot", tmp_path / "operator"
    robot_dir.mkdir()
    scenario = StackServices.of(config, []).scenario
    files = run_credentials(config, robot_dir, [*scenario])
    assert files is not None
    overrides = [*GRASP, 'site.name="robot"', 'bus.endpoint="tls/127.0.0.1:9"', "run.seed=2"]
    [(_, bundle)] = write_site_bundles(robot_dir, config, overrides, files, scenario)
    assert bundle == robot_dir / OPERATOR_BUNDLE_FILE
    assert stat.S_IMODE(bundle.stat().st_mode) == 0o600
    content = json.loads(bundle.read_text())
    # Only the operator site's identities: no key of the robot site's leaves it.
    assert set(content["identities"]["participants"]) == {
        "haptic", "hmd", "operator", "operator_router", OPERATOR_OBSERVER,
    }  # fmt: skip

    joined = join_site(OPERATOR_SITE, bundle, operator_dir)
    assert joined.connect == SITE_LISTEN
    assert joined.overrides == [*GRASP, "run.seed=2", 'robot.robot_id="arm0"']
    assert set(joined.credentials) == set(content["identities"]["participants"])
    assert stat.S_IMODE((operator_dir / "auth").stat().st_mode) == 0o700
    for name, path in joined.credentials.items():
        mine, theirs = json.loads(path.read_text()), json.loads(files[name].read_text())
        assert mine["zid"] == theirs["zid"]
        assert mine["access_control"] == theirs["access_control"]
        for key in ("connect_certificate", "connect_private_key", "root_ca_certificate"):
            assert os.path.dirname(mine["tls"][key]) == str(operator_dir / "auth")
            assert open(mine["tls"][key]).read() == open(theirs["tls"][key]).read()
            assert stat.S_IMODE(os.stat(mine["tls"][key]).st_mode) == 0o600


def test_a_bundle_others_may_read_or_that_is_no_bundle_is_refused(tmp_path):
    path = tmp_path / "bundle.json"
    with pytest.raises(SiteError, match="copy the robot site's"):
        join_site(OPERATOR_SITE, path, tmp_path / "run")
    path.write_text(json.dumps({"format": BUNDLE_FORMAT, "site": OPERATOR_SITE}))
    path.chmod(0o644)
    with pytest.raises(SiteError, match="chmod 600"):
        join_site(OPERATOR_SITE, path, tmp_path / "run")
    path.chmod(0o600)
    with pytest.raises(SiteError, match="malformed"):
        join_site(OPERATOR_SITE, path, tmp_path / "run")
    path.write_text("{not json")
    with pytest.raises(SiteError, match="not JSON"):
        join_site(OPERATOR_SITE, path, tmp_path / "run")
    path.write_text(json.dumps({"format": "something else"}))
    with pytest.raises(SiteError, match="not a site bundle"):
        join_site(OPERATOR_SITE, path, tmp_path / "run")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--site-listen", SITE_LISTEN], "go with --site"),
        (["--site", "operator"], "needs --join"),
        (["--site", "robot", "--connect", SITE_LISTEN], "goes with --join"),
        (["--site", "operator", "--site-listen", SITE_LISTEN], "first robot's site's"),
        (["--site", "robot", "--site-listen", SITE_LISTEN], "path-following has no operator"),
        (["--site", "robot", "--set", 'run.scenario="grasp"'], "--site-listen tls/"),
        (
            [
                "--site",
                "robot",
                "--set",
                'run.scenario="grasp"',
                "--set",
                "run.robots=2",
                "--set",
                'site.robot="arm1"',
                "--set",
                'site.connect="tls/10.0.0.1:1"',
            ],
            "--join robot-site-arm1.json",
        ),
    ],
)
def test_up_refuses_site_options_that_do_not_go_together(tmp_path, capsys, args, message):
    assert main(["up", *args, "--run-dir", str(tmp_path / "run")]) == EXIT_USAGE
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()  # nothing started


def test_a_sites_router_writes_its_summary_under_its_participants_name():
    config = load_config(None, ['site.name="robot"', 'site.listen="tls/127.0.0.1:7447"'])
    assert RouterService(config).instance == "robot_router"


TWO_ROBOTS = ["run.robots=2"]


def test_a_run_of_several_robots_has_a_robot_site_per_robot_the_first_one_the_hub():
    hub = StackServices.of(robot_config(*TWO_ROBOTS), [])
    second = StackServices.of(
        load_config(None, [*GRASP, *TWO_ROBOTS, 'site.name="robot"', 'site.robot="arm1"',
                           f'site.connect="{SITE_LISTEN}"']), [],
    )  # fmt: skip
    operator = StackServices.of(
        load_config(None, [*GRASP, *TWO_ROBOTS, 'site.name="operator"',
                           f'site.connect="{SITE_LISTEN}"']), [],
    )  # fmt: skip
    assert hub.started == (
        "robot_router", "plant-arm0", "controller-arm0", "recorder", "eyeview-arm0",
    )  # fmt: skip
    assert second.started == (
        "robot_router-arm1", "plant-arm1", "controller-arm1", "eyeview-arm1",
    )  # fmt: skip
    assert operator.started == ("operator_router", "haptic", "hmd", "operator")
    # Every process of the run on exactly one site.
    every = [n for s in (hub, second, operator) for n in s.started if not graph.is_router(n)]
    assert sorted(every) == sorted(hub.scenario)
    assert set(second.remote) == set(hub.scenario) - set(second.started)


def test_another_robots_site_acts_for_its_robot_alone():
    assert participant_robots("robot_router", ("arm0", "arm1")) == (
        "robot_router", ("arm0", "arm1"),
    )  # fmt: skip
    assert participant_robots("robot_router-arm1", ("arm0", "arm1")) == ("robot_router", ("arm1",))
    assert participant_robots(f"{OBSERVER}-arm1", ("arm0", "arm1")) == (OBSERVER, ("arm1",))
    names = ["robot_router-arm1", f"{OBSERVER}-arm1"]
    acl = access_control({n: Credentials.generate(n) for n in names}, ("arm0", "arm1"))
    keys = {k for rule in acl["rules"] for k in rule["key_exprs"] if rule["flows"] == ["ingress"]}
    assert any(k.startswith("teleop/arm1/") for k in keys)
    # Its peers' tokens: it sees every robot's (liveliness), sends and forwards arm1's only.
    published = {k for rule in acl["rules"] if rule["id"].endswith("-publishes")
                 for k in rule["key_exprs"]}  # fmt: skip
    assert published and all(k.startswith("teleop/arm1/") for k in published)
    second = RouterService(
        load_config(None, [*GRASP, *TWO_ROBOTS, 'site.name="robot"', 'site.robot="arm1"',
                           'robot.robot_id="arm1"', f'site.connect="{SITE_LISTEN}"'])
    )  # fmt: skip
    assert second.instance == "robot_router-arm1"
    assert [t.robot_id for t in second.robot_topics] == ["arm1"]


def test_a_robot_sites_services_wait_for_their_peers_under_their_own_robots_keys():
    """The hub's router (and recorder) work every robot's keys, but their peers on the
    hub are arm0's processes: arm1's run on another site and may come much later."""
    hub = RouterService(robot_config(*TWO_ROBOTS))
    assert [t.robot_id for t in hub.robot_topics] == ["arm0", "arm1"]
    assert [t.robot_id for t in hub.peer_topics] == ["arm0"]
    operator = RouterService(
        load_config(None, [*GRASP, *TWO_ROBOTS, 'site.name="operator"',
                           f'site.connect="{SITE_LISTEN}"'])
    )  # fmt: skip
    assert [t.robot_id for t in operator.peer_topics] == ["arm0", "arm1"]


def test_the_hub_hands_each_other_robots_site_its_own_identities(tmp_path):
    config = robot_config(*TWO_ROBOTS)
    check_site(config)
    hub_dir, second_dir = tmp_path / "hub", tmp_path / "second"
    hub_dir.mkdir()
    scenario = StackServices.of(config, []).scenario
    files = run_credentials(config, hub_dir, [*scenario])
    assert files is not None
    overrides = [*GRASP, *TWO_ROBOTS, 'site.name="robot"', "run.seed=2"]
    (operator_site, operator_bundle), (robot_site, robot_bundle) = write_site_bundles(
        hub_dir, config, overrides, files, scenario
    )
    assert (operator_site, robot_site) == (OPERATOR_SITE, ROBOT_SITE)
    assert operator_bundle.name == OPERATOR_BUNDLE_FILE
    assert robot_bundle == hub_dir / robot_bundle_file("arm1")
    content = json.loads(robot_bundle.read_text())
    assert set(content["identities"]["participants"]) == {
        "robot_router-arm1", f"{OBSERVER}-arm1", "plant-arm1", "controller-arm1", "eyeview-arm1",
    }  # fmt: skip
    with pytest.raises(SiteError, match="not of the operator site"):
        join_site(OPERATOR_SITE, robot_bundle, second_dir)
    joined = join_site(ROBOT_SITE, robot_bundle, second_dir)
    assert joined.connect == SITE_LISTEN
    assert joined.overrides == [*GRASP, *TWO_ROBOTS, "run.seed=2", 'robot.robot_id="arm0"',
                                'site.robot="arm1"']  # fmt: skip
    second = load_config(None, [*joined.overrides, 'site.name="robot"',
                                f'site.connect="{joined.connect}"'])  # fmt: skip
    check_site(second)
    assert second.robot_ids() == ("arm0", "arm1")
    elsewhere = [*joined.overrides[:-1], 'site.robot="arm2"', 'site.name="robot"',
                 f'site.connect="{SITE_LISTEN}"']  # fmt: skip
    with pytest.raises(SiteError, match="site.robot=arm2"):
        check_site(load_config(None, elsewhere))
