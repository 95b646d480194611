"""The `obsjax` command: --version, the benchmark help, and reproduce's progress and paper-vs-obsjax
tables (obsjax/_reproduce/_report.py)."""

import importlib.util
import math
import os
import sys
import types

import pytest

import obsjax
from obsjax import cli
from obsjax._reproduce._report import Row, announce_figures, format_table, summary_line

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"obsjax {obsjax.__version__}"


def _run_all():
    spec = importlib.util.spec_from_file_location(
        "run_all", os.path.join(ROOT, "benchmarks", "run_all.py")
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bench_help_names_and_describes_every_benchmark(capsys):
    assert set(cli.BENCHMARKS) == set(_run_all().BENCHMARKS)
    with pytest.raises(SystemExit):
        cli.main(["bench", "--help"])
    lines = capsys.readouterr().out.splitlines()
    for name, what in cli.BENCHMARKS.items():
        start = f"  {name}  {' '.join(what.split()[:3])}"
        assert any(line.startswith(start) for line in lines), start


def test_bench_refuses_unknown_names(capsys):
    assert cli.bench(["z"], bench_dir=os.path.join(ROOT, "benchmarks")) == 2
    assert "unknown benchmark" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, match",
    [
        (["demo", "--batch", "0"], "argument --batch: expected a positive integer, got 0"),
        (["demo", "-n", "0"], "argument -n: expected a positive integer, got 0"),
        (["demo", "--steps", "-1"], "argument --steps: expected a positive integer, got -1"),
        (["demo", "-n", "ten"], "argument -n: expected a positive integer, got 'ten'"),
    ],
)
def test_demo_refuses_bad_arguments_before_running(argv, match, capsys):
    """`--batch 0` ended in a TypeError traceback from tree_map, `-n 0` in one from monte_carlo after
    the whole tuning had run: now argparse refuses them up front (exit status 2)."""
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    assert match in capsys.readouterr().err


def test_demo_refuses_an_output_path_that_is_a_file(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("")
    with pytest.raises(SystemExit) as e:
        cli.main(["demo", "--out", str(f)])
    assert e.value.code == 2 and "is a file, not a directory" in capsys.readouterr().err
    with pytest.raises(ValueError, match="`batch` must be a positive integer, got 0"):
        cli.demo(str(tmp_path / "out"), batch=0)


def test_noisy_batch_refuses_a_bad_batch():
    import jax.random as jr

    from obsjax.montecarlo import noisy_batch

    plant = obsjax.chen_yen_example()
    noise = obsjax.noise.BandLimitedNoise(0.1, dt=0.01)
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="`batch` .* must be a positive integer"):
            noisy_batch(plant, noise, jr.PRNGKey(0), bad, 0.0, 1.0)
    with pytest.raises(ValueError, match="`t0`, `t1` must be finite with t0 < t1"):
        noisy_batch(plant, noise, jr.PRNGKey(0), 2, 1.0, 1.0)
    assert noisy_batch(plant, noise, jr.PRNGKey(0), 2, 0.0, 1.0) is not None


def test_row_relations_and_tolerances():
    assert Row("q", 2.0, 2.0 + 1e-7, rtol=1e-6).within
    assert not Row("q", 2.0, 2.0 + 1e-5, rtol=1e-6).within
    assert math.isclose(Row("q", 2.0, 2.5).difference, 0.25)
    assert Row("q", 0.0, 3e-9, rtol=0.0, atol=1e-8).within  # absolute tolerance for a zero value
    assert Row("q", 0.0, 3e-9, rtol=0.0, atol=1e-8).difference == 3e-9
    assert Row("bound", 1.0, 0.5, relation="<=").within
    assert not Row("bound", 1.0, 1.5, relation="<=").within
    assert Row("bound", 0.0, -1e-9, rtol=0.0, atol=1e-8, relation=">=").within
    assert not Row("bound", 0.0, -1e-7, rtol=0.0, atol=1e-8, relation=">=").within
    assert not Row("q", 1.0, float("nan")).within
    assert Row("eig", -1 + 1j, -1 + 1j + 1e-9).within
    with pytest.raises(ValueError, match="relation"):
        Row("q", 1.0, 1.0, relation="<")


def test_table_and_summary():
    rows = [Row("a value", 3.0, 3.0), Row("a bound", 2.5, 3.0, relation="<=", source="text: ≤ 2.5")]
    table = format_table(rows).splitlines()
    assert table[0].split() == [
        "quantity",
        "source",
        "paper",
        "obsjax",
        "rel.",
        "diff.",
        "tolerance",
        "within",
    ]
    assert "yes" in table[2] and "NO" in table[3] and "≤ 2.5" in table[3]
    assert summary_line(rows) == "1 of 2 values within tolerance (not: a bound)"


def test_announce_figures_reports_each_saved_figure(tmp_path, capsys):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.figure
    import matplotlib.pyplot as plt

    original = matplotlib.figure.Figure.savefig
    with announce_figures() as count:
        fig, _ = plt.subplots()
        fig.savefig(tmp_path / "a.png")
        plt.savefig(tmp_path / "b.png")
        plt.close(fig)
    assert count[0] == 2 and matplotlib.figure.Figure.savefig is original
    out = capsys.readouterr().out
    assert "figure 1:" in out and "a.png" in out and "figure 2:" in out and "b.png" in out


def _fake_document(values):
    mod = types.ModuleType("obsjax._reproduce.fake_doc")
    mod.__doc__ = "A fake document: one figure and two values."

    def reproduce(outdir):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        os.makedirs(outdir, exist_ok=True)
        fig, _ = plt.subplots()
        path = os.path.join(outdir, "fake.png")
        fig.savefig(path)
        plt.close(fig)
        return [path]

    mod.reproduce = reproduce
    mod.paper_values = lambda: values
    return mod


@pytest.mark.parametrize("ok", [True, False])
def test_reproduce_prints_progress_table_and_summary(ok, monkeypatch, tmp_path, capsys):
    rows = [Row("G1 of (2.8)", 3.0, 3.0), Row("G2 of (2.8)", 4.0, 4.0 if ok else 4.5)]
    monkeypatch.setitem(sys.modules, "obsjax._reproduce.fake_doc", _fake_document(rows))
    monkeypatch.setattr(cli, "available_reproductions", lambda: ["fake_doc"])
    rc = cli.run_reproductions(["fake_doc"], str(tmp_path))
    out = capsys.readouterr().out
    assert "[1/1] fake_doc: A fake document: one figure and two values" in out
    assert "figure 1:" in out and os.path.isfile(tmp_path / "fake_doc" / "fake.png")
    assert "quantity" in out and "G2 of (2.8)" in out
    if ok:
        assert rc == 0 and "2 of 2 values within tolerance" in out
    else:
        assert rc == 1 and "1 of 2 values within tolerance (not: G2 of (2.8))" in out
    assert "Summary: 1 of 1 document module(s) reproduced" in out


def test_reproduce_reports_a_module_without_reproduce(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "obsjax._reproduce.fake_doc", types.ModuleType("x"))
    monkeypatch.setattr(cli, "available_reproductions", lambda: ["fake_doc"])
    assert cli.run_reproductions(["fake_doc"], str(tmp_path)) == 1
    out, err = capsys.readouterr()
    assert "[fail] fake_doc" in out and "defines no `reproduce(outdir)`" in err


def test_document_modules_only():
    present = cli.available_reproductions()
    assert "references" not in present and set(cli.DOCUMENT_MODULES) <= set(present)


@pytest.mark.extended
def test_hassan_values_match_the_thesis():
    # The cheapest document module: its stated values (example (2.8), (2.13)-(2.16), (3.3), Theorem 4).
    from obsjax._reproduce import luenberger

    rows = luenberger.paper_values()
    assert len(rows) == 13 and all(r.within for r in rows), format_table(rows)
