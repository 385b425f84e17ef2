"""The figures that RESULTS.md, README.md and the results READMEs quote in their prose, against
the committed data they come from (experiments/quoted.py)."""

import os
import sys
from pathlib import Path

import pytest

EXP = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXP))

import quoted  # noqa: E402


def test_quoted_figures_match_the_committed_data():
    if not (EXP / "results" / "benchmark").is_dir():
        pytest.skip("no committed experiment results")
    n, bad = quoted.check()
    assert n > 0, "no checked figures found: is the q: link convention still in use?"
    assert not bad, (f"{len(bad)} of {n} quoted figures differ from the committed data "
                     "(fix the text, or run python experiments/quoted.py --write):\n"
                     + "\n".join(bad))


def test_the_check_names_file_line_figure_text_and_value(tmp_path):
    if not (EXP / "results" / "benchmark").is_dir():
        pytest.skip("no committed experiment results")
    md = tmp_path / "README.md"
    her = os.path.relpath(EXP / "results" / "benchmark" / "cpu" / "FetchPush" / "her", tmp_path)
    md.write_text(f"HER ends at\n[91.6]({her} \"q:bc/push/her:final\") and "
                  f"[92]({her}/ \"q:bc/push/her:final\"),\n"
                  f"[+1.0]({her} \"q:no/such:figure\"), [91.7](. \"q:bc/push/her:final\").\n",
                  encoding="utf-8")
    n, bad = quoted.check([md], root=tmp_path)
    assert n == 4
    assert bad[0] == ("README.md:2: bc/push/her:final: the text says '91.6', the committed data "
                      f"give '91.7' ({quoted.value('bc/push/her:final')!r})")
    assert bad[1].startswith("README.md:3: no/such:figure: ")
    assert bad[2] == ("README.md:3: bc/push/her:final: the link goes to ., not to the data the "
                      "figure comes from (experiments/results/benchmark/cpu/FetchPush/her)")
    assert len(bad) == 3


@pytest.mark.parametrize(("val", "like", "out"), [
    (-17.33, "−17.3", "−17.3"), (-17.33, "-17", "-17"), (3.33, "+0.0", "+3.3"),
    (-0.04, "+1.1", "+0.0"), (0.03215, "0.03", "0.03"), (0.000123, "0.0001", "0.0001"),
    (1.53e-7, "1.5e-07", "1.5e-07"), (490000.0, "495,000", "490,000"), (91.67, "92", "92"),
    ("33 min 16 s", "anything", "33 min 16 s")])
def test_render_writes_a_figure_in_the_style_of_its_text(val, like, out):
    assert quoted.render(val, like) == out


def test_the_write_command_mends_a_figure(tmp_path):
    if not (EXP / "results" / "benchmark").is_dir():
        pytest.skip("no committed experiment results")
    md = tmp_path / "x.md"
    rd = os.path.relpath(EXP / "results" / "benchmark" / "paper" / "FetchSlide" / "rdher",
                         tmp_path)
    md.write_text(f"final [−1.0]({rd} \"q:bp/slide/rdher-her:final\") (p [0.50]({rd} "
                  "\"q:bp/slide/rdher-her:final:p\"))\n", encoding="utf-8")
    assert quoted.write([md]) == 2
    assert md.read_text(encoding="utf-8") == (
        f"final [−17.3]({rd} \"q:bp/slide/rdher-her:final\") "
        f"(p [0.03]({rd} \"q:bp/slide/rdher-her:final:p\"))\n")
    assert quoted.check([md], root=tmp_path)[1] == []
