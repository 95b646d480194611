"""Gradient tuning of observer gains on recorded experiments (:func:`tune_on_data`)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._checks import real_array
from .._config import require_x64
from .._data._estimate import estimate
from .._data._measurements import Measurements
from .._simulate import num_segments
from ..montecarlo._fingerprint import content_key
from ..observers._base import AbstractObserver
from ..systems._plants import LTI
from ._losses import output_error
from ._tune import (
    _check_types,
    _checked_message,
    _descend,
    _period_depends_on,
    _selected_leaves,
    _sorted_weighted,
    risk_weights,
)


@eqx.filter_jit
def _value_and_grad(theta, signs, observer, data, xhat0s, weights, spec):
    """J(θ) and ∇J for :func:`tune_on_data` (one compilation per problem structure)."""
    where, loss, single, max_segments, kwargs, _ = spec  # _: the content digest (a key, see content_key)

    def J(th):
        new = tuple(th) if signs is None else tuple(s * jnp.exp(t) for s, t in zip(signs, th))
        obs = eqx.tree_at(where, observer, new[0] if single else new)

        def one(d, xh0):
            est = estimate(obs, d, xh0, throw=False, max_segments=max_segments, **dict(kwargs))
            val = jnp.asarray(loss(est))
            if val.shape != () or not jnp.issubdtype(val.dtype, jnp.floating):
                raise ValueError(
                    "`loss` must map an Estimate to a real scalar (e.g. obsjax.losses.output_error), got an "
                    f"array of shape {val.shape} and dtype {val.dtype}."
                )
            return jnp.where(est.status == 0, val, jnp.nan)

        losses = eqx.filter_vmap(one)(data, xhat0s)
        return _sorted_weighted(losses, weights)

    return jax.value_and_grad(J)(theta)


def _log_parametrisation(leaves0):
    """signs, θ0 with leaf = sign · exp(θ); an entry that is exactly zero (the off-diagonal of a diagonal
    covariance) has sign 0 and stays zero."""
    signs, thetas = [], []
    for i, leaf in enumerate(leaves0):
        v = np.asarray(leaf)
        if np.iscomplexobj(v) or not np.all(np.isfinite(v)):
            raise ValueError(f"tuned leaf {i} must be real and finite for positive=True, got {v.tolist()}.")
        if not np.any(v != 0):
            raise ValueError(f"tuned leaf {i} is all zeros: positive=True keeps zeros at zero, nothing to tune.")
        signs.append(jnp.sign(leaf))
        thetas.append(jnp.log(jnp.where(leaf != 0, jnp.abs(leaf), 1.0)))
    return tuple(signs), tuple(thetas)


def _batch(datasets, xhat0):
    if isinstance(datasets, Measurements):
        data = datasets if datasets.batched else Measurements.stack([datasets])
    elif isinstance(datasets, (list, tuple)) and datasets:
        data = Measurements.stack(datasets)
    else:
        raise ValueError(
            f"`datasets` must be an obsjax.Measurements or a non-empty list of them, got {type(datasets).__name__}."
        )
    B = data.ts.shape[0]
    xhat0 = real_array(xhat0, "xhat0")
    if xhat0.ndim == 1:
        xhat0 = jnp.broadcast_to(xhat0, (B,) + xhat0.shape)
    if xhat0.ndim != 2 or xhat0.shape[0] != B:
        raise ValueError(f"`xhat0` must be (n,) or ({B}, n) for {B} experiment(s), got {tuple(xhat0.shape)}.")
    if not bool(jnp.all(jnp.isfinite(xhat0))):
        raise ValueError("`xhat0` must be finite, got NaN or inf entries.")
    return data, xhat0


def tune_on_data(
    observer,
    datasets,
    *,
    where,
    xhat0,
    loss=output_error,
    optimizer=None,
    steps=100,
    positive=True,
    risk="mean",
    estimate_kwargs=None,
    rtol=None,
    patience=10,
    max_rejections=8,
    progress=True,
):
    """Tune observer gains by gradient descent on recorded experiments.

    Minimises  J(θ) = risk_i [ loss(estimate(observer(θ), data_i, x̂0_i)) ]  over the leaves selected by
    ``where``, differentiating through :func:`obsjax.estimate`.  The default loss,
    :func:`obsjax.losses.output_error`, is the mean squared output prediction error at the samples (the
    prediction-error method: for a sampled-data filter it is the one-step-ahead prediction error); with
    states measured for validation (``x_ref`` of :class:`obsjax.Measurements`) use
    :func:`obsjax.losses.state_error`.  Experiments of different lengths are padded to the longest and
    masked (:meth:`obsjax.Measurements.stack`), so one compiled, vmapped gradient serves them all.

    The optimisation loop (backtracking on rejected points, the stopping rule, the history) is that of
    :func:`obsjax.tune`, and so are its guarantees: each bad argument raises ``ValueError`` naming it, a
    rejected point (invalid observer, a non-finite loss or gradient, a failed estimate) is retried with a
    halved step, and the best accepted observer is returned.

    **Arguments:**

    - `observer`: the observer to tune.
    - `datasets`: a :class:`obsjax.Measurements`, a list of them (stacked with padding), or a stacked batch.
    - `where`: the tuned leaves, e.g. ``lambda o: o.poles`` or ``lambda o: (o.Qw, o.Rv)``, each
      selected once.
    - `xhat0`: the initial estimate, (n,) for every experiment or (batch, n).
    - `loss`: Estimate -> real scalar (default :func:`obsjax.losses.output_error`).
    - `positive`: leaf = sign(leaf₀)·exp(θ) entrywise, as for :func:`obsjax.tune`, except that entries that
      are exactly zero stay zero (so a diagonal covariance stays diagonal and positive definite).
    - `optimizer`, `steps`, `risk`, `rtol`, `patience`, `max_rejections`, `progress`: as for
      :func:`obsjax.tune` (``risk`` across the experiments: ``"mean"``, ``"worst"``, ``("cvar", α)``).
    - `estimate_kwargs`: extra keyword arguments of :func:`obsjax.estimate` (solver, rtol, atol, …).

    **Returns:** an :class:`obsjax.TuneResult`.

    **Example:**::

        res = obsjax.tune_on_data(kf, [run1, run2], where=lambda o: o.Qw, xhat0=jnp.zeros(3),
                                  optimizer=optax.adam(0.05), steps=60)
        obsjax.estimate(res.observer, run3, jnp.zeros(3))     # validate on a held-out experiment
    """
    require_x64("obsjax.tune_on_data")
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`observer` must be an obsjax observer, got {type(observer).__name__}.")
    # the checks shared with tune (recorded data have no plant: a placeholder plant passes its check)
    _check_types(observer, LTI([[0.0]], C=[[1.0]]), where, loss, optimizer, steps, positive, rtol, patience,
                 max_rejections)
    estimate_kwargs = {} if estimate_kwargs is None else estimate_kwargs
    if not isinstance(estimate_kwargs, dict):
        raise ValueError(f"`estimate_kwargs` must be a dict or None, got {type(estimate_kwargs).__name__}.")
    for bad in ("throw", "max_segments", "ts"):
        if bad in estimate_kwargs:
            raise ValueError(f"`estimate_kwargs` must not contain {bad!r}: tune_on_data sets it.")
    data, xhat0s = _batch(datasets, xhat0)
    weights = jnp.asarray(risk_weights(risk, data.ts.shape[0]))
    leaves0, single = _selected_leaves(observer, where)
    optimizer = optax.adam(1e-2) if optimizer is None else optimizer
    if positive:
        signs, theta0 = _log_parametrisation(leaves0)

        def to_leaves(theta):
            return tuple(s * jnp.exp(t) for s, t in zip(signs, theta))
    else:
        signs, theta0 = None, leaves0

        def to_leaves(theta):
            return tuple(theta)

    def build(theta):
        new = to_leaves(theta)
        return eqx.tree_at(where, observer, new[0] if single else new)

    span = float(np.max(np.asarray(data.ts[:, -1] - data.ts[:, 0])))
    kw = tuple(sorted(estimate_kwargs.items()))
    bucket = [None]
    first = [True]
    content = content_key((where, loss, observer, kw))  # functions keyed by content, not identity

    def evaluate(theta):
        try:
            obs = build(theta).check()
        except (ValueError, RuntimeError) as e:
            return None, math.nan, None, f"the observer is invalid: {_checked_message(e)}"
        T = obs.reset_period
        if T is not None:
            need = int(2 ** math.ceil(math.log2(max(num_segments(T, 0.0, span), 1))))
            bucket[0] = need if bucket[0] is None else max(bucket[0], need)
        try:
            val, grads = _value_and_grad(theta, signs, observer, data, xhat0s, weights,
                                         (where, loss, single, bucket[0], kw, content))
            val = float(val)
        except (ValueError, RuntimeError) as e:
            if first[0]:
                raise
            return None, math.nan, None, f"a check failed while estimating: {_checked_message(e)}"
        finally:
            first[0] = False
        if not math.isfinite(val):
            return None, val, None, "the loss is not finite (an estimate failed or diverged)"
        if not all(bool(jnp.all(jnp.isfinite(g))) for g in grads):
            return None, val, None, "the gradient is not finite"
        return obs, val, grads, None

    # every experiment's samples (the padding of a stacked batch left out), each with its own t0
    ts_all, mask_all = np.asarray(data.ts), np.asarray(data.mask)
    ts_np = []
    for t_e, m_e in zip(ts_all, mask_all):
        last = np.flatnonzero(m_e)
        ts_np.append(t_e[: last[-1] + 1] if last.size else t_e)
    depends = _period_depends_on(build, theta0, build(theta0).reset_period)
    return _descend(evaluate, depends, to_leaves, theta0, optimizer, steps, rtol, patience, max_rejections, ts_np,
                    progress)
