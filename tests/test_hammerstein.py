"""Hammerstein model: composition of NLS and ARX, model files and their failure modes."""

import hashlib
import json
from pathlib import Path

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


def _rehash(model_json, weights):
    """Make ``model.json``'s checksum match an edited ``weights.npz`` (to reach its checks)."""
    description = json.loads(model_json.read_text())
    description["weights_sha256"] = hashlib.sha256(weights.read_bytes()).hexdigest()
    model_json.write_text(json.dumps(description))


def _saved(model, tmp_path):
    directory = model.save(tmp_path / "m")
    return directory, directory / "model.json", directory / "weights.npz"


def test_truncated_weights_raise(model, tmp_path):
    _, _, weights = _saved(model, tmp_path)
    weights.write_bytes(weights.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"weights\.npz"):
        HammersteinModel.load(tmp_path / "m")


def test_missing_checksum_raises(model, tmp_path):
    _, model_json, _ = _saved(model, tmp_path)
    description = json.loads(model_json.read_text())
    del description["weights_sha256"]
    model_json.write_text(json.dumps(description))
    with pytest.raises(ValueError, match=r"model\.json.*weights_sha256.*mandatory"):
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
        (lambda d: d["arx"].pop("b"), r"arx\.b"),
        (lambda d: d["nls"].update(version=7), r"nls\.version. is 7"),
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
    _rehash(model_json, weights)
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


# -- atomic save ------------------------------------------------------------------------------


def test_refused_save_leaves_the_old_model_loadable(model, tmp_path):
    directory = model.save(tmp_path / "m")
    before = {p.name: p.read_bytes() for p in directory.iterdir()}
    bad = HammersteinModel(model.nls, ARX, metadata={"value": float("nan")})
    with pytest.raises(ValueError, match="JSON-safe"):
        bad.save(directory)
    assert {p.name: p.read_bytes() for p in directory.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no staging folder left
    u = _input(300, seed=8)
    np.testing.assert_array_equal(HammersteinModel.load(directory).simulate(u), model.simulate(u))


@pytest.mark.parametrize("fail_at", ["json", "rename-new", "rename-old"])
def test_interrupted_save_leaves_the_old_model_loadable(model, tmp_path, monkeypatch, fail_at):
    import identification.model_files as model_files

    directory = model.save(tmp_path / "m")
    u = _input(300, seed=9)
    other = HammersteinModel(model.nls, ARXModel([0.5], [1.0], noise_bound=0.1, dt=1e-3))
    real_replace, real_dumps = model_files.os.replace, model_files.json.dumps
    calls = []

    def replace(src, dst):
        calls.append((Path(src).name, Path(dst).name))
        if fail_at == "rename-old" and len(calls) == 1:
            raise KeyboardInterrupt  # before the old model moved aside
        if fail_at == "rename-new" and len(calls) == 2:
            raise KeyboardInterrupt  # old model aside, new one not yet in place
        return real_replace(src, dst)

    def dumps(*args, **kwargs):
        if kwargs.get("indent"):  # the write into the staging folder, after the weights
            raise KeyboardInterrupt
        return real_dumps(*args, **kwargs)

    if fail_at == "json":
        monkeypatch.setattr(model_files.json, "dumps", dumps)
    else:
        monkeypatch.setattr(model_files.os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        other.save(directory)
    monkeypatch.undo()
    np.testing.assert_array_equal(HammersteinModel.load(directory).simulate(u), model.simulate(u))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]
    other.save(directory)  # and a complete save replaces it
    np.testing.assert_array_equal(HammersteinModel.load(directory).simulate(u), other.simulate(u))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]


def test_save_onto_a_file_is_refused(model, tmp_path):
    (tmp_path / "m").write_text("not a folder")
    with pytest.raises(ValueError, match="not a folder"):
        model.save(tmp_path / "m")
    assert (tmp_path / "m").read_text() == "not a folder"


# -- fuzzed model files: ValueError naming the field, never another exception -----------------

_NUMBER = ["nan", "NaN", None, [1.0], {}, True, "1.0"]
_NUMBERS = [5, 5.0, "x", None, {}, ["nan"], [[1.0]], [None], [True]]
_INTEGER = [1.5, "3", None, [3], True, -1]
_STRING = [5, None, [], {}, "other"]
_OBJECT = [5, "x", [], [1.0]]
STRICT = {
    ("format",): _STRING,
    ("version",): _INTEGER,
    ("weights_sha256",): [*_STRING, "0" * 63, "g" * 64],
    ("weights_file",): [*_STRING, "other.npz"],
    ("metadata",): _OBJECT,
    ("arx",): [*_OBJECT, None],
    ("arx", "format"): _STRING,
    ("arx", "version"): _INTEGER,
    ("arx", "a"): _NUMBERS,
    ("arx", "a", 0): _NUMBER,
    ("arx", "b"): [*_NUMBERS, []],
    ("arx", "b", 1): _NUMBER,
    ("arx", "noise_bound"): _NUMBER,
    ("arx", "dt"): [*_NUMBER, 0.0, -1e-3],
    ("arx", "method"): [5, [], {}],
    ("arx", "history"): _OBJECT,
    ("nls",): [*_OBJECT, None],
    ("nls", "format"): _STRING,
    ("nls", "version"): _INTEGER,
    ("nls", "features"): [*_OBJECT, None],
    ("nls", "features", "name"): _STRING,
    ("nls", "features", "radii"): [*_NUMBERS, []],
    ("nls", "features", "radii", 0): [*_NUMBER, 0.0, -2.0],
    ("nls", "features", "initial_input"): _NUMBER,
    ("nls", "hidden"): [*_NUMBERS, [], [16, 16], [16, 16, 16, 16]],
    ("nls", "hidden", 0): [*_INTEGER, 0, 16.0],
    ("nls", "u_range"): [*_NUMBERS, [], [1.0], [1.0, 2.0, 3.0], [30.0, -30.0]],
    ("nls", "u_range", 1): [*_NUMBER, -40.0],
    ("nls", "training"): _OBJECT,
}
OPTIONAL = {("arx", "method"), ("arx", "history"), ("nls", "training"), ("metadata",),
            ("weights_file",)}  # fmt: skip


def _get(tree, path):
    for key in path:
        tree = tree[key]
    return tree


def _mutations():
    for path, values in STRICT.items():
        for value in values:
            yield path, "set", value
        if path not in OPTIONAL and not isinstance(path[-1], int):
            yield path, "delete", None


@pytest.fixture(scope="module")
def saved(model, tmp_path_factory):
    directory = model.save(tmp_path_factory.mktemp("fuzz") / "m")
    return json.loads((directory / "model.json").read_text()), (directory / "weights.npz")


def test_fuzzed_model_json_raises_value_error_naming_the_field(saved, tmp_path):
    description, weights = saved
    (tmp_path / "weights.npz").write_bytes(weights.read_bytes())
    n = 0
    for path, action, value in _mutations():
        edited = json.loads(json.dumps(description))
        parent = _get(edited, path[:-1])
        if action == "delete":
            del parent[path[-1]]
        else:
            parent[path[-1]] = value
        (tmp_path / "model.json").write_text(json.dumps(edited))
        with pytest.raises(ValueError) as caught:
            HammersteinModel.load(tmp_path)
        field = ".".join(str(p) for p in path if not isinstance(p, int))
        message = str(caught.value)
        assert field in message or "hidden widths" in message, (
            path,
            action,
            value,
            message,
        )
        n += 1
    assert n > 200


@pytest.mark.parametrize("number", ["NaN", "Infinity", "-Infinity"])
def test_non_standard_json_numbers_raise(saved, tmp_path, number):
    description, weights = saved
    (tmp_path / "weights.npz").write_bytes(weights.read_bytes())
    text = json.dumps(description).replace(
        f'"noise_bound": {description["arx"]["noise_bound"]!r}', f'"noise_bound": {number}'
    )
    assert number in text
    (tmp_path / "model.json").write_text(text)
    with pytest.raises(ValueError, match=number):
        HammersteinModel.load(tmp_path)


def test_random_json_mutations_raise_only_value_error(saved, tmp_path):
    """Any leaf (metadata and history included) set to any JSON value: loads or ValueError."""
    description, weights = saved
    (tmp_path / "weights.npz").write_bytes(weights.read_bytes())
    leaves = []

    def walk(tree, path):
        items = tree.items() if isinstance(tree, dict) else enumerate(tree)
        for key, value in items:
            if isinstance(value, (dict, list)) and value:
                walk(value, (*path, key))
            leaves.append((*path, key))

    walk(description, ())
    pool = [None, True, 0, -1, 1.5, 1e308, "", "nan", [], [1.0, "a"], {}, {"a": 1}, [[1.0]]]
    rng = np.random.default_rng(0)
    outcomes = {"loaded": 0, "ValueError": 0}
    for _ in range(300):
        edited = json.loads(json.dumps(description))
        for _ in range(int(rng.integers(1, 3))):
            path = leaves[int(rng.integers(len(leaves)))]
            try:
                parent = _get(edited, path[:-1])
                parent[path[-1]] = pool[int(rng.integers(len(pool)))]
            except (KeyError, IndexError, TypeError):
                continue  # an earlier mutation removed the parent
        (tmp_path / "model.json").write_text(json.dumps(edited))
        try:
            loaded = HammersteinModel.load(tmp_path)
        except ValueError:
            outcomes["ValueError"] += 1
            continue
        assert np.all(np.isfinite(loaded.simulate([0.0, 5.0, -5.0])))
        outcomes["loaded"] += 1
    assert outcomes["ValueError"] > 50 and outcomes["loaded"] > 20, outcomes


def _write_npz(path, arrays):
    with path.open("wb") as handle:
        np.savez(handle, **arrays)


def _weight_mutations(arrays):
    names = sorted(arrays)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if arrays[a].shape != arrays[b].shape:
                yield f"swap {a} {b}", {**arrays, a: arrays[b], b: arrays[a]}
    for name in names:
        value = arrays[name]
        yield f"drop {name}", {k: v for k, v in arrays.items() if k != name}
        yield f"add axis {name}", {**arrays, name: value[None]}
        if value.ndim:
            yield f"flatten-drop {name}", {**arrays, name: value.reshape(-1)[:-1]}
        yield f"nan {name}", {**arrays, name: np.full_like(value, np.nan)}
        yield f"text {name}", {**arrays, name: np.full(value.shape, "x")}
    yield "extra array", {**arrays, "nls.extra": np.zeros(3)}
    yield "foreign array", {**arrays, "other": np.zeros(3)}
    yield "empty archive", {}


def test_fuzzed_weights_raise_value_error(saved, tmp_path):
    description, weights = saved
    with np.load(weights, allow_pickle=False) as data:
        arrays = {k: np.array(data[k]) for k in data.files}
    model_json, weights_copy = tmp_path / "model.json", tmp_path / "weights.npz"
    n = 0
    for label, mutated in _weight_mutations(arrays):
        model_json.write_text(json.dumps(description))
        _write_npz(weights_copy, mutated)
        with pytest.raises(ValueError, match="SHA-256"):  # the checksum sees every change
            HammersteinModel.load(tmp_path)
        _rehash(model_json, weights_copy)  # and behind it, the array checks
        with pytest.raises(ValueError, match=r"weights\.npz") as caught:
            HammersteinModel.load(tmp_path)
        assert caught.type is ValueError, label
        n += 1
    raw = weights.read_bytes()
    for cut in (0, 1, 30, len(raw) // 3, len(raw) // 2, len(raw) - 22, len(raw) - 1):
        model_json.write_text(json.dumps(description))
        weights_copy.write_bytes(raw[:cut])
        _rehash(model_json, weights_copy)
        with pytest.raises(ValueError, match=r"weights\.npz.*cannot read"):
            HammersteinModel.load(tmp_path)
        n += 1
    np.save(weights_copy.with_suffix(".npy"), arrays["nls.skip_weight"])
    weights_copy.write_bytes(weights_copy.with_suffix(".npy").read_bytes())
    _rehash(model_json, weights_copy)
    with pytest.raises(ValueError, match=r"weights\.npz"):
        HammersteinModel.load(tmp_path)
    assert n > 60


def test_missing_files_raise_file_not_found(saved, tmp_path):
    description, weights = saved
    (tmp_path / "model.json").write_text(json.dumps(description))
    with pytest.raises(FileNotFoundError, match=r"weights\.npz"):
        HammersteinModel.load(tmp_path)
    (tmp_path / "model.json").unlink()
    (tmp_path / "weights.npz").write_bytes(weights.read_bytes())
    with pytest.raises(FileNotFoundError, match=r"model\.json"):
        HammersteinModel.load(tmp_path)


def test_loading_the_shipped_model_imports_no_env_or_torch():
    """Loading and simulating a saved model imports neither torch nor the env and its physics.

    ``identification.features`` imports ``piezo_env.operators``, which runs
    ``piezo_env/__init__``: that registers ``PiezoBender-v0`` and so imports
    ``gymnasium.envs.registration`` (gymnasium itself), but every other public name of the
    package loads on first access, so the env, the vector env and the FE model stay out.
    """
    import subprocess
    import sys

    shipped = Path(__file__).resolve().parents[1] / "docs" / "identify" / "model"
    code = (
        "import json, sys\n"
        "from identification import HammersteinModel\n"
        f"y = HammersteinModel.load({str(shipped)!r}).simulate([0.0, 5.0, 10.0, 3.0])\n"
        "assert len(y) == 4\n"
        "modules = ('torch', 'piezo_env.env', 'piezo_env.vector_env', 'piezo_env.model')\n"
        "heavy = [m for m in modules if m in sys.modules]\n"
        "import identification\n"
        "assert callable(identification.identify) and callable(identification.collect)\n"
        "print(json.dumps(heavy))\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], check=True, timeout=120, capture_output=True, text=True
    )
    assert json.loads(run.stdout.strip().splitlines()[-1]) == []
