"""MkDocs hooks of the obsjax documentation.

- Pages from outside ``docs/``: the notebooks (``notebooks/*.ipynb``, rendered with their stored outputs by
  mkdocs-jupyter, never executed at build time) and the benchmark tables (``benchmarks/README.md``,
  ``benchmarks/results/*.md``) are added to the site under the same paths.
- Every notebook must be stored executed, without error outputs: the build fails otherwise (the test
  suite re-executes them with nbmake; refresh the stored outputs with the command in the message).
- Docstrings use Sphinx-style roles (``:func:`obsjax.tune```); in the rendered API they become links to
  the documented object (or plain code when the object has no page).
"""

from __future__ import annotations

import glob
import json
import os
import re

from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXTERNAL = ("notebooks/*.ipynb", "benchmarks/README.md", "benchmarks/results/*.md")
REFRESH = "jupyter nbconvert --to notebook --execute --inplace notebooks/*.ipynb"
ROLE = re.compile(r":(?:func|class|meth|attr|mod|data|obj):<code>~?([A-Za-z_][\w.]*)(\(\))?</code>")


def _check_notebook(path: str) -> None:
    with open(path, encoding="utf-8") as f:
        nb = json.load(f)
    rel = os.path.relpath(path, ROOT)
    for i, cell in enumerate(nb.get("cells", [])):
        if cell.get("cell_type") != "code" or not "".join(cell.get("source", [])).strip():
            continue
        if cell.get("execution_count") is None:
            raise PluginError(
                f"{rel}: code cell {i} is stored without outputs; the documentation renders the stored "
                f"outputs. Execute the notebooks once and store them: {REFRESH}"
            )
        for out in cell.get("outputs", []):
            if out.get("output_type") == "error":
                raise PluginError(
                    f"{rel}: code cell {i} stored an error ({out.get('ename')}: {out.get('evalue')}); "
                    f"fix it and store the outputs again: {REFRESH}"
                )


@event_priority(100)  # before mkdocs-jupyter, so that it sees the notebooks
def on_files(files, config):
    for pattern in EXTERNAL:
        for path in sorted(glob.glob(os.path.join(ROOT, pattern))):
            rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
            if rel.endswith(".ipynb"):
                _check_notebook(path)
            files.append(File(rel, ROOT, config["site_dir"], config["use_directory_urls"]))
    return files


_NAMES: dict[str, str] = {}


def _public_names() -> dict[str, str]:
    """Short name -> documented path (``MonteCarloResult`` -> ``obsjax.MonteCarloResult``)."""
    if _NAMES:
        return _NAMES
    try:
        import obsjax
        import obsjax.montecarlo
        import obsjax.plotting
    except ImportError:  # obsjax not importable: roles still lose their prefix, without links
        return _NAMES
    for mod in (
        obsjax.plotting,
        obsjax.losses,
        obsjax.noise,
        obsjax.signals,
        obsjax.analysis,
        obsjax.design,
        obsjax.montecarlo,
        obsjax,
    ):
        for name in getattr(mod, "__all__", None) or dir(mod):
            if not name.startswith("_"):
                _NAMES[name] = f"{mod.__name__}.{name}"
    return _NAMES


def _role(match: re.Match) -> str:
    name, call = match.group(1), match.group(2) or ""
    names = _public_names()
    head, _, rest = name.partition(".")
    if name.startswith("obsjax."):
        target = name
    elif head in names:
        target = names[head] + (f".{rest}" if rest else "")
    else:
        return f"<code>{name}{call}</code>"
    return f'<autoref identifier="{target}" optional><code>{name}{call}</code></autoref>'


def on_page_content(html, page, config, files):
    return ROLE.sub(_role, html)
