"""Host values (Python numbers, lists, NumPy arrays) reach the device without a compiled program.

On jax 0.10 ``jnp.asarray`` of a host value, and a dtype conversion of an array, compile a small program
once per shape and dtype in each process (tens of milliseconds each on a CPU); the validation of every
input, ``tune``'s bookkeeping and ``noisy_batch`` used to pay them on a script's first call.  The counts
below come from ``jax.monitoring``'s lowering events, the conversions are checked against ``jnp.asarray``.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import obsjax
from obsjax._checks import as_float_array, device_array, host_array

LOWERING = "/jax/core/compile/jaxpr_to_mlir_module_duration"


@contextlib.contextmanager
def count_lowerings():
    """Counts the programs JAX lowers (one event per program, compiled or read from a cache)."""
    seen = []

    def listener(event, duration, **kwargs):
        if event == LOWERING:
            seen.append(event)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def test_the_counter_sees_a_compiled_program():
    with count_lowerings() as seen:
        jax.jit(lambda x: x * 3.0 + 1.0)(np.zeros((3, 7, 6))).block_until_ready()
    assert len(seen) >= 1


def test_host_values_reach_the_device_without_a_compiled_program():
    # shapes no other test uses, so that nothing is cached in this process
    with count_lowerings() as seen:
        a = as_float_array(np.zeros((3, 7, 5)), "a")
        b = as_float_array(list(range(11)), "b")
        c = as_float_array(17, "c")
        d = as_float_array(np.arange(13, dtype=np.float32), "d")
        e = device_array(np.ones((5, 19)), dtype=np.float32)
        f = device_array(0.125)
        jax.block_until_ready((a, b, c, d, e, f))
    assert seen == []
    assert [x.dtype for x in (a, b, c, d, e, f)] == [jnp.float64] * 4 + [jnp.float32, jnp.float64]
    np.testing.assert_array_equal(b, np.arange(11.0))
    assert float(c) == 17.0 and float(f) == 0.125


@pytest.mark.parametrize(
    "x",
    [2, 2.5, [1, 2], np.float32(1.5), np.arange(3, dtype=np.int16), np.zeros(2, np.float16),
     jnp.asarray(3.0), jnp.asarray(3), jnp.asarray([1.0, 2.0], dtype=jnp.float32)],
)  # fmt: skip
def test_as_float_array_equals_jax_conversion(x):
    out = as_float_array(x, "x")
    expected = jnp.asarray(x).astype(jnp.float64)
    assert out.dtype == jnp.float64 and out.shape == expected.shape
    np.testing.assert_array_equal(out, expected)
    if host_array(x) is not None:  # host values come out strongly typed
        assert not jax.typeof(out).weak_type


def test_as_float_array_keeps_complex_and_refuses_booleans_and_text():
    z = as_float_array(1 + 2j, "z")
    assert z.dtype == jnp.complex128 and complex(z) == 1 + 2j
    with pytest.raises(ValueError, match="`flag` must hold numbers, got booleans"):
        as_float_array(True, "flag")
    with pytest.raises(ValueError, match="`flags` must hold numbers, got booleans"):
        as_float_array([True, False], "flags")
    with pytest.raises(ValueError, match="`name` must be array-like"):
        as_float_array("abc", "name")
    if np.dtype(np.longdouble).itemsize > 8:  # extended precision: not a JAX dtype, refused by name
        with pytest.raises(ValueError, match="`wide` must be array-like"):
            as_float_array(np.ones(2, np.longdouble), "wide")


def test_host_array_leaves_jax_values_alone():
    assert host_array(jnp.ones(2)) is None
    assert host_array("abc") is None
    assert host_array(object()) is None

    def f(x):
        assert host_array(x) is None  # a tracer
        return as_float_array(x, "x") * 2.0

    np.testing.assert_array_equal(jax.jit(f)(np.arange(3)), [0.0, 2.0, 4.0])
    # a Python constant inside a trace is converted as outside
    np.testing.assert_array_equal(jax.jit(lambda x: x + as_float_array(2, "two"))(1.0), 3.0)


def test_tune_bookkeeping_on_the_host_gives_the_kernels_gains():
    """tune's θ = log|leaf| and leaf = sign·exp(θ) are computed on the host: the returned observer and
    the history hold sign·exp(θ) to rounding, the signs of the initial gains are kept."""
    plant = obsjax.chen_yen_example()
    obs = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.25)
    x0s = np.array([[1.0, -0.5], [0.3, 0.8]])
    res = obsjax.tune(
        obs, plant, where=lambda o: (o.gamma, o.T), loss=obsjax.losses.ise, x0s=x0s,
        xhat0s=np.zeros((2, 2)), ts=np.linspace(0.0, 2.03, 8), steps=3,
        simulate_kwargs={"adaptive": False, "dt0": 0.01},
    )  # fmt: skip
    gam, T = res.history["params"]
    np.testing.assert_allclose([gam[0], T[0]], [20.0, 0.25], rtol=4e-16)  # exp(log x) = x to rounding
    assert np.all(np.diff(gam) != 0.0)  # the optimizer moved γ at every accepted step
    best = res.history["best_step"]
    assert float(res.observer.gamma) == gam[best] and float(res.observer.T) == T[best]
    assert res.observer.gamma.dtype == jnp.float64 and not jax.typeof(res.observer.gamma).weak_type


def test_noisy_batch_draws_in_one_program_the_eager_paths():
    """noisy_batch draws all paths in one compiled program: the same values, bit for bit, as the
    realisations drawn one key at a time."""
    from obsjax.montecarlo import noisy_batch
    from obsjax.systems._noise import realise_band_limited

    plant = obsjax.chen_yen_example()
    noise = obsjax.noise.BandLimitedNoise(0.07, dt=0.05)
    key = jr.PRNGKey(11)
    batch = noisy_batch(plant, noise, key, 5, 0.0, 1.3)
    for b, k in enumerate(jr.split(key, 5)):
        one = realise_band_limited(noise, k, 0.0, 1.3, plant.m)
        np.testing.assert_array_equal(batch.path.values[b], one.values)
        assert float(batch.path.t0[b]) == float(one.t0)


def test_pole_decoding_and_vectors_agree_on_host_and_traced_paths():
    """Concrete poles are decoded and converted by NumPy, traced ones by JAX: the same values."""
    from obsjax.design import pole_structure
    from obsjax.design._place import pole_vector
    from obsjax.design._poles import decode, encode

    poles = np.array([-1.0 + 2.0j, -1.0 - 2.0j, -3.0, -0.5 + 0.25j, -0.5 - 0.25j])
    st = pole_structure(poles)
    x = encode(poles, st)
    re_h, im_h = decode(x, st)
    re_t, im_t = jax.jit(lambda v: decode(v, st))(x)
    np.testing.assert_array_equal(re_h, re_t)
    np.testing.assert_array_equal(im_h, im_t)
    np.testing.assert_array_equal(np.sort_complex(np.asarray(re_h) + 1j * np.asarray(im_h)), np.sort_complex(poles))
    assert re_h.dtype == jnp.float64
    for p, n in (([-1, -2], 2), (-4.0, 1), (poles, 5), (np.float32([-1.5, -2.5]), 2)):
        h = pole_vector(p, n)
        t = jax.jit(lambda v, n=n: pole_vector(v, n))(jnp.asarray(p))
        assert h.dtype == t.dtype and h.shape == (n,)
        np.testing.assert_array_equal(h, t)
    with pytest.raises(ValueError, match="must hold exactly n = 3 observer poles, got 2"):
        pole_vector([-1.0, -2.0], 3)
    with pytest.raises(ValueError, match="must be numbers, got booleans"):
        pole_vector([True, False], 2)


def test_placement_of_a_concrete_pair_compiles_no_eager_checks():
    """Luenberger.from_poles on concrete matrices decides its checks in NumPy: what it lowers is its
    placement kernel, not one program per check and conversion."""
    plant = obsjax.LTI(A=[[-2.0, 1.0, 0.0], [0.0, -1.0, 1.0], [0.3, 0.0, -4.0]], B=[[0.0], [0.0], [1.0]],
                       C=[[1.0, 0.0, 0.0]])  # fmt: skip
    with count_lowerings() as seen:
        obs = obsjax.Luenberger.from_poles(plant, [-5.5, -6.5, -7.5])
        jax.block_until_ready(obs.gain)
    # the placement kernel and the Layout's count of null directions (a Python int); 21 in a fresh
    # process before, when each check and conversion compiled its own program
    assert len(seen) <= 2
    eig = np.linalg.eigvals(np.asarray(plant.A) - np.asarray(obs.gain) @ np.asarray(plant.C))
    np.testing.assert_allclose(np.sort(eig.real), [-7.5, -6.5, -5.5], rtol=1e-9)
    with pytest.raises(ValueError, match="place the poles|not finite|observable"):
        obsjax.Luenberger.from_poles(
            obsjax.LTI(A=[[1.0, 0.0], [0.0, 2.0]], B=[[1.0], [1.0]], C=[[1.0, 0.0]]), [-1.0, -2.0]
        )


def test_schedule_from_constants_equals_the_traced_schedule():
    """With constant save times, period and jumps the schedule is built by NumPy (no program compiled);
    traced, by JAX: the same breakpoints, kinds and save windows."""
    from obsjax._integrate import _schedule

    ts_np = np.linspace(0.0, 3.0, 31)
    ts = jnp.asarray(ts_np)
    jumps = (0.55, 1.75, 2.5)  # 2.5 = 10 T: a jump and a reset at one instant (the jump first)
    with count_lowerings() as seen:
        s = _schedule.build(ts, ts_np, 0.25, 16, jumps, lambda a, b: None)
    assert seen == []

    def traced(ts_, T):
        t = _schedule.build(ts_, None, T, 16, jumps, lambda a, b: None)
        return t.times, t.reset, t.event, t.jump, t.first_save

    times, reset, event, jump, first = jax.jit(traced)(ts, jnp.asarray(0.25))
    act = np.asarray(reset | event | jump)
    np.testing.assert_array_equal(np.asarray(times)[act], s.times)
    for a, b in ((reset, s.reset), (event, s.event), (jump, s.jump)):
        np.testing.assert_array_equal(np.asarray(a)[act], b)
    assert s.times.shape == (14,) and int(np.sum(s.jump)) == 3 and int(np.sum(s.reset)) == 11
    np.testing.assert_array_equal(s.concrete[0], s.times)
    # the first save time of each segment: one past the breakpoint's save index, as the traced search
    np.testing.assert_array_equal(np.asarray(first)[np.r_[True, act, True]], s.first_save)
    assert s.first_save.dtype == jnp.int32 and float(s.t0) == 0.0 and float(s.t1) == 3.0


def test_host_arrays_are_copied_not_shared():
    """jax.device_put may keep a NumPy buffer itself on the CPU: the caller's array, edited afterwards,
    must not change what obsjax holds (as with jnp.asarray, which copies)."""
    buf = np.zeros(64 + 8)  # a 64-byte aligned matrix: the buffer device_put would share
    off = (-buf.ctypes.data % 64) // 8
    A = buf[off : off + 4].reshape(2, 2)
    A[0, 0] = -1.0
    plants, arrays = [], []
    for a01 in (1.0, 2.0, 3.0):
        A[0, 1] = a01
        plants.append(obsjax.LTI(A, None, [[1.0, 0.0]]))
        arrays.append((as_float_array(A, "A"), device_array(A), device_array(A[:, 1])))
    assert [float(p.A[0, 1]) for p in plants] == [1.0, 2.0, 3.0]
    assert [float(a[0][0, 1]) for a in arrays] == [1.0, 2.0, 3.0]
    assert [float(a[1][0, 1]) for a in arrays] == [1.0, 2.0, 3.0]
    assert [float(a[2][0]) for a in arrays] == [1.0, 2.0, 3.0]
    x0 = buf[off : off + 2]
    x0[:] = [0.5, -0.25]
    traj_x0 = as_float_array(x0, "x0")
    x0[:] = 7.0
    np.testing.assert_array_equal(traj_x0, [0.5, -0.25])


def test_noisy_batch_under_jit_vmap_and_its_derivative_in_sigma():
    """With a traced key (jit, vmap) or a σ being differentiated (even eagerly) noisy_batch draws by JAX:
    the same paths, and d/dσ of a loss of them is kept (a NumPy product would drop it)."""
    from obsjax.montecarlo import noisy_batch

    plant = obsjax.chen_yen_example()
    noise = obsjax.noise.BandLimitedNoise(0.2, dt=0.05)
    eager = noisy_batch(plant, noise, jr.PRNGKey(3), 4, 0.0, 1.0).path.values
    jitted = jax.jit(lambda k: noisy_batch(plant, noise, k, 4, 0.0, 1.0).path.values)(jr.PRNGKey(3))
    np.testing.assert_allclose(jitted, eager, rtol=1e-15, atol=1e-16)
    both = jax.vmap(lambda k: noisy_batch(plant, noise, k, 4, 0.0, 1.0).path.values)(
        jnp.stack([jr.PRNGKey(3), jr.PRNGKey(4)])
    )
    np.testing.assert_allclose(both[0], eager, rtol=1e-15, atol=1e-16)

    def loss(s):
        nz = obsjax.noise.BandLimitedNoise(s, dt=0.05)
        return jnp.sum(noisy_batch(plant, nz, jr.PRNGKey(0), 4, 0.0, 1.0).path.values ** 2)

    g, gj = jax.grad(loss)(0.3), jax.jit(jax.grad(loss))(0.3)
    # the loss is σ² Σ z², so d/dσ = 2 loss(σ)/σ
    np.testing.assert_allclose(g, 2.0 * loss(0.3) / 0.3, rtol=1e-12)
    np.testing.assert_allclose(gj, g, rtol=1e-12)


def test_tune_leaves_are_the_kernels_exp():
    """tune's observer and history hold sign·exp(θ) by XLA's exp, the kernel's, bit for bit (NumPy's exp
    differs from it by an ulp in about one value of seven)."""
    from obsjax.tuning._tune import _signed_exp

    th = np.random.default_rng(0).normal(size=5000) * 5.0
    signs = np.where(np.arange(5000) % 3 == 0, -1.0, 1.0)
    got = np.asarray(_signed_exp((jnp.asarray(signs),), (jnp.asarray(th),))[0])
    kernel = np.asarray(jax.jit(lambda s, t: s * jnp.exp(t))(jnp.asarray(signs), jnp.asarray(th)))
    np.testing.assert_array_equal(got, kernel)
    np.testing.assert_array_equal(got, np.asarray(jnp.asarray(signs) * jnp.exp(jnp.asarray(th))))
