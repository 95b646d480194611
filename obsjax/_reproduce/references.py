"""The source documents of obsjax, cited bibliographically, and the reference values its tests and
``obsjax reproduce`` compare against.

Every value below was computed independently of obsjax (no obsjax code involved), as described beside it.
Equation, figure and example numbers are the documents' own.
"""

from __future__ import annotations

#: The five documents obsjax implements.
SOURCES = {
    "chen-yen": (
        'M.-S. Chen and J.-Y. Yen, "Application of the least squares algorithm to the observer design for '
        'linear time-varying systems", IEEE Transactions on Automatic Control, 44(9), 1999.'
    ),
    "hassan": (
        'A. D. Hassan, "Observer design techniques for time invariant linear systems", M.Eng. thesis, '
        "Concordia University, Montreal, 1979."
    ),
    "lovass-nagy": (
        'K. Chaisanguanmitt, "Developed observers for time-varying linear systems" (lecture slides on '
        "Lovass-Nagy observers by matrix generalized inverses and min-max initial-state estimation)."
    ),
    "huang-zhu": (
        'R. Huang and J. J. Zhu, "Time-varying high-gain trajectory linearization observer design", '
        "conference paper (manuscript received September 2008)."
    ),
    "byrski-fuksa": (
        'W. Byrski and S. Fuksa, "Optimal finite parameter observer. An application to synthesis of '
        'stabilizing feedback for a linear system", journal article (received March 1982).'
    ),
}

# ----------------------------------------------------------------------------------------------- Chen & Yen
#: ‖x̃(t)‖ of the Chen & Yen example (A(t), C(t) from cos t and √t, x(0) = 0, x̂(0) = [5, −5]) under the
#: error dynamics (9) with gain (13) and P from (15), P(kT⁺) = p0·I at every reset.  Computed with SciPy's
#: ``solve_ivp`` (RK45, rtol 1e-10, atol 1e-12), segment by segment, integrated to each query time exactly.
#: Keys: (γ, p0, T) → {t: ‖x̃(t)‖}, values to four significant digits.
CHEN_YEN_ERROR_NORM = {
    (20.0, 0.1, 0.25): {1.0: 5.775, 2.0: 7.126, 5.0: 1.052, 10.0: 3.347e-2},  # Fig. 1
    (20.0, 0.1, 2.0): {1.0: 4.853, 2.0: 5.280, 5.0: 1.120, 10.0: 3.707e-3},  # Fig. 2
    (40.0, 0.1, 0.25): {10.0: 6.037e-4},
    (20.0, 1.0, 0.25): {10.0: 1.702e-4},
}
#: The open loop of the example is unstable: ‖x(10)‖ from x(0) = [5, −5] (same SciPy integration).
CHEN_YEN_OPEN_LOOP_NORM_10 = 11.63
#: A plain Python loop over SciPy ``solve_ivp`` (RK45, rtol 1e-6, atol 1e-8, 40 segments of T = 0.25 on
#: [0, 10]) integrates about this many trajectories per second on a 2-core machine: the baseline a user
#: would otherwise write (benchmark (a) re-measures it in the same run as obsjax).
CHEN_YEN_SCIPY_LOOP_TRAJ_PER_S = 30.0

# ----------------------------------------------------------------------------------------------- Hassan
#: Example (2.8): A = [[−2, 1], [0, −1]], B = [0, 1]ᵀ, C = [1, 0], observer poles {−3, −3} → G = [3, 4]ᵀ,
#: A − GC = [[−5, 1], [−4, −1]] (hand computation from the characteristic polynomial).
HASSAN_28_GAIN = (3.0, 4.0)
#: Reduced-order observer of the same plant with pole −3: G = 2 (A22 − G·A12 = −1 − G = −3).
HASSAN_REDUCED_GAIN = 2.0
#: Section 3.2 / (3.3): subsystem [[−2, 1], [0, −2]] observed through x1 with F = −3: T = [1, −1].
HASSAN_33_T = (1.0, -1.0)

# ----------------------------------------------------------------------------------------------- Byrski & Fuksa
#: Norm (31) of the minimum-norm observer of the double integrator (29) (C = [2, 0], α = β = I) on a window
#: [0, T], checked by an independent discretisation of the minimum-norm problem (600 points).
BYRSKI_FUKSA_NORM31 = {0.5: 5.11731, 1.0: 2.09271, 2.0: 1.28257, 4.0: 1.22576}
#: Its limit as T → ∞: √1.5.
BYRSKI_FUKSA_NORM31_LIMIT = 1.5**0.5
