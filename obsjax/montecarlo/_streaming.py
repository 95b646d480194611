"""Streaming statistics of a Monte-Carlo study: exact sums and counts, and logarithmic histograms
for quantiles, so that a study of any size is summarised in memory bounded by one chunk.

Exact quantiles cannot be computed in one pass over data that is not kept.  :class:`LogHistogram`
is a relative-accuracy sketch (the store of DDSketch: Masson, Rim & Lee, "DDSketch: a fast and
fully-mergeable quantile sketch with relative-error guarantees", Proc. VLDB Endowment 12(12), 2019,
§2): a value x > 0 is counted in bin i = ⌈log_γ x⌉, which holds (γ^(i−1), γ^i], with
γ = (1 + α)/(1 − α); the bin is represented by x̂_i = 2γ^i/(γ + 1), and every x in it satisfies
|x̂_i − x| ≤ α·x.  Zeros (and values below the sketch's floor, see below) are counted apart and
represented by 0; +∞ is counted apart and represented by +∞.

A quantile at level q follows ``numpy.quantile``'s definition with the order statistics replaced by
their representatives: for ``"linear"`` (numpy's default) the estimate is
(1 − f)·x̂_(j) + f·x̂_(j+1) with h = q(N − 1), j = ⌊h⌋, f = h − j, and since each representative is
within α of its order statistic, the estimate q̂ satisfies

    |q̂ − q_exact| ≤ α·q_exact + floor        (the error bound),

and likewise for ``"lower"`` (x̂_(j)) and for the mean of the k largest values (conditional value at
risk).  The bound is the sketch's only approximation: counts are exact integers, so the estimate does
not depend on the order in which chunks arrive or on the chunk size.

The store is one dense array of counts per column over the bins seen so far; it grows with the
dynamic range of the data (ln(10)/ln(γ) ≈ 1151 bins per decade at α = 10⁻³), up to ``max_bins``
bins.  Beyond that the lowest bins are folded into the zero count and the floor rises to the lower
edge of the lowest bin kept (``floor`` is then > 0 and enters the bound above); the largest values,
which the bands' upper levels and the CVaR read, are never folded.
"""

from __future__ import annotations

import math

import numpy as np

#: Default relative accuracy α of the quantile sketches of a streaming study.
DEFAULT_SKETCH_RTOL = 1e-3
#: Default maximum number of bins of one column of a sketch (2^15: 28 decades at α = 10⁻³).
DEFAULT_MAX_BINS = 2**15
_TINY = np.finfo(np.float64).tiny  # values below this (subnormals) count as zero


class LogHistogram:
    """A relative-accuracy quantile sketch of ``columns`` independent streams of values ≥ 0 (or +∞).

    **Arguments:**

    - `columns`: the number of streams (e.g. one per save time).
    - `rtol`: the relative accuracy α ∈ (0, 0.5).
    - `max_bins`: the largest number of bins kept per column.
    """

    def __init__(self, columns: int, rtol: float = DEFAULT_SKETCH_RTOL, max_bins=DEFAULT_MAX_BINS):
        if not 0.0 < rtol < 0.5:
            raise ValueError(f"the sketch's relative accuracy must be in (0, 0.5), got {rtol!r}.")
        if int(max_bins) < 16:
            raise ValueError(f"`max_bins` must be at least 16, got {max_bins!r}.")
        self.rtol = float(rtol)
        self.gamma = (1.0 + rtol) / (1.0 - rtol)
        self._log_gamma = math.log(self.gamma)
        self.max_bins = int(max_bins)
        self.columns = int(columns)
        self.counts = np.zeros((self.columns, 0), dtype=np.int64)
        self.k0 = 0  # bin index of counts[:, 0]
        self.zeros = np.zeros(self.columns, dtype=np.int64)  # zeros and values below the floor
        self.infs = np.zeros(self.columns, dtype=np.int64)
        self.floor = 0.0  # values below it are counted as zeros (0 until bins were folded)

    @property
    def count(self) -> np.ndarray:
        """(columns,) the number of values added to each column."""
        return self.zeros + self.infs + self.counts.sum(axis=1)

    def _index(self, v):
        return np.ceil(np.log(v) / self._log_gamma).astype(np.int64)

    def representative(self, k):
        """x̂ of bin(s) k: 2γ^k/(γ + 1)."""
        return 2.0 * np.exp(np.asarray(k, dtype=np.float64) * self._log_gamma) / (self.gamma + 1.0)

    def add(self, values) -> None:
        """Count the values of a (rows, columns) array (every entry ≥ 0 or +∞; NaN is refused)."""
        v = np.asarray(values, dtype=np.float64)
        if v.ndim == 1 and self.columns == 1:
            v = v[:, None]
        if v.ndim != 2 or v.shape[1] != self.columns:
            raise ValueError(f"expected values of shape (rows, {self.columns}), got {v.shape}.")
        if np.isnan(v).any() or (v < 0).any():
            raise ValueError("a sketch counts values >= 0 or +inf; got NaN or a negative value.")
        inf = np.isinf(v)
        small = v < max(_TINY, self.floor)
        mid = ~(inf | small)
        self.infs += inf.sum(axis=0)
        self.zeros += small.sum(axis=0)
        if not mid.any():
            return
        cols = np.broadcast_to(np.arange(self.columns), v.shape)[mid]
        k = self._index(v[mid])
        self._cover(int(k.min()), int(k.max()))
        low = k < self.k0  # folded below the floor by _cover
        if low.any():
            np.add.at(self.zeros, cols[low], 1)
            k, cols = k[~low], cols[~low]
        width = self.counts.shape[1]
        flat = cols * width + (k - self.k0)
        self.counts += np.bincount(flat, minlength=self.columns * width).reshape(self.columns, width)

    def _cover(self, kmin: int, kmax: int) -> None:
        """Grow the store to bins [kmin, kmax]; keep the highest ``max_bins`` bins, folding the rest
        into the zero count (the floor rises to the lower edge of the lowest bin kept)."""
        width = self.counts.shape[1]
        if width:
            kmin, kmax = min(kmin, self.k0), max(kmax, self.k0 + width - 1)
        lo = max(kmin, kmax - self.max_bins + 1)
        if width and lo == self.k0 and kmax == self.k0 + width - 1:
            return
        if lo > kmin:
            self.floor = max(self.floor, float(np.exp((lo - 1) * self._log_gamma)))
        new = np.zeros((self.columns, kmax - lo + 1), dtype=np.int64)
        if width:
            old_lo, old_hi = self.k0, self.k0 + width - 1
            cut = max(old_lo, lo)  # the first old bin kept
            if cut > old_lo:
                self.zeros += self.counts[:, : min(cut, old_hi + 1) - old_lo].sum(axis=1)
            if cut <= old_hi:
                new[:, cut - lo : old_hi - lo + 1] = self.counts[:, cut - old_lo :]
        self.counts, self.k0 = new, lo

    def _order_statistic(self, c: int, j: np.ndarray) -> np.ndarray:
        """Representatives of the order statistics j (0-based) of column c."""
        j = np.asarray(j, dtype=np.int64)
        z, bins = self.zeros[c], self.counts[c]
        nb = int(bins.sum())
        out = np.full(j.shape, np.inf)
        out[j < z] = 0.0
        mid = (j >= z) & (j < z + nb)
        if mid.any():
            cum = np.cumsum(bins)
            b = np.searchsorted(cum, j[mid] - z, side="right")
            out[mid] = self.representative(self.k0 + b)
        return out

    def quantile(self, qs, method: str = "linear") -> np.ndarray:
        """(len(qs), columns) estimated quantiles (NaN for an empty column); ``method`` is numpy's
        ``"linear"`` or ``"lower"``."""
        qs = np.atleast_1d(np.asarray(qs, dtype=np.float64))
        out = np.full((qs.size, self.columns), np.nan)
        n = self.count
        for c in range(self.columns):
            if n[c] == 0:
                continue
            h = qs * (n[c] - 1)
            j = np.floor(h).astype(np.int64)
            lo = self._order_statistic(c, j)
            if method == "lower":
                out[:, c] = lo
                continue
            if method != "linear":
                raise ValueError(f"method must be 'linear' or 'lower', got {method!r}.")
            f = h - j
            hi = self._order_statistic(c, np.minimum(j + 1, n[c] - 1))
            with np.errstate(invalid="ignore"):
                out[:, c] = np.where(f > 0, (1 - f) * lo + f * hi, lo)
        return out

    def top_mean(self, k: int, column: int = 0) -> float:
        """The mean of the representatives of the k largest values of a column."""
        n = int(self.count[column])
        if k < 1 or n == 0:
            return float("nan")
        k = min(int(k), n)
        total, left = 0.0, k
        if self.infs[column]:
            return float("inf")
        bins = self.counts[column]
        for b in np.flatnonzero(bins)[::-1]:
            take = min(left, int(bins[b]))
            total += take * float(self.representative(self.k0 + b))
            left -= take
            if left == 0:
                break
        return total / k  # any remainder is zeros, represented by 0

    def histogram(self, column: int = 0):
        """(representatives, counts) of the nonzero bins of a column (zeros and +∞ left out)."""
        bins = self.counts[column]
        nz = np.flatnonzero(bins)
        return self.representative(self.k0 + nz), bins[nz]

    @property
    def nbytes(self) -> int:
        return int(self.counts.nbytes + self.zeros.nbytes + self.infs.nbytes)
