"""Bad-input matrix, `pairvpr-eval` numeric flags: each bad value is a usage error (exit 2)
naming the flag, before any dataset or model is read (issue 13 #8)."""

from __future__ import annotations

import pytest

from pair_vpr_ros.learn.evaluate import main

CASES = {
    "radius negative": (["--radius=-5"], "argument --radius: must be a finite number > 0"),
    "radius nan": (["--radius", "nan"], "argument --radius: must be a finite number > 0"),
    "radius zero": (["--radius", "0"], "got '0'"),
    "rerank-k negative": (["--rerank-k=-1"], "argument --rerank-k: must be an integer >= 0"),
    "global-weight negative": (
        ["--global-weight=-2"],
        "argument --global-weight: must be a finite number >= 0, got '-2'",
    ),
    "global-weight inf": (["--global-weight", "inf"], "must be a finite number >= 0, got 'inf'"),
    "recall zero": (["--recall", "1", "0"], "argument --recall: must be an integer >= 1, got 0"),
    "batch-size zero": (["--batch-size", "0"], "argument --batch-size: must be an integer >= 1"),
    "workers negative": (["--workers=-2"], "argument --workers: must be an integer >= 0"),
    "image-size text": (["--image-size", "big"], "argument --image-size: must be an integer"),
}


def _exit_code(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # argparse's own exit, where main does not catch it
        return exc.code


@pytest.mark.parametrize("case", list(CASES))
def test_bad_eval_flag(tmp_path, capsys, case) -> None:
    args, message = CASES[case]
    assert _exit_code([str(tmp_path / "set"), "--random-init", "tiny", *args]) == 2
    assert message in capsys.readouterr().err
