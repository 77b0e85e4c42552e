"""What `vpr_node`'s map services do, ROS-free: save, load, clear, background build, autosave.

`MapControl` owns the live `LoopClosurePipeline` on one thread of its own, the map thread: the
pipeline is created there, and every frame and every map operation runs there in arrival order.
This is the node's whole concurrency design (stated in `pipeline.py`): the pipeline has no lock,
a save, load or clear falls between two frames, never inside one, and other threads (the
diagnostics timer) read `state`, a copy the map thread makes after each task. Operations return
`(success, message)` for a `std_srvs` response; errors are messages, never exceptions.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

from pair_vpr_ros.errors import ConfigError, MapError, PairVPRError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame, FrameOutcome, PipelineCounts
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.prior_maps import refuse_prior_target
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.model.threads import limit_this_thread
from pair_vpr_ros.offline.bags.sources import check_source
from pair_vpr_ros.offline.replay.build_map import BuildResult, build_map
from pair_vpr_ros.types import Pose

T = TypeVar("T")
Result = tuple[bool, str]
MAP_DIR_HINT = "ros2 param set /vpr_node map_dir /path/to/map"
SOURCE_HINT = "ros2 param set /vpr_node build_source /path/to/bag_or_image_folder"


def _map_dir(map_dir: str) -> Path:
    if not map_dir:
        raise ConfigError(f"map_dir is not set: {MAP_DIR_HINT}")
    return Path(map_dir).expanduser()


def check_map_target(map_dir: str) -> Path:
    """`map_dir` as a folder a map can be saved to (ConfigError: unset, a file, or under a
    folder that does not let us write)."""
    path = _map_dir(map_dir)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"map_dir {path} is a file, not a folder: {MAP_DIR_HINT}")
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(
            f"map_dir {path} cannot be written ({existing} is not a writable folder): "
            f"{MAP_DIR_HINT}"
        )
    return path


@dataclass
class BuildStatus:
    """The background build as `~/map_info` reports it. `state`: idle, building, done, failed
    or cancelled; `error` stays set from a failure until the next successful build."""

    state: str = "idle"
    source: str = ""
    map_dir: str = ""
    detail: str = ""  # the result line when done, the reason when failed
    error: str = ""
    progress: BuildResult | None = None  # the running build's counts (frames read so far)

    def to_dict(self) -> dict[str, object]:
        frames = self.progress.frames if self.progress is not None else 0
        keys = ("state", "source", "map_dir", "detail", "error")
        return {**{k: getattr(self, k) for k in keys}, "frames_read": frames}


@dataclass(frozen=True)
class LiveState:
    """The live pipeline as of the end of the map thread's last task."""

    keyframes: int = 0
    mode: str = ""
    counts: PipelineCounts = field(default_factory=PipelineCounts)
    bytes_per_keyframe: int = 0


class MapControl:
    """The live pipeline and the map operations of the node's services.

    `factory()` builds the pipeline (on the map thread). `context()` (e.g. autocast) is entered
    around every task on the map thread and around builds. `log(level, text)` reports what
    background builds do ("info" / "error").
    """

    def __init__(
        self,
        factory: Callable[[], LoopClosurePipeline],
        log: Callable[[str, str], None],
        context: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext,
    ) -> None:
        self.build = BuildStatus()
        self._log, self._context = log, context
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vpr_map")
        self._stop = threading.Event()
        self._build: threading.Thread | None = None
        self._saved: tuple[int, int] | None = None  # (map object id, keyframes) at last save
        self._live = LiveState()
        self.pipeline: LoopClosurePipeline = self.call(factory)
        self.call(self._note_state)

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """Queue `fn(*args)` for the map thread."""

        def task() -> T:
            with self._context():
                try:
                    return fn(*args)
                finally:
                    self._note_state()

        return self._thread.submit(task)

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run `fn(*args)` on the map thread and return its result (or raise its error)."""
        return self.submit(fn, *args).result()

    def _note_state(self) -> None:
        """Copy what other threads may read of the pipeline (on the map thread)."""
        pipeline = getattr(self, "pipeline", None)
        if pipeline is None:  # the factory's own task
            return
        with contextlib.suppress(MapError):  # a closed map (shutting down, mid-swap)
            self._live = LiveState(
                keyframes=len(pipeline.place_map),
                mode=pipeline.config.mode,
                counts=replace(pipeline.counts),
                bytes_per_keyframe=pipeline.place_map.bytes_per_keyframe,
            )

    # ---- live map ----------------------------------------------------------------------------
    def process(self, frame: Frame) -> tuple[FrameOutcome, list[tuple[LoopRecord, Pose | None]]]:
        """One frame through the pipeline -> (outcome, its records to publish, each with the
        pose of its match when accepted: `FrameOutcome.reported`, one per map at most)."""

        def run() -> tuple[FrameOutcome, list[tuple[LoopRecord, Pose | None]]]:
            outcome = self.pipeline.process(frame)
            pipe = self.pipeline
            return outcome, [
                (r, pipe.match_meta(outcome, r).pose if r.accepted else None)  # live or prior
                for r in outcome.reported()
            ]

        return self.call(run)

    def process_group(
        self, frames: list[Frame]
    ) -> list[tuple[FrameOutcome, list[tuple[LoopRecord, Pose | None]]]]:
        """One rig keyframe (one frame per camera) through the pipeline -> `process`'s result
        for each frame, in order."""

        def run() -> list[tuple[FrameOutcome, list[tuple[LoopRecord, Pose | None]]]]:
            pipe = self.pipeline
            outcomes = list(pipe.process_groups([frames], batch_size=len(frames)))
            return [(o, [(r, pipe.match_meta(o, r).pose if r.accepted else None)
                         for r in o.reported()]) for o in outcomes]  # fmt: skip

        return self.call(run)

    @property
    def state(self) -> LiveState:
        """The live pipeline after the last map-thread task (never waits)."""
        return self._live

    def size(self) -> int:
        """Keyframes in the live map after the last map-thread task (never waits)."""
        return self._live.keyframes

    def set_config(self, config: DetectorConfig) -> None:
        self.call(self.pipeline.set_config, config)

    def _save_mark(self) -> tuple[int, int]:
        return id(self.pipeline.place_map), len(self.pipeline.place_map)

    # ---- services ----------------------------------------------------------------------------
    def save(self, map_dir: str) -> Result:
        """Save with the slow I/O off the map thread (keyframes keep flowing): the dense tokens
        are fsynced here first, the map thread then fsyncs the few added since and commits the
        new rows, and the store's WAL is folded in here afterwards (place_map/persist.py)."""
        place_map = self.pipeline.place_map  # may be swapped meanwhile: flush is then a no-op

        def run() -> Result:
            path = self.pipeline.save_map(_map_dir(map_dir), checkpoint=False)
            self._saved = self._save_mark()
            return True, f"saved {self._saved[1]} keyframes to {path}"

        place_map.flush()
        result = self._result(run)
        self.pipeline.place_map.checkpoint()
        return result

    def load(self, map_dir: str) -> Result:
        def run() -> Result:
            n = self.pipeline.load_map(_map_dir(map_dir))
            self._saved = self._save_mark()
            note = self.pipeline.place_map.load_note
            return True, f"loaded {n} keyframes from {_map_dir(map_dir)}" + (
                f" ({note})" if note else ""
            )

        return self._result(run)

    def load_if_present(self, map_dir: str) -> Result:
        """Start-up load: a missing or empty folder is a fresh start, not an error."""
        try:
            path = _map_dir(map_dir)
        except ConfigError as err:
            return False, str(err)
        if not path.is_dir() or not any(path.iterdir()):
            return True, f"no map in {path} yet: starting with an empty map"
        return self.load(map_dir)

    def clear(self) -> Result:
        self.call(self.pipeline.clear_map)
        return True, "map cleared (the saved copy is unchanged)"

    def autosave(self, map_dir: str) -> Result | None:
        """Save when the map changed since the last save (None: nothing to do)."""
        if not map_dir or self.call(self._save_mark) == self._saved:
            return None
        return self.save(map_dir)

    def _result(self, run: Callable[[], Result]) -> Result:
        try:
            return self.call(run)
        except PairVPRError as err:
            return False, str(err)

    # ---- background build ---------------------------------------------------------------------
    def start_build(self, source: str, map_dir: str, config: DetectorConfig, **options) -> Result:
        """Build a map of `source` in a thread, save it to `map_dir`, then load it live.
        `options` go to `build_map` (image_topic, image_period, index, max_pixels)."""
        try:
            if self._build is not None and self._build.is_alive():
                raise ConfigError(
                    f"a map build is running already ({self.build_state}): wait for it to finish"
                )
            target = check_map_target(map_dir)
            refuse_prior_target(target, self.pipeline.maps.priors)  # fixed since start-up
            check_source(source)
        except (ConfigError, MapError) as err:
            return False, f"{err} ({SOURCE_HINT})" if "build_source" in str(err) else str(err)
        progress = BuildResult(source=str(source))
        error = self.build.error  # kept until a build succeeds
        self.build = BuildStatus("building", str(source), str(target), "", error, progress)
        args = (source, target, config, {**options, "result": progress})
        self._build = threading.Thread(target=self._run_build, args=args, name="vpr_build")
        self._build.daemon = True
        self._build.start()
        return True, (
            f"building a map from {source} into {target} in the background; "
            "the log and /diagnostics say when it is done"
        )

    def wait_build(self, timeout: float | None = None) -> bool:
        """Wait for a running build; True when none is running any more."""
        if self._build is not None:
            self._build.join(timeout)
        return self._build is None or not self._build.is_alive()

    def _run_build(self, source: str, target: Path, config: DetectorConfig, options) -> None:
        limit_this_thread(background=True)  # the live frames keep their cores
        try:
            with self._context():
                built, result = build_map(
                    self.pipeline.model, config, source, stop=self._stop, **options
                )
            if result.cancelled:
                built.close()
                self.build = replace(self.build, state="cancelled")
                return
            self._swap_in(built, target)
            self.build = replace(self.build, state="done", detail=result.line(), error="")
            self._log("info", f"map built, saved to {target} and loaded: {result.line()}")
        except Exception as err:  # noqa: BLE001 - a failed build must not take the node down
            why = f"building a map from {source} into {target} failed: {err}"
            self.build = replace(self.build, state="failed", detail=str(err), error=why)
            self._log("error", why)

    @property
    def build_state(self) -> str:
        """One line: "idle", "building from SOURCE", "done: RESULT", "failed: WHY", "cancelled"."""
        b = self.build
        if b.state == "building":
            return f"building from {b.source}"
        return f"{b.state}: {b.detail}" if b.detail else b.state

    def _swap_in(self, built: LoopClosurePipeline, target: Path) -> None:
        """Save `built` (this thread's) to `target` and load it live (map thread), which lets go
        of `target` first and processes no frame in between. Closes `built`."""
        released, saved = threading.Event(), threading.Event()
        failed: list[BaseException] = []

        def on_map_thread() -> None:
            live = self.pipeline
            held = live.place_map.directory == target.resolve()
            try:
                if held:  # its directory lock would refuse the save
                    live.close()
            finally:
                released.set()
            saved.wait()
            if not failed or held:  # on failure: back to the previous, intact save
                live.load_map(target)
                self._saved = self._save_mark()

        pending = None
        try:
            pending = self.submit(on_map_thread)
            released.wait()
            built.save_map(target)
        except BaseException as err:
            failed.append(err)
            raise
        finally:
            built.close()  # the saved map holds the directory lock until closed
            saved.set()
            if pending is not None:
                pending.result()

    # ---- shutdown ----------------------------------------------------------------------------
    def close(self, save_to: str = "") -> Result | None:
        """Cancel a build, save to `save_to` when given, release the map and the map thread."""
        self._stop.set()
        self.wait_build(timeout=60.0)
        result = self.save(save_to) if save_to else None
        self.call(self.pipeline.close)
        self._thread.shutdown(wait=True)
        return result
