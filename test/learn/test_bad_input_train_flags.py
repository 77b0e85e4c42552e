"""Bad-input matrix, issue 24's training inputs: --conditions, --twin-share, --eval-every and the
--heldout place set. Each is a clear error before any training place is read or step taken."""

from __future__ import annotations

from pathlib import Path

import pytest
from synthetic_data import place_image, write_rgb

from pair_vpr_ros.learn.train import stage2

CASES = {
    "conditions negative": (["--conditions=-1"], "conditions=-1: must be >= 0 (0 = unknown)"),
    "twin-share above 1": (["--twin-share", "1.5"], "twin_share=1.5: a share of the batch"),
    "twin-share nan": (["--twin-share", "nan"], "twin_share=nan: a share of the batch"),
    "eval-every negative": (["--eval-every=-5"], "eval_every=-5: must be >= 0 (0 = never)"),
    "pair-negatives unknown": (["--pair-negatives", "easy"], "invalid choice: 'easy'"),
    "conditions text": (["--conditions", "three"], "argument --conditions: invalid int value"),
    "heldout missing": (["--heldout", "{tmp}/nowhere", "--eval-every", "5"], "nowhere"),
    "heldout one place": (["--heldout", "{tmp}/one", "--eval-every", "5"], "needs >= 2 places"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_train_flag(tmp_path: Path, capsys: pytest.CaptureFixture, case: str) -> None:
    for k in range(2):
        write_rgb(tmp_path / "one" / "place_00" / f"{k}.png", place_image(0, k, 32))
    args, message = CASES[case]
    argv = ["--data", str(tmp_path / "no-data"), "--out", str(tmp_path / "out"), "--arch", "tiny"]
    argv += [a.replace("{tmp}", str(tmp_path)) for a in args]
    try:
        code = stage2.main(argv)
    except SystemExit as exc:  # argparse's own exit
        code = exc.code
    assert code != 0
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # nothing trained, nothing written
