"""Hammerstein model: composition of NLS and ARX, model files and their failure modes."""

import json

import numpy as np
import pytest

from identification.arx import ARXModel
from identification.features import play_operators
from identification.hammerstein import HammersteinModel
from identification.nls import fit_nls

pytest.importorskip("torch")


def _input(n, seed):
    rng = np.random.default_rng(seed)
    knots = rng.uniform(-30.0, 30.0, size=n // 15 + 2)
    times = np.concatenate([[0], np.cumsum(rng.integers(5, 25, size=knots.size - 1))])
    return np.interp(np.arange(n), times, knots)


def _hysteresis(u):
    plays, _ = play_operators(u, [3.0, 9.0, 16.0])
    return 0.7 * u + plays @ np.array([0.2, 0.1, 0.05])


ARX = ARXModel([1.5, -0.7], [0.5, 0.3], noise_bound=0.8, dt=1e-3)


@pytest.fixture(scope="module")
def model():
    u = _input(2000, seed=1)
    nls = fit_nls(u, _hysteresis(u), max_epochs=8, seed=0, hidden=(16, 16, 16))
    return HammersteinModel(nls, ARX, metadata={"bender": "PL140", "fit_percent": 97.5})


def test_simulate_and_predict_compose_nls_and_arx(model):
    u = _input(500, seed=2)
    z = model.nls_output(u)
    np.testing.assert_array_equal(z, model.nls(u))
    np.testing.assert_array_equal(model.simulate(u), ARX.simulate(z))
    y = model.simulate(u) + np.random.default_rng(0).uniform(-0.5, 0.5, size=u.size)
    np.testing.assert_array_equal(model.predict(u, y), ARX.predict(z, y))
    assert model.dt == 1e-3


def test_identity_nls_reduces_to_arx():
    u = _input(1500, seed=3)
    identity = fit_nls(u, u, max_epochs=2)
    hm = HammersteinModel(identity, ARX)
    u_test = _input(400, seed=4)
    np.testing.assert_allclose(hm.simulate(u_test), ARX.simulate(u_test), atol=1e-8)


def test_inverse_nls_round_trip(model):
    u = _input(200, seed=5) * 0.9
    z = model.nls_output(u)
    _, state = model.nls.features(u[:100])
    assert model.inverse_nls(z[100], state) == pytest.approx(u[100], abs=1e-6)


def test_save_load_round_trip_identical(model, tmp_path):
    model.save(tmp_path / "m")
    loaded = HammersteinModel.load(tmp_path / "m")
    u = _input(600, seed=6)
    np.testing.assert_array_equal(loaded.simulate(u), model.simulate(u))
    np.testing.assert_array_equal(loaded.arx.theta, model.arx.theta)
    assert loaded.arx.noise_bound == model.arx.noise_bound
    assert loaded.metadata == model.metadata
    assert loaded.nls.to_dict() == json.loads(json.dumps(model.nls.to_dict()))
    description = json.loads((tmp_path / "m" / "model.json").read_text())
    assert description["format"] == "piezo-hammerstein"
    assert description["version"] == 1
    with np.load(tmp_path / "m" / "weights.npz", allow_pickle=False) as data:
        assert all(data[k].dtype == np.float64 for k in data.files)


def _saved(model, tmp_path):
    directory = model.save(tmp_path / "m")
    return directory, directory / "model.json", directory / "weights.npz"


def test_truncated_weights_raise(model, tmp_path):
    _, _, weights = _saved(model, tmp_path)
    weights.write_bytes(weights.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"weights\.npz"):
        HammersteinModel.load(tmp_path / "m")


def test_truncated_weights_without_checksum_raise(model, tmp_path):
    _, model_json, weights = _saved(model, tmp_path)
    description = json.loads(model_json.read_text())
    del description["weights_sha256"]
    model_json.write_text(json.dumps(description))
    weights.write_bytes(weights.read_bytes()[:300])
    with pytest.raises(ValueError, match=r"weights\.npz.*cannot read"):
        HammersteinModel.load(tmp_path / "m")


def test_truncated_json_raises(model, tmp_path):
    _, model_json, _ = _saved(model, tmp_path)
    model_json.write_text(model_json.read_text()[:100])
    with pytest.raises(ValueError, match=r"model\.json.*not valid JSON"):
        HammersteinModel.load(tmp_path / "m")


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d.update(version=2), "version 2 is not supported"),
        (lambda d: d.update(format="other"), "format"),
        (lambda d: d.pop("arx"), "missing key"),
        (lambda d: d["arx"].pop("b"), "arx"),
        (lambda d: d["nls"].update(version=7), "NLS.*version"),
        (lambda d: d["nls"].update(hidden=[4, 4, 4]), "hidden widths"),
    ],
)
def test_edited_description_raises(model, tmp_path, edit, match):
    _, model_json, _ = _saved(model, tmp_path)
    description = json.loads(model_json.read_text())
    edit(description)
    model_json.write_text(json.dumps(description))
    with pytest.raises(ValueError, match=match):
        HammersteinModel.load(tmp_path / "m")


def test_weights_of_another_model_raise(model, tmp_path):
    u = _input(1000, seed=7)
    other = HammersteinModel(fit_nls(u, u, max_epochs=1, n_play=4, hidden=(16, 16, 16)), ARX)
    other.save(tmp_path / "other")
    _, model_json, weights = _saved(model, tmp_path)
    weights.write_bytes((tmp_path / "other" / "weights.npz").read_bytes())
    with pytest.raises(ValueError, match="SHA-256"):
        HammersteinModel.load(tmp_path / "m")
    description = json.loads(model_json.read_text())
    del description["weights_sha256"]
    model_json.write_text(json.dumps(description))
    with pytest.raises(ValueError, match=r"weights\.npz.*has shape"):
        HammersteinModel.load(tmp_path / "m")


def test_missing_file_and_bad_metadata(model, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"model\.json"):
        HammersteinModel.load(tmp_path / "nowhere")
    bad = HammersteinModel(model.nls, ARX, metadata={"value": float("nan")})
    with pytest.raises(ValueError, match="JSON-safe"):
        bad.save(tmp_path / "bad")
    with pytest.raises(ValueError, match="ARXModel"):
        HammersteinModel(model.nls, object())


def test_loaded_model_runs_without_torch(model, tmp_path):
    import subprocess
    import sys

    model.save(tmp_path / "m")
    code = (
        "import sys\n"
        "from identification.hammerstein import HammersteinModel\n"
        f"m = HammersteinModel.load({str(tmp_path / 'm')!r})\n"
        "y = m.simulate([0.0, 5.0, 10.0, 3.0])\n"
        "u = m.inverse_nls(2.0)\n"
        "m.nls.to_casadi_step()\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
