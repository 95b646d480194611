"""Placement under jit, vmap and grad; observers built on it (no complex leaf, no NaN); the multi-output
canonical form of thesis §3.2 against python-control's observable form and its defining structure."""

import warnings

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax.design import observable_canonical_form, place, pole_structure
from obsjax.design._poles import decode, encode


def match(eig, poles) -> float:
    """Largest relative distance |λ̂ − λ| / |λ| between two multisets (greedy matching)."""
    rest = list(np.asarray(eig, complex))
    worst = 0.0
    for p in np.asarray(poles, complex):
        d = [abs(p - q) for q in rest]
        k = int(np.argmin(d))
        worst = max(worst, d[k] / max(abs(p), 1e-300))
        rest.pop(k)
    return worst


def eig_error(A, C, L, poles) -> float:
    return match(np.linalg.eigvals(A - L @ C), poles)


@pytest.mark.parametrize("im", [1e-13, 1e-11, 1e-10])
def test_a_pair_closer_than_the_cluster_tolerance_is_a_real_double_pole(im):
    """−1 ± i·im with |Im| below CLUSTER_RTOL/2: the two members are one repeated pole by the cluster rule.
    Between REAL_RTOL (was 1e-12) and CLUSTER_RTOL each member matched itself and its conjugate: the
    structure listed both as "up" and "down", place failed with a reshape error and Luenberger stored the
    poles as [1e-11, 1e-11, −2] (the real part lost)."""
    poles = np.array([-1 + 1j * im, -1 - 1j * im, -2.0])
    assert pole_structure(poles).clusters == ((1, (0, 1), ()), (1, (2,), ()))
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the Jordan-chain warning of a double pole with one output
        L = np.asarray(place(A, C, poles))
        obs = obsjax.Luenberger.from_poles(obsjax.LTI(A, np.eye(3)[:, 2:], C), poles)
    # a double pole with one output is a Jordan block: its eigenvalues move by ~sqrt(rounding)
    assert eig_error(A, C, L, [-1.0, -1.0, -2.0]) < 1e-6
    np.testing.assert_allclose(np.sort(np.asarray(obs.spectrum).real), [-2.0, -1.0, -1.0], rtol=1e-12)


# ---------------------------------------------------------------- derivatives, jit, vmap
@pytest.mark.extended
def test_eager_derivative_in_the_model_includes_the_balancing():
    """jax.jvp/grad of place in A or C run eagerly (no jit), m = 2 < n = 4: the balancing (d, e) of the pair
    was computed in NumPy from the tracers' primal values, so its derivative was dropped (relative error
    0.44 in dL/dA against central differences; under jit it was right).  Eager, jitted and central
    differences must agree."""
    rng = np.random.default_rng(11)
    A, C = rng.standard_normal((4, 4)), rng.standard_normal((2, 4))
    poles = np.array([-1.0, -2.0, -3.0, -4.0])
    h = 1e-5
    for which, E in (("A", np.eye(4, k=-1)), ("C", np.eye(2, 4))):
        f = (lambda a: place(a, C, poles)) if which == "A" else (lambda c: place(A, c, poles))
        x = jnp.asarray(A if which == "A" else C)
        eager = np.asarray(jax.jvp(f, (x,), (jnp.asarray(E),))[1])
        jitted = np.asarray(jax.jit(lambda x_, t_: jax.jvp(f, (x_,), (t_,))[1])(x, jnp.asarray(E)))
        fd = (np.asarray(f(x + h * E)) - np.asarray(f(x - h * E))) / (2 * h)
        np.testing.assert_allclose(eager, jitted, rtol=1e-8, atol=1e-10 * np.abs(fd).max())
        np.testing.assert_allclose(eager, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


@pytest.mark.extended
def test_gradient_mimo_against_central_differences():
    """d‖L‖²/d(A, C, poles) for n = 6, m = 2 (real poles and a conjugate pair, the pair through its
    real encoding) against central differences of the re-optimised placement."""
    rng = np.random.default_rng(7)
    A, C = rng.standard_normal((6, 6)), rng.standard_normal((2, 6))
    poles = np.array([-1 + 1j, -1 - 1j, -2.0, -3.0, -4 + 2j, -4 - 2j])
    structure = pole_structure(poles)
    enc = encode(poles, structure)

    @jax.jit
    def f(A, C, e):
        re, im = decode(e, structure)
        return jnp.sum(place(A, C, re + 1j * im, structure=structure) ** 2)

    grads = jax.grad(f, argnums=(0, 1, 2))(jnp.asarray(A), jnp.asarray(C), jnp.asarray(enc))
    args = [A, C, enc]
    h = 1e-6
    for k, g in enumerate(grads):
        fd = np.zeros(args[k].size)
        for i in range(args[k].size):
            up, dn = [np.array(a, copy=True) for a in args], [np.array(a, copy=True) for a in args]
            up[k].flat[i] += h
            dn[k].flat[i] -= h
            fd[i] = (f(*map(jnp.asarray, up)) - f(*map(jnp.asarray, dn))) / (2 * h)
        np.testing.assert_allclose(np.ravel(g), fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


@pytest.mark.extended
def test_jit_vmap_over_pole_sets_matches_a_loop():
    rng = np.random.default_rng(9)
    A, C = rng.standard_normal((5, 5)), rng.standard_normal((2, 5))
    sets = -rng.uniform(0.5, 4.0, (6, 5))
    Ls = jax.jit(jax.vmap(lambda p: place(A, C, p)))(jnp.asarray(sets))
    for p, L in zip(sets, Ls):
        np.testing.assert_allclose(L, place(A, C, p), rtol=1e-9, atol=1e-12)
        assert eig_error(A, C, np.asarray(L), p) < 1e-10
    # complex pole sets: one pattern, declared once
    pairs = np.array([[-1 + 1j, -1 - 1j, -2.0, -3 + 0.5j, -3 - 0.5j], [-2 + 2j, -2 - 2j, -1.0, -4 + 1j, -4 - 1j]])
    stc = pole_structure(pairs[0])
    Lc = jax.vmap(lambda p: place(A, C, p, structure=stc))(jnp.asarray(pairs))
    for p, L in zip(pairs, Lc):
        assert eig_error(A, C, np.asarray(L), p) < 1e-10


def _independent_batched_lapack_calls(hlo: str) -> list:
    """Pairs of batched LAPACK custom calls in one HLO computation with no data path between them
    (XLA may run such a pair at once)."""
    import itertools
    import re

    pairs = []
    for block in re.split(r"\n(?=\S)", hlo):
        ins = {}
        for line in block.splitlines()[1:]:
            m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = (.*)", line)
            if m:
                rhs = m.group(2).split("metadata=")[0]
                ins[m.group(1)] = (re.findall(r"%([\w.\-]+)", rhs), rhs)
        calls = []
        for k, (_, rhs) in ins.items():
            shape = re.match(r"\(?\w+\[([\d,]*)\]", rhs)
            if "lapack_" in rhs and shape and len(shape.group(1).split(",")) > 2:
                calls.append(k)
        memo = {}

        def ancestors(k):
            if k not in memo:
                memo[k] = set()
                for o in ins.get(k, ((), ""))[0]:
                    if o in ins:
                        memo[k] |= {o} | ancestors(o)
            return memo[k]

        for a, b in itertools.combinations(calls, 2):
            if a not in ancestors(b) and b not in ancestors(a):
                pairs.append((a, b))
    return pairs


@pytest.mark.extended
def test_batched_factorisations_never_run_at_once():
    """jaxlib 0.10's batched LAPACK kernels wait for their chunks inside the CPU thread pool; two
    running at once deadlocked jit(vmap(place)) over a few hundred pole sets on two cores.  In the
    compiled program every batched factorisation must depend on the one before it."""
    import sys

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 20_000))
    rng = np.random.default_rng(22)
    A, C = rng.standard_normal((6, 6)), rng.standard_normal((2, 6))
    sets = np.array([[-1 + 1j, -1 - 1j, -2.0, -3.0, -4.0, -5.0]] * 8) * rng.uniform(0.5, 1.5, (8, 1))
    st = pole_structure(sets[0])
    f = jax.jit(jax.vmap(lambda p: place(A, C, p, structure=st)))
    hlo = f.lower(jnp.asarray(sets)).compile().as_text()
    assert hlo.count("lapack_") >= 5  # the test sees the factorisations
    assert _independent_batched_lapack_calls(hlo) == []


@pytest.mark.extended
def test_under_jit_bad_values_raise():
    rng = np.random.default_rng(10)
    A, C = rng.standard_normal((4, 4)), rng.standard_normal((2, 4))
    stc = pole_structure([-1 + 1j, -1 - 1j, -2.0, -3.0])
    f = jax.jit(lambda p: place(A, C, p, structure=stc))
    assert np.all(np.isfinite(f(jnp.array([-1 + 1j, -1 - 1j, -2.0, -3.0]))))
    with pytest.raises(Exception, match="closed under conjugation"):
        f(jnp.array([-1 + 1j, -1 + 2j, -2.0, -3.0])).block_until_ready()
    with pytest.raises(Exception, match="must be finite"):
        jax.jit(lambda p: place(A, C, p))(jnp.array([-1.0, jnp.nan, -2.0, -3.0])).block_until_ready()
    # an unobservable pair traced under jit: refused at run time, never a silent NaN
    Au = np.diag([1.0, 2.0, 3.0, 4.0])
    Cu = np.array([[1.0, 1.0, 1.0, 0.0], [0.0, 1.0, 1.0, 0.0]])  # x4 unobservable
    g = jax.jit(lambda A, C: place(A, C, jnp.array([-1.0, -2.0, -3.0, -5.0])))
    with pytest.raises(Exception, match="does not place the poles"):
        g(jnp.asarray(Au), jnp.asarray(Cu)).block_until_ready()


@pytest.mark.extended
def test_traced_repeated_poles_without_their_pattern_say_how_to_place_them():
    """A placeable repeated real pole (multiplicity 2 = m) traced without its pattern is refused; the
    message said only that "a repeated pole exceeds the number of outputs", which is false here."""
    Ac = np.array([[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [-1, -2, -3, -4.0]])
    Cc = np.array([[1, 0, 0, 0], [0, 0, 1, 0.0]])
    rep = jnp.array([-2.0, -2.0, -3.0, -4.0])
    with pytest.raises(Exception, match=r"`structure=obsjax\.design\.pole_structure\(poles\)`"):
        jax.jit(lambda p: place(Ac, Cc, p))(rep).block_until_ready()
    L = jax.jit(lambda p: place(Ac, Cc, p, structure=pole_structure(rep)))(rep)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(Ac - np.asarray(L) @ Cc).real), [-4, -3, -2, -2], atol=1e-6)


def test_design_refuses_float32_mode():
    """With OBSJAX_NO_X64=1 a design raises instead of returning a float32 gain."""
    import subprocess
    import sys

    code = (
        "import obsjax, numpy as np\n"
        "try:\n"
        "    obsjax.design.place(np.array([[-2., 1.], [0., -1.]]), np.array([[1., 0.]]), [-3., -4.])\n"
        "except RuntimeError as e:\n"
        "    print('refused:', 'float64' in str(e))\n"
    )
    env = {**__import__("os").environ, "OBSJAX_NO_X64": "1", "JAX_ENABLE_X64": "0"}
    out = subprocess.run(
        [sys.executable, "-c", code], check=False, capture_output=True, text=True, env=env, timeout=300
    )
    assert "refused: True" in out.stdout, out.stdout + out.stderr


# ---------------------------------------------------------------- observers: no complex leaf, no NaN
@pytest.mark.extended
def test_complex_poles_never_reach_diffrax():
    plant = obsjax.LTI([[0.0, 1.0], [-2.0, -0.3]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.Luenberger.from_poles(plant, [-3 + 2j, -3 - 2j])
    assert all(not jnp.iscomplexobj(x) for x in jax.tree_util.tree_leaves(obs))
    np.testing.assert_allclose(obs.spectrum, [-3 + 2j, -3 - 2j])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # diffrax warns on complex leaves
        tr = obsjax.simulate(plant, obs, jnp.array([1.0, 0.0]), jnp.zeros(2), jnp.linspace(0.0, 2.0, 5))
    assert int(tr.status) == 0
    eig = np.linalg.eigvals(np.asarray(obs.observer_matrix))
    assert match(eig, [-3 + 2j, -3 - 2j]) < 1e-12


@pytest.mark.extended
def test_mimo_luenberger_error_obeys_the_placed_spectrum():
    """A 4-state, 2-output plant: the simulated error equals exp((A − LC) t) x̃(0)."""
    import scipy.linalg

    rng = np.random.default_rng(12)
    A, C = rng.standard_normal((4, 4)), rng.standard_normal((2, 4))
    plant = obsjax.LTI(A, np.zeros((4, 1)), C)
    obs = obsjax.Luenberger.from_poles(plant, [-2.0, -3.0, -4 + 1j, -4 - 1j])
    ts = jnp.linspace(0.0, 2.0, 5)
    x0 = np.array([1.0, -1.0, 0.5, 0.0])
    tr = obsjax.simulate(plant, obs, x0, np.zeros(4), ts, rtol=1e-10, atol=1e-12)
    F = np.asarray(obs.observer_matrix)
    ref = np.stack([scipy.linalg.expm(F * t) @ (-x0) for t in np.asarray(ts)])
    np.testing.assert_allclose(tr.error, ref, atol=1e-8)


# ---------------------------------------------------------------- thesis §3.2: the canonical form
A4 = np.array([[-2, 1, 0, 0], [0, -2, 1, 0], [0, 0, -1, 1], [-1, 0, 0, 0.0]])
B4 = np.array([[0.0], [0.0], [0.0], [1.0]])
C4 = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])


def test_canonical_form_single_output_is_python_controls_observable_form():
    rng = np.random.default_rng(13)
    A, C = rng.standard_normal((5, 5)), rng.standard_normal((1, 5))
    cf = observable_canonical_form(A, C)
    so, _ = control.observable_form(control.ss(A, np.zeros((5, 1)), C, 0))
    J = np.eye(5)[::-1]  # the same form with the states in reverse order
    np.testing.assert_allclose(J @ np.asarray(cf.A) @ J, so.A, atol=1e-9)
    np.testing.assert_allclose(np.asarray(cf.C) @ J, so.C, atol=1e-12)
    assert cf.indices == (5,)


@pytest.mark.parametrize("seed,n,m", [(14, 7, 3), (15, 6, 2), (16, 4, 2)])
@pytest.mark.extended
def test_canonical_form_structure_3_1c(seed, n, m):
    """The defining structure of (3.1c) and Fig. 3.3, and the spectrum of A kept."""
    rng = np.random.default_rng(seed)
    A, C = rng.standard_normal((n, n)), rng.standard_normal((m, n))
    cf = observable_canonical_form(A, C)
    nu = cf.indices
    assert nu == obsjax.design.observability_indices(A, C)
    Az, Cz, P = np.asarray(cf.A), np.asarray(cf.C), np.asarray(cf.P)
    ends = np.cumsum(nu) - 1
    S = np.zeros((n, n))
    start = 0
    for v in nu:
        S[start + 1 : start + v, start : start + v - 1] = np.eye(v - 1)
        start += v
    # A_z = S + Γ C_z : ones on each block's sub-diagonal, free entries only in the output columns
    np.testing.assert_allclose(Az, S + np.asarray(cf.Gamma) @ Cz, atol=1e-8)
    free = np.zeros((n, n), bool)
    free[:, ends] = True
    np.testing.assert_allclose(np.where(free | (S > 0), 0.0, Az), 0.0, atol=1e-8)
    # C_z = R E with R unit lower triangular
    E = np.eye(n)[ends]
    R = np.asarray(cf.R)
    np.testing.assert_allclose(Cz, R @ E, atol=1e-10)
    np.testing.assert_allclose(np.triu(R, 1), 0.0, atol=0)
    np.testing.assert_allclose(np.diag(R), 1.0)
    # (3.1c) itself: c_k A^{ν_k} = Σ α_ij(k) c_j A^i, with α_{ν_k, j}(k) = 0 for j ≥ k
    for k in range(m):
        ak = np.asarray(cf.alpha[k])
        lhs = C[k] @ np.linalg.matrix_power(A, nu[k])
        rhs = sum(ak[i, j] * C[j] @ np.linalg.matrix_power(A, i) for i in range(nu[k] + 1) for j in range(m))
        np.testing.assert_allclose(lhs, rhs, atol=1e-8 * np.abs(lhs).max())
        assert np.all(ak[nu[k], k:] == 0.0)
    np.testing.assert_allclose(P @ A, Az @ P, atol=1e-8 * np.abs(P).max() * np.abs(A).max())
    np.testing.assert_allclose(
        np.sort_complex(np.linalg.eigvals(Az)), np.sort_complex(np.linalg.eigvals(A)), atol=1e-7
    )


@pytest.mark.parametrize("time_unit, out_units", [(1.0, (1.0, 1.0)), (1e-6, (1.0, 1.0)), (1.0, (1e6, 1e-6))])
def test_canonical_form_is_exact_after_a_change_of_units(time_unit, out_units):
    """A → 1e-6 A (microseconds) or outputs in units 1e12 apart: the returned A_z = P A P⁻¹ and
    C_z = C P⁻¹ were formed with P⁻¹, whose rows differ in scale by powers of ‖A‖: C_z came back as
    [[−48, 0, 0, 1, −6e-5, …], …] instead of R E (every structural zero lost), while P, α, R, Γ were
    right.  Checked here without P⁻¹: C_z P = C and A_z P = P A to rounding relative to each row's
    scale, and the structure exact."""
    rng = np.random.default_rng(7)
    n, m = 7, 2
    A = time_unit * rng.standard_normal((n, n))
    C = np.diag(out_units) @ rng.standard_normal((m, n))
    cf = observable_canonical_form(A, C)
    Az, Cz, P = (np.asarray(v) for v in (cf.A, cf.C, cf.P))
    ends = np.cumsum(cf.indices) - 1
    np.testing.assert_array_equal(Cz, np.asarray(cf.R) @ np.eye(n)[ends])
    res_c = np.abs(Cz @ P - C).max(axis=1) / np.abs(C).max(axis=1)
    assert res_c.max() < 1e-10, res_c
    rows = np.abs(P @ A).max(axis=1) + np.abs(Az).max(axis=1) * np.abs(P).max(axis=1)
    res_a = np.abs(Az @ P - P @ A).max(axis=1) / rows
    assert res_a.max() < 1e-10, res_a
    np.testing.assert_allclose(
        np.sort_complex(np.linalg.eigvals(Az)), np.sort_complex(np.linalg.eigvals(A)),
        rtol=1e-6, atol=1e-9 * time_unit,
    )


@pytest.mark.extended
def test_canonical_placement_and_section_3_2_example():
    """place(..., method='canonical') = m single-output designs (Fig. 3.4); on the fourth-order
    example of §3.2 (subsystem (3.2) and a second block consistent with (3.5)-(3.7)) the reduced-order
    observer with poles {-3, -3} is the thesis's: G = [[1, 0], [0, 3]], x̂2 = x1 - Z (3.6),
    x̂4 = 3 x3 - 6 w."""
    cf = observable_canonical_form(A4, C4)
    assert cf.indices == (2, 2)
    poles = [-3.0, -4.0, -5.0, -6.0]
    L = np.asarray(place(A4, C4, poles, method="canonical"))
    assert eig_error(A4, C4, L, poles) < 1e-9
    ro = obsjax.ReducedOrder.from_poles(obsjax.LTI(A4, B4, C4), [-3.0, -3.0], Dc=[[0, 1, 0, 0], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(ro.gain, [[1.0, 0.0], [0.0, 3.0]], atol=1e-12)
    # the thesis's T rows: (3.3) T = [1, -1] for (x1, x2), and w = (3 x3 - x4)/6 for (x3, x4)
    T1 = obsjax.design.sylvester(A4[:2, :2], [[-3.0]], [[1.0, 0.0]])
    np.testing.assert_allclose(T1, [[1.0, -1.0]], atol=1e-12)
    T2 = obsjax.design.sylvester(A4[2:, 2:], [[-3.0]], [[1.0, 0.0]])
    np.testing.assert_allclose(T2, [[0.5, -1.0 / 6.0]], atol=1e-12)


def test_canonical_method_keeps_pairs_in_one_subsystem():
    with pytest.raises(ValueError, match="conjugate pair cannot be split"):
        place(np.diag([1.0, 2.0]), np.eye(2), [-1 + 1j, -1 - 1j], method="canonical")


def _true_error(A, C, L, poles, dps=60) -> float:
    """Largest relative eigenvalue error of A − L·C evaluated exactly (mpmath, `dps` digits, on the float64
    entries), relative to max(|λ|, 1e-3·max|λ_k|) as place's estimate is."""
    import mpmath as mp

    with mp.workdps(dps):
        M = mp.matrix(A.tolist()) - mp.matrix(L.tolist()) * mp.matrix(C.tolist())
        rest = [complex(e) for e in mp.eig(M, left=False, right=False)]
    floor = 1e-3 * np.max(np.abs(poles))
    worst = 0.0
    for p in np.asarray(poles, complex):
        d = [abs(p - q) for q in rest]
        k = int(np.argmin(d))
        worst = max(worst, d[k] / max(abs(p), floor))
        rest.pop(k)
    return worst


def _canonical_estimate(A, C, poles, method="canonical") -> float:
    """place's a-posteriori error for `method`, read from its refusal at rtol = 1e-300."""
    with pytest.raises(ValueError, match="a-posteriori relative eigenvalue error") as info:
        place(A, C, poles, method=method, rtol=1e-300)
    return float(str(info.value).split("eigenvalue error ")[1].split(",")[0])


@pytest.mark.parametrize(
    "n, m, seed, pairs",
    [(6, 1, 0, 0), (8, 1, 0, 0), (10, 1, 0, 0), (12, 1, 0, 0), (12, 2, 5, 0), (15, 3, 5, 0), (8, 2, 3, 2)],
)
@pytest.mark.extended
def test_canonical_estimate_bounds_the_exact_error(n, m, seed, pairs):
    """The canonical design's accuracy check against eigenvalues computed in 60-digit arithmetic: the
    estimate is never below the exact error (it used to take only each companion block's backward error
    and accepted n = 12, poles −1 … −12, whose exact error is 2.4e-5, at rtol = 1e-6), and within 1e4 of it.
    Companion roots are sensitive: from n ≈ 10 single-output gains are refused at the default rtol."""
    rng = np.random.default_rng(seed)
    A, C = rng.standard_normal((n, n)), rng.standard_normal((m, n))
    poles = -np.arange(1.0, n + 1.0).astype(complex)
    for k in range(pairs):  # conjugate pairs −k ± k·j in place of real poles
        poles[2 * k], poles[2 * k + 1] = -(k + 1) * (1 + 1j), -(k + 1) * (1 - 1j)
    poles = poles if pairs else poles.real
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        L = np.asarray(place(A, C, poles, method="canonical", rtol=np.inf))
        est = _canonical_estimate(A, C, poles)
    true = _true_error(A, C, L, poles)
    assert true <= est <= 1e4 * max(true, 1e-15)
    if true > 1e-6:  # the default rtol
        with pytest.raises(ValueError, match="does not place the poles"):
            place(A, C, poles, method="canonical")


def _robust_case(kind, n, m, seed):
    if kind == "chain":  # integrator chain: poles −1 … −n ask for an ill-conditioned eigenvector matrix
        A, C = np.diag(np.ones(n - 1), 1), np.eye(1, n)
    else:
        rng = np.random.default_rng(seed)
        A, C = rng.standard_normal((n, n)), rng.standard_normal((m, n))
    return A, C, -np.arange(1.0, n + 1.0)


@pytest.mark.parametrize(
    "kind, n, m, seed",
    [("chain", 6, 1, 0), ("chain", 8, 1, 0), ("chain", 10, 1, 0), ("random", 10, 1, 0), ("random", 12, 1, 0),
     ("random", 12, 2, 5), ("random", 20, 2, 5), ("random", 20, 4, 7)],
)
@pytest.mark.extended
def test_robust_estimate_bounds_the_exact_error(kind, n, m, seed):
    """The robust design's accuracy check against 60-digit eigenvalues of A − L·C: never below the exact
    error, and within 1e3 of it.  It used to multiply ε·‖A − LC‖ by each eigenvalue's condition number,
    which read 2e-4 for the 8-state chain whose gain is exact to 1.2e-10 (and refused it at rtol 1e-6)."""
    A, C, poles = _robust_case(kind, n, m, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        L = np.asarray(place(A, C, poles, method="robust", rtol=np.inf))
        est = _canonical_estimate(A, C, poles, method="robust")
    true = _true_error(A, C, L, poles)
    assert true <= est <= 1e3 * max(true, 1e-15)
    if est <= 1e-6:
        place(A, C, poles, method="robust")  # accepted at the default rtol


@pytest.mark.parametrize("method", ["robust", "canonical"])
@pytest.mark.extended
def test_nan_pole_in_a_batch_is_that_members_status(method):
    """vmap over the poles of an observer with one member's pole NaN: that member's status is 2
    (NONFINITE) and the others are unaffected -- the design's run-time check used to abort the whole
    batch.  `place` itself still raises on a NaN pole under jit (tested above), and simulate(throw=True)
    raises on the NaN gain."""
    import equinox as eqx

    plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    ts = jnp.linspace(0.0, 2.0, 11)
    obs = obsjax.Luenberger.from_poles(plant, [-3.0, -4.0], method=method)

    def run(p, throw=False):
        o = eqx.tree_at(lambda o: o.poles, obs, p)
        return obsjax.simulate(plant, o, jnp.ones(2), jnp.zeros(2), ts, throw=throw)

    ps = jnp.array([[-3.0, -4.0], [jnp.nan, -4.0], [-5.0, -6.0]])
    tr = jax.jit(jax.vmap(run))(ps)
    np.testing.assert_array_equal(tr.status, [0, 2, 0])
    ref = run(ps[2])
    np.testing.assert_allclose(tr.xhat[2], ref.xhat, rtol=1e-12, atol=1e-12)
    with pytest.raises(Exception, match="non-finite values"):
        jax.jit(lambda p: run(p, throw=True).xhat)(ps[1]).block_until_ready()
    ro = obsjax.ReducedOrder.from_poles(plant, [-3.0])
    run_ro = lambda p: obsjax.simulate(plant, eqx.tree_at(lambda o: o.poles, ro, p), jnp.ones(2), jnp.zeros(2), ts, throw=False).status
    np.testing.assert_array_equal(jax.vmap(run_ro)(jnp.array([[-3.0], [jnp.nan]])), [0, 2])


@pytest.mark.parametrize("s", [1e4, 1e7, 1e10])
@pytest.mark.extended
def test_estimate_under_a_change_of_state_units(s):
    """x → D x with D spanning s² in scale: the robust estimate is never below the exact error.  Its
    floor was 10⁻³·‖A‖_F, which a change of units inflates (‖A‖_F ≈ 1e20 at s = 1e10), so that any
    error read as small; it is now 10⁻³·max|λ_k| as in analysis.placement_error."""
    rng = np.random.default_rng(11)
    A0, C0 = rng.standard_normal((5, 5)), rng.standard_normal((2, 5))
    D = np.diag(s ** np.linspace(-1.0, 1.0, 5))
    A, C = D @ A0 @ np.linalg.inv(D), C0 @ np.linalg.inv(D)
    poles = [-1.0, -2.0, -3.0, -4.0, -5.0]
    for method in ("robust", "canonical"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            L = np.asarray(place(A, C, poles, method=method, rtol=np.inf))
            est = _canonical_estimate(A, C, poles, method=method)
        assert _true_error(A, C, L, poles) <= est


def test_canonical_form_refuses_indices_that_do_not_fit_the_pair():
    """The indices of (A, C) are (2, 1); given (1, 2) the rows of P are dependent: the form came back NaN,
    eagerly and under jit, without a word."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"`indices` must be the observability indices of \(A, C\), which are \(2, 1\), got \(1, 2\)"):
        observable_canonical_form(A, C, indices=(1, 2))
    f = jax.jit(lambda A, C: observable_canonical_form(A, C, indices=(1, 2)).A)
    with pytest.raises(Exception, match="`indices` are not the observability indices"):
        jax.block_until_ready(f(A, C))
    good = jax.jit(lambda A, C: observable_canonical_form(A, C, indices=(2, 1)).A)(A, C)
    np.testing.assert_allclose(np.asarray(good), np.asarray(observable_canonical_form(A, C).A), atol=1e-12)
    # indices whose rows are independent but not the lexicographic ones: the form dropped terms and
    # came back finite and wrong (P A ≠ A_z P, another spectrum) under jit
    rng = np.random.default_rng(0)
    A4, C4 = rng.standard_normal((4, 4)), rng.standard_normal((2, 4))
    assert observable_canonical_form(A4, C4).indices == (2, 2)
    g = jax.jit(lambda A, C: observable_canonical_form(A, C, indices=(3, 1)).A)
    with pytest.raises(Exception, match=r"P A ≠ A_z P"):
        jax.block_until_ready(g(A4, C4))


@pytest.mark.extended
def test_robust_gain_without_a_derivative_is_refused_when_differentiated():
    """m > (n+1)/2: the Tits-Yang minimiser is not isolated (a family of equally conditioned eigenvector
    matrices), the gain returned is one member and does not move smoothly; the implicit derivative gave
    16.6 where central differences give 1.68 (n = 4, m = 3), silently.  Now differentiating it raises,
    eagerly and under jit; the placement itself stays exact; method='canonical' differentiates; and at
    m = (n+1)/2 (isolated) the robust derivative still equals central differences."""
    for n, m, seed, isolated in ((4, 3, 1, False), (5, 3, 4, True)):
        rng = np.random.default_rng(seed)
        A, C = rng.standard_normal((n, n)), rng.standard_normal((m, n))
        p0, W, D = -np.arange(1.0, n + 1), rng.standard_normal((n, m)), rng.standard_normal(n)
        L = np.asarray(place(A, C, p0))
        np.testing.assert_allclose(np.sort(np.linalg.eigvals(A - L @ C).real), np.sort(p0), atol=1e-8)

        def fd(f, h=1e-5):
            return (float(f(p0 + h * D)) - float(f(p0 - h * D))) / (2 * h)

        def robust(p):
            return jnp.sum(W * place(A, C, p))

        if isolated:
            ad = float(jax.grad(robust)(jnp.asarray(p0)) @ D)
            assert ad == pytest.approx(fd(robust), rel=1e-6)
            continue
        for g in (jax.grad(robust), jax.jit(jax.grad(robust))):
            with pytest.raises(Exception, match="not differentiable here.*method='canonical'"):
                jax.block_until_ready(g(jnp.asarray(p0)))

        def canonical(p):
            return jnp.sum(W * place(A, C, p, method="canonical"))

        ad = float(jax.grad(canonical)(jnp.asarray(p0)) @ D)
        assert ad == pytest.approx(fd(canonical), rel=1e-6)
