"""The masked adaptive Runge–Kutta back-end against diffrax's diffeqsolve (step for step), closed
forms, SciPy, the segmented diffrax solve of obsjax.simulate, and central finite differences."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import obsjax
from obsjax._integrate._adaptive_rk import NONFINITE, SOLVER_FAILED, SUCCESS, adaptive_rk_solve
from obsjax._simulate import _Args, _drift

PID = diffrax.PIDController(rtol=1e-6, atol=1e-8)
K = np.linspace(1.0, 4.0, 5)  # stiffness and damping of five forced oscillators
CD = np.linspace(0.1, 0.5, 5)
ARGS = jnp.stack([K, CD], axis=1)
Y0 = jnp.stack([np.linspace(1.0, 2.0, 5), np.zeros(5)], axis=1)
TS = jnp.linspace(0.0, 5.0, 11)


def oscillator(t, y, args):
    return jnp.array([y[1], -args[0] * y[0] - args[1] * y[1] + jnp.sin(t)])


@eqx.filter_jit
def _solve(solver, y0, args, dt0):
    return adaptive_rk_solve(
        oscillator,
        y0,
        0.0,
        5.0,
        args=args,
        args_axes=0,
        ts=TS,
        solver=solver,
        stepsize_controller=PID,
        dt0=dt0,
    )


@eqx.filter_jit
def _diffrax(solver, y0, args, dt0):
    def one(y, a):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(oscillator),
            solver,
            0.0,
            5.0,
            dt0,
            y,
            args=a,
            saveat=diffrax.SaveAt(ts=TS),
            stepsize_controller=PID,
        )
        return sol.ys, sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"]

    return jax.vmap(one)(y0, args)


@pytest.mark.parametrize("solver", [diffrax.Tsit5(), diffrax.Dopri5()], ids=["Tsit5", "Dopri5"])
@pytest.mark.extended
def test_step_for_step_with_diffrax(solver):
    # the same first step (0.01), then the same PID decisions: the same steps, the same numbers
    sol = _solve(solver, Y0, ARGS, 0.01)
    ys, acc, rej = _diffrax(solver, Y0, ARGS, 0.01)
    assert np.all(np.asarray(sol.status) == SUCCESS)
    np.testing.assert_array_equal(sol.num_accepted_steps, acc)
    np.testing.assert_array_equal(sol.num_rejected_steps, rej)
    np.testing.assert_allclose(sol.ys, ys, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.y1, ys[:, -1], rtol=0, atol=1e-12)


@pytest.mark.extended
def test_initial_step_selection_against_scipy():
    # dt0=None: Hairer & Wanner's starting step; the solution meets the tolerance against SciPy's
    # DOP853
    sol = _solve(diffrax.Tsit5(), Y0, ARGS, None)
    _, acc, _ = _diffrax(diffrax.Tsit5(), Y0, ARGS, 0.01)
    for b in range(5):
        ref = solve_ivp(
            lambda t, y, a=ARGS[b]: np.asarray(oscillator(t, y, a)),
            (0, 5),
            np.asarray(Y0[b]),
            method="DOP853",
            t_eval=np.asarray(TS),
            rtol=1e-12,
            atol=1e-14,
        ).y.T
        assert np.max(np.abs(np.asarray(sol.ys[b]) - ref)) < 2e-6
    # a different first step changes the count of steps by a few, not more
    assert np.all(
        np.abs(np.asarray(sol.num_accepted_steps) - np.asarray(acc)) <= 0.1 * np.asarray(acc)
    )


# ------------------------------------------------------------------------------------------ resets:
# Chen & Yen

PLANT = obsjax.chen_yen_example()


def _chen_yen(
    gamma, T, x0s, xh0s, ts, t1, *, dt0=None, rtol=1e-6, atol=1e-8, adjoint=None, solver=None
):
    obs = eqx.tree_at(
        lambda o: (o.gamma, o.T), obsjax.LeastSquaresReset(PLANT, 20.0, 0.1, 0.25), (gamma, T)
    )
    args = _Args(PLANT, obs, None, None, None)
    z0 = jax.vmap(lambda x, xh: obs.init(0.0, xh, PLANT.h(0.0, x, jnp.zeros(0))))(x0s, xh0s)
    n = (
        int(np.ceil(t1 / 0.2)) + 1
    )  # a static bound on the number of resets (those beyond t1 are ignored)
    return adaptive_rk_solve(
        _drift,
        (x0s, z0),
        0.0,
        t1,
        args=args,
        ts=ts,
        dt0=dt0,
        solver=solver,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        reset=lambda t, y, a: (y[0], a.observer.reset(t, y[1])),
        reset_ts=T * jnp.arange(1, n),
        max_steps=4096,
        adjoint=adjoint,
    )


X0S = jnp.array([[0.3, -1.2], [1.0, 0.5], [-0.7, 0.1]])
XH0S = jnp.tile(jnp.array([5.0, -5.0]), (3, 1))


@pytest.mark.extended
def test_resets_match_the_segmented_diffrax_solve():
    # save times on and between the reset instants; the same first step in every segment as
    # diffrax's
    ts = jnp.linspace(0.0, 2.0, 17)
    sol = jax.jit(lambda x, xh: _chen_yen(20.0, 0.25, x, xh, ts, 2.0, dt0=0.01))(X0S, XH0S)
    obs = obsjax.LeastSquaresReset(PLANT, 20.0, 0.1, 0.25)
    ref = jax.jit(jax.vmap(lambda x, xh: obsjax.simulate(PLANT, obs, x, xh, ts, dt0=0.01)))(
        X0S, XH0S
    )
    assert np.all(np.asarray(sol.status) == SUCCESS)
    np.testing.assert_allclose(sol.ys[0], ref.x, rtol=0, atol=1e-11)
    np.testing.assert_allclose(sol.ys[1].xhat, ref.xhat, rtol=0, atol=1e-11)
    # the state saved at a reset instant is the state after the reset (right-continuous)
    np.testing.assert_allclose(
        sol.ys[1].Phi[:, 4], jnp.broadcast_to(jnp.eye(2), (3, 2, 2)), atol=1e-15
    )


def _toy(t, y, a):
    # a small time-varying system, cheap to compile: gradients are checked on it
    return jnp.array([-a * y[0] + y[1] * jnp.sin(3.0 * t), -y[1] + jnp.cos(2.0 * t)])


def _toy_loss(p, adjoint=None, block_size=None):
    # p = (a, T, y0): a gain of the vector field, the reset period (reset q -> q/2 + 1 at kT), a
    # start value
    y0 = jnp.array([[1.0, 0.5], [-0.5, 1.0]]).at[0, 0].set(p[2])
    sol = adaptive_rk_solve(
        _toy,
        y0,
        0.0,
        1.0,
        args=p[0],
        ts=jnp.linspace(0.0, 1.0, 5),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
        reset=lambda t, y, a: jnp.array([y[0], 0.5 * y[1] + 1.0]),
        reset_ts=p[1] * jnp.arange(1, 6),
        adjoint=adjoint,
        block_size=block_size,
    )
    return jnp.sum(sol.ys**2)


@pytest.mark.extended
def test_gradients_match_central_differences():
    # reverse mode (checkpointed loop) and forward mode against central differences, with respect to
    # a gain, the reset period (the reset instants move) and an initial state; T = 0.31 keeps the
    # reset instants off the save times (where the loss has a kink)
    _, fd = _check_toy_gradients(block_size=None)
    assert np.all(np.abs(fd) > 1e-2)  # every direction matters


def _check_toy_gradients(block_size):
    """Reverse and forward mode of `_toy_loss` against central differences (rtol 1e-6); returns
    (reverse mode, central differences)."""
    p = jnp.array([1.3, 0.31, 1.0])
    rev = jax.jit(jax.grad(lambda q: _toy_loss(q, None, block_size)))(p)
    fwd = jax.jit(jax.jacfwd(lambda q: _toy_loss(q, diffrax.ForwardMode(), block_size)))(p)
    f = jax.jit(lambda q: _toy_loss(q, None, block_size))
    eps = 1e-6
    fd = np.array([(f(p + eps * e) - f(p - eps * e)) / (2 * eps) for e in np.eye(3)])
    np.testing.assert_allclose(rev, fd, rtol=1e-6)
    np.testing.assert_allclose(fwd, fd, rtol=1e-6)
    return rev, fd


@pytest.mark.slow
def test_gradient_through_chen_yen_resets():
    # d/dT of Chen & Yen's observer (reverse mode), against central differences (slow: compiling the
    # reverse pass of the observer's loop takes a minute on two cores; the mechanism is tested above
    # on a small system)
    ts = jnp.linspace(0.0, 1.0, 5)

    def loss(T):
        sol = _chen_yen(20.0, T, X0S[:2], XH0S[:2], ts, 1.0, rtol=1e-10, atol=1e-12)
        return jnp.sum((sol.ys[1].xhat - sol.ys[0]) ** 2)

    g = jax.jit(jax.grad(loss))(0.31)
    f = jax.jit(loss)
    fd = (f(0.31 + 1e-6) - f(0.31 - 1e-6)) / 2e-6
    np.testing.assert_allclose(g, fd, rtol=1e-6)


# ------------------------------------------------------------------------------------------- jumps,
# per-member t


def test_jump_in_the_vector_field_against_the_closed_form():
    # ẏ = −y + H(t − s): y = y0 e^{−t} before s, 1 + (y(s) − 1) e^{−(t − s)} after; s differs per
    # member
    s = jnp.array([0.3, 0.5, 0.77])
    f = lambda t, y, a: -y + jnp.where(t >= a, 1.0, 0.0)
    ts = jnp.linspace(0.0, 1.5, 16)
    sol = jax.jit(
        lambda y0: adaptive_rk_solve(
            f,
            y0,
            0.0,
            1.5,
            args=s,
            args_axes=0,
            ts=ts,
            jump_ts=s[:, None],
            stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-12),
        )
    )(jnp.full((3,), 2.0))
    y0, tt, ss = 2.0, np.asarray(ts)[None, :], np.asarray(s)[:, None]
    ys_ = y0 * np.exp(-ss)
    exact = np.where(tt < ss, y0 * np.exp(-tt), 1 + (ys_ - 1) * np.exp(-(tt - ss)))
    assert np.all(np.asarray(sol.status) == SUCCESS)
    np.testing.assert_allclose(sol.ys, exact, rtol=0, atol=1e-8)


@pytest.mark.parametrize(
    "solver, rtol, tol",
    [  # (the FSAL path's moving breakpoints: the default tier's Chen & Yen tests on the masked loop)
        pytest.param(diffrax.Tsit5(), 1e-11, 1e-8, marks=pytest.mark.extended),
        (diffrax.Heun(), 1e-9, 1e-5),
    ],
    ids=["Tsit5 (FSAL)", "Heun (not FSAL)"],
)
@pytest.mark.extended
def test_moving_reset_and_jump_times_against_closed_forms(solver, rtol, tol):
    # The steps do not move with a reset or jump time; its derivative is the jump condition at
    # arrival (y⁺ + δτ (∂R/∂t + ∂R/∂y f⁻ − f⁺)).  Two closed forms, both modes, three members:
    # - reset: ẏ = −a y, y ← c y + d t at τ:  y(t) = c y0 e^{−a t} + d τ e^{−a (t − τ)} for t > τ, so
    #   dy(t)/dτ = d e^{−a (t − τ)} (1 + a τ)  (∂R/∂t = d enters too);
    # - jump: ẏ = −y + H(t − s):  y(t) = 1 + y0 e^{−t} − e^{−(t − s)} for t > s, dy(t)/ds = −e^{−(t − s)}.
    a, c, d, y0 = 1.3, 0.5, 0.7, 2.0
    ts = jnp.array([0.2, 0.9, 1.5])
    pid = diffrax.PIDController(rtol=rtol, atol=1e-3 * rtol)

    def reset_case(tau, adjoint):
        return adaptive_rk_solve(
            lambda t, y, _: -a * y, jnp.full((3,), y0), 0.0, 1.5, ts=ts, solver=solver,
            stepsize_controller=pid, reset=lambda t, y, _: c * y + d * t, reset_ts=tau[:, None],
            adjoint=adjoint, max_steps=100_000,
        ).ys

    def jump_case(s, adjoint):
        f = lambda t, y, s_: -y + jnp.where(t >= s_, 1.0, 0.0)
        return adaptive_rk_solve(
            f, jnp.full((3,), y0), 0.0, 1.5, args=s, args_axes=0, ts=ts, solver=solver,
            stepsize_controller=pid, jump_ts=s[:, None], adjoint=adjoint, max_steps=100_000,
        ).ys

    taus = jnp.array([0.3, 0.55, 0.8])
    tt, tau_ = np.asarray(ts)[None, :], np.asarray(taus)[:, None]
    after = tt > tau_
    d_reset = np.where(after, d * np.exp(-a * (tt - tau_)) * (1 + a * tau_), 0.0)
    d_jump = np.where(after, -np.exp(-(tt - tau_)), 0.0)
    for case, exact in ((reset_case, d_reset), (jump_case, d_jump)):
        # members are independent: the derivative of member b's saved values in τ_b is the diagonal
        # block of the Jacobian; forward mode with one tangent along all τ gives it at once
        one = jnp.ones(3)
        _, fwd = jax.jit(lambda q: jax.jvp(lambda r: case(r, diffrax.ForwardMode()), (q,), (one,)))(taus)
        rev = jax.jit(jax.grad(lambda q: jnp.sum(case(q, None))))(taus)
        np.testing.assert_allclose(fwd, exact, rtol=0, atol=tol)
        np.testing.assert_allclose(rev, exact.sum(axis=1), rtol=0, atol=tol)


@pytest.mark.extended
def test_reset_time_gradient_where_a_mid_segment_reset_leaves_the_domain():
    # ẏ = √y, y(0) = 1, reset y ← y − 3 at τ: y(τ⁻) = (1 + τ/2)², y(3) = (g + (3 − τ)/2)² with
    # g = √((1 + τ/2)² − 3), so at τ = 2 (g = 1, g' = 1) y(3) = 2.25 and dy(3)/dτ = 2 · 1.5 · (1 − 1/2) = 1.5.
    # The jump condition's coefficients are evaluated
    # for every member at every iteration; a member in mid-segment, reset there, lies outside the domain
    # of √ (y − 3 < 0): that NaN must not reach reverse mode's cotangent of τ.
    f = lambda t, y, a: jnp.sqrt(y)
    pid = diffrax.PIDController(rtol=1e-10, atol=1e-12)

    def run(tau, adjoint):
        sol = adaptive_rk_solve(f, jnp.ones(1), 0.0, 3.0, stepsize_controller=pid, ts=jnp.array([3.0]),
                                reset=lambda t, y, a: y - 3.0, reset_ts=tau, adjoint=adjoint)  # fmt: skip
        return sol.ys[0, 0]

    tau = jnp.array([2.0])
    assert float(jax.jit(lambda t: run(t, None))(tau)) == pytest.approx(2.25, rel=1e-9)
    rev = jax.jit(jax.grad(lambda t: run(t, None)))(tau)
    fwd = jax.jit(jax.jacfwd(lambda t: run(t, diffrax.ForwardMode())))(tau)
    np.testing.assert_allclose(rev, [1.5], rtol=1e-7)
    np.testing.assert_allclose(fwd, [1.5], rtol=1e-7)


@pytest.mark.extended
def test_rejected_steps_outside_the_domain_carry_no_gradient():
    # ẏ = −λ(t) y with λ = k before s = 1 and 50 k after (a switch the solver is not told of), the field
    # written so that it is defined for y > 0 only (NaN below), and a reset y ← 2 y at 1.5 written the
    # same way.  After the slow phase the steps are long; those that cross s have stages with y < 0 and
    # are rejected (dozens per member).  Closed form: y(t) = e^{−k t} before s, e^{−k s − 50 k (t − s)}
    # after (times 2 after 1.5), dy/dk = −y·(t or s + 50 (t − s)).  The rejected stages' cotangent is
    # zero and their partial derivatives NaN: reverse mode gave a NaN gradient for every member (and so
    # did the reset, evaluated at the rejected candidates of members not arriving at it).
    k = jnp.array([0.5, 0.8, 1.1])
    ts = jnp.linspace(0.0, 2.0, 9)
    s, r, c = 1.0, 50.0, 2.0

    def f(t, y, k_):
        return -k_ * jnp.where(t < s, 1.0, r) * jnp.exp(jnp.log(y))

    def run(k_, adjoint, ts=ts):
        return adaptive_rk_solve(
            f, jnp.ones(3), 0.0, 2.0, args=k_, args_axes=0, ts=ts,
            stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-12),
            reset=lambda t, y, k_: c * jnp.exp(jnp.log(y)), reset_ts=jnp.array([1.5]), adjoint=adjoint,
        )  # fmt: skip

    sol = jax.jit(lambda k_: run(k_, None))(k)
    tt, kk = np.asarray(ts)[None, :], np.asarray(k)[:, None]
    y = np.exp(-np.where(tt < s, kk * tt, kk * s + r * kk * (tt - s))) * np.where(tt >= 1.5, c, 1.0)
    dy = -y * np.where(tt < s, tt, s + r * (tt - s))
    assert np.all(np.asarray(sol.status) == SUCCESS)
    assert np.all(np.asarray(sol.num_rejected_steps) >= 20)
    np.testing.assert_allclose(sol.ys, y, rtol=0, atol=1e-6)
    exact = np.sum(2 * y * dy, axis=1)
    rev = jax.jit(jax.grad(lambda k_: jnp.sum(run(k_, None).ys ** 2)))(k)
    fwd = jax.jit(jax.jacfwd(lambda k_: jnp.sum(run(k_, diffrax.ForwardMode()).ys ** 2)))(k)
    np.testing.assert_allclose(rev, exact, rtol=1e-6)
    np.testing.assert_allclose(fwd, exact, rtol=1e-6)
    # in the save times (the dense interpolant's slope): d/dt_j Σ_b y_b(t_j)² = Σ_b 2 y ẏ, NaN before for the
    # save times members waited for during rejected steps; at s itself (a kink) only finite
    d_ts = jax.jit(jax.grad(lambda q: jnp.sum(run(k, None, ts=q).ys ** 2)))(ts)
    ydot = -np.where(tt < s, 1.0, r) * kk * y
    away = np.abs(np.asarray(ts) - s) > 1e-12
    assert np.all(np.isfinite(np.asarray(d_ts)))
    np.testing.assert_allclose(np.asarray(d_ts)[away], np.sum(2 * y * ydot, axis=0)[away], rtol=1e-5, atol=1e-12)


@pytest.mark.extended
def test_rejected_steps_outside_the_domain_carry_no_gradient_with_direct_adjoint():
    """The problem above with ``adjoint=diffrax.DirectAdjoint()`` (a bounded loop that allows both modes):
    reverse mode was NaN for every member; the stages now mask their tangents where they are not finite
    (a custom_jvp), so both modes give the closed form."""
    k = jnp.array([0.5, 0.8, 1.1])
    ts = jnp.linspace(0.0, 2.0, 9)
    s, r, c = 1.0, 50.0, 2.0

    def f(t, y, k_):
        return -k_ * jnp.where(t < s, 1.0, r) * jnp.exp(jnp.log(y))

    def loss(k_):
        sol = adaptive_rk_solve(
            f, jnp.ones(3), 0.0, 2.0, args=k_, args_axes=0, ts=ts,
            stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-12),
            reset=lambda t, y, k_: c * jnp.exp(jnp.log(y)), reset_ts=jnp.array([1.5]),
            adjoint=diffrax.DirectAdjoint(), max_steps=2000,
        )  # fmt: skip
        return jnp.sum(sol.ys**2)

    tt, kk = np.asarray(ts)[None, :], np.asarray(k)[:, None]
    y = np.exp(-np.where(tt < s, kk * tt, kk * s + r * kk * (tt - s))) * np.where(tt >= 1.5, c, 1.0)
    exact = np.sum(2 * y * (-y * np.where(tt < s, tt, s + r * (tt - s))), axis=1)
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(k), exact, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(loss))(k), exact, rtol=1e-6)


def test_per_member_horizons():
    t1 = jnp.array([1.0, 2.5, 4.0])
    f = lambda t, y, a: jnp.array([y[1], -y[0]])
    ts = jnp.stack([jnp.linspace(0.0, t, 6) for t in t1])
    sol = adaptive_rk_solve(
        f,
        jnp.tile(jnp.array([1.0, 0.0]), (3, 1)),
        0.0,
        t1,
        ts=ts,
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
    )
    np.testing.assert_allclose(sol.ys[..., 0], np.cos(np.asarray(ts)), atol=1e-8)
    np.testing.assert_allclose(sol.t1, t1)
    assert np.asarray(sol.num_accepted_steps)[0] < np.asarray(sol.num_accepted_steps)[2]


# ------------------------------------------------------------------------------------------- status


@pytest.mark.extended
def test_status_per_member():
    # member 0 fine; member 1 stiff (runs out of steps); member 2 starts non-finite; member 3 blows
    # up (ẏ = y²)
    rates = jnp.array([1.0, 1e6, 1.0, 0.0])
    f = lambda t, y, a: jnp.where(a > 0, -a * y, y * y)
    y0 = jnp.array([[1.0], [1.0], [jnp.nan], [2.0]])
    sol = adaptive_rk_solve(
        f, y0, 0.0, 1.0, args=rates, args_axes=0, ts=jnp.linspace(0.0, 1.0, 5), max_steps=200
    )
    status = np.asarray(sol.status)
    assert status[0] == SUCCESS and status[2] == NONFINITE
    assert status[1] == SOLVER_FAILED and status[3] in (SOLVER_FAILED, NONFINITE)
    np.testing.assert_allclose(sol.ys[0, :, 0], np.exp(-np.linspace(0, 1, 5)), rtol=1e-6)
    assert np.all(np.isnan(np.asarray(sol.y1)[1:]))  # no silent values for failed members
    assert np.isnan(np.asarray(sol.ys)[1, -1, 0]) and np.isnan(np.asarray(sol.ys)[3, -1, 0])
    assert np.asarray(sol.num_steps)[1] == 200


def test_a_reset_that_gives_non_finite_values():
    f = lambda t, y, a: -y
    reset = lambda t, y, a: jnp.where(a > 0, y / 2, jnp.log(-jnp.abs(y) - 1.0))
    sol = adaptive_rk_solve(
        f,
        jnp.ones((2, 1)),
        0.0,
        1.0,
        args=jnp.array([1.0, -1.0]),
        args_axes=0,
        reset=reset,
        reset_ts=jnp.array([0.5]),
    )
    np.testing.assert_array_equal(sol.status, [SUCCESS, NONFINITE])
    np.testing.assert_allclose(sol.y1[0, 0], np.exp(-1.0) / 2, rtol=1e-6)


# ---------------------------------------------------------------------------------------- bad input


def test_bad_input_fails_fast():
    f = lambda t, y, a: -y
    y0 = jnp.ones((2, 1))
    with pytest.raises(ValueError, match="solver"):
        adaptive_rk_solve(f, y0, 0.0, 1.0, solver=diffrax.Kvaerno5())
    with pytest.raises(ValueError, match="stepsize_controller"):
        adaptive_rk_solve(f, y0, 0.0, 1.0, stepsize_controller=diffrax.ConstantStepSize())
    with pytest.raises(ValueError, match="y0"):
        adaptive_rk_solve(f, (jnp.ones((2, 1)), jnp.ones((3, 1))), 0.0, 1.0)
    with pytest.raises(ValueError, match="reset"):
        adaptive_rk_solve(f, y0, 0.0, 1.0, reset_ts=jnp.array([0.5]))
    with pytest.raises(ValueError, match="ts"):
        adaptive_rk_solve(f, y0, 0.0, 1.0, ts=jnp.array([0.0, 2.0]))
    with pytest.raises(ValueError, match="adjoint"):
        adaptive_rk_solve(f, y0, 0.0, 1.0, adjoint=diffrax.BacksolveAdjoint())
    with pytest.raises(ValueError, match="t0"):
        adaptive_rk_solve(f, y0, jnp.zeros(3), 1.0)


# ------------------------------------------------------------------------------------------- blocks


def _mixed_batch(block_size):
    # seven members, every per-member input at once: horizons, save times, reset instants, args (a
    # pytree with a shared and a per-member part); member 4 starts non-finite, member 5 runs out of
    # steps, member 6 blows up
    t1 = jnp.array([1.0, 1.5, 2.0, 1.2, 1.0, 1.0, 1.0])
    ts = jnp.stack([jnp.linspace(0.0, t, 6) for t in t1])
    rates = jnp.array([1.0, 2.0, 0.5, 3.0, 1.0, 1e6, 0.0])
    shift = jnp.array([0.3, 0.0])

    def f(t, y, a):
        shared, rate = a
        lin = -rate * y + shared * jnp.sin(3.0 * t)
        return jnp.where(rate > 0, lin, y * y)

    y0 = jnp.stack([jnp.linspace(0.5, 1.5, 7), jnp.linspace(-1.0, 1.0, 7)], axis=1)
    y0 = y0.at[4, 0].set(jnp.nan).at[6].set(jnp.array([2.0, 2.0]))
    reset_ts = jnp.stack([jnp.array([0.3, 0.6]) * (1 + 0.1 * k) for k in range(7)])
    return adaptive_rk_solve(
        f,
        y0,
        0.0,
        t1,
        args=(shift, rates),
        args_axes=(None, 0),
        ts=ts,
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10),
        reset=lambda t, y, a: 0.5 * y + a[0],
        reset_ts=reset_ts,
        max_steps=300,
        block_size=block_size,
    )


@pytest.mark.extended
def test_blocks_give_the_solution_of_one_loop():
    # 7 members in blocks of 3 (three blocks, two padding members) and of 1, against one loop: the
    # members are independent, so the solution, the step counts and the status agree member by
    # member
    whole = _mixed_batch(10_000)
    np.testing.assert_array_equal(whole.status, [0, 0, 0, 0, NONFINITE, SOLVER_FAILED, whole.status[6]])
    assert int(whole.status[6]) in (SOLVER_FAILED, NONFINITE)
    for bs in (3, 1):
        part = _mixed_batch(bs)
        for a, b in zip(jax.tree_util.tree_leaves(part), jax.tree_util.tree_leaves(whole)):
            assert a.shape == b.shape
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15, equal_nan=True)


@pytest.mark.extended
def test_gradients_through_blocks_match_central_differences():
    # the toy loss of the gradient test, its two members in blocks of one: reverse and forward mode
    # against central differences (the loop runs once per block inside jax.lax.map)
    rev, _ = _check_toy_gradients(block_size=1)
    p = jnp.array([1.3, 0.31, 1.0])
    np.testing.assert_allclose(rev, jax.jit(jax.grad(lambda q: _toy_loss(q, None, 2)))(p), rtol=1e-10)


def test_default_block_size(monkeypatch):
    from obsjax._integrate import _adaptive_rk as AR

    # on the CPU: the largest power of two with a (block, n) float64 array of at most 32 KiB, at least 64
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")  # (the suite may run on a GPU)
    assert AR.default_block_size(12) == 256  # 32768 / 96 = 341
    assert AR.default_block_size(4) == 1024
    assert AR.default_block_size(1) == 4096
    assert AR.default_block_size(200) == 64
    assert AR.default_block_size(12, jnp.float32) == 512
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert AR.default_block_size(12) == float("inf")  # the whole batch at once off the CPU


def test_bad_block_size_fails_fast():
    f = lambda t, y, a: -y
    for bad in (0, -3, True):
        with pytest.raises(ValueError, match="block_size"):
            adaptive_rk_solve(f, jnp.ones((2, 1)), 0.0, 1.0, block_size=bad)


@pytest.mark.extended
def test_blocks_cut_args_along_their_mapped_axis():
    # args mapped at axis 1 (and at -1): cut along that axis, as jax.vmap reads them
    rates = jnp.stack([jnp.linspace(0.5, 2.0, 5), jnp.linspace(0.1, 0.3, 5)])  # (2, B)
    f = lambda t, y, a: -a[0] * y + a[1] * jnp.sin(t)
    y0 = jnp.linspace(1.0, 2.0, 5)[:, None]
    run = lambda bs, ax: adaptive_rk_solve(f, y0, 0.0, 1.0, args=rates, args_axes=ax, block_size=bs).y1
    whole = run(100, 1)
    np.testing.assert_allclose(run(2, 1), whole, rtol=1e-13)
    np.testing.assert_allclose(run(2, -1), whole, rtol=1e-13)
    with pytest.raises(ValueError, match="args"):  # a mapped leaf with another number of members
        adaptive_rk_solve(f, y0, 0.0, 1.0, args=rates[:, :4], args_axes=1, block_size=2)


def test_reset_on_jump_matching_agrees_with_the_outer_comparison_and_scales():
    """Which resets fall on a jump time (and which jumps on a reset) is decided against the nearest
    neighbours in the other sorted list; it agrees with the all-pairs comparison (duplicates, NaN,
    distances of exactly the tolerance, unsorted input), and the trace of the targets holds no
    (B, R, J) array: with thousands of resets on a plant switching thousands of times the all-pairs
    comparison needed gigabytes."""
    from obsjax._integrate._adaptive_rk import _has_neighbour, _targets

    rng = np.random.default_rng(0)
    tol = np.array([1e-3, 0.0, 0.05])
    a = np.round(rng.uniform(0, 1, (3, 40)), 2)
    b = np.round(rng.uniform(0, 1, (3, 25)), 2)
    a[0, :5] = b[0, :5] + 1e-3  # exactly the tolerance away
    a[1, :3] = b[1, 3:6]  # equal
    a[2, 0], b[2, 1] = np.nan, np.nan
    a[2, 1] = np.inf
    for x, y in ((a, b), (b, a)):
        outer = np.any(np.abs(x[:, :, None] - y[:, None, :]) <= tol[:, None, None], axis=2)
        got = np.asarray(jax.jit(_has_neighbour)(jnp.asarray(x), jnp.asarray(y), jnp.asarray(tol)))
        np.testing.assert_array_equal(got, outer)
    assert _has_neighbour(jnp.zeros((2, 3)), jnp.zeros((2, 0)), jnp.ones(2)).shape == (2, 3)

    B, R, J = 2, 20_000, 30_000
    jaxpr = jax.make_jaxpr(
        lambda r, j: _targets(jnp.zeros(B), jnp.full(B, 10.0), r, j, B, jnp.float64)
    )(jnp.zeros((B, R)), jnp.zeros((B, J)))

    def sizes(jx):
        for eqn in jx.eqns:
            for v in eqn.outvars:
                yield int(np.prod(v.aval.shape)) if hasattr(v.aval, "shape") else 0
            for p in eqn.params.values():
                for sub in p if isinstance(p, (tuple, list)) else (p,):
                    sub = getattr(sub, "jaxpr", sub)
                    if hasattr(sub, "eqns"):
                        yield from sizes(sub)

    assert max(sizes(jaxpr.jaxpr)) <= 4 * B * (R + J)
