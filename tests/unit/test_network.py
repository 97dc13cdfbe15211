"""Lipschitz MLP: training bound, certificate vs empirical gradients, numpy/torch parity,
network-file round trip and refusals, rescaling, and the no-torch import rule."""
from __future__ import annotations

import json
import pickle
import struct
import subprocess
import sys

import numpy as np
import pytest

from neso.netfile import (NetworkFileError, load_network, network_from_bytes,
                          network_to_bytes, save_network)
from neso.network import LipschitzMLP
from neso.features import FEATURE_SETS, feature_set
from neso.network import fold_scalers
from neso.training import to_torch, train_lipschitz_mlp
from tests.helpers import random_network

# Paper-like inputs: 5 features with different scales and offsets (m, m/s, N, rad, rad).
_SCALES = np.array([0.4, 0.8, 3.0, 0.1, 0.1])
_OFFSETS = np.array([0.5, 0.0, 14.0, 0.0, 0.0])


def _inputs(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 5)) * _SCALES + _OFFSETS


def _gentle(z: np.ndarray, seed: int = 0) -> np.ndarray:
    zn = (z - _OFFSETS) / _SCALES
    return 0.3 * np.sin(zn[:, 0]) + 0.1 * zn[:, 1] + 0.02 * np.random.default_rng(seed).normal(size=len(z))


def _steep(z: np.ndarray, seed: int = 0) -> np.ndarray:
    zn = (z - _OFFSETS) / _SCALES
    return 2.0 * np.tanh(2.0 * zn[:, 0]) + 0.5 * zn[:, 1] + 0.02 * np.random.default_rng(seed).normal(size=len(z))


@pytest.fixture(scope="module")
def trained():
    """{(target, bound): TrainResult} for the gentle and steep targets at bounds 0.2, 0.5, 2.0."""
    z = _inputs(1200, seed=1)
    out = {}
    for name, fn in (("gentle", _gentle), ("steep", _steep)):
        y = fn(z)
        for bound in (0.2, 0.5, 2.0):
            out[(name, bound)] = train_lipschitz_mlp(
                z, y, lipschitz_bound=bound, epochs=30, seed=0,
                metadata={"id": f"{name}-{bound}", "data": "synthetic"})
    return out


@pytest.fixture(scope="module")
def net(trained) -> LipschitzMLP:
    return trained[("gentle", 2.0)].network


def _random_net(seed: int = 0, sizes=(5, 20, 25, 10, 1), bound: float = 1e6) -> LipschitzMLP:
    rng = np.random.default_rng(seed)
    ws = tuple(rng.normal(size=(sizes[i + 1], sizes[i])) for i in range(len(sizes) - 1))
    bs = tuple(rng.normal(size=sizes[i + 1]) for i in range(len(sizes) - 1))
    return LipschitzMLP(ws, bs, _OFFSETS, _SCALES, np.array([1.0]), np.array([2.0]), bound, {"id": "rand"})


# ---- (1) the bound holds after training ----------------------------------------------------
@pytest.mark.parametrize("target", ["gentle", "steep"])
@pytest.mark.parametrize("bound", [0.5, 2.0])
def test_trained_network_certified_within_bound(trained, target, bound):
    res = trained[(target, bound)]
    net = res.network
    assert net.lipschitz_bound == bound
    assert net.certified_lipschitz_normalised() <= bound
    # enforced per layer during training (projection to L^(1/n)), not just rescaled at export
    cap = bound ** (1 / net.n_layers)
    assert all(np.linalg.norm(w, ord=2) <= cap * (1 + 1e-6) for w in net.weights)
    # a binding bound: the optimiser pushes against it, so the certificate is close to it
    assert net.certified_lipschitz_normalised() > 0.5 * bound
    # the physical certificate folds the z-scores into the end layers: never above the loose L_N·σ_y/min σ_z
    phys = net.certified_lipschitz_physical()
    folded = fold_scalers(net.weights, net.input_std, net.output_std)
    assert phys == pytest.approx(np.prod([np.linalg.norm(w, 2) for w in folded]), rel=1e-12)
    assert phys <= net.certified_lipschitz_normalised() * net.output_std.max() / net.input_std.min() * (1 + 1e-12)
    assert res.n_train == 960 and res.n_val == 240
    assert len(res.history) == 30 and np.isfinite(res.val_loss)
    assert net.layer_sizes == (5, 20, 25, 10, 1)


# ---- (2) empirical gradients never exceed the certificate -----------------------------------
@pytest.mark.parametrize("key", [("gentle", 2.0), ("steep", 0.5), ("steep", 2.0)])
def test_empirical_gradient_below_certificate(trained, key):
    import torch

    net = trained[key].network
    model = to_torch(net)
    zn = np.random.default_rng(7).normal(scale=2.0, size=(2000, 5))
    z = torch.tensor(zn * net.input_std + net.input_mean, requires_grad=True)
    model(z).sum().backward()
    # chain rule into normalised units: dh_n/dzn = dh/dz * std_in / std_out
    g = z.grad.numpy() * net.input_std / net.output_std[0]
    emp = float(np.linalg.norm(g, axis=1).max())
    cert = net.certified_lipschitz_normalised()
    print(f"{key}: empirical max |grad h_n| = {emp:.4f}, certificate = {cert:.4f}, ratio = {emp / cert:.3f}")
    assert emp <= cert * (1 + 1e-9)
    assert emp > 0.05 * cert  # sanity: the certificate is not absurdly loose


def test_certificate_is_exact_svd_product():
    net = _random_net()
    expected = np.prod([np.linalg.svd(w, compute_uv=False)[0] for w in net.weights])
    assert net.certified_lipschitz_normalised() == pytest.approx(expected, rel=1e-12)


# ---- (3) numpy == torch ------------------------------------------------------------------------
def test_numpy_predict_matches_torch(net):
    import torch

    z = _inputs(500, seed=3) * 1.5
    with torch.no_grad():
        ref = to_torch(net)(torch.from_numpy(z)).numpy()
    np.testing.assert_allclose(net.predict(z), ref, atol=1e-5, rtol=0)
    np.testing.assert_allclose(net.predict(z[0]), ref[0], atol=1e-5, rtol=0)
    assert net.predict(z[0]).shape == (1,) and net.predict(z).shape == (500, 1)
    # folded fast path agrees with the plain normalised formula
    plain = net.output_mean + net.output_std * net.predict_normalised((z - net.input_mean) / net.input_std)
    np.testing.assert_allclose(net.predict(z), plain, rtol=1e-10, atol=1e-10)


# ---- (4) file round trip -------------------------------------------------------------------------
def test_save_load_round_trip(tmp_path, net):
    path = tmp_path / "net.safetensors"
    save_network(path, net)
    back = load_network(path, expected_inputs=5, expected_outputs=1)
    z = _inputs(300, seed=4)
    assert np.array_equal(back.predict(z), net.predict(z))
    for a, b in zip((*back.weights, *back.biases), (*net.weights, *net.biases)):
        assert np.array_equal(a, b)
    assert back.metadata == net.metadata
    assert back.metadata["id"] == "gentle-2.0" and "val_loss" in back.metadata
    assert back.lipschitz_bound == net.lipschitz_bound
    assert [p.name for p in tmp_path.iterdir()] == ["net.safetensors"]  # no temp file left

    header = _split(path.read_bytes())[0]
    meta = header["__metadata__"]
    assert meta["format"] == "neso-lipschitz-mlp" and meta["format_version"] == "2"
    assert meta["lipschitz_bound_units"] == "normalised"
    assert float(meta["certified_lipschitz_normalised"]) <= float(meta["lipschitz_bound"])
    assert float(meta["lipschitz_bound_physical"]) == pytest.approx(net.lipschitz_bound_physical())
    assert float(meta["certified_lipschitz_physical"]) == pytest.approx(net.certified_lipschitz_physical())
    assert meta["n_layers"] == "4"


def test_f32_tensors_accepted(net):
    tensors, meta = _tensors_meta(net)
    back = network_from_bytes(_build(tensors, meta, dtype="F32"))
    np.testing.assert_allclose(back.predict(_inputs(10, 5)), net.predict(_inputs(10, 5)), rtol=1e-5, atol=1e-5)


# ---- (5) refusals -------------------------------------------------------------------------------
def _split(data: bytes) -> tuple[dict, bytes]:
    (n,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8:8 + n]), data[8 + n:]


def _tensors_meta(net: LipschitzMLP) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    header, buf = _split(network_to_bytes(net))
    meta = header.pop("__metadata__")
    tensors = {k: np.frombuffer(buf[v["data_offsets"][0]:v["data_offsets"][1]], dtype="<f8").reshape(v["shape"]).copy()
               for k, v in header.items()}
    return tensors, meta


def _build(tensors: dict[str, np.ndarray], meta: dict[str, str], dtype: str = "F64") -> bytes:
    npd = {"F64": "<f8", "F32": "<f4", "F16": "<f2"}[dtype]
    header, chunks, off = {}, [], 0
    for k, a in tensors.items():
        raw = np.ascontiguousarray(a, dtype=npd).tobytes()
        header[k] = {"dtype": dtype, "shape": list(np.shape(a)), "data_offsets": [off, off + len(raw)]}
        chunks.append(raw)
        off += len(raw)
    header["__metadata__"] = meta
    h = json.dumps(header).encode()
    return struct.pack("<Q", len(h)) + h + b"".join(chunks)


def _refuses(data: bytes, word: str, **kw) -> None:
    with pytest.raises(NetworkFileError) as exc:
        network_from_bytes(data, **kw)
    assert word in str(exc.value), str(exc.value)


def test_builder_reproduces_a_loadable_file(net):
    tensors, meta = _tensors_meta(net)
    assert network_from_bytes(_build(tensors, meta)).metadata == net.metadata


def test_refuses_truncated(net):
    data = network_to_bytes(net)
    _refuses(data[:5], "truncated")       # shorter than the length prefix
    _refuses(data[:40], "truncated")      # header runs past the end
    _refuses(data[:-16], "truncated")     # tensor data cut off


def test_refuses_nan_weight(net):
    t, m = _tensors_meta(net)
    t["layers.2.weight"][3, 4] = np.nan
    _refuses(_build(t, m), "non-finite")


def test_refuses_inf_std(net):
    t, m = _tensors_meta(net)
    t["input_std"][2] = np.inf
    _refuses(_build(t, m), "non-finite")


def test_refuses_zero_std(net):
    t, m = _tensors_meta(net)
    t["output_std"][0] = 0.0
    _refuses(_build(t, m), "std")


def test_refuses_wrong_layer_shape(net):
    t, m = _tensors_meta(net)
    t["layers.1.weight"] = t["layers.1.weight"][:, :19]  # takes 19 inputs, layer 0 gives 20
    _refuses(_build(t, m), "chain")


def test_refuses_bias_mismatch(net):
    t, m = _tensors_meta(net)
    t["layers.0.bias"] = t["layers.0.bias"][:-1]
    _refuses(_build(t, m), "bias")


def test_refuses_normalisation_dims(net):
    t, m = _tensors_meta(net)
    t["input_mean"] = np.zeros(4)
    _refuses(_build(t, m), "input_mean")


def test_refuses_certificate_over_bound(net):
    t, m = _tensors_meta(net)
    # push the certificate 0.1 % over the stated bound; metadata unchanged
    t["layers.1.weight"] = t["layers.1.weight"] * (1.001 * net.lipschitz_bound / net.certified_lipschitz_normalised())
    _refuses(_build(t, m), "certificate")


def test_accepts_certificate_within_tolerance(net):
    t, m = _tensors_meta(net)
    m["lipschitz_bound_normalised"] = repr(net.certified_lipschitz_normalised() * (1 - 1e-8))
    network_from_bytes(_build(t, m))


def test_refuses_non_json_header(net):
    data = bytearray(network_to_bytes(net))
    data[8:16] = b"not json"
    _refuses(bytes(data), "JSON")


def test_header_length_with_pickle_like_first_byte_loads(net):
    t, m = _tensors_meta(net)
    for pad in range(0, 300):  # find a metadata size giving header length == 128 (mod 256)
        data = network_to_bytes(LipschitzMLP(net.weights, net.biases, net.input_mean, net.input_std,
                                             net.output_mean, net.output_std, net.lipschitz_bound,
                                             {**net.metadata, "pad": "x" * pad}))
        if data[0] == 0x80:
            break
    assert data[0] == 0x80
    assert network_from_bytes(data).metadata["pad"] == "x" * pad


def test_refuses_pickle(net):
    _refuses(pickle.dumps({"weights": list(net.weights)}), "pickle")
    _refuses(pickle.dumps(net.weights, protocol=0), "header")  # protocol 0 has no magic: still refused


def test_refuses_wrong_format_and_version(net):
    t, m = _tensors_meta(net)
    _refuses(_build(t, {**m, "format": "other"}), "format")
    _refuses(_build(t, {**m, "format_version": "3"}), "format_version")
    _refuses(_build(t, {**m, "lipschitz_bound_units": "furlongs"}), "lipschitz_bound_units")


def test_refuses_missing_tensor_and_bad_dtype(net):
    t, m = _tensors_meta(net)
    del t["output_mean"]
    _refuses(_build(t, m), "missing")
    t, m = _tensors_meta(net)
    _refuses(_build(t, m, dtype="F16"), "dtype")


def test_refuses_bad_offsets(net):
    data = network_to_bytes(net)
    header, buf = _split(data)
    header["input_std"]["data_offsets"][1] += 8  # size no longer matches shape
    h = json.dumps(header).encode()
    _refuses(struct.pack("<Q", len(h)) + h + buf, "size")


def test_refuses_unexpected_dims(net):
    _refuses(network_to_bytes(net), "expected", expected_inputs=6)
    _refuses(network_to_bytes(net), "expected", expected_outputs=3)


# ---- (6) rescaling ---------------------------------------------------------------------------
def test_scaled_to_bound_meets_bound_and_is_pure_rescale():
    net = _random_net()
    cert = net.certified_lipschitz_normalised()
    assert cert > 10.0
    bound = 1.5
    scaled = net.scaled_to_bound(bound)
    assert scaled.lipschitz_bound == bound
    assert scaled.certified_lipschitz_normalised() <= bound
    assert scaled.certified_lipschitz_normalised() == pytest.approx(bound, rel=1e-9)
    zn = np.random.default_rng(2).normal(size=(1000, 5))
    np.testing.assert_allclose(scaled.predict_normalised(zn), (bound / cert) * net.predict_normalised(zn),
                               rtol=1e-9, atol=1e-12)
    assert scaled.metadata == net.metadata
    # already within the bound: weights unchanged, stated bound updated
    same = scaled.scaled_to_bound(2.0)
    assert same.lipschitz_bound == 2.0
    assert all(np.array_equal(a, b) for a, b in zip(same.weights, scaled.weights))
    assert all(np.array_equal(a, b) for a, b in zip(same.biases, scaled.biases))


# ---- (7) the bound bites -----------------------------------------------------------------------
def test_tight_bound_fits_steep_function_worse(trained):
    tight, loose = trained[("steep", 0.2)], trained[("steep", 2.0)]
    print(f"steep: val loss L=0.2 {tight.val_loss:.4f}, L=2.0 {loose.val_loss:.4f}")
    assert tight.val_loss > 5.0 * loose.val_loss
    assert tight.val_loss_physical > loose.val_loss_physical


def test_training_deterministic_and_warm_start():
    z = _inputs(400, seed=9)
    y = _gentle(z)
    a = train_lipschitz_mlp(z, y, lipschitz_bound=1.0, epochs=5, seed=3)
    b = train_lipschitz_mlp(z, y, lipschitz_bound=1.0, epochs=5, seed=3)
    assert all(np.array_equal(p, q) for p, q in zip(a.network.weights, b.network.weights))
    assert a.history == b.history
    # TDR: warm start from `a`, new data, tighter bound; the base's normalisation is kept
    z2 = _inputs(400, seed=10) + np.array([0.0, 0.0, 2.0, 0.0, 0.0])
    c = train_lipschitz_mlp(z2, y + 0.5, lipschitz_bound=0.5, epochs=1, seed=0, init=a.network,
                            metadata={"id": "tdr"})
    assert c.network.certified_lipschitz_normalised() <= 0.5
    assert np.array_equal(c.network.input_mean, a.network.input_mean)
    assert np.array_equal(c.network.output_std, a.network.output_std)
    assert c.network.lipschitz_bound_physical() == pytest.approx(a.network.lipschitz_bound_physical() / 2)
    assert c.network.metadata["id"] == "tdr"


# ---- (8) no torch in the flight process -------------------------------------------------------
def test_imports_do_not_pull_torch():
    code = ("import sys, neso.network, neso.training, neso.netfile; "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr or "torch was imported"


# ---- physical bounds, feature sets ---------------------------------------------------------
@pytest.fixture(scope="module")
def physical():
    """A network trained to a physical bound on inputs of very different scales (0.1 rad vs 3 N)."""
    z = _inputs(1200, seed=7)
    return train_lipschitz_mlp(z, _steep(z), lipschitz_bound=0.8, bound_units="physical", epochs=30, seed=0,
                               metadata={"id": "phys", "feature_set": "paper@1"}).network


def test_a_physical_bound_is_met_exactly_by_the_folded_weights(physical):
    assert physical.bound_units == "physical" and physical.lipschitz_bound == 0.8
    assert physical.certified_lipschitz_physical() <= 0.8 * (1 + 1e-12)
    assert physical.certified_lipschitz_physical() > 0.4, "a binding bound: the optimiser pushes against it"
    assert physical.lipschitz_bound_physical() == 0.8


@pytest.mark.parametrize("which", ["physical", "normalised"])
def test_the_physical_bound_from_the_weights_is_never_exceeded_by_a_finite_difference_slope(physical, net, which):
    """Random pairs of physical inputs, near and far: |h(a) − h(b)| / ‖a − b‖ ≤ the certificate."""
    model = physical if which == "physical" else net
    bound = model.certified_lipschitz_physical()
    rng = np.random.default_rng(11)
    a = _inputs(20000, seed=12)
    steps = rng.normal(size=a.shape) * _SCALES * rng.choice([1e-3, 1e-1, 1.0, 10.0], size=(len(a), 1))
    b = a + steps
    slopes = np.abs(model.predict(a) - model.predict(b))[:, 0] / np.linalg.norm(a - b, axis=1)
    assert np.max(slopes) <= bound * (1 + 1e-9)
    assert np.max(slopes) > 0.05 * bound, "the pairs probe the steep directions too"


def test_re_expressing_a_network_under_other_z_scores_keeps_the_function_and_the_physical_bound(physical):
    z = _inputs(500, seed=9)
    other = physical.with_scalers(z.mean(axis=0) + 1.0, z.std(axis=0) * 3.0, np.array([0.7]), np.array([4.0]))
    np.testing.assert_allclose(other.predict(z), physical.predict(z), rtol=1e-11, atol=1e-11)
    assert other.certified_lipschitz_physical() == pytest.approx(physical.certified_lipschitz_physical(), rel=1e-12)
    assert other.certified_lipschitz_normalised() != pytest.approx(physical.certified_lipschitz_normalised(), rel=1e-3)


def test_a_warm_start_under_refitted_scalers_starts_from_the_same_function():
    z = _inputs(600, seed=2)
    base = train_lipschitz_mlp(z, _gentle(z), lipschitz_bound=2.0, bound_units="physical", epochs=10, seed=0,
                               metadata={"feature_set": "paper@1"}).network
    shifted = z * 1.5 + 0.3
    start = train_lipschitz_mlp(shifted, _gentle(z), lipschitz_bound=2.0, bound_units="physical", epochs=0, seed=0,
                                init=base, scalers="fit", start="init").network
    np.testing.assert_allclose(start.predict(z), base.predict(z), rtol=1e-9, atol=1e-9)
    assert not np.allclose(start.input_mean, base.input_mean)
    assert start.metadata["start"] == "init"
    # by default the start is whichever validates better: here the warm start no longer fits (inputs moved)
    best = train_lipschitz_mlp(shifted, _gentle(z), lipschitz_bound=2.0, bound_units="physical", epochs=0, seed=0,
                               init=base, scalers="fit")
    assert best.network.metadata["start"] == "linear"
    assert best.val_loss_vs_mean < 1.0


def test_every_feature_set_round_trips_through_the_network_file(tmp_path):
    for key, fs in FEATURE_SETS.items():
        net = random_network(3, sizes=(fs.size, 8, 1), bound=1.0)
        net = LipschitzMLP(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                           1.0, {"id": key, "feature_set": key, "thrust_lag_s": "0.04", "thrust_delay_s": "0.01"})
        path = tmp_path / f"{fs.name}.safetensors"
        save_network(path, net)
        back = load_network(path)
        assert back.feature_set is feature_set(key) and back.n_inputs == fs.size
        assert back.thrust_lag.time_constant_s == 0.04 and back.thrust_lag.delay_s == 0.01


def test_a_file_with_an_unknown_or_mis_sized_feature_set_is_refused_with_the_reason(net):
    t, m = _tensors_meta(net)
    _refuses(_build(t, {**m, "feature_set": "lidar@7"}), "unknown feature set 'lidar@7'")
    _refuses(_build(t, {**m, "feature_set": "state@1"}), "feature set state@1 has 4 inputs, the network takes 5")
    _refuses(_build(t, {**m, "feature_set": "paper@2"}), "unknown feature set")
    assert network_from_bytes(_build(t, {**m, "feature_set": "paper@1"})).feature_set.key == "paper@1"


def test_a_file_without_a_feature_set_was_trained_on_the_papers_inputs(net):
    t, m = _tensors_meta(net)
    m = {k: v for k, v in m.items() if k != "feature_set"}
    assert network_from_bytes(_build(t, m)).feature_set.key == "paper@1"
