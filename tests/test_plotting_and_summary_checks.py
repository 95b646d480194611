"""Failed trajectories in the figures, and the argument checks of `summarise` and `devices=`.

- `plot_error_norm` draws the quantiles of the successful members of a batch only (warning and legend
  name the failed ones); a batch without any successful member, or a failed trajectory with nothing
  finite, raises.
- `plot_states` labels the state it draws (negative indices), refuses out-of-range indices and a batch,
  and warns on a failed trajectory.
- `summarise` refuses bad arguments with a ``ValueError`` naming them; valid input gives the statistics
  of the successful rows (checked against NumPy).
- `MonteCarloResult.plot` without any successful trajectory raises a clear ``ValueError``.
- `monte_carlo(devices=...)` refuses duplicated devices, non-integer numbers and booleans.
"""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import jax.random as jr
import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

import obsjax  # noqa: E402
from obsjax.montecarlo import summarise  # noqa: E402
from obsjax.plotting import plot_error_norm, plot_states  # noqa: E402

TS = np.linspace(0.0, 2.0, 5)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _traj(error, status, x=None, xhat=None, ts=TS):
    """A Trajectory built from arrays (no solve): x̂ = x + error unless given."""
    error = np.asarray(error, dtype=float)
    x = np.ones_like(error) if x is None else np.asarray(x, dtype=float)
    xhat = x + error if xhat is None else np.asarray(xhat, dtype=float)
    return obsjax.Trajectory(
        ts=jnp.asarray(ts), x=jnp.asarray(x), xhat=jnp.asarray(xhat), y=jnp.asarray(x[..., :1]),
        error=jnp.asarray(error), z=None, status=jnp.asarray(status, dtype=jnp.int32),
    )


def _band(ax):
    """(lower, upper) edges of the first fill_between polygon of `ax` at the save times: the lowest
    and highest vertex at each t (independent of the order matplotlib lists the vertices in)."""
    v = ax.collections[0].get_paths()[0].vertices
    lo = np.array([v[v[:, 0] == t, 1].min() for t in TS])
    hi = np.array([v[v[:, 0] == t, 1].max() for t in TS])
    return lo, hi


# ---------------------------------------------------------------------------------------------------
# plot_error_norm
# ---------------------------------------------------------------------------------------------------


def _batch_rows():
    """Norm rows of 6 members: 0, 2, 4, 5 succeed; 1 (status 1) holds finite but meaningless values,
    3 (status 2) NaN; the error is put on the first of 2 state components, so ‖x̃‖ = the row."""
    rng = np.random.default_rng(3)
    rows = rng.uniform(0.5, 2.0, (6, 1)) * np.exp(-rng.uniform(1.0, 3.0, (6, 1)) * TS)
    rows[1] = 1e3  # a failed member's rows: finite, huge, not meaningful
    rows[3, 2:] = np.nan
    status = np.array([0, 1, 0, 2, 0, 0])
    err = np.stack([rows, np.zeros_like(rows)], axis=-1)
    return rows, status, err


def test_plot_error_norm_batch_uses_only_successful_members():
    rows, status, err = _batch_rows()
    good = rows[status == 0]
    with pytest.warns(UserWarning, match=r"2 of the 6 members .* left out"):
        ax = plot_error_norm(_traj(err, status), label="L")
    line = ax.get_lines()[0]
    np.testing.assert_allclose(line.get_ydata(), np.median(good, axis=0), rtol=1e-12)
    lo, hi = _band(ax)
    np.testing.assert_allclose(lo, np.quantile(good, 0.1, axis=0), rtol=1e-12)
    np.testing.assert_allclose(hi, np.quantile(good, 0.9, axis=0), rtol=1e-12)
    assert "4/6" in line.get_label() and "2 failed" in line.get_label()
    assert any("2 failed" in t.get_text() for t in ax.get_legend().get_texts())


def test_plot_error_norm_batch_note_without_label_and_overflow_with_status_zero():
    rows, status, err = _batch_rows()
    err[4, 3, 0] = np.inf  # status 0, but an overflowing error: a failure, as in monte_carlo
    good = rows[[0, 2, 5]]
    with pytest.warns(UserWarning, match=r"3 of the 6 members"):
        ax = plot_error_norm(_traj(err, status))
    np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), np.median(good, axis=0), rtol=1e-12)
    assert ax.get_legend() is not None and "3 failed" in ax.get_legend().get_texts()[0].get_text()


def test_plot_error_norm_without_status_leaves_out_nonfinite_members():
    rows, _, err = _batch_rows()
    plain = types.SimpleNamespace(ts=TS, error=err)  # no `status` field
    good = rows[[0, 1, 2, 4, 5]]  # only the NaN member can be told apart
    with pytest.warns(UserWarning, match=r"1 of the 6 members .*non-finite"):
        ax = plot_error_norm(plain)
    np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), np.median(good, axis=0), rtol=1e-12)


def test_plot_error_norm_every_member_failed_raises():
    rows, _, err = _batch_rows()
    with pytest.raises(ValueError, match=r"every one of the 6 members"):
        plot_error_norm(_traj(err, np.array([1, 2, 2, 1, 1, 2])))


def test_plot_error_norm_single_failed_trajectory():
    e = np.stack([np.array([1.0, 0.5, np.inf, np.inf, np.inf]), np.zeros(5)], axis=-1)
    with pytest.warns(UserWarning, match=r"status 1.*t = 0\.5"):
        ax = plot_error_norm(_traj(e, 1))
    np.testing.assert_array_equal(ax.get_lines()[0].get_ydata()[:2], [1.0, 0.5])
    with pytest.raises(ValueError, match="nothing to draw"):
        plot_error_norm(_traj(np.full((5, 2), np.nan), 2))


@pytest.mark.extended  # 6 s here (a simulate_batch compilation); the synthetic-batch tests above are its twins
def test_plot_error_norm_simulated_batch_with_a_nan_initial_state():
    plant = obsjax.LTI([[-1.0, 1.0], [0.0, -2.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.Luenberger.from_poles(plant, [-3.0, -4.0])
    x0s = jr.normal(jr.PRNGKey(0), (5, 2)).at[0].set(jnp.nan)
    bt = obsjax.simulate_batch(plant, obs, x0s, jnp.zeros((5, 2)), TS, throw=False, lockstep=False)
    st = np.asarray(bt.status)
    assert st[0] == 2 and np.all(st[1:] == 0)
    good = np.linalg.norm(np.asarray(bt.xhat) - np.asarray(bt.x), axis=-1)[1:]
    with pytest.warns(UserWarning, match=r"1 of the 5 members"):
        ax = plot_error_norm(bt)
    med = ax.get_lines()[0].get_ydata()
    assert np.all(np.isfinite(med))
    np.testing.assert_allclose(med, np.median(good, axis=0), rtol=1e-12)


# ---------------------------------------------------------------------------------------------------
# plot_states
# ---------------------------------------------------------------------------------------------------


def _three_states(status=0):
    x = np.stack([np.sin(TS), np.cos(TS), 10.0 + TS], axis=-1)
    return x, _traj(np.zeros_like(x) + 0.1, status, x=x)


def test_plot_states_negative_index_is_labelled_with_the_state_it_draws():
    x, tr = _three_states()
    ax = plot_states(tr, indices=[-1, 0])
    lines = ax.get_lines()
    assert [ln.get_label() for ln in lines] == [
        "$x_{3}$", r"$\hat x_{3}$", "$x_{1}$", r"$\hat x_{1}$",
    ]
    np.testing.assert_array_equal(lines[0].get_ydata(), x[:, 2])
    np.testing.assert_array_equal(lines[2].get_ydata(), x[:, 0])


@pytest.mark.parametrize("indices", [[3], [-4], [1.0], [True]])
def test_plot_states_refuses_bad_indices(indices):
    _, tr = _three_states()
    with pytest.raises(ValueError, match="`indices`"):
        plot_states(tr, indices=indices)


def test_plot_states_refuses_a_batch_naming_the_batch_axis():
    x = np.ones((4, TS.shape[0], 3))
    batch = _traj(np.zeros_like(x), np.zeros(4), x=x)
    with pytest.raises(ValueError, match=r"batch of 4 members .*axis 0"):
        plot_states(batch)


def test_plot_states_warns_on_a_failed_trajectory():
    x, tr = _three_states(status=1)
    x[3:] = np.inf
    tr = _traj(np.zeros_like(x), 1, x=x)
    with pytest.warns(UserWarning, match=r"status 1.*t = 1"):
        plot_states(tr)


# ---------------------------------------------------------------------------------------------------
# summarise
# ---------------------------------------------------------------------------------------------------

EN = np.exp(-np.outer([1.0, 2.0, 3.0], TS))


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(error_norm=-EN), "error_norm"),
        (dict(error_norm=EN * (1 + 1j)), "error_norm"),
        (dict(status=np.array([0.7, 0.0, 0.0])), "status"),
        (dict(status=np.array([1.9, 0.0, 0.0])), "status"),
        (dict(status=np.array([np.nan, 0.0, 0.0])), "status"),
        (dict(status=np.array([7, 0, 0])), "status"),
        (dict(status=np.array([-5, 0, 0])), "status"),
        (dict(ts=TS[::-1].copy()), "ts"),
        (dict(ts=np.array([0.0, 0.5, 0.5, 1.0, 2.0])), "ts"),
        (dict(ts=np.array([0.0, np.nan, 1.0, 1.5, 2.0])), "ts"),
        (dict(conv_tol=0.0), "conv_tol"),
        (dict(conv_tol=-1.0), "conv_tol"),
        (dict(conv_tol=float("nan")), "conv_tol"),
        (dict(n=2), "n"),
    ],
)
def test_summarise_refuses_bad_arguments(kw, name):
    args = dict(ts=TS, error_norm=EN, status=np.zeros(3, int))
    args.update(kw)
    with pytest.raises(ValueError, match=f"`{name}`"):
        summarise(args.pop("ts"), args.pop("error_norm"), args.pop("status"), **args)


def test_summarise_valid_input_statistics_of_the_successful_rows():
    # a failed row may hold a negative or NaN value: it is not used; integral float status codes pass
    rows = np.vstack([EN, -np.ones(TS.shape[0])])
    for status in (np.array([0, 2, 0, 1]), np.array([0.0, 2.0, 0.0, 1.0])):
        r = summarise(TS, rows, status, conv_tol=0.05)
        good = EN[[0, 2]]
        np.testing.assert_array_equal(r.status, [0, 2, 0, 1])
        assert r.n_failed == 2 and r.n == 4
        np.testing.assert_allclose(r.bands, np.quantile(good, r.quantiles, axis=0), rtol=1e-14)
        ise = np.sum(0.5 * (good[:, 1:] ** 2 + good[:, :-1] ** 2) * np.diff(TS), axis=1)
        np.testing.assert_allclose(r.ise[[0, 2]], ise, rtol=1e-14)
        # rate 1: never below 5 % within t = 2 (e^-2 = 0.135); rate 3: crosses at ln(20)/3
        assert np.isinf(r.convergence_time[0])
        np.testing.assert_allclose(r.convergence_time[2], np.log(20.0) / 3.0, rtol=1e-12)


# ---------------------------------------------------------------------------------------------------
# MonteCarloResult.plot
# ---------------------------------------------------------------------------------------------------


def test_result_plot_without_successful_trajectory_raises():
    with pytest.raises(ValueError, match=r"every one of the 3 computed trajectories failed"):
        summarise(TS, EN, np.array([2, 1, 2])).plot()
    with pytest.raises(ValueError, match=r"no trajectory has been computed"):
        summarise(TS, np.full_like(EN, np.nan), np.full(3, -1)).plot()
    fig = summarise(TS, EN, np.array([2, 0, 2])).plot()  # one success is enough
    np.testing.assert_allclose(fig.axes[0].get_lines()[0].get_ydata(), EN[1], rtol=1e-14)
    assert "failed 2" in fig.axes[0].get_title()


# ---------------------------------------------------------------------------------------------------
# monte_carlo(devices=...)
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("devices", ["dup", 2.0, 1.0, True, False, "cpu", [0]])
def test_monte_carlo_refuses_bad_devices(devices):
    if devices == "dup":
        devices = [jax.devices()[0], jax.devices()[0]]
    plant = obsjax.LTI([[-1.0]], [[1.0]], [[1.0]])
    obs = obsjax.Luenberger.from_poles(plant, [-3.0])
    with pytest.raises(ValueError, match="`devices`"):
        obsjax.monte_carlo(
            plant, obs, jr.PRNGKey(0), 2, x0_sampler=np.ones(1), xhat0_sampler=np.zeros(1),
            ts=TS, chunk_size=2, progress=False, devices=devices,
        )
