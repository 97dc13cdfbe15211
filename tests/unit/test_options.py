"""Every service's command line is generated from its config dataclass: the defaults are the config's."""
from __future__ import annotations

import argparse
import math

import pytest

from dashboard.service import DashboardConfig
from flight.controller import ControllerConfig
from flight.estimator import EstimatorConfig
from flight.source import SourceConfig
from neso.types import OMEGA_O_RPS
from runtime.options import add_options, config_from_options
from services.px4_gateway import GatewayConfig
from services.recorder import RecorderConfig
from services.trainer import TrainerConfig

CONFIGS = (EstimatorConfig, ControllerConfig, SourceConfig, GatewayConfig, RecorderConfig, TrainerConfig,
           DashboardConfig)


def parse(cls, argv: list[str]):
    parser = argparse.ArgumentParser(prog=cls.__name__)
    add_options(parser, cls)
    return config_from_options(cls, parser.parse_args(argv)), parser


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_no_options_give_the_configs_defaults(cls):
    config, _ = parse(cls, [])
    assert config == cls()


def test_options_convert_units_and_forms():
    est, _ = parse(EstimatorConfig, ["--rate", "100", "--omega-o", "20", "--canary-window", "70", "--allow-uncertified"])
    assert (est.dt_s, est.omega_o_rps, est.canary.window_samples, est.allow_uncertified) == (0.01, 20.0, 70, True)
    assert est.canary.margin == EstimatorConfig().canary.margin
    ctl, _ = parse(ControllerConfig, ["--rate", "250", "--mission", "idle"])
    assert ctl.control.dt_s == 1.0 / 250 and ctl.control.kp == ControllerConfig().control.kp and ctl.mission == "idle"
    gw, _ = parse(GatewayConfig, ["--max-tilt-deg", "30", "--no-learn-hover", "--forward-sources", "sim,mocap"])
    assert math.isclose(gw.max_tilt_rad, math.radians(30)) and not gw.learn_hover
    assert gw.forward_sources == ("sim", "mocap")
    src, _ = parse(SourceConfig, ["--wait-for", "", "--mocap-host", "10.0.0.2"])
    assert src.wait_for == () and src.mocap.hostname == "10.0.0.2" and src.mocap.type == SourceConfig().mocap.type
    rec, _ = parse(RecorderConfig, ["--manual"])
    assert rec.auto is False


def test_help_shows_each_default_with_its_unit():
    _, parser = parse(EstimatorConfig, [])
    text = " ".join(parser.format_help().split())
    assert "--rate RATE sample rate (must match the source's) [Hz]; default 50.0" in text
    assert f"--omega-o OMEGA_O observer bandwidth [rad/s]; default {OMEGA_O_RPS}" in text
    assert "--canary-window CANARY_WINDOW" in text


def test_a_bad_value_is_one_line_from_argparse(capsys):
    with pytest.raises(SystemExit):
        parse(ControllerConfig, ["--mission", "loop"])
    assert "invalid choice: 'loop'" in capsys.readouterr().err


def test_a_value_the_config_refuses_ends_with_its_reason():
    with pytest.raises(SystemExit, match="EstimatorConfig: canary: window_samples >= 10"):
        parse(EstimatorConfig, ["--canary-window", "7"])
