"""The pattern of a set of observer poles (real, conjugate pairs, repeated) and the Jordan structure that
pole placement gives it.

Pole placement assigns a spectrum *and* an eigenstructure.  With m outputs, an eigenvalue can have at most
m independent eigenvectors in A − LC (rank(A − LC − λI) ≥ n − m), and by Rosenbrock's theorem the sizes of
the Jordan chains must be compatible with the observability indices: the degrees d_1 ≥ … ≥ d_m of the
invariant polynomials of A − LC must majorise the indices κ_1 ≥ … ≥ κ_m (Σ_{i≤j} d_i ≥ Σ_{i≤j} κ_i,
equality at j = m) [H. H. Rosenbrock, *State-space and multivariable theory*, Nelson, 1970].  A pole
that cannot be given independent eigenvectors is assigned with a Jordan chain, which makes the gain
sensitive: an eigenvalue of a Jordan block of size s moves by about ε^{1/s} under a perturbation ε.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Poles closer than this (relative) are one repeated pole; a conjugate must match this closely.
CLUSTER_RTOL = 1e-9
#: |Im p| ≤ this · |p| makes p real.  Half of CLUSTER_RTOL: a "pair" whose two members are closer than
#: CLUSTER_RTOL is one repeated pole by the rule above, i.e. a real double pole (with a smaller threshold
#: such a pair matched both itself and its conjugate, and its structure was corrupt).
REAL_RTOL = CLUSTER_RTOL / 2


class PoleStructure(NamedTuple):
    """The static pattern of a pole vector (hashable: it is a static argument under ``jit``).

    `clusters`: one entry per distinct pole value, ``(kind, indices, conjugates)`` with kind 1 (a real
    pole) or 2 (a conjugate pair), the positions in the pole vector of its copies (for a pair: of the
    members with Im > 0; multiplicity = len(indices)) and, for a pair, the positions of the conjugates.
    `n`: the number of poles.
    """

    n: int
    clusters: tuple[tuple[int, tuple[int, ...], tuple[int, ...]], ...]


class Block(NamedTuple):
    """One Jordan chain of the assignment: kind 1 (real) or 2 (pair), its length s, the positions of the
    s poles it consumes, the position of its cluster, and whether its rows are fixed (a cluster of m
    simple copies: then the eigenvectors span the whole admissible space and nothing is to choose)."""

    kind: int
    length: int
    indices: tuple[int, ...]
    cluster: int
    fixed: bool


def pole_structure(poles) -> PoleStructure:
    """The pattern of concrete observer poles: which are real, which are conjugate pairs, which repeat.

    Under ``jit`` the pattern cannot be read from traced values; pass the structure of an example pole
    vector with the same pattern to :func:`obsjax.design.place` (``structure=``).

    **Raises** ``ValueError`` for a non-finite pole or a complex pole without its conjugate.

    **Example:** ``pole_structure([-1 + 2j, -1 - 2j, -3, -3])`` → two clusters: a pair (once) and a real
    pole of multiplicity 2.
    """
    v = np.atleast_1d(np.asarray(poles)).astype(complex)
    if v.ndim != 1:
        raise ValueError(f"`poles` must be a vector, got shape {v.shape}.")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"`poles` must be finite, got {v.tolist()}.")
    n = v.shape[0]
    scale = np.abs(v)
    real = np.abs(v.imag) <= REAL_RTOL * scale
    used = np.zeros(n, bool)
    clusters = []
    for i in range(n):
        if used[i]:
            continue
        p = v[i]
        close = lambda q, p=p: abs(q - p) <= CLUSTER_RTOL * max(abs(p), abs(q))
        if real[i]:
            members = [k for k in range(n) if not used[k] and real[k] and close(v[k].real + 0j)]
            used[members] = True
            clusters.append((1, tuple(members), ()))
            continue
        up = p if p.imag > 0 else np.conj(p)
        free = [k for k in range(n) if not used[k] and not real[k]]
        members_up = [k for k in free if v[k].imag > 0 and close(v[k], up)]
        members_dn = [k for k in free if v[k].imag < 0 and close(v[k], np.conj(up))]
        if len(members_up) != len(members_dn):
            raise ValueError(
                "`poles` must be closed under conjugation for a real gain: "
                f"{up} appears {len(members_up)} time(s) but its conjugate {np.conj(up)} "
                f"{len(members_dn)} time(s)."
            )
        used[members_up] = True
        used[members_dn] = True
        clusters.append((2, tuple(members_up), tuple(members_dn)))
    return PoleStructure(n=n, clusters=tuple(clusters))


def default_structure(n: int) -> PoleStructure:
    """n distinct real poles (the pattern assumed for traced real poles)."""
    return PoleStructure(n=n, clusters=tuple((1, (i,), ()) for i in range(n)))


def _balanced_parts(k: int, m: int) -> list[int]:
    q = min(k, m)
    return [k // q + (1 if i < k % q else 0) for i in range(q)]


def chain_lengths(structure: PoleStructure, m: int, kronecker=None) -> list[list[int]]:
    """Jordan chain lengths per cluster: as many simple eigenvalues as possible (a cluster of
    multiplicity k gets min(k, m) chains as equal as possible), then lengthened where Rosenbrock's
    majorisation by the observability indices `kronecker` (sorted, decreasing) requires it."""
    parts = [_balanced_parts(len(idx), m) for _, idx, _ in structure.clusters]
    if kronecker is None:
        return parts
    kap = list(kronecker) + [0] * (m - len(kronecker))
    weights = [kind for kind, _, _ in structure.clusters]

    def degrees():
        return [sum(w * (p[i] if i < len(p) else 0) for w, p in zip(weights, parts)) for i in range(m)]

    while True:
        d = degrees()
        bad = [j for j in range(m) if sum(d[: j + 1]) < sum(kap[: j + 1])]
        if not bad:
            return parts
        j = bad[0]  # the partial sum D_{j+1} is short: move a pole from a chain beyond j into one ≤ j
        cands = [c for c, p in enumerate(parts) if len(p) > j + 1]
        c = max(cands, key=lambda c: (len(parts[c]), sum(parts[c]), -c))
        p = parts[c]
        p[-1] -= 1
        if p[-1] == 0:
            p.pop()
        q = max(i for i in range(min(j + 1, len(p))) if i == 0 or p[i - 1] > p[i])
        p[q] += 1


def blocks_of(structure: PoleStructure, m: int, kronecker=None) -> tuple[Block, ...]:
    """The Jordan chains of the assignment (see :func:`chain_lengths`)."""
    out = []
    for c, ((kind, idx, _), lengths) in enumerate(
        zip(structure.clusters, chain_lengths(structure, m, kronecker))
    ):
        fixed = len(lengths) == m and all(s == 1 for s in lengths)
        start = 0
        for s in lengths:
            out.append(Block(kind, s, tuple(idx[start : start + s]), c, fixed))
            start += s
    return tuple(out)


def jordan_summary(structure: PoleStructure, blocks, poles) -> list[str]:
    """Human-readable list of the poles assigned with Jordan chains longer than 1."""
    v = np.asarray(poles).astype(complex)
    out = []
    for c, (kind, idx, _) in enumerate(structure.clusters):
        lengths = [b.length for b in blocks if b.cluster == c]
        if max(lengths) > 1:
            p = v[idx[0]]
            name = f"{p.real:.6g}" if kind == 1 else f"{p.real:.6g} ± {abs(p.imag):.6g}j"
            out.append(f"{name} (multiplicity {len(idx)}: Jordan chains {tuple(lengths)})")
    return out


def encode(poles, structure: PoleStructure) -> np.ndarray:
    """Real encoding of a conjugate-closed pole vector: real poles as they are; for each pair, Re p at the
    position of the member with Im > 0 and |Im p| at the position of its conjugate.  Under
    ``positive=True`` tuning (sign-preserving) a pair then stays a stable complex pair."""
    v = np.asarray(poles).astype(complex)
    out = v.real.copy()
    for kind, up, dn in structure.clusters:
        if kind == 2:
            out[list(dn)] = np.abs(v[list(up)].imag)
    return out


def decode(x, structure: PoleStructure):
    """(Re, Im) arrays (jax, real) of the poles from their real encoding (see :func:`encode`)."""
    import jax.numpy as jnp

    from .._checks import device_array, static_value

    v = static_value(x)
    if v is not None and not np.iscomplexobj(v):
        # constant poles: decoded by NumPy (the same assignments; run eagerly, each JAX operation would
        # compile a program on its first call)
        v = np.asarray(v, dtype=np.float64).reshape(-1)
        re, im = v.copy(), np.zeros_like(v)
        for kind, up, dn in structure.clusters:
            if kind == 2:
                up, dn = np.asarray(up), np.asarray(dn)
                re[dn] = v[up]
                im[up] = v[dn]
                im[dn] = -v[dn]
        return device_array(re), device_array(im)
    x = jnp.asarray(x)
    re, im = x, jnp.zeros_like(x)
    for kind, up, dn in structure.clusters:
        if kind == 2:
            up, dn = np.asarray(up), np.asarray(dn)
            re = re.at[dn].set(x[up])
            im = im.at[up].set(x[dn]).at[dn].set(-x[dn])
    return re, im
