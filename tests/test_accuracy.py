"""obsjax.analysis.closed_loop_eigvals / placement_error: eigenvalues of A − LC in extended precision,
checked on integer matrices whose spectrum is known exactly (an integer similarity of a triangular
matrix), where float64 eigvals is measurably off."""

import warnings

import numpy as np
import pytest

import obsjax
from obsjax.analysis import closed_loop_eigvals, placement_error


def _known(n=10, seed=0, big=20):
    """(A, C, L, eigenvalues): A − LC = S U S⁻¹ with U upper triangular (integer diagonal 1…n, large
    integer entries above it) and S unit lower triangular with small integers, so S⁻¹ is an integer
    matrix too; every entry is an exactly representable integer (object arithmetic, then float64)."""
    rng = np.random.default_rng(seed)
    d = -np.arange(1, n + 1)
    U = np.triu(rng.integers(-big, big + 1, (n, n)), 1).astype(object) + np.diag(d).astype(object)
    S = (np.tril(rng.integers(-2, 3, (n, n)), -1) + np.eye(n, dtype=int)).astype(object)
    Si = np.eye(n, dtype=int).astype(object)  # S⁻¹ by forward substitution, exact
    for i in range(n):
        for j in range(i):
            Si[i] -= S[i, j] * Si[j]
    M = S.dot(U).dot(Si)
    C = rng.integers(-3, 4, (2, n)).astype(object)
    L = rng.integers(-5, 6, (n, 2)).astype(object)
    A = M + L.dot(C)
    as_f = [np.array(x, dtype=np.float64) for x in (A, C, L)]
    assert all(np.all(np.abs(x) < 2.0**52) for x in as_f)  # exact in float64
    return (*as_f, d.astype(float))


def test_known_spectrum_to_extended_precision_where_float64_is_off():
    A, C, L, d = _known()
    lam, acc = closed_loop_eigvals(A, C, L, return_accuracy=True)
    f64 = np.sort_complex(np.linalg.eigvals(A - L @ C))
    err64 = np.max(np.abs(f64 - np.sort_complex(d.astype(complex))) / np.abs(np.sort(d)))
    err = np.max(np.abs(np.sort_complex(lam) - np.sort_complex(d.astype(complex))) / np.abs(np.sort(d)))
    assert err64 > 1e-8  # ill-conditioned enough for float64 to be off (measured 1.1e-7)
    assert err < 1e-2 * err64 and err < 1e-9, (err, err64)  # (measured 5e-11)
    # the reported accuracy is honest: the refined values are within it (up to a factor)
    assert err <= 10 * np.max(acc) + 1e-15 and np.max(acc) < 1e-9
    assert placement_error(A, C, L, d) == pytest.approx(err, rel=1e-6, abs=1e-15)
    # the requested poles in another order, matched greedily
    assert placement_error(A, C, L, d[::-1]) == pytest.approx(err, rel=1e-6, abs=1e-15)


def test_complex_pairs_and_a_design_of_obsjax():
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    poles = np.array([-2.0 + 1.0j, -2.0 - 1.0j, -5.0])
    L = np.asarray(obsjax.design.place(A, C, poles))
    lam = closed_loop_eigvals(A, C, L)
    assert np.iscomplexobj(lam) and lam.shape == (3,)
    assert placement_error(A, C, L, poles) < 1e-14
    # a deliberately wrong gain is measured as wrong
    assert placement_error(A, C, L * (1 + 1e-6), poles) > 1e-8


def test_bad_input_raises():
    A, C, L = np.eye(3), np.ones((1, 3)), np.ones((3, 1))
    with pytest.raises(ValueError, match="`A` must be square"):
        closed_loop_eigvals(np.ones((3, 2)), C, L)
    with pytest.raises(ValueError, match="`C` must be"):
        closed_loop_eigvals(A, np.ones((1, 2)), L)
    with pytest.raises(ValueError, match="`L` must be"):
        closed_loop_eigvals(A, C, np.ones((2, 1)))
    with pytest.raises(ValueError, match="`L` must be finite"):
        closed_loop_eigvals(A, C, np.full((3, 1), np.nan))
    with pytest.raises(ValueError, match="`iters` must be an integer >= 3"):
        closed_loop_eigvals(A, C, L, iters=1)
    with pytest.raises(ValueError, match="`A` must be real"):
        closed_loop_eigvals(A + 0j, C, L)
    with pytest.raises(ValueError, match="`poles` must be finite"):
        placement_error(np.diag([-1.0, -2.0, -3.0]), C, 0 * L, [np.nan, -2.0, -3.0])
    with pytest.raises(ValueError, match="`poles` must hold n = 3"):
        placement_error(np.diag([-1.0, -2.0, -3.0]), C, 0 * L, [-1.0, -2.0])


def test_a_jordan_block_is_refused_not_refined():
    """A double defective eigenvalue cannot be refined one by one: an error, not a wrong value."""
    A = np.array([[-1.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -3.0]])
    with pytest.raises(RuntimeError, match="closed_loop_eigvals"):
        closed_loop_eigvals(A, np.zeros((1, 3)), np.zeros((3, 1)))


def test_placement_error_falls_back_to_float64_with_infinite_accuracy():
    """A Jordan pair: no refinement, the float64 eigenvalues and an accuracy of inf say so."""
    A = np.array([[-1.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -3.0]])
    err, acc = placement_error(A, np.zeros((1, 3)), np.zeros((3, 1)), [-1.0, -1.0, -3.0], return_accuracy=True)
    assert err < 1e-7 and acc == np.inf


def test_placement_error_alone_warns_when_its_figure_is_not_refined():
    """Returned without its accuracy, a figure measured in float64 (no refinement possible) warns; a
    refined one does not."""
    A = np.array([[-1.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -3.0]])
    with pytest.warns(RuntimeWarning, match="float64 eigenvalues were used"):
        err = placement_error(A, np.zeros((1, 3)), np.zeros((3, 1)), [-1.0, -1.0, -3.0])
    assert err < 1e-7
    A2 = np.array([[-2.0, 1.0], [0.0, -1.0]])
    C2 = np.array([[1.0, 0.0]])
    L2 = np.asarray(obsjax.design.place(A2, C2, [-3.0, -4.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert placement_error(A2, C2, L2, [-3.0, -4.0]) < 1e-14
        placement_error(A, np.zeros((1, 3)), np.zeros((3, 1)), [-1.0, -1.0, -3.0], return_accuracy=True)


def test_a_pole_at_the_origin_is_measured_against_the_size_of_the_problem():
    """A requested pole at 0 placed to rounding reads as a small error, not as 1e293 (the distance
    divided by the smallest positive float)."""
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    C = np.array([[1.0, 0.0]])
    L = np.asarray(obsjax.design.place(A, C, [0.0, -1.0]))
    assert obsjax.analysis.placement_error(A, C, L, [0.0, -1.0]) < 1e-10  # L = [-2, 4] is exact
    # a gain that misses the origin by 1e-5 (1e-3 of the largest pole, 1) reads as 1e-2
    off = np.asarray(obsjax.design.place(A, C, [-1e-5, -1.0]))
    err = obsjax.analysis.placement_error(A, C, off, [0.0, -1.0])
    assert err == pytest.approx(1e-2, rel=1e-6)


def _mp_eigvals(A, C, L, dps=40):
    """Eigenvalues of the exact A − LC (float64 entries taken as exact) in `dps`-digit arithmetic
    (mpmath: code independent of obsjax's refinement)."""
    import mpmath

    with mpmath.workdps(dps):
        M = mpmath.matrix(A.tolist()) - mpmath.matrix(L.tolist()) * mpmath.matrix(C.tolist())
        return np.array([complex(e) for e in mpmath.eig(M, left=False, right=False)])


def _nearest(ref, lam):
    return np.array([lam[np.argmin(np.abs(lam - r))] for r in ref])


@pytest.mark.parametrize("which", ["obsjax", "scipy"])
def test_large_single_output_gain_against_40_digit_eigenvalues(which):
    """A single-output placement with ‖L‖ ~ 1e4 (n = 10, κ_k up to ~1e7): the long-double residuals
    used before settled at 1.5e-8 relative here and read a gain placing its poles to 2.4e-9 as 1.1e-8.
    The double-double refinement agrees with 40-digit eigenvalues to ~1e-15 (the float64 rounding of
    the result), and the accuracy it states is below the distance to them only where both are noise."""
    import scipy.signal

    rng = np.random.default_rng(2024)  # the first structured case of tests/test_placement.py
    n = 10
    A, C = rng.standard_normal((n, n)), rng.standard_normal((1, n))
    poles = []
    while len(poles) < n:
        if n - len(poles) >= 2 and rng.random() < 0.4:
            re, im = -rng.uniform(0.5, 4.0), rng.uniform(0.2, 3.0)
            poles += [re + 1j * im, re - 1j * im]
        else:
            poles.append(-rng.uniform(0.5, 4.0))
    poles = np.array(poles)
    if which == "obsjax":
        L = np.asarray(obsjax.design.place(A, C, poles))
    else:
        L = scipy.signal.place_poles(A.T, C.T, poles).gain_matrix.T
    assert np.linalg.norm(L) > 1e3
    ref = _mp_eigvals(A, C, L)
    lam, acc = closed_loop_eigvals(A, C, L, return_accuracy=True)
    f64 = np.linalg.eigvals(A - L @ C)
    rel = np.abs(_nearest(ref, lam) - ref) / np.abs(ref)
    rel64 = np.abs(_nearest(ref, f64) - ref) / np.abs(ref)
    assert np.max(rel64) > 1e-10  # float64 is measurably off here
    assert np.max(rel) < 1e-14, np.max(rel)
    assert np.max(acc / np.abs(lam)) < 1e-14
    err, err_acc = placement_error(A, C, L, poles, return_accuracy=True)
    mp_err = max(np.min(np.abs(ref - p)) / abs(p) for p in poles)
    assert err == pytest.approx(mp_err, rel=1e-6), (err, mp_err)
    assert err_acc < 1e-14


def test_agrees_with_40_digit_eigenvalues_on_random_gains():
    """Random (A, C, L) with n = 6 … 14 and m = 1 … 3, some scaled by 1e3: the refined eigenvalues
    equal mpmath's to 1e-14 relative (the float64 rounding of the returned value)."""
    rng = np.random.default_rng(5)
    for n, m, s in [(6, 1, 1.0), (8, 2, 1e3), (11, 3, 1.0), (14, 2, 1e-3)]:
        A = s * rng.standard_normal((n, n))
        C, L = rng.standard_normal((m, n)), s * 30.0 * rng.standard_normal((n, m))
        ref = _mp_eigvals(A, C, L)
        lam = closed_loop_eigvals(A, C, L)
        assert np.max(np.abs(_nearest(ref, lam) - ref) / np.abs(ref)) < 1e-14


def test_placement_error_matches_poles_to_eigenvalues_at_the_smallest_worst_error():
    """Eigenvalues {−1.04, −0.9}, requested {−1, −1.05}: the greedy matching paired −1 with −1.04 and left
    −1.05 with −0.9 (0.143); the best one-to-one matching has a worst error of 0.1 (−1 ↔ −0.9)."""
    A, C, L = np.diag([-1.04, -0.9]), np.eye(2), np.zeros((2, 2))
    err, acc = placement_error(A, C, L, [-1.0, -1.05], return_accuracy=True)
    assert abs(err - 0.1) < 1e-12 and acc < 1e-14
    brute = min(max(abs(e - q) / abs(q) for e, q in zip(perm, [-1.0, -1.05])) for perm in ((-1.04, -0.9), (-0.9, -1.04)))
    assert abs(err - brute) < 1e-12


def test_one_output_as_a_vector():
    """`place` takes C of one output as a vector; placement_error and closed_loop_eigvals refused it."""
    A, c = np.array([[-2.0, 1.0], [0.0, -1.0]]), np.array([1.0, 0.0])
    L = np.asarray(obsjax.design.place(A, c, [-3.0, -4.0]))
    assert placement_error(A, c, L, [-3.0, -4.0]) < 1e-14
    np.testing.assert_allclose(np.sort(closed_loop_eigvals(A, c, L.ravel()).real), [-4.0, -3.0], atol=1e-14)
