"""The public API documents itself: `__all__`, module docstrings that `help()` shows, a docstring on every
public name, module examples that run, and a documentation site whose navigation covers every notebook
and benchmark table."""

import contextlib
import glob
import io
import os
import pydoc
import re
import types

import pytest

import obsjax
import obsjax.montecarlo
import obsjax.plotting

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODULES = [
    obsjax.losses,
    obsjax.noise,
    obsjax.signals,
    obsjax.plotting,
    obsjax.design,
    obsjax.analysis,
    obsjax.montecarlo,
]
IDS = [m.__name__ for m in MODULES]


def _public(mod):
    """Names a user reaches by ``mod.<name>``: not private, not a submodule, not a ``__future__`` flag."""
    return sorted(
        n
        for n, v in vars(mod).items()
        if not n.startswith("_")
        and not isinstance(v, types.ModuleType)
        and type(v).__name__ != "_Feature"
    )


def _own_doc(obj) -> str:
    doc = vars(obj).get("__doc__") if isinstance(obj, type) else getattr(obj, "__doc__", None)
    return (doc or "").strip()


@pytest.mark.parametrize("mod", MODULES, ids=IDS)
def test_all_lists_every_public_name(mod):
    # an export line added below the `__all__` line of a module would be missing here
    assert sorted(mod.__all__) == _public(mod)
    assert all(hasattr(mod, n) for n in mod.__all__)


@pytest.mark.parametrize("mod", [obsjax, *MODULES], ids=["obsjax", *IDS])
def test_every_public_name_has_a_docstring(mod):
    missing = [n for n in _public(mod) if not _own_doc(getattr(mod, n))]
    assert not missing, f"{mod.__name__}: no docstring on {missing}"


@pytest.mark.parametrize("mod", MODULES, ids=IDS)
def test_help_shows_a_description_and_the_names(mod):
    text = pydoc.render_doc(mod, renderer=pydoc.plaintext)
    doc = (mod.__doc__ or "").strip()
    assert len(doc.splitlines()) >= 3, f"{mod.__name__}: a one-line module docstring"
    first = doc.splitlines()[0]
    assert first in text and "DESCRIPTION" in text
    for name in mod.__all__:  # pydoc lists re-exported names only through __all__
        assert re.search(rf"\b{name}\b", text.split("DESCRIPTION", 1)[1]), name


def _examples(mod):
    return re.findall(r"```python\n(.*?)```", mod.__doc__ or "", flags=re.DOTALL)


@pytest.mark.parametrize("mod", MODULES, ids=IDS)
@pytest.mark.extended
def test_module_docstring_examples_run(mod, tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    blocks = _examples(mod)
    assert blocks, f"{mod.__name__}: no example in the module docstring"
    monkeypatch.chdir(tmp_path)  # plotting's example writes a PNG
    for code in blocks:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            exec(compile(code, f"<{mod.__name__} docstring>", "exec"), {})  # noqa: S102
        if "print(" in code:
            assert out.getvalue().strip(), f"{mod.__name__}: the example prints nothing"


def test_design_example_prints_the_thesis_gain(capsys):
    exec(_examples(obsjax.design)[0], {})  # noqa: S102
    assert re.search(r"\[\[3\.\]\s*\[4\.\]\]", capsys.readouterr().out)


def test_site_navigation_covers_notebooks_and_benchmark_tables():
    with open(os.path.join(ROOT, "mkdocs.yml"), encoding="utf-8") as f:
        nav = f.read().split("\nnav:", 1)[1]
    wanted = sorted(glob.glob(os.path.join(ROOT, "notebooks", "*.ipynb"))) + sorted(
        glob.glob(os.path.join(ROOT, "benchmarks", "results", "*.md"))
    )
    assert wanted
    for path in wanted:
        rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
        assert rel in nav, f"{rel} is not in the navigation of mkdocs.yml"
    for page in re.findall(r":\s*([\w/.-]+\.md)\s*$", nav, flags=re.MULTILINE):
        if not page.startswith("benchmarks/"):
            assert os.path.isfile(os.path.join(ROOT, "docs", page)), page


def _readme_snippets():
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        blocks = re.findall(r"```python\n(.*?)```", f.read(), flags=re.DOTALL)
    return [b for b in blocks if "jax.distributed" not in b]  # the multi-host recipe needs hosts


def _run_script(code, tmp_path):
    import subprocess
    import sys

    path = tmp_path / "snippet.py"
    path.write_text(code, encoding="utf-8")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env["MPLBACKEND"] = "Agg"
    out = subprocess.run(
        [sys.executable, str(path)], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


@pytest.mark.extended
def test_readme_first_snippet_prints_what_it_promises(tmp_path):
    first = _readme_snippets()[0]
    assert "Luenberger.from_poles" in first
    lines = _run_script(first, tmp_path).splitlines()
    assert lines[0] == "[3. 4.]"  # the thesis's G = [3, 4]ᵀ
    norms = [float(v) for v in " ".join(lines[1:]).strip("[] ").split()]
    assert len(norms) == 6 and norms[0] > norms[1] > norms[-1] > 0 and norms[-1] < 1e-4


@pytest.mark.slow
def test_readme_tour_snippet_prints_what_it_promises(tmp_path):
    tour = _readme_snippets()[1]
    assert "obsjax.tune" in tour and "obsjax.monte_carlo" in tour
    out = _run_script(tour, tmp_path)
    assert "‖x̃(10)‖ = 0.03347" in out  # Chen & Yen's Fig. 1 (SciPy reference 3.347e-2)
    assert re.search(r"γ·p0 = [\d.]+, T = [\d.]+: mean ISE [\d.]+ -> [\d.]+", out)
    assert "MonteCarloResult(n=2000" in out and "failed=0" in out
    assert (tmp_path / "monte_carlo.png").stat().st_size > 10_000


def test_api_reference_documents_every_public_name():
    pages = "".join(
        open(p, encoding="utf-8").read() for p in glob.glob(os.path.join(ROOT, "docs", "api", "*.md"))
    )
    documented = set(re.findall(r"^::: ([\w.]+)", pages, flags=re.MULTILINE))
    short = {d.rsplit(".", 1)[-1] for d in documented}
    missing = [
        f"{mod.__name__}.{n}"
        for mod in [obsjax, *MODULES]
        for n in _public(mod)
        if f"{mod.__name__}.{n}" not in documented and n not in short
    ]
    assert not missing, f"add a `::: <name>` line to a page of docs/api/ for {missing}"
