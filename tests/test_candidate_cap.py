"""`greybox compare` bounds its work: each candidate is a whole fit, so a folder with more
than `MAX_CANDIDATES` (32) is refused before anything is loaded or fitted (exit 2 at
experiment.toml's ``candidates``, nothing written); 32 pass the cap."""

import time

from greybox.cli import main
from greybox.io._experiment_set import MAX_CANDIDATES, candidate_nests


def _folder(tmp_path, n):
    exp = tmp_path / f"exp{n}"
    exp.mkdir()
    (exp / "experiment.toml").write_text(
        '[experiment]\ndevice = "chevron_laser"\n\n'
        + "".join(f'[[candidates]]\nname = "c{i}"\n\n' for i in range(n))
    )
    return exp


def test_more_candidates_than_the_cap_are_refused_before_the_work(tmp_path, capsys):
    assert MAX_CANDIDATES == 32
    assert len(candidate_nests(_folder(tmp_path, 32))) == 32
    out = tmp_path / "out"
    t0 = time.perf_counter()
    assert main(["compare", str(_folder(tmp_path, 33)), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "experiment.toml" in err and "candidates:" in err and "at most 32" in err, err
    assert time.perf_counter() - t0 < 5 and not out.exists()
