"""What ``obsjax reproduce`` prints: progress per document and per figure, and the paper-vs-obsjax table.

Each document module may define ``paper_values() -> list[Row]``: the values a document states in its text
(or, where it gives only a figure, an independent reference value with its provenance, see
``references.py``) beside the same quantity computed by obsjax.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time

#: relations a row can check: the document's value itself, or a bound the document claims
RELATIONS = ("=", "<=", ">=")


@dataclasses.dataclass(frozen=True)
class Row:
    """One compared value.

    - `quantity`: what is compared, with the document's equation / figure / example number.
    - `paper`: the document's value (a real or complex number), or the bound it claims.
    - `obsjax`: the same quantity computed by obsjax.
    - `source`: where `paper` comes from (e.g. ``"text"``, ``"closed form (31)"``, ``"SciPy reference"``).
    - `rtol`, `atol`: tolerance; for ``"="`` the row passes when |obsjax − paper| ≤ atol + rtol·|paper|.
    - `relation`: ``"="`` (a value), ``"<="`` or ``">="`` (obsjax must satisfy the document's bound, with
      the same tolerance as slack).
    """

    quantity: str
    paper: float | complex
    obsjax: float | complex
    source: str = "text"
    rtol: float = 1e-6
    atol: float = 0.0
    relation: str = "="

    def __post_init__(self):
        if self.relation not in RELATIONS:
            raise ValueError(f"`relation` must be one of {RELATIONS}, got {self.relation!r}.")

    @property
    def difference(self) -> float:
        """|obsjax − paper| / |paper| (the absolute difference when the paper's value is 0)."""
        d = abs(complex(self.obsjax) - complex(self.paper))
        p = abs(complex(self.paper))
        return d / p if p > 0 else d

    @property
    def within(self) -> bool:
        """Whether obsjax's value meets the paper's value (or bound) within the tolerance."""
        o, p = complex(self.obsjax), complex(self.paper)
        if not (math.isfinite(abs(o)) and math.isfinite(abs(p))):
            return False
        slack = self.atol + self.rtol * abs(p)
        if self.relation == "=":
            return abs(o - p) <= slack
        if self.relation == "<=":
            return o.real <= p.real + slack
        return o.real >= p.real - slack


def _number(v) -> str:
    v = complex(v)
    if v.imag == 0:
        return f"{v.real:.6g}"
    sign = "+" if v.imag >= 0 else "−"
    return f"{v.real:.6g} {sign} {abs(v.imag):.6g}j"


def format_table(rows) -> str:
    """A plain-text table: quantity | source | paper | obsjax | rel. diff. | tolerance | within."""
    head = ("quantity", "source", "paper", "obsjax", "rel. diff.", "tolerance", "within")
    body = []
    for r in rows:
        bound = {"=": "", "<=": "≤ ", ">=": "≥ "}[r.relation]
        paper = bound + _number(r.paper)
        tol = " + ".join(
            [f"rel {r.rtol:.0e}"] * (r.rtol > 0 or r.atol == 0)
            + [f"abs {r.atol:.0e}"] * (r.atol > 0)
        )
        diff = f"{r.difference:.2e}" if r.relation == "=" else "—"
        body.append(
            (r.quantity, r.source, paper, _number(r.obsjax), diff, tol, "yes" if r.within else "NO")
        )
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body)]
    fmt = lambda cells: "  ".join(str(c).ljust(w) for c, w in zip(cells, widths)).rstrip()
    lines = [fmt(head), fmt(["-" * w for w in widths])] + [fmt(b) for b in body]
    return "\n".join(lines)


def summary_line(rows) -> str:
    """``"k of n values within tolerance"`` (and which are not)."""
    bad = [r.quantity for r in rows if not r.within]
    line = f"{len(rows) - len(bad)} of {len(rows)} values within tolerance"
    return line + (f" (not: {'; '.join(bad)})" if bad else "")


@contextlib.contextmanager
def announce_figures(indent: str = "    "):
    """Print a line each time a matplotlib figure is saved inside the block (path and elapsed seconds).

    The document modules save their figures with ``Figure.savefig``; wrapping it here gives per-figure
    progress without the modules knowing about it.  The original method is restored on exit.
    """
    import matplotlib.figure

    original = matplotlib.figure.Figure.savefig
    t0 = time.perf_counter()
    count = [0]

    def savefig(self, fname, *args, **kwargs):
        out = original(self, fname, *args, **kwargs)
        count[0] += 1
        print(f"{indent}figure {count[0]}: {fname} ({time.perf_counter() - t0:.1f} s)", flush=True)
        return out

    matplotlib.figure.Figure.savefig = savefig
    try:
        yield count
    finally:
        matplotlib.figure.Figure.savefig = original
