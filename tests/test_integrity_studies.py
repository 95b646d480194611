"""Study integrity: a checkpoint is never mixed with another study; damaged files are rebuilt.

The audit's three silent reuses (another x0 scale in a sampler's closure, another LTV plant, another
noise grid) must be refused; truncated, altered or renamed chunks and a damaged ``meta.json`` must
be named (file path) and recomputed, never surface as a raw
``BadZipFile``/``EOFError``/``JSONDecodeError``.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import obsjax
from obsjax.montecarlo import CheckpointWarning

MODEL = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
OBS = obsjax.Luenberger.from_poles(MODEL, [-3.0, -3.5])
TS = np.linspace(0.0, 1.0, 6)
KEY = jr.PRNGKey(3)
N, CHUNK = 8, 4


def ltv_plant(amp):
    """The model's A plus a time-varying perturbation of amplitude `amp` (a closure value)."""
    A0 = jnp.asarray(MODEL.A)

    def A(t):
        return A0 + amp * jnp.sin(3.0 * t) * jnp.eye(2)

    return obsjax.LTV(A, lambda t: jnp.asarray(MODEL.C), B=lambda t: jnp.asarray(MODEL.B))


def scaled_normal(scale):
    return lambda k: scale * jr.normal(k, (2,))


def xhat0_zero(k):
    return jnp.zeros(2)


def study(plant, noise, x0_sampler, ckpt, **kw):
    kw = dict(x0_sampler=x0_sampler, xhat0_sampler=xhat0_zero, ts=TS, noise=noise, **kw)
    return obsjax.monte_carlo(
        plant, OBS, KEY, N, chunk_size=CHUNK, checkpoint=ckpt, progress=False, **kw
    )


# One study, computed once: its plant, noise and sampler objects are reused so the kernel compiles
# once.
PLANT_A = ltv_plant(0.3)
NOISE_A = obsjax.noise.BandLimitedNoise(0.05, dt=0.05)
X0_A = scaled_normal(1.0)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    ckpt = tmp_path_factory.mktemp("ref") / "ck"
    res = study(PLANT_A, NOISE_A, X0_A, ckpt)
    assert res.complete and res.n_failed == 0 and res.n_computed == N
    return res, ckpt


def _copy(reference, tmp_path):
    dst = tmp_path / "ck"
    shutil.copytree(reference[1], dst)
    return dst


@pytest.mark.extended
def test_an_equal_study_built_anew_resumes(reference, tmp_path):
    """Fingerprints are by content, not identity: freshly built equal objects load every chunk."""
    ck = _copy(reference, tmp_path)
    res = study(
        ltv_plant(0.3), obsjax.noise.BandLimitedNoise(0.05, dt=0.05), scaled_normal(1.0), ck
    )
    assert res.n_computed == 0
    np.testing.assert_array_equal(res.error_norm, reference[0].error_norm)


@pytest.mark.parametrize(
    "what",
    [
        "x0 scale in a closure",
        "LTV plant",
        "noise grid",
        "noise sigma",
        "simulate_kwargs",
        "study_id",
    ],
)
def test_a_changed_study_never_reuses_old_chunks(reference, tmp_path, what):
    ck = _copy(reference, tmp_path)
    plant, noise, x0, kw = PLANT_A, NOISE_A, X0_A, {}
    if what == "x0 scale in a closure":
        x0 = scaled_normal(1.5)
    elif what == "LTV plant":
        plant = ltv_plant(0.31)
    elif what == "noise grid":
        noise = obsjax.noise.BandLimitedNoise(0.05, dt=0.04)
    elif what == "noise sigma":
        noise = obsjax.noise.BandLimitedNoise(0.06, dt=0.05)
    elif what == "simulate_kwargs":
        kw = dict(simulate_kwargs={"rtol": 1e-7})
    else:
        kw = dict(study_id="second")
    with pytest.raises(ValueError, match="holds a different study"):
        study(plant, noise, x0, ck, **kw)


SCALE = 1.0


def x0_global_scale(k):
    return SCALE * jr.normal(k, (2,))


def test_globals_read_by_a_sampler_enter_the_fingerprint(tmp_path):
    global SCALE
    ck = tmp_path / "ck"
    study(
        PLANT_A, NOISE_A, x0_global_scale, ck, max_chunks=0
    )  # starts the directory, computes nothing
    try:
        SCALE = 2.0
        with pytest.raises(ValueError, match="holds a different study"):
            study(PLANT_A, NOISE_A, x0_global_scale, ck, max_chunks=0)
    finally:
        SCALE = 1.0
    study(PLANT_A, NOISE_A, x0_global_scale, ck, max_chunks=0)  # the same study again: accepted


def _settings_module(scale):
    """A user's settings module (``cfg.SCALE``), as a sampler reads it."""
    import types

    cfg = types.ModuleType("user_settings")
    cfg.SCALE = scale
    return cfg


@pytest.mark.extended
def test_settings_module_attributes_read_by_a_sampler_enter_the_fingerprint(tmp_path):
    # a module was hashed by its name only: a changed setting reused the old study's chunks without a word
    cfg = _settings_module(1.0)

    def x0_settings(k):
        return cfg.SCALE * jr.normal(k, (2,))

    ck = tmp_path / "ck"
    first = study(PLANT_A, None, x0_settings, ck)
    cfg.SCALE = 100.0
    with pytest.raises(ValueError, match="holds a different study"):
        study(PLANT_A, None, x0_settings, ck)
    fresh = study(PLANT_A, None, x0_settings, None)  # the changed study, computed anew in this process
    np.testing.assert_allclose(fresh.error_norm[:, 0], 100.0 * first.error_norm[:, 0], rtol=1e-12)
    cfg.SCALE = 1.0
    assert study(PLANT_A, None, x0_settings, ck).n_computed == 0  # the first study again: resumed


def _getattr_sampler(cfg):
    def x0_getattr(k):
        return getattr(cfg, "SCALE") * jr.normal(k, (2,))  # noqa: B009 - the access under test

    return x0_getattr


def x0_globals_dict(k):
    return globals()["SCALE"] * jr.normal(k, (2,))


@pytest.mark.parametrize("access", ["attribute", "getattr", "vars", "globals"])
def test_a_setting_read_by_name_enters_the_fingerprint(access):
    """``getattr(cfg, "SCALE")``, ``vars(cfg)["SCALE"]`` and ``globals()["SCALE"]`` name the setting by a
    string constant: the fingerprint read only co_names, so a resumed study and the in-process kernel
    cache served the old value (a fresh process resumed chunks drawn with SCALE = 1 for SCALE = 2)."""
    global SCALE
    from obsjax.montecarlo._fingerprint import fingerprint

    cfg = _settings_module(1.0)
    sampler = {
        "attribute": lambda k: cfg.SCALE * jr.normal(k, (2,)),
        "getattr": _getattr_sampler(cfg),
        "vars": lambda k: vars(cfg)["SCALE"] * jr.normal(k, (2,)),
        "globals": x0_globals_dict,
    }[access]
    before = fingerprint({"x0_sampler": sampler})[0]
    try:
        cfg.SCALE = SCALE = 2.0
        assert fingerprint({"x0_sampler": sampler})[0] != before
    finally:
        cfg.SCALE = SCALE = 1.0
    assert fingerprint({"x0_sampler": sampler})[0] == before


@pytest.mark.parametrize("form", ["import", "from-import", "relative"])
def test_a_setting_of_a_module_imported_inside_the_sampler_enters_the_fingerprint(tmp_path, monkeypatch, form):
    """``import cfg`` (or ``from cfg import SCALE``) inside the sampler: the module was bound by the
    function's own code, not read as a global, and was never hashed.  A changed setting resumed the old
    study's chunks, and a fresh study in the same process was served the kernel compiled with the old
    value (‖x̃(0)‖ unchanged after SCALE 1 → 100)."""
    import importlib
    import sys

    pkg = tmp_path / "user_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "cfg.py").write_text("SCALE = 1.0\n")
    body = {
        "import": "    import user_pkg.cfg\n    return user_pkg.cfg.SCALE * jr.normal(k, (2,))\n",
        "from-import": "    from user_pkg.cfg import SCALE\n    return SCALE * jr.normal(k, (2,))\n",
        "relative": "    from . import cfg\n    return cfg.SCALE * jr.normal(k, (2,))\n",
    }[form]
    (pkg / "samplers.py").write_text("import jax.random as jr\n\n\ndef x0(k):\n" + body)
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("user_pkg", "user_pkg.cfg", "user_pkg.samplers"):
        sys.modules.pop(name, None)
    try:
        sampler = importlib.import_module("user_pkg.samplers").x0
        ck = tmp_path / "ck"
        first = study(PLANT_A, None, sampler, ck)
        cfg = importlib.import_module("user_pkg.cfg")
        cfg.SCALE = 100.0
        with pytest.raises(ValueError, match="holds a different study"):
            study(PLANT_A, None, sampler, ck)
        fresh = study(PLANT_A, None, sampler, None)
        np.testing.assert_allclose(fresh.error_norm[:, 0], 100.0 * first.error_norm[:, 0], rtol=1e-12)
        cfg.SCALE = 1.0
        assert study(PLANT_A, None, sampler, ck).n_computed == 0
    finally:
        for name in ("user_pkg", "user_pkg.cfg", "user_pkg.samplers"):
            sys.modules.pop(name, None)


def test_a_setting_read_by_getattr_is_not_served_from_the_kernel_compiled_before():
    cfg = _settings_module(1.0)
    sampler = _getattr_sampler(cfg)
    first = study(PLANT_A, None, sampler, None)
    cfg.SCALE = 5.0
    second = study(PLANT_A, None, sampler, None)
    np.testing.assert_allclose(second.error_norm[:, 0], 5.0 * first.error_norm[:, 0], rtol=1e-12)


def test_the_random_stream_setting_enters_the_fingerprint():
    """``jax_threefry_partitionable`` changes every draw of jax.random from the same key: a study resumed
    under the other setting mixed chunks of two random streams (equal to neither uninterrupted study)."""
    import jax

    from obsjax.montecarlo._fingerprint import fingerprint

    old = jax.config.jax_threefry_partitionable
    before = fingerprint({"x0_sampler": X0_A})[0]
    draw = np.asarray(jr.normal(jr.fold_in(KEY, 3), (2,)))
    try:
        jax.config.update("jax_threefry_partitionable", not old)
        assert not np.allclose(np.asarray(jr.normal(jr.fold_in(KEY, 3), (2,))), draw)  # the premise
        assert fingerprint({"x0_sampler": X0_A})[0] != before
    finally:
        jax.config.update("jax_threefry_partitionable", old)
    assert fingerprint({"x0_sampler": X0_A})[0] == before


def test_a_changed_global_is_not_served_from_the_kernel_compiled_before(tmp_path):
    # same sampler object, a global it reads changed between two calls in one process (a notebook re-run):
    # the kernel must be traced again, not reused with the value baked in at the first trace
    global SCALE
    first = study(PLANT_A, None, x0_global_scale, None)
    try:
        SCALE = 100.0
        second = study(PLANT_A, None, x0_global_scale, None)
    finally:
        SCALE = 1.0
    np.testing.assert_allclose(second.error_norm[:, 0], 100.0 * first.error_norm[:, 0], rtol=1e-12)


AMP = 1.0
W = 1.0


def u_global_amp(t):
    return AMP * jnp.array([jnp.sin(3.0 * t)])


def ltv_A_global(t):
    return jnp.array([[-1.0, W], [0.0, -2.0]])


def loss_global_scale(traj):
    return SCALE * obsjax.losses.ise(traj)


@pytest.mark.parametrize(
    "how",
    [
        "adaptive",
        "fixed",
        pytest.param("lockstep", marks=pytest.mark.extended),
        "own-steps",
        pytest.param("ltv", marks=pytest.mark.extended),
    ],
)
@pytest.mark.extended
def test_simulate_traces_again_after_a_changed_global(how):
    """The same input function (or LTV plant function), a global it reads changed between two calls:
    simulate and simulate_batch must give the trajectory of the new value -- that of a new function
    object with the value written in -- not the one compiled before (diffrax's and equinox's jit key a
    function by identity; these calls returned the old trajectory)."""
    global AMP, W
    model = obsjax.LTI([[-2.0, 1.0], [0.0, -1.5]], [[0.0], [1.0]], [[1.0, 0.0]])  # a model mismatch
    obs = obsjax.Luenberger(model, L=[[3.0], [4.0]])
    x0, xh0 = jnp.array([1.0, 0.0]), jnp.zeros(2)

    def run(u):
        if how == "adaptive":
            return obsjax.simulate(MODEL, obs, x0, xh0, TS, u=u).xhat
        if how == "fixed":
            return obsjax.simulate(MODEL, obs, x0, xh0, TS, u=u, adaptive=False, dt0=0.01).xhat
        if how == "ltv":
            plant = obsjax.LTV(A=ltv_A_global, B=lambda t: jnp.zeros((2, 1)), C=lambda t: jnp.array([[1.0, 0.0]]))
            return obsjax.simulate(plant, obs, jnp.ones(2), xh0, TS).xhat
        batch = obsjax.simulate_batch(
            MODEL, obs, jnp.stack([x0, 2 * x0]), jnp.zeros((2, 2)), TS, u=u, lockstep=how == "lockstep"
        )
        return batch.xhat

    first = run(u_global_amp)
    try:
        AMP, W = 100.0, 5.0
        second = run(u_global_amp)
        if how == "ltv":
            ltv_fresh = obsjax.LTV(
                A=lambda t: jnp.array([[-1.0, 5.0], [0.0, -2.0]]),
                B=lambda t: jnp.zeros((2, 1)),
                C=lambda t: jnp.array([[1.0, 0.0]]),
            )
            fresh = obsjax.simulate(ltv_fresh, obs, jnp.ones(2), xh0, TS).xhat
        else:
            fresh = run(lambda t: 100.0 * jnp.array([jnp.sin(3.0 * t)]))
    finally:
        AMP, W = 1.0, 1.0
    assert np.max(np.abs(np.asarray(second) - np.asarray(first))) > 1e-3
    np.testing.assert_allclose(np.asarray(second), np.asarray(fresh), rtol=1e-12, atol=1e-14)


@pytest.mark.extended
def test_tune_traces_again_after_a_changed_global():
    """tune's kernel is keyed on its functions' content: a loss and an input that read a changed global
    give the loss of the new value (the first step's J), not the kernel compiled before."""
    global SCALE, AMP
    model = obsjax.LTI([[-2.0, 1.0], [0.0, -1.5]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.Luenberger(model, L=[[3.0], [4.0]])
    kw = dict(where=lambda o: o.L, x0s=jnp.array([[1.0, 0.0]]), xhat0s=jnp.zeros((1, 2)), ts=TS, steps=1,
              progress=False)  # fmt: skip

    def J(**more):
        return float(obsjax.tune(obs, MODEL, **kw, **more).history["loss"][0])

    j1 = J(loss=loss_global_scale, u=u_global_amp)
    try:
        SCALE, AMP = 10.0, 100.0
        j2 = J(loss=loss_global_scale, u=u_global_amp)
        fresh = J(loss=lambda tr: 10.0 * obsjax.losses.ise(tr), u=lambda t: 100.0 * jnp.array([jnp.sin(3.0 * t)]))
    finally:
        SCALE, AMP = 1.0, 1.0
    assert abs(j2 / j1 - 1.0) > 1.0
    np.testing.assert_allclose(j2, fresh, rtol=1e-12)


class _Drift:
    """A plain (non-dataclass) callable object: hashed by class code and instance attributes."""

    def __init__(self, a):
        self.a = a

    def __call__(self, t):
        return jnp.asarray(MODEL.A) + self.a * jnp.eye(2)


def test_methods_and_attributes_of_user_objects_enter_the_fingerprint(tmp_path):
    ck = tmp_path / "ck"
    C = lambda t: jnp.asarray(MODEL.C)  # noqa: E731
    plant = obsjax.LTV(_Drift(0.1), C)
    kw = dict(max_chunks=0)
    study(plant, None, X0_A, ck, **kw)
    study(obsjax.LTV(_Drift(0.1), C), None, X0_A, ck, **kw)
    with pytest.raises(ValueError, match="holds a different study"):
        study(obsjax.LTV(_Drift(0.2), C), None, X0_A, ck, **kw)


def test_what_cannot_be_fingerprinted_is_refused_unless_the_study_is_named(tmp_path):
    rng = np.random.default_rng(0)
    offset = rng.normal(size=2)

    def x0_from_generator(k):
        return jr.normal(k, (2,)) + jnp.asarray(offset) + 0.0 * rng.random()

    with pytest.raises(ValueError, match=r"x0_sampler\.<closure rng>.*Generator.*study_id"):
        study(PLANT_A, NOISE_A, x0_from_generator, tmp_path / "ck", max_chunks=0)
    res = study(
        PLANT_A, NOISE_A, x0_from_generator, tmp_path / "ck", max_chunks=0, study_id="gen-0"
    )
    assert res.n_done == 0
    with open(tmp_path / "ck" / "meta.json") as fh:
        assert json.load(fh)["study_id"] == "gen-0"
    with pytest.raises(ValueError, match="`study_id`"):
        study(PLANT_A, NOISE_A, X0_A, tmp_path / "other", study_id="")


# ---- what a sampler reads from the process: environment variables, hidden random generators


def x0_env_scale(k):
    return float(os.environ.get("OBSJAX_TEST_X0_SCALE", "1.0")) * jr.normal(k, (2,))


def x0_getenv_scale(k):
    return float(os.getenv("OBSJAX_TEST_X0_SCALE", "1.0")) * jr.normal(k, (2,))


def x0_random_module(k):
    import random

    return (1.0 + random.random()) * jr.normal(k, (2,))


def x0_numpy_global(k):
    return (1.0 + np.random.random()) * jr.normal(k, (2,))


def x0_numpy_random_imported_as(k):
    import numpy.random as npr

    return (1.0 + npr.random()) * jr.normal(k, (2,))


def x0_numpy_random_imported_from(k):
    from numpy import random as npr

    return (1.0 + npr.random()) * jr.normal(k, (2,))


def test_environment_variables_read_by_a_sampler_enter_the_fingerprint(tmp_path, monkeypatch):
    """A sampler scaled by an environment variable (a cluster job's parameter): with the variable
    changed, a checkpoint was resumed with n_computed = 0 and the old result (12.43 for 21.13), and in
    one process the kernel compiled for the old value was served."""
    from obsjax.montecarlo._fingerprint import fingerprint

    monkeypatch.setenv("OBSJAX_TEST_X0_SCALE", "1.0")
    for f in (x0_env_scale, x0_getenv_scale):
        before = fingerprint({"s": f})[0]
        monkeypatch.setenv("OBSJAX_TEST_UNRELATED", "x")  # a variable the sampler does not name
        assert fingerprint({"s": f})[0] == before
        monkeypatch.setenv("OBSJAX_TEST_X0_SCALE", "1.7")
        assert fingerprint({"s": f})[0] != before
        monkeypatch.setenv("OBSJAX_TEST_X0_SCALE", "1.0")
        assert fingerprint({"s": f})[0] == before
    ck = tmp_path / "ck"
    first = study(PLANT_A, None, x0_env_scale, ck)
    monkeypatch.setenv("OBSJAX_TEST_X0_SCALE", "3.0")
    with pytest.raises(ValueError, match="holds a different study"):
        study(PLANT_A, None, x0_env_scale, ck)
    second = study(PLANT_A, None, x0_env_scale, None)  # not the kernel traced for 1.0
    np.testing.assert_allclose(second.error_norm[:, 0], 3.0 * first.error_norm[:, 0], rtol=1e-12)


def test_the_state_of_a_python_random_generator_enters_the_fingerprint(tmp_path):
    """A sampler drawing from a ``random.Random`` when it is traced: its Mersenne Twister's state lives
    in C, so the generator was hashed by its empty ``__dict__``; reseeded, a checkpoint of the other
    seed was resumed (10.50 for 7.74).  The state is hashed now: the same seed resumes, another is
    refused, and the draw of a user's own generator does not depend on the ``random`` module's."""
    import random

    from obsjax.montecarlo._fingerprint import fingerprint

    rng = random.Random(0)

    def x0_own_generator(k):
        return (1.0 + rng.random()) * jr.normal(k, (2,))

    before = fingerprint({"s": x0_own_generator})[0]
    random.seed(1)  # the module's hidden generator: not read by this sampler
    assert fingerprint({"s": x0_own_generator})[0] == before
    rng.seed(5)
    assert fingerprint({"s": x0_own_generator})[0] != before
    rng.seed(0)
    assert fingerprint({"s": x0_own_generator})[0] == before
    # the random module's functions (imported inside the sampler, or by name) and NumPy's legacy
    # global generator: their hidden state
    from random import gauss

    def x0_gauss(k):
        return gauss(1.0, 0.1) * jr.normal(k, (2,))

    cases = (
        (x0_random_module, random.seed),
        (x0_gauss, random.seed),
        (x0_numpy_global, np.random.seed),
        (x0_numpy_random_imported_as, np.random.seed),
        (x0_numpy_random_imported_from, np.random.seed),
    )
    for f, seed in cases:
        seed(0)
        a = fingerprint({"s": f})[0]
        seed(0)
        assert fingerprint({"s": f})[0] == a, f.__name__
        seed(1)
        assert fingerprint({"s": f})[0] != a, f.__name__
    assert fingerprint({"s": random.SystemRandom()})[1]  # no state: refused unless named
    ck = tmp_path / "ck"
    rng.seed(0)
    first = study(PLANT_A, None, x0_own_generator, ck, max_chunks=1)
    assert first.n_done == CHUNK
    rng.seed(5)
    with pytest.raises(ValueError, match="holds a different study"):
        study(PLANT_A, None, x0_own_generator, ck)
    rng.seed(0)
    resumed = study(PLANT_A, None, x0_own_generator, ck)
    assert resumed.complete and resumed.n_computed == N - CHUNK
    rng.seed(0)
    np.testing.assert_array_equal(resumed.error_norm, study(PLANT_A, None, x0_own_generator, None).error_norm)


# ---- damaged files: named, recomputed
# ---------------------------------------------------------------------


def _resume_with_warning(reference, ck, match):
    with pytest.warns(CheckpointWarning, match=match):
        res = study(PLANT_A, NOISE_A, X0_A, ck)
    np.testing.assert_array_equal(res.error_norm, reference[0].error_norm)
    np.testing.assert_array_equal(res.status, reference[0].status)
    return res


def test_truncated_chunk_is_named_and_recomputed(reference, tmp_path):
    ck = _copy(reference, tmp_path)
    path = os.path.join(ck, "chunk_000001.npz")
    with open(path, "r+b") as fh:
        fh.truncate(os.path.getsize(path) // 2)
    res = _resume_with_warning(reference, ck, r"chunk_000001\.npz.*damaged.*unreadable")
    assert res.n_computed == N - CHUNK
    # the recomputed chunk was written back whole: the next call loads everything silently
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointWarning)
        assert study(PLANT_A, NOISE_A, X0_A, ck).n_computed == 0


def test_empty_and_garbage_chunks_are_named_and_recomputed(reference, tmp_path):
    ck = _copy(reference, tmp_path)
    open(os.path.join(ck, "chunk_000000.npz"), "wb").close()
    with open(os.path.join(ck, "chunk_000001.npz"), "wb") as fh:
        fh.write(b"PK\x03\x04 not a zip archive")
    with pytest.warns(CheckpointWarning) as record:
        res = study(PLANT_A, NOISE_A, X0_A, ck)
    messages = " ".join(str(w.message) for w in record)
    assert "chunk_000000.npz" in messages and "chunk_000001.npz" in messages
    assert "BadZipFile" in messages  # the reason is named, not raised
    assert res.n_computed == N
    np.testing.assert_array_equal(res.error_norm, reference[0].error_norm)


def test_altered_chunk_fails_its_checksum(reference, tmp_path):
    ck = _copy(reference, tmp_path)
    path = os.path.join(ck, "chunk_000000.npz")
    with np.load(path) as d:
        content = {k: d[k] for k in d.files}
    content["error_norm"] = content["error_norm"] * 0.5  # a plausible but wrong content
    with open(path, "wb") as fh:
        np.savez(fh, **content)
    _resume_with_warning(reference, ck, r"chunk_000000\.npz.*checksum mismatch")


def test_renamed_chunk_is_not_loaded_into_another_slot(reference, tmp_path):
    ck = _copy(reference, tmp_path)
    shutil.copy(os.path.join(ck, "chunk_000000.npz"), os.path.join(ck, "chunk_000001.npz"))
    _resume_with_warning(reference, ck, r"chunk_000001\.npz.*holds chunk 0")


@pytest.mark.parametrize("damage", ["truncated", "empty", "edited", "not an object"])
def test_damaged_meta_json_is_named_and_rewritten(reference, tmp_path, damage):
    ck = _copy(reference, tmp_path)
    meta_path = os.path.join(ck, "meta.json")
    text = open(meta_path).read()
    if damage == "truncated":
        text = text[: len(text) // 2]
    elif damage == "empty":
        text = ""
    elif damage == "edited":
        meta = json.loads(text)
        meta["n"] = 9
        text = json.dumps(meta)
    else:
        text = "[1, 2]"
    with open(meta_path, "w") as fh:
        fh.write(text)
    res = _resume_with_warning(reference, ck, r"meta\.json.*damaged")
    assert res.n_computed == 0  # every chunk verified by its own fingerprint and checksum
    with open(meta_path) as fh:
        assert json.load(fh)["n"] == N  # rewritten (atomically)


def test_damaged_meta_json_never_adopts_another_studys_chunks(reference, tmp_path):
    ck = _copy(reference, tmp_path)
    with open(os.path.join(ck, "meta.json"), "w") as fh:
        fh.write("{")
    with pytest.raises(ValueError, match=r"chunk_000000\.npz.*different study"):
        study(PLANT_A, NOISE_A, scaled_normal(2.0), ck)


def test_checkpoint_of_an_earlier_format_is_refused(tmp_path):
    ck = tmp_path / "ck"
    os.makedirs(ck)
    with open(ck / "meta.json", "w") as fh:
        json.dump(
            {"fingerprint": "0" * 64, "n": N, "chunk_size": CHUNK, "n_chunks": 2, "version": 1}, fh
        )
    with pytest.raises(ValueError, match="earlier obsjax"):
        study(PLANT_A, NOISE_A, X0_A, ck, max_chunks=0)


def test_files_are_written_atomically(reference):
    """No temporary file is left behind, and every file carries its checksum."""
    ck = reference[1]
    assert sorted(os.listdir(ck)) == ["chunk_000000.npz", "chunk_000001.npz", "meta.json"]
    with open(os.path.join(ck, "meta.json")) as fh:
        meta = json.load(fh)
    assert meta["format"] == 2 and len(meta["checksum"]) == 64 and meta["n_chunks"] == 2
    with np.load(os.path.join(ck, "chunk_000000.npz")) as d:
        assert str(d["fingerprint"]) == meta["fingerprint"] and int(d["chunk"]) == 0
        assert len(str(d["checksum"])) == 64


# ---- the fingerprint itself
# --------------------------------------------------------------------------------


def _fp_parts():
    import functools

    import equinox as eqx
    import jax

    return {
        "jit": jax.jit(x0_global_scale),
        "filter_jit": eqx.filter_jit(xhat0_zero),
        "vmap": jax.vmap(xhat0_zero),
        "partial": functools.partial(jr.normal, shape=(2,)),
        "plant": PLANT_A,
        "noise": NOISE_A,
        "x0": X0_A,
        "set": frozenset({"a", "b", 3}),
    }


def test_fingerprint_covers_wrapped_functions_by_content():
    import jax

    from obsjax.montecarlo._fingerprint import fingerprint

    fp, opaque = fingerprint(_fp_parts())
    assert opaque == []
    assert fingerprint(_fp_parts())[0] == fp
    assert (
        fingerprint({"f": jax.jit(scaled_normal(1.0))})[0]
        == fingerprint({"f": jax.jit(scaled_normal(1.0))})[0]
    )
    assert (
        fingerprint({"f": jax.jit(scaled_normal(1.0))})[0]
        != fingerprint({"f": jax.jit(scaled_normal(2.0))})[0]
    )


def test_fingerprint_is_the_same_in_another_process():
    """No ids, addresses or hash-randomised orderings enter the fingerprint (resuming happens in a
    new process, with another PYTHONHASHSEED)."""
    import subprocess
    import sys

    from obsjax.montecarlo._fingerprint import fingerprint

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    here = os.path.dirname(os.path.abspath(__file__))
    module = (
        _fp_parts.__module__
    )  # import this file under the name pytest gave it (functions carry it)
    code = (
        f"import sys; sys.path[:0] = [{root!r}, {here!r}]\n"
        f"from {module} import _fp_parts\n"
        "from obsjax.montecarlo._fingerprint import fingerprint\n"
        "print('FP', fingerprint(_fp_parts())[0])\n"
    )
    env = dict(os.environ, PYTHONHASHSEED="12345", JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300, cwd=root
    )
    assert out.returncode == 0, out.stderr[-2000:]
    line = next(ln for ln in out.stdout.splitlines() if ln.startswith("FP "))
    assert line.split()[1] == fingerprint(_fp_parts())[0]


def test_a_deeply_nested_sampler_is_fingerprinted():
    """A sampler whose closures nest 3000 functions deep: the walk recursed beyond Python's default
    limit of 1000 frames and monte_carlo failed with a RecursionError (seen in a test session, where a
    runtime type checker multiplies the frames).  It is hashed now, and a change at the bottom of the
    chain changes the fingerprint."""
    from obsjax.montecarlo._fingerprint import fingerprint

    def chain(depth, scale):
        def f0(k):
            return scale * jr.normal(k, (2,))

        f = f0
        for _ in range(depth):
            f = (lambda g: (lambda k: g(k)))(f)
        return f

    a, opaque = fingerprint({"x0_sampler": chain(3000, 1.0)})
    assert not opaque
    assert fingerprint({"x0_sampler": chain(3000, 2.0)})[0] != a
    assert fingerprint({"x0_sampler": chain(3000, 1.0)})[0] == a
