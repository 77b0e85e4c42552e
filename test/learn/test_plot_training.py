"""scripts/plot_training.py: the training-curve picture of the demo recipe, and its bad inputs."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "plot_training.py"


def _main():  # noqa: ANN202
    spec = importlib.util.spec_from_file_location("plot_training", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


def test_plot_writes_one_panel_per_log(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    log = tmp_path / "train_log.jsonl"
    rows = [{"step": s, "loss": 1.0 / s, "pair": 0.69} for s in (1, 10, 20)] + [{"val": {}}]
    log.write_text("".join(json.dumps(r) + "\n" for r in rows))
    dest = tmp_path / "out" / "curves.png"
    assert _main()([str(dest), f"stage two: A={log}", f"again={log}"]) == 0
    assert dest.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out == f"wrote {dest}\n"


@pytest.mark.parametrize(
    ("content", "arg", "code", "message"),
    [
        (None, "a={log}", 1, "error: [Errno 2] No such file or directory"),
        ("", "a={log}", 1, "holds no training steps"),
        ('{"val": {}}\n', "a={log}", 1, "holds no training steps"),
        ("{broken\n", "a={log}", 1, "error: Expecting property name"),
        ("", "{log}", 2, "give each log as TITLE=PATH"),
    ],
)
def test_plot_bad_inputs(
    tmp_path: Path,
    capsys: pytest.CaptureFixture,
    content: str | None,
    arg: str,
    code: int,
    message: str,
) -> None:
    log = tmp_path / "train_log.jsonl"
    if content is not None:
        log.write_text(content)
    argv = [str(tmp_path / "x.png"), arg.format(log=log)]
    if code == 2:
        with pytest.raises(SystemExit) as exit_info:
            _main()(argv)
        assert exit_info.value.code == 2
    else:
        assert _main()(argv) == code
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
