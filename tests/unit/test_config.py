"""The typed config: file, defaults and --set overrides agree; bad input is refused clearly."""

from __future__ import annotations

import pytest

from teleop.core.config import Config, ConfigError, load_config


def test_deploy_file_matches_dataclass_defaults():
    assert load_config() == Config()


def test_overrides_parse_toml_literals():
    config = load_config(
        None,
        [
            "control.compensation=false",
            "path.center_m=[0.2, 0.1, 0.3]",
            "run.seed=7",
            "robot.robot_id=arm9",
            "run.duration_s=5",
        ],
    )
    assert config.control.compensation is False
    assert config.path.center_m == (0.2, 0.1, 0.3)
    assert config.run.seed == 7
    assert config.robot.robot_id == "arm9"
    assert config.run.duration_s == 5.0 and isinstance(config.run.duration_s, float)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("control.bogus=1", "unknown key"),
        ("nosection.x=1", "unknown key"),
        ("control.compensation=3", "true or false"),
        ("run.duration_s=-1", "run.duration_s > 0"),
        ("run.duration_s=nan", "finite"),
        ("path.center_m=[1, 2]", "path.center_m: expected 3 items"),
        ("robot.arm_actuators=['a']", "one actuator per arm joint"),
        ("missing-equals", "dotted.key=value"),
        ("plant.lockstep_delay_steps=-1", "plant.lockstep_delay_steps in"),
        ("plant.lockstep_delay_steps=9", "plant.lockstep_delay_steps in"),
    ],
)
def test_bad_values_are_refused_with_the_key_named(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")


def test_a_misspelt_key_gets_a_suggestion():
    with pytest.raises(ConfigError, match=r"duraton_s \(did you mean duration_s\?\)"):
        load_config(None, ["run.duraton_s=3"])
    with pytest.raises(ConfigError, match=r"runn \(did you mean run\?\)"):
        load_config(None, ["runn.seed=3"])


def test_a_range_error_shows_the_value_given():
    with pytest.raises(ConfigError, match=r"run.duration_s > 0 \(got -3.0\)"):
        load_config(None, ["run.duration_s=-3"])


def test_a_malformed_toml_literal_is_reported_as_such():
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(None, ["path.center_m=[0.1, 0.0"])
    # A bare word is still a string.
    assert load_config(None, ["bus.zenoh_config=local.json5"]).bus.zenoh_config == "local.json5"


def test_the_recorder_flushes_often_only_while_a_live_viewer_watches():
    file_only = load_config().recorder
    assert file_only.flush_every_s == file_only.flush_period_s
    for live in ("recorder.spawn=true", 'recorder.grpc_url="rerun+http://127.0.0.1:9876/proxy"'):
        recorder = load_config(None, [live]).recorder
        assert recorder.flush_every_s == recorder.live_flush_period_s < recorder.flush_period_s


@pytest.mark.parametrize(
    ("rate_hz", "message"),
    [
        ("300", "loop.rate_hz = 300: must divide the physics rate 1000 Hz"),
        ("2000", "loop.rate_hz = 2000: must divide the physics rate 1000 Hz"),
        ("20", "loop.rate_hz >= 100"),
    ],
)
def test_a_bus_rate_that_does_not_divide_the_physics_rate_is_refused(rate_hz, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [f"loop.rate_hz={rate_hz}"])


@pytest.mark.parametrize("rate_hz", [100, 200, 250, 500, 1000])
def test_each_bus_rate_takes_whole_physics_steps_and_servo_periods(rate_hz):
    config = load_config(None, [f"loop.rate_hz={rate_hz}"])
    assert config.physics_steps_per_tick * config.plant.timestep_s == pytest.approx(config.tick_s)
    assert config.renders_per_tick * config.haptic.render_period_s == pytest.approx(config.tick_s)
    assert config.plant.watchdog_s >= 2 * config.tick_s
