"""The project is self-contained: no file names a path outside the repository, and every reference value
the tests use lives in it with its provenance."""

import pathlib
import re
import subprocess

import pytest

from obsjax._reproduce import references

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Paths of working material outside the repository, which a user does not have (written in pieces so that
# this file does not match itself).
_SH, _SE, _RE = "shared" + "/", "seeds" + "/", "REFERENCE" + r"\.md"
OUTSIDE = re.compile(rf"\b{_SH}|{_SE}0\d\d|\b{_RE}\b|\b00[0-4]_[0-9a-f]{{16}}\.txt\b")
TEXT = {".py", ".md", ".ipynb", ".toml", ".yml", ".yaml", ".txt", ".cfg", ".ini", ".json", ""}


def _tracked_files():
    try:
        out = subprocess.run(
            ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the tracked files cannot be listed")
    return [ROOT / f for f in out if (ROOT / f).suffix in TEXT and (ROOT / f).is_file()]


def test_no_file_names_a_path_outside_the_repository():
    offenders = []
    for path in _tracked_files():
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if OUTSIDE.search(line):
                offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not offenders, "files name paths outside the repository:\n" + "\n".join(offenders)


def test_the_pattern_catches_what_it_should():
    ref = "REFERENCE" + ".md"
    for bad in (f"see {_SH}{ref}", f"../{_SH}{_SE}x", f"{_SE}000_feec7a3e030c3a73" + ".txt", f"{ref} lists",
                "001_48f9b38d098610c1" + ".txt"):
        assert OUTSIDE.search(bad), bad
    for good in ("the SciPy reference values", "a shared mesh", "np.random.seed(0)"):
        assert not OUTSIDE.search(good), good


def test_sources_are_cited_bibliographically():
    assert set(references.SOURCES) == {"chen-yen", "hassan", "lovass-nagy", "huang-zhu", "byrski-fuksa"}
    for key, cite in references.SOURCES.items():
        assert re.search(r'^[A-Z][^"]+ "[^"]{20,}"', cite), cite  # authors, then the title in quotes
        if key != "lovass-nagy":  # the slides carry no date
            assert re.search(r"\b(19|20)\d\d\b", cite), cite
