"""A disk cache of the OpenVINO back end's converted (int8: quantized) graphs.

Exporting ViT-B and calibrating its int8 graphs takes minutes on a small CPU; a later start with
the same model and settings reads the graphs from here instead. One entry is a folder named by a
hash of everything that changes the graphs (`entry_parts`): the weights themselves and the model
config, image size, precision, chunk size, the calibration images, the torch / OpenVINO / NNCF
versions and `CACHE_VERSION`. It holds `<graph>.xml`/`.bin` per graph (`openvino.save_model`,
weights kept in f32) and `manifest.json` (what the key was made of, size and sha256 of each file).

An entry is written under a temporary name and renamed into place, so a killed process leaves
no half-written entry under a key. An entry that does not load (missing, truncated or changed
files, other input shapes) is warned about, naming its folder, and rebuilt; a cache folder that
cannot be written is warned about and the model runs without it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from pair_vpr_ros.model.network import PairVPR

# Bump when what is cached changes for the same inputs: `openvino_backend.convert`, `quantize`
# or `advanced_parameters`, `head_layers`, or the export graphs.
CACHE_VERSION = 3  # 2: int8 with NNCF's overflow fix on every layer; 3: one-direction chunks
AUTO = "auto"  # the parameter value for the per-user cache folder
GRAPHS = ("encoder", "query", "chunk", "chunk_query", "chunk_candidate")
OUTPUTS = {"encoder": 2, "query": 3, "chunk": 1, "chunk_query": 1, "chunk_candidate": 1}
MANIFEST = "manifest.json"
STALE_TEMP_S = 3600.0  # temporary folders older than this were left by a killed process
LOG = logging.getLogger("pair_vpr_ros.openvino_cache")


def user_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/pair_vpr_ros/openvino`` (an absolute XDG_CACHE_HOME only, as the XDG
    spec says), else ``~/.cache/pair_vpr_ros/openvino``."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".cache"
    return root / "pair_vpr_ros" / "openvino"


def resolve_cache_dir(value: str | os.PathLike | None) -> Path | None:
    """The cache folder a parameter value names: ``auto`` -> `user_cache_dir()`, '' or None ->
    None (no cache), anything else -> that folder (``~`` expanded)."""
    if value is None or str(value) == "":
        return None
    return user_cache_dir() if str(value) == AUTO else Path(value).expanduser()


def tensor_digest(tensors: dict[str, Tensor]) -> str:
    """sha256 over names, dtypes, shapes and bytes of `tensors` (in name order)."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{list(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().data)
    return h.hexdigest()


def entry_parts(
    model: PairVPR, precision: str, chunk: int, calibration: Tensor | None
) -> dict[str, str]:
    """Everything the cached graphs depend on. The weights are hashed, not trusted by their id:
    an unseeded random network and a model changed in memory keep the id of other weights."""
    import openvino  # the caller has checked the optional packages

    parts = {
        "cache_version": str(CACHE_VERSION),
        "fingerprint": model.fingerprint,
        "config": json.dumps(asdict(model.config), sort_keys=True),
        "weights": tensor_digest(model.state_dict()),
        "image_size": str(model.config.image_size),
        "precision": precision,
        "chunk": str(chunk),
        "torch": torch.__version__,
        "openvino": openvino.get_version(),
    }
    if precision == "int8":
        import nncf

        parts["nncf"] = nncf.__version__
        parts["calibration"] = tensor_digest({"images": calibration.float()})
    return parts


_CORES: list = []


def shared_core(ov: ModuleType):
    """The process's one OpenVINO Core, never destroyed. Why: compiling for the CPU gives the
    calling thread a new signal stack (sigaltstack), and destroying that Core frees it and puts
    back the one it found; with several Cores destroyed out of order the thread kept a freed
    stack, and the next signal it handled (a DataLoader worker's SIGCHLD) crashed the process
    with SIGSEGV (measured: OpenVINO 2026.4)."""
    if not _CORES:
        _CORES.append(ov.Core())
    return _CORES[0]


def _file_digest(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


class CacheEntry:
    """The cache entry of one set of `entry_parts` under `root`."""

    def __init__(self, root: str | os.PathLike, parts: dict[str, str]) -> None:
        self.root = Path(root)
        self.parts = parts
        key = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:24]
        self.path = self.root / key

    def load(self, ov: ModuleType, shapes: dict[str, list[tuple[int, ...]]]) -> dict | None:
        """The cached graphs (OpenVINO models), or None when there is no entry or it does not
        load: then a warning names the folder. `shapes`: each graph's expected input shapes."""
        if not self.path.exists():
            return None
        try:
            return self._read(ov, shapes)
        except Exception as err:  # noqa: BLE001 - a damaged entry can fail anywhere in OpenVINO
            reason = str(err)  # not `err`: its traceback would keep half-read graphs alive
        LOG.warning(
            "OpenVINO cache entry %s is damaged (%s): building the model again and replacing "
            "the entry",
            self.path,
            reason,
        )
        return None

    def _read(self, ov: ModuleType, shapes: dict[str, list[tuple[int, ...]]]) -> dict:
        manifest = json.loads((self.path / MANIFEST).read_text())
        if manifest.get("parts") != self.parts:
            raise ValueError(f"{MANIFEST} was written for other inputs")
        for name, entry in manifest["files"].items():
            file = self.path / name
            if file.stat().st_size != entry["size"] or _file_digest(file) != entry["sha256"]:
                raise ValueError(f"{name} is not the file that was saved (size or sha256)")
        graphs = {}
        for name in GRAPHS:
            graph = shared_core(ov).read_model(
                self.path / f"{name}.xml", self.path / f"{name}.bin"
            )
            got = [tuple(i.get_partial_shape().to_shape()) for i in graph.inputs]
            if got != shapes[name] or len(graph.outputs) != OUTPUTS[name]:
                raise ValueError(
                    f"{name} graph has inputs {got} and {len(graph.outputs)} outputs, expected "
                    f"{shapes[name]} and {OUTPUTS[name]}"
                )
            graphs[name] = graph
        return graphs

    def save(self, ov: ModuleType, graphs: dict) -> bool:
        """Write `graphs` as this entry (replacing a damaged one); False, after a warning, when
        the cache folder cannot be written."""
        temp = None
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            _remove_stale_temps(self.root)
            temp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.root))
            files = {}
            for name in GRAPHS:
                ov.save_model(graphs[name], temp / f"{name}.xml", compress_to_fp16=False)
                for suffix in (".xml", ".bin"):
                    file = temp / f"{name}{suffix}"
                    files[file.name] = {"size": file.stat().st_size, "sha256": _file_digest(file)}
            manifest = {"parts": self.parts, "files": files}
            (temp / MANIFEST).write_text(json.dumps(manifest, indent=1))
            self._publish(temp)
            return True
        except (OSError, RuntimeError) as err:  # RuntimeError: OpenVINO could not write a file
            LOG.warning(
                "cannot write the OpenVINO cache at %s (%s): running without it, so the next "
                "start builds the model again; set openvino_cache_dir to a writable folder, or "
                "'' to turn the cache off",
                self.root,
                err,
            )
            return False
        finally:
            if temp is not None and temp.exists():
                shutil.rmtree(temp, ignore_errors=True)

    def _publish(self, temp: Path) -> None:
        """Rename the finished `temp` folder to the entry's name, moving a damaged entry out
        of the way first. Another process that published the same entry meanwhile wins."""
        old = None
        if self.path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.old.", dir=self.root))
            os.replace(self.path, old / "entry")
        try:
            os.rename(temp, self.path)
        except OSError:
            if not (self.path / MANIFEST).exists():
                raise
        finally:
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)


def _remove_stale_temps(root: Path) -> None:
    """Remove the temporary folders of writers killed more than `STALE_TEMP_S` ago."""
    now = time.time()
    for path in root.glob(".*"):
        try:
            if path.is_dir() and now - path.stat().st_mtime > STALE_TEMP_S:
                shutil.rmtree(path, ignore_errors=True)
        except OSError:
            continue
