"""The reproduction report's one-screen summary and what it says about its data (the
report review): each headline's paper column is the paper's figure, its best-peer column
a peer tool's number, simulation rows say so, excerpt rows say so, and ``--help`` says
where the default data comes from."""

from __future__ import annotations

from robustloc.cli import main
from robustloc.paths import default_data_candidates


def test_help_says_what_the_default_data_folder_is(capsys):
    assert main(["reproduce", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    cwd, checkout = default_data_candidates()
    # both places default_data_dir looks, in its order, and the fallback
    assert "../shared/data from the working folder" in out
    assert str(checkout.resolve()) in out
    assert out.index("../shared/data from the working folder") < out.index(
        str(checkout.resolve()))
    assert "excerpts shipped in the package" in out

