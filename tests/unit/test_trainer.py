"""The trainer's job, driven directly (no bus): real `.rrd` in, certified network in the registry, gate passed."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from neso.certificate import CertificateInputs, max_certified_lipschitz
from neso.hotswap import gate
from neso.netfile import load_network
from services import registry
from services.trainer import Job, TrainerConfig, parse_job, train_job
from tests.helpers import BASE, flight_messages, write_recording

ACTIVE = {"id": "base-L1.0", "path": BASE, "lipschitz_norm": 1.0}


@pytest.fixture
def rrd(tmp_path):
    path = tmp_path / "flight.rrd"
    write_recording(path, flight_messages(300, pathway="neural_eso"))
    return str(path)


def test_a_tdr_job_trains_from_the_active_network_stores_certifies_and_offers(rrd, tmp_path):
    config = TrainerConfig(registry=str(tmp_path / "registry"))
    offered = []
    job = parse_job(1, {"recordings": [rrd], "label": "tdr", "epochs": 3}, config)
    result = train_job(job, config, "uav1", ACTIVE, lambda p: offered.append(p) or (True, "in shadow"))
    assert offered == [result.path] and result.offer == (True, "in shadow")
    assert set(result.timings_s) == {"dataset", "train", "certify", "store", "offer"}
    net = load_network(result.path)
    base = load_network(BASE)
    assert net.layer_sizes == base.layer_sizes and (net.input_std == base.input_std).all(), "TDR keeps normalisation"
    assert net.metadata["parent"] == "base-L1.0" and net.metadata["vehicle"] == "uav1"
    assert json.loads(net.metadata["recordings"]) == [rrd]
    assert gate(Path(result.path).read_bytes(), active=base, vehicle="uav1").passed
    (entry,) = registry.entries(config.registry)
    assert entry.id == result.network_id
    row = entry.row()
    assert row["label"] == "tdr" and row["lipschitz_norm"] == 1.0 and row["lipschitz_phys"] == pytest.approx(
        base.lipschitz_bound_physical())
    cert = entry.info["certificate"]
    gains = CertificateInputs(kp=config.kp, kd=config.kd, omega_o=config.omega_o_rps, lipschitz=0.0)
    assert cert["max_certified_lipschitz"] == pytest.approx(max_certified_lipschitz(gains, "tight"), rel=1e-3)
    assert cert["holds"] is False and net.lipschitz_bound_physical() > cert["max_certified_lipschitz"], \
        "L_N = 31.6 physical is far above what the z gains certify (README)"
    assert entry.info["val_loss"] >= 0


def test_an_eso_job_trains_from_scratch_at_the_bound_asked(tmp_path):
    path = tmp_path / "eso.rrd"
    write_recording(path, flight_messages(300, pathway="eso"))
    config = TrainerConfig(registry=str(tmp_path / "registry"))
    job = parse_job(1, {"recordings": [str(path)], "label": "eso", "epochs": 2, "lipschitz_bound": 0.5,
                        "offer": False}, config)
    result = train_job(job, config, "uav1", None)
    assert result.offer is None and load_network(result.path).lipschitz_bound == 0.5
    assert load_network(result.path).metadata["parent"] == ""


def test_jobs_that_cannot_be_done_are_refused_with_the_reason(rrd, tmp_path):
    config = TrainerConfig(registry=str(tmp_path / "registry"), recordings_dir=str(tmp_path / "none"))
    for args, reason in (({}, "no recordings given"), ({"recordings": ["/nope.rrd"]}, "no such recording"),
                         ({"recordings": [rrd], "label": "x"}, "label"), ({"recordings": [rrd], "epochs": 0}, "epochs"),
                         ({"recordings": [rrd], "lipschitz_bound": -1}, "lipschitz_bound"),
                         ({"recordings": [rrd], "bogus": 1}, "unknown")):
        with pytest.raises(ValueError, match=reason):
            parse_job(1, args, config)
    job = Job(1, (rrd,), "tdr", None, 2, True, 0)
    with pytest.raises(ValueError, match="no NetworkMsg"):
        train_job(job, config, "uav1", None)
    with pytest.raises(ValueError, match="vehicle 'uav1'"):
        train_job(job, config, "uav2", ACTIVE)
