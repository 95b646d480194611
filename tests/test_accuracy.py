"""obsjax.analysis.closed_loop_eigvals / placement_error: eigenvalues of A − LC in extended precision,
checked on integer matrices whose spectrum is known exactly (an integer similarity of a triangular
matrix), where float64 eigvals is measurably off."""

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
