"""The fast paths: fixed-step Runge-Kutta scan, lock-step batches, the unrolled SPD solve."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import obsjax
from obsjax._integrate._fixed_step import grid, tableau_of
from obsjax._integrate._schedule import build, num_segments, tolerance
from obsjax._linalg import spd_solve
from obsjax._simulate_batch import lockstep_norm

CY_PLANT = obsjax.chen_yen_example()
CY_OBS = obsjax.LeastSquaresReset(CY_PLANT, gamma=20.0, p0=0.1, T=0.25)
X0, XH0 = jnp.array([1.0, -1.0]), jnp.array([5.0, -5.0])
TIGHT = dict(rtol=1e-11, atol=1e-13)


# ---------------------------------------------------------------- spd_solve


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 10])
def test_spd_solve_matches_numpy(n):
    rng = np.random.default_rng(n)
    M = rng.normal(size=(n, n))
    A = M @ M.T + n * np.eye(n)
    B = rng.normal(size=(n, 3))
    np.testing.assert_allclose(spd_solve(jnp.asarray(A), jnp.asarray(B)), np.linalg.solve(A, B), rtol=1e-11)
    np.testing.assert_allclose(spd_solve(jnp.asarray(A), jnp.asarray(B[:, 0])), np.linalg.solve(A, B[:, 0]), rtol=1e-11)


def test_spd_solve_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    M = rng.normal(size=(3, 3))
    A0 = jnp.asarray(M @ M.T + 3 * np.eye(3))
    b = jnp.asarray(rng.normal(size=3))
    E = jnp.asarray(rng.normal(size=(3, 3)))
    E = E + E.T
    f = lambda s: jnp.sum(spd_solve(A0 + s * E, b) ** 2)
    g = jax.grad(f)(0.0)
    h = 1e-6
    np.testing.assert_allclose(g, (f(h) - f(-h)) / (2 * h), rtol=1e-7)


@pytest.mark.parametrize("n, k", [(1, None), (3, 2), (5, None)])
def test_spd_solve_derivatives_match_finite_differences_and_numpy(n, k):
    # The solve reads the lower triangle of A only: a tangent E that is not symmetric moves the matrix
    # tril(E) + tril(E, -1)ᵀ.  Forward mode (one tangent, and three vmapped as jacfwd does) and reverse mode
    # against central differences of the solve itself and against numpy's dX = A⁻¹ (dB − dA X).
    rng = np.random.default_rng(10 * n + (k or 0))
    M = rng.normal(size=(n, n))
    A0 = M @ M.T + n * np.eye(n)
    shape = (n,) if k is None else (n, k)
    B0, dB = rng.normal(size=shape), rng.normal(size=shape)
    E = rng.normal(size=(n, n))  # not symmetric
    f = jax.jit(lambda s: spd_solve(jnp.asarray(A0) + s * jnp.asarray(E), jnp.asarray(B0) + s * jnp.asarray(dB)))
    _, tangent = jax.jvp(f, (0.0,), (1.0,))
    h = 1e-6
    np.testing.assert_allclose(tangent, (f(h) - f(-h)) / (2 * h), rtol=1e-7, atol=1e-9)
    X = np.linalg.solve(A0, B0)
    E_read = np.tril(E) + np.tril(E, -1).T
    np.testing.assert_allclose(tangent, np.linalg.solve(A0, dB - E_read @ X), rtol=1e-10, atol=1e-12)
    # three directions at once (jax.jacfwd's vmap over tangents) and reverse mode
    g = jax.jit(lambda s: jnp.sum(jnp.sin(f(s[0]) + s[1] * f(s[2]))))
    s0 = jnp.asarray([0.1, 0.3, -0.2])
    fd = [(g(s0 + h * e) - g(s0 - h * e)) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(jax.jit(jax.jacfwd(g))(s0), fd, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(jax.jit(jax.grad(g))(s0), jax.jit(jax.jacfwd(g))(s0), rtol=1e-12, atol=1e-14)


def test_spd_solve_rejects_bad_shapes():
    with pytest.raises(ValueError, match="spd_solve"):
        spd_solve(jnp.eye(2), jnp.ones(3))


# ---------------------------------------------------------------- fixed-step path


def test_tableau_of_explicit_and_implicit_solvers():
    a, b, c = tableau_of(diffrax.Tsit5())
    assert len(b) == 6 and np.isclose(b.sum(), 1.0)  # the FSAL stage (weight 0) is trimmed
    assert tableau_of(diffrax.Euler())[1].tolist() == [1.0]
    assert tableau_of(diffrax.Kvaerno5()) is None


def _grid(ts, dt0, T=None, jumps=None, events=None):
    n_reset = 1 if T is None else num_segments(T, ts[0], ts[-1])
    sched = build(jnp.asarray(ts), ts, T, n_reset, jumps, lambda a, b: events)
    return grid(ts, dt0, sched.concrete, tolerance(ts[-1] - ts[0]))


def test_grid_puts_breakpoints_on_saves_resets_and_before_jumps():
    g = _grid(np.array([0.0, 0.3, 1.0]), 0.1, T=0.25, jumps=[0.6])
    starts = np.asarray(g["start"])
    np.testing.assert_allclose(starts, [0.0, 0.25, 0.3, 0.5, 0.6, 0.75])
    assert g["reset"].tolist() == [False, True, False, True, False, True]
    # the interval ending at the jump 0.6 stops one float before it
    assert starts[3] + g["h"][3] * g["nsteps"][3] < 0.6
    assert g["save_idx"].tolist() == [0, 2, 6]
    seen = []
    jax.jit(lambda t: seen.append(grid(t, 0.1, (np.zeros(0),) * 4, 1e-9)) or t)(jnp.array([0.0, 1.0]))
    assert seen == [None]  # traced save times: no concrete grid (simulate then uses diffrax)
    # events: a node each, the update applied at the start of the interval they open (an event at t0 too);
    # a save time at a breakpoint shares its node (the state after it), except at t1
    g = _grid(np.array([0.0, 1.0]), 0.1, events=np.array([0.0, 0.45, 1.0]))
    np.testing.assert_allclose(g["start"], [0.0, 0.45, 1.0])
    assert g["event"].tolist() == [True, True, True] and g["save_idx"].tolist() == [0, 3]
    assert g["nsteps"].tolist() == [5, 6, 1] and g["h"][-1] == 0.0


@pytest.mark.extended
def test_fixed_step_scan_matches_diffrax_constant_steps_with_resets():
    """Same tableau, same steps: the direct scan equals diffeqsolve(ConstantStepSize) segment by segment."""
    ts = np.linspace(0.0, 5.0, 21)
    a = obsjax.simulate(CY_PLANT, CY_OBS, X0, XH0, ts, adaptive=False, dt0=0.0125)
    # traced ts force the diffrax route
    route = jax.jit(
        lambda t: obsjax.simulate(CY_PLANT, CY_OBS, X0, XH0, t, adaptive=False, dt0=0.0125, max_segments=20)
    )
    b = route(jnp.asarray(ts))
    np.testing.assert_allclose(a.error, b.error, atol=1e-12)
    np.testing.assert_allclose(a.z.Qinv, b.z.Qinv, atol=1e-12)


@pytest.mark.parametrize(
    "plant,obs,ts,order",
    [
        # save times off the reset grid: intervals of unequal step counts (masked steps)
        (CY_PLANT, CY_OBS, np.linspace(0.0, 3.0, 8), 5),
        # a switched plant: the grid must step onto the declared jumps to keep the method's order
        (
            obsjax.switching_ltv_example(period=0.7, horizon=4.0),
            obsjax.LeastSquaresReset(obsjax.switching_ltv_example(period=0.7, horizon=4.0), 20.0, 1.0, 0.93),
            np.linspace(0.0, 3.0, 7),
            5,
        ),
    ],
)
@pytest.mark.extended
def test_fixed_step_converges_at_the_method_order(plant, obs, ts, order):
    """Halving h divides the error by ≈ 2^order (Tsit5: 5), measured against a tight adaptive solve."""
    x0 = jnp.ones(plant.n)
    xh0 = jnp.zeros(plant.n)
    ref = obsjax.simulate(plant, obs, x0, xh0, ts, **TIGHT)
    errs = []
    for h in (0.05, 0.025):
        tr = obsjax.simulate(plant, obs, x0, xh0, ts, adaptive=False, dt0=h)
        errs.append(float(jnp.max(jnp.abs(tr.error - ref.error))))
    rate = np.log2(errs[0] / errs[1])
    assert rate > order - 1.0, (errs, rate)


@pytest.mark.extended
def test_fixed_step_gradient_matches_finite_differences():
    ts = np.linspace(0.0, 2.0, 9)

    def loss(gamma):
        obs = eqx.tree_at(lambda o: o.gamma, CY_OBS, gamma)  # T stays concrete: the direct path
        tr = obsjax.simulate(CY_PLANT, obs, X0, XH0, ts, adaptive=False, dt0=0.025)
        return jnp.sum(tr.error_norm**2)

    g = jax.jit(jax.grad(loss))(20.0)
    h = 1e-4
    lj = jax.jit(loss)
    np.testing.assert_allclose(g, (lj(20.0 + h) - lj(20.0 - h)) / (2 * h), rtol=1e-6)


# ---------------------------------------------------------------- fixed steps with a traced reset period

SWITCH = obsjax.switching_ltv_example(period=0.7, horizon=4.0)


def _traced_route(monkeypatch):
    """Make the diffrax back-end unreachable: a fixed-step solve that still takes it fails the test."""

    def refuse(*a, **k):
        raise AssertionError("fixed steps with a traced reset period went to the diffrax back-end")

    monkeypatch.setattr(obsjax._integrate._diffrax, "integrate", refuse)


def _switch_run(T, ts, max_segments=None, dt0=0.025):
    obs = obsjax.LeastSquaresReset(SWITCH, 20.0, 1.0, T)
    return obsjax.simulate(SWITCH, obs, jnp.ones(3), jnp.zeros(3), ts, adaptive=False, dt0=dt0,
                           max_segments=max_segments, throw=False)


@pytest.mark.extended
@pytest.mark.parametrize("T", [0.25, 0.23, 0.31, 1.7, 5.9])
def test_traced_reset_period_takes_the_concrete_fixed_step_grid(T, monkeypatch):
    """Under jit with T traced (tune's case) the fixed steps run on the grid of a concrete T: the same
    trajectory to rounding (resets on save times, between them, one reset, band-limited noise)."""
    ts = np.linspace(0.0, 6.0, 61)
    kw = dict(adaptive=False, dt0=0.0125, noise=obsjax.noise.BandLimitedNoise(0.05, dt=0.05),
              key=jr.PRNGKey(1), throw=False)

    def run(T, ms=None):
        obs = obsjax.LeastSquaresReset(CY_PLANT, gamma=20.0, p0=0.1, T=T)
        return obsjax.simulate(CY_PLANT, obs, X0, XH0, ts, max_segments=ms, **kw)

    ref = run(T)
    _traced_route(monkeypatch)
    got = jax.jit(lambda T: run(T, 40))(jnp.asarray(T))
    assert int(got.status) == 0
    np.testing.assert_allclose(got.xhat, ref.xhat, rtol=0, atol=1e-13)
    np.testing.assert_allclose(got.z.Qinv, ref.z.Qinv, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("T", [0.93, 0.7, 0.5, 0.35])
@pytest.mark.extended
def test_traced_reset_period_on_a_switched_plant_matches_an_adaptive_solve(T, monkeypatch):
    """Declared jumps with traced resets, including resets on the jumps (T = 0.7, 0.35) and on the save
    times (T = 0.5): the fixed-step solve equals the concrete one and a tight adaptive solve to the
    method's accuracy (an interval before a jump never evaluates the vector field after it)."""
    ts = np.linspace(0.0, 3.0, 7)
    ref = obsjax.simulate(SWITCH, obsjax.LeastSquaresReset(SWITCH, 20.0, 1.0, T), jnp.ones(3), jnp.zeros(3),
                          ts, **TIGHT)
    concrete = _switch_run(T, ts)
    _traced_route(monkeypatch)
    traced = jax.jit(lambda T: _switch_run(T, ts, 12))(jnp.asarray(T))
    np.testing.assert_allclose(traced.xhat, concrete.xhat, rtol=0, atol=1e-13)
    np.testing.assert_allclose(traced.error, ref.error, rtol=0, atol=3e-7)


@pytest.mark.extended
def test_fixed_step_last_stage_stays_before_a_jump():
    """A reset 1e-8 after a save time leaves an interval of 8 steps before the jump at 0.7 whose last stage
    time, t + h, rounds onto the jump; the stage is held one float before it.  (Before: error 0.22.)"""
    T = 0.5 + 1e-8
    ts = np.array([0.0, 0.5, 1.0])
    ref = obsjax.simulate(SWITCH, obsjax.LeastSquaresReset(SWITCH, 20.0, 1.0, T), jnp.ones(3), jnp.zeros(3),
                          ts, **TIGHT)
    np.testing.assert_allclose(_switch_run(T, ts).error, ref.error, rtol=0, atol=1e-7)


@pytest.mark.parametrize("T0", [0.93, 0.61])
@pytest.mark.extended
def test_traced_reset_period_gradient_matches_finite_differences(T0):
    """d/dT of Σ‖x̃‖² through the traced fixed-step grid, reverse and forward mode.  The grid is held fixed
    and the resets move with T through the jump condition at each reset instant (see
    ``_fixed_step.integrate_traced``), so the derivative is that of the exact loss up to the method's
    error: against central differences of the fixed-step solves (T off the save times and jumps, so the
    grid's step counts do not change within ±h) to the O(h⁴) by which the two differ at dt0 = 0.025, and
    against central differences of a tight adaptive solve to 3e-7 at dt0 = 0.0125 (1e-5 and 1e-6 at
    dt0 = 0.05 and 0.025: it converges to the exact derivative)."""
    ts = np.linspace(0.0, 3.0, 7)

    def loss(T, dt0=0.025):
        return jnp.sum(_switch_run(T, ts, 12, dt0=dt0).error_norm ** 2)

    rev = jax.jit(jax.grad(loss))(T0)
    fwd = jax.jit(jax.jacfwd(loss))(T0)
    lj = jax.jit(loss)
    h = 1e-6
    fd = (lj(T0 + h) - lj(T0 - h)) / (2 * h)
    np.testing.assert_allclose(rev, fd, rtol=5e-6)
    np.testing.assert_allclose(fwd, rev, rtol=1e-12)

    def exact(T):
        obs = obsjax.LeastSquaresReset(SWITCH, 20.0, 1.0, T)
        tr = obsjax.simulate(SWITCH, obs, jnp.ones(3), jnp.zeros(3), ts, rtol=1e-12, atol=1e-14, max_steps=200_000)
        return jnp.sum(tr.error_norm**2)

    h = 1e-5
    fd_exact = (exact(T0 + h) - exact(T0 - h)) / (2 * h)
    fine = jax.jit(jax.grad(lambda T: loss(T, 0.0125)))(T0)
    np.testing.assert_allclose(fine, fd_exact, rtol=3e-7)


@pytest.mark.extended
def test_traced_reset_period_gradient_in_closed_loop(monkeypatch):
    """With output feedback u = −K x̂ the plant's state moves with T too (its input reads the estimate), so
    the jump condition keeps its plant part there (open loop drops it: it is identically zero).  Forward
    mode through the traced fixed-step grid against central differences of tight adaptive solves."""
    _traced_route(monkeypatch)
    plant = obsjax.chen_yen_example(B=lambda t: jnp.array([[0.0], [1.0]]))
    K = jnp.array([[0.5, 1.0]])
    ts = np.linspace(0.0, 2.0, 9)

    def loss(T, **kw):
        obs = obsjax.LeastSquaresReset(plant, 20.0, 0.1, T)
        tr = obsjax.simulate(plant, obs, X0, XH0, ts, controller=lambda t, xh: -K @ xh, max_segments=10,
                             throw=False, **kw)
        return jnp.sum(tr.error_norm**2) + jnp.sum(tr.x**2)

    T0 = 0.31
    fwd = jax.jit(jax.jacfwd(lambda T: loss(T, adaptive=False, dt0=0.0125)))(T0)
    rev = jax.jit(jax.grad(lambda T: loss(T, adaptive=False, dt0=0.0125)))(T0)
    fixed = jax.jit(lambda T: loss(T, adaptive=False, dt0=0.0125))
    fd_fixed = (fixed(T0 + 1e-6) - fixed(T0 - 1e-6)) / 2e-6
    monkeypatch.undo()
    exact = jax.jit(lambda T: loss(T, rtol=1e-12, atol=1e-14, max_steps=200_000))
    h = 1e-5
    fd = (exact(T0 + h) - exact(T0 - h)) / (2 * h)
    assert abs(fd) > 1e-2
    np.testing.assert_allclose(fwd, rev, rtol=1e-12)
    # the derivative of the fixed-step loss (measured 4.7e-8), and of the exact loss up to the method's
    # error: C(t) = [cos √t + sin √t, 3 cos² √t] is not smooth at t = 0, which cuts the fixed steps' order to
    # about 1.5 there (8.3e-5 at dt0 = 0.0125, 2.8e-5 at 0.00625; the open loop alike)
    np.testing.assert_allclose(fwd, fd_fixed, rtol=1e-6)
    np.testing.assert_allclose(fwd, fd, rtol=2e-4)


@pytest.mark.extended
def test_traced_reset_on_a_save_time_gives_the_left_derivative():
    """At T with a reset on a save time the loss has a kink; the traced grid orders the reset before the
    save (the save sees the state after it), so autodiff returns the derivative from below, as the diffrax
    back-end does."""
    ts = np.array([0.0, 0.5, 0.6])

    def loss(T):
        return jnp.sum(_switch_run(T, ts, 3).error_norm ** 2)

    lj = jax.jit(loss)
    h = 1e-5  # one-sided differences of second order
    left = (3 * lj(0.5) - 4 * lj(0.5 - h) + lj(0.5 - 2 * h)) / (2 * h)
    right = -(3 * lj(0.5) - 4 * lj(0.5 + h) + lj(0.5 + 2 * h)) / (2 * h)
    g = jax.jit(jax.grad(loss))(0.5)
    assert abs(left - right) > 0.5  # a real kink
    np.testing.assert_allclose(g, left, rtol=2e-5)


@pytest.mark.extended
def test_traced_reset_on_a_plant_jump_gives_the_derivative_from_below():
    """Resets on the switched plant's jumps (T = 0.7): the loss has a kink in T there (the vector field
    before and after the jump differ), and the jump condition reads the vector field before the jump, so
    autodiff returns the derivative from below (the reset just before the jump), in both modes."""
    ts = np.array([0.0, 0.5, 1.0, 1.5])  # no save time on a reset; dt0 divides no interval exactly

    def loss(T):
        return jnp.sum(_switch_run(T, ts, 3, dt0=0.0275).error_norm ** 2)

    lj = jax.jit(loss)
    h = 1e-5  # one-sided differences of second order
    left = (3 * lj(0.7) - 4 * lj(0.7 - h) + lj(0.7 - 2 * h)) / (2 * h)
    right = -(3 * lj(0.7) - 4 * lj(0.7 + h) + lj(0.7 + 2 * h)) / (2 * h)
    g = jax.jit(jax.grad(loss))(0.7)
    assert abs(left - right) > 1e-2 * abs(left)  # a real kink
    np.testing.assert_allclose(g, left, rtol=1e-4)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(loss))(0.7), g, rtol=1e-12)


@pytest.mark.extended
@pytest.mark.parametrize("backend", ["simulate", "lockstep", "masked"])
def test_adaptive_reset_on_a_plant_jump_gives_the_derivative_from_below(backend):
    """Resets at 0.5, 1.0, 1.5 on jumps of a plant switching every 0.25 (T = 0.5): the loss has a kink in
    T.  The fixed-step back-end returned the derivative from below (−0.513), the adaptive ones the one
    from above (−2.78), a factor 5 apart: the segmented back-end read f⁻ at the end of the zero-length
    segment between the jump and the reset (after the jump) and f⁺ at the reset; the masked loop landed
    its step on the reset itself (stages in the mode after the jump).  All read the vector field one
    float below the reset now, and the masked loop takes a reset on a jump as one target, landing one
    float before it."""
    import equinox as eqx

    plant = obsjax.switching_ltv_example(period=0.25, horizon=3.0)
    ts = jnp.asarray([0.0, 0.3, 0.62, 1.13, 1.37, 1.9])  # no save time on a reset
    x0, xh0 = jnp.array([1.0, -0.5, 0.3]), jnp.array([2.0, 1.0, -1.0])
    obs0 = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=1.0, T=0.5)
    kw = dict(rtol=1e-10, atol=1e-12, max_segments=8)

    def loss(T):
        obs = eqx.tree_at(lambda o: o.T, obs0, T)
        if backend == "simulate":
            tr = obsjax.simulate(plant, obs, x0, xh0, ts, **kw)
        else:
            tr = obsjax.simulate_batch(plant, obs, x0[None], xh0[None], ts, lockstep=backend == "lockstep", **kw)
        return jnp.sum(tr.error**2)

    lj = jax.jit(loss)
    h = 1e-5  # one-sided differences of second order
    left = (3 * lj(0.5) - 4 * lj(0.5 - h) + lj(0.5 - 2 * h)) / (2 * h)
    right = -(3 * lj(0.5) - 4 * lj(0.5 + h) + lj(0.5 + 2 * h)) / (2 * h)
    assert abs(left - right) > 1.0  # a real kink
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(0.5), left, rtol=1e-4)


def test_fixed_step_euler_is_forward_euler():
    plant = obsjax.LTI([[-1.0]], None, [[1.0]])
    obs = obsjax.Luenberger(plant, [[1.0]])
    tr = obsjax.simulate(plant, obs, jnp.ones(1), jnp.zeros(1), jnp.array([0.0, 1.0]), adaptive=False, dt0=0.1,
                         solver=diffrax.Euler())
    # x̃' = -2 x̃ with forward Euler: (1 - 0.2)^10
    np.testing.assert_allclose(tr.error[-1, 0], -(0.8**10), rtol=1e-13)


# ---------------------------------------------------------------- lock-step batches

TS_B = np.linspace(0.0, 3.0, 13)


def _batch(n=16, seed=0):
    x0s = jr.normal(jr.key(seed), (n, 2))
    return x0s, jnp.broadcast_to(XH0, (n, 2))


@pytest.mark.extended
def test_lockstep_batch_matches_individual_solves():
    x0s, xh0s = _batch()
    lock = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS_B, rtol=1e-9, atol=1e-11)
    ref = jax.vmap(lambda a, b: obsjax.simulate(CY_PLANT, CY_OBS, a, b, TS_B, **TIGHT))(x0s, xh0s)
    assert lock.error.shape == ref.error.shape == (16, 13, 2)
    assert lock.ts.shape == (16, 13)
    np.testing.assert_allclose(lock.error, ref.error, atol=1e-8)
    np.testing.assert_allclose(lock.z.Phi, ref.z.Phi, atol=1e-8)
    np.testing.assert_array_equal(lock.status, 0)


@pytest.mark.extended
def test_lockstep_batch_with_band_limited_noise_matches_individual_solves():
    x0s, xh0s = _batch(6)
    keys = jr.split(jr.key(3), 6)
    noise = obsjax.noise.BandLimitedNoise(0.05, 0.05)
    lock = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS_B, noise=noise, keys=keys, rtol=1e-10, atol=1e-12)
    ref = jax.vmap(
        lambda a, b, k: obsjax.simulate(CY_PLANT, CY_OBS, a, b, TS_B, noise=noise, key=k, rtol=1e-10, atol=1e-12)
    )(x0s, xh0s, keys)
    np.testing.assert_allclose(lock.y, ref.y, atol=1e-12)  # the same noise draw per member
    # both are within 3e-7 of a tight solve (the noise path's kinks every dt are stepped over, not declared)
    np.testing.assert_allclose(lock.error, ref.error, atol=5e-7)


@pytest.mark.extended
def test_lockstep_nonfinite_member_does_not_stop_the_others():
    x0s, xh0s = _batch(4)
    x0s = x0s.at[1, 0].set(jnp.nan)
    tr = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS_B, throw=False)
    assert tr.status.tolist() == [0, 2, 0, 0]
    ref = obsjax.simulate(CY_PLANT, CY_OBS, x0s[2], xh0s[2], TS_B, **TIGHT)
    np.testing.assert_allclose(tr.error[2], ref.error, atol=1e-5)


def test_lockstep_norm_is_the_worst_members_rms():
    y = (jnp.array([[3.0, 4.0], [1.0, 1.0], [jnp.nan, 0.0]]),)
    np.testing.assert_allclose(lockstep_norm(y), np.sqrt(12.5))


@pytest.mark.extended
def test_lockstep_batch_gradient_matches_finite_differences():
    x0s, xh0s = _batch(4)

    def loss(p0):
        obs = eqx.tree_at(lambda o: o.p0, CY_OBS, p0)
        tr = obsjax.simulate_batch(CY_PLANT, obs, x0s, xh0s, TS_B, rtol=1e-10, atol=1e-12)
        return jnp.mean(jnp.sum(tr.error_norm**2, axis=1))

    g = jax.jit(jax.grad(loss))(0.1)
    h = 1e-5
    lj = jax.jit(loss)
    np.testing.assert_allclose(g, (lj(0.1 + h) - lj(0.1 - h)) / (2 * h), rtol=1e-5)


@pytest.mark.extended
def test_simulate_batch_falls_back_to_vmap_for_fixed_steps():
    x0s, xh0s = _batch(3)
    a = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS_B, adaptive=False, dt0=0.025)
    b = jax.vmap(lambda x, xh: obsjax.simulate(CY_PLANT, CY_OBS, x, xh, TS_B, adaptive=False, dt0=0.025))(x0s, xh0s)
    np.testing.assert_array_equal(a.error, b.error)


def test_simulate_batch_rejects_bad_input():
    x0s, xh0s = _batch(3)
    with pytest.raises(ValueError, match="`x0s` must have shape"):
        obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s[0], xh0s, TS_B)
    with pytest.raises(ValueError, match="`xhat0s` must have shape"):
        obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s[:2], TS_B)
    with pytest.raises(ValueError, match="`keys`"):
        obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS_B, noise=obsjax.noise.BandLimitedNoise(0.1, 0.1))
    with pytest.raises(ValueError, match="`keys` must hold 3 keys"):
        obsjax.simulate_batch(
            CY_PLANT, CY_OBS, x0s, xh0s, TS_B, noise=obsjax.noise.BandLimitedNoise(0.1, 0.1), keys=jr.split(jr.key(0), 2)
        )


@pytest.mark.extended
def test_adjoint_is_passed_to_diffrax():
    """Another adjoint, the same gradient; an invalid one is rejected by diffrax (so it does reach it)."""
    ts = np.linspace(0.0, 1.0, 5)

    def loss(gamma, adjoint):
        obs = eqx.tree_at(lambda o: o.gamma, CY_OBS, gamma)
        return jnp.sum(obsjax.simulate(CY_PLANT, obs, X0, XH0, ts, adjoint=adjoint, **TIGHT).error_norm ** 2)

    g0 = jax.grad(loss)(20.0, None)
    g1 = jax.grad(loss)(20.0, diffrax.RecursiveCheckpointAdjoint(checkpoints=64))
    np.testing.assert_allclose(g1, g0, rtol=1e-10)
    # forward-mode differentiation of the solve: jacfwd works, reverse mode is refused by diffrax
    np.testing.assert_allclose(jax.jacfwd(loss)(20.0, diffrax.ForwardMode()), g0, rtol=1e-8)
    with pytest.raises(Exception):
        jax.grad(loss)(20.0, diffrax.ForwardMode())


def _ramp_after(tau):
    """ẋ = b(t)·1 with b = 0 before τ and 1 from τ on (declared jump τ): x(t) = max(0, t − τ)."""
    plant = obsjax.LTV(lambda t: jnp.zeros((1, 1)), lambda t: jnp.ones((1, 1)),
                       B=lambda t: jnp.where(t >= tau, 1.0, 0.0).reshape(1, 1), jump_ts=(tau,))
    obs = obsjax.Luenberger(obsjax.LTI([[0.0]], [[0.0]], [[1.0]]), L=[[1.0]])
    return plant, obs


@pytest.mark.parametrize("shift", [0.0, 1e-10, -1e-10, "linspace"])
def test_fixed_steps_keep_a_plant_jump_where_the_plant_switches(shift):
    """A plant jump within the schedule's tolerance of a save time (np.linspace puts 0.7000000000000001
    beside the jump at 0.7) was moved onto the save time: the steps beside it then had stages on the
    wrong side of the switch, x(2) = 1.32325 for 1.3 at h = 0.01 (2.3e-3 at h = 0.001), status 0.  The
    jump now stays a node of its own; exact for this piecewise-constant field, eagerly and with the
    reset period traced (the in-trace grid)."""
    tau = 0.7
    ts = np.linspace(0, 2, 21) if shift == "linspace" else np.r_[np.linspace(0, 0.6, 7), tau + shift,
                                                                   np.linspace(0.8, 2, 13)]
    plant, obs = _ramp_after(tau)
    u = lambda t: jnp.ones(1)  # noqa: E731
    exact = np.maximum(0.0, ts - tau)
    tr = obsjax.simulate(plant, obs, jnp.zeros(1), jnp.zeros(1), ts, u=u, adaptive=False, dt0=0.01)
    assert int(tr.status) == 0
    np.testing.assert_allclose(np.asarray(tr.x[:, 0]), exact, rtol=0, atol=1e-12)
    if shift == "linspace":  # the in-trace grid: resets at a traced period
        ls_model = obsjax.LTV(lambda t: jnp.zeros((1, 1)), lambda t: jnp.ones((1, 1)))

        @jax.jit
        def run(T):
            o = obsjax.LeastSquaresReset(ls_model, 1.0, 1.0, T)
            return obsjax.simulate(plant, o, jnp.zeros(1), jnp.zeros(1), ts, u=u, adaptive=False, dt0=0.01,
                                   max_segments=8).x[:, 0]

        np.testing.assert_allclose(np.asarray(run(0.33)), exact, rtol=0, atol=1e-12)


@pytest.mark.parametrize("gap", [0.0, 1e-10])
def test_fixed_steps_stop_before_a_plant_jump_at_the_end(gap):
    """A jump at t1 (or within the tolerance below it) is no breakpoint of the schedule, and the last step's
    final stage at t1 saw the field after it: x(2) = 2.3e-2 for 0 (h = 0.01).  The last interval now ends
    one float before the jump."""
    tau = 2.0 - gap
    plant, obs = _ramp_after(tau)
    ts = np.linspace(0.0, 2.0, 5)
    tr = obsjax.simulate(plant, obs, jnp.zeros(1), jnp.zeros(1), ts, u=lambda t: jnp.ones(1), adaptive=False,
                         dt0=0.01)
    assert abs(float(tr.x[-1, 0])) <= 2e-10
