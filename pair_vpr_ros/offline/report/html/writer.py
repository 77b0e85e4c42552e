"""`ReportWriter`: the report folder, written while the replay runs, so that nothing grows with
the bag in memory but a row number per keyframe id.

Layout of ``OUT/report/``::

    index.html            the page (summary, settings, plots, the table's script and style inline)
    index.js              written last: every row's flags and ground-truth labels (filters)
    rows/rows-0003.js     250 rows a file: ``PAIRVPR.rows(3, [...])``, loaded by the page as
                          ``<script>`` elements (a browser refuses fetch() of file:// URLs)
    img/0012/12345.jpg    the keyframe of row 12345, longer side 256 px (also every candidate's)
    loops/0012/12345-0.jpg  each accepted loop: query | match, inlier matches, pose
    pr_curve.png, trajectory.png

Per keyframe about 8 KB of JPEG and 0.5 KB of row text (K = 5), plus ~25 KB per accepted loop.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pair_vpr_ros.errors import OutputError
from pair_vpr_ros.images.thumbnails import FolderThumbnails, Thumbnail
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.records import Candidate
from pair_vpr_ros.messages.loop_image import LoopPictures
from pair_vpr_ros.offline.report.html.rows import row_data, row_flags

CHUNK = 250  # rows a rows-NNNN.js file
THUMB_SIDE, THUMB_QUALITY = 256, 72
LOOP_HEIGHT, LOOP_QUALITY = 192, 75


class ReportWriter:
    """Rows, keyframe images and loop images into `folder` as the replay decides.

    `identity`: (robot, session) of the replay: only its own keyframes have images here.
    `pose_on`: relative poses are computed (an accepted loop without one is "pose refused").
    """

    def __init__(self, folder: str | Path, config: DetectorConfig, identity: tuple[str, str],
                 pose_on: bool = True) -> None:  # fmt: skip
        self.folder = Path(folder)
        self.config, self.identity, self.pose_on = config, identity, pose_on
        try:
            _clear(self.folder)
            (self.folder / "rows").mkdir(parents=True)
        except OSError as err:
            raise OutputError(f"cannot create the report folder {self.folder}: {err}") from err
        self.images = FolderThumbnails(self.folder / "img", THUMB_SIDE, THUMB_QUALITY)
        self.pictures = LoopPictures(identity, images=self.match_image, height=LOOP_HEIGHT)
        self._row_of: dict[int, int] = {}  # live keyframe id -> its row (its image)
        self._rows: list[dict] = []  # the chunk being filled
        self.rows = 0
        self.flags = bytearray()  # per row: rows.ACCEPTED | VERIFY_REJECTED | POSE_REFUSED
        self.loop_bytes = 0
        self.seconds = 0.0  # time spent writing, for the summary

    def image_row(self, cand: Candidate) -> int:
        """The row whose image shows `cand`; -1 for a keyframe this replay did not see."""
        if cand.prior >= 0 or (cand.robot, cand.session) != self.identity:
            return -1
        return self._row_of.get(cand.id, -1)

    def add(self, row: int, outcome: FrameOutcome, rgb: np.ndarray | None) -> None:
        """Keyframe `row` (the `DecisionLog` row of `outcome`), its image `rgb` [H, W, 3]
        (None: none, e.g. a keyframe that came without one)."""
        start = time.perf_counter()
        assert row == self.rows, "rows come in order"
        try:
            if rgb is not None:
                self.images.put(row, rgb)
            if outcome.keyframe_id is not None:
                self._row_of[outcome.keyframe_id] = row
            loops = self._loop_images(row, outcome, rgb)
            data = row_data(row, outcome, self.config, self.image_row, loops)
            if rgb is None:
                data["i"] = False  # no image of this keyframe
            self._rows.append(data)
            self.flags.append(row_flags(outcome.decisions(), self.pose_on))
            self.rows += 1
            if len(self._rows) == CHUNK:
                self._flush()
        except OSError as err:
            raise OutputError(f"cannot write the report into {self.folder}: {err}") from err
        finally:
            self.seconds += time.perf_counter() - start

    def _loop_images(self, row: int, outcome: FrameOutcome, rgb) -> dict[int, str]:
        """Draw each accepted loop of `outcome`; -> {rank_before: file}."""
        out = {}
        for n, record in enumerate(r for r in outcome.decisions() if r.accepted):
            drawn = self.pictures.draw(outcome, record, rgb)
            ok, data = cv2.imencode(".jpg", drawn, [cv2.IMWRITE_JPEG_QUALITY, LOOP_QUALITY])
            name = f"loops/{row // 1000:04d}/{row}-{n}.jpg"
            path = self.folder / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data.tobytes())
            self.loop_bytes += len(data)
            out[record.rank_before] = name
        return out

    def match_image(self, cand: Candidate) -> Thumbnail | None:
        """The image of a keyframe this replay saw (`LoopPictures`' source)."""
        row = self.image_row(cand)
        return self.images.get(row) if row >= 0 else None

    def _flush(self) -> None:
        """Write the chunk being filled (rows/rows-NNNN.js)."""
        if not self._rows:
            return
        number = self._rows[0]["n"] // CHUNK
        text = json.dumps(self._rows, separators=(",", ":"), allow_nan=False)
        (self.folder / "rows" / f"rows-{number:04d}.js").write_text(
            f"PAIRVPR.rows({number},{text});\n", encoding="utf-8"
        )
        self._rows = []

    def close_rows(self) -> None:
        """Write the last chunk (the page and the labels come after: `page.write_page`)."""
        start = time.perf_counter()
        try:
            self._flush()
        except OSError as err:
            raise OutputError(f"cannot write the report into {self.folder}: {err}") from err
        finally:
            self.seconds += time.perf_counter() - start

    def sizes(self) -> dict[str, Any]:
        return {"rows": self.rows, "image_bytes": self.images.nbytes,
                "loop_image_bytes": self.loop_bytes}  # fmt: skip


def check_report_folder(folder: Path) -> None:
    """OutputError unless `folder` is missing, empty or an earlier run's report (which the
    writer replaces): checked before the bag is read."""
    if not folder.exists():
        return
    if not folder.is_dir():
        raise OutputError(f"the report folder {folder} is a file: move it, or pass --no-report")
    ours = (folder / "rows").is_dir() or (folder / "index.html").is_file()
    if not ours and any(folder.iterdir()):
        raise OutputError(f"the report folder {folder} holds other files: move them, or pass "
                          "--no-report")  # fmt: skip


def _clear(folder: Path) -> None:
    """Remove an earlier run's report at `folder` (its pages would mislead)."""
    check_report_folder(folder)
    if folder.exists():
        shutil.rmtree(folder)
