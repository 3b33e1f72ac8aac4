"""Run folders: what a training run writes and what ``render``/``eval``/``export`` read back.

    RUN/config.json      the run's config tree (config.RunConfig as JSON; resuming checks it)
    RUN/log.jsonl        one JSON line per logged step
    RUN/checkpoint.pt    the latest checkpoint (tensors and numbers only, written atomically)
    RUN/model/           point_cloud.ply + MLP files (`securegs train`: the Scaffold-GS model)
    RUN/public/          the same files (`securegs hide`: the public release)
    RUN/key.safetensors  or key.sealed (`securegs hide`: the key)
    RUN/metrics.json     held-out metrics of the final model
    RUN/renders/         PNG renders
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from .io.atomic import atomic_write

# Everything a run writes into its folder; --force removes these and nothing else.
RUN_FILES = ("config.json", "log.jsonl", "checkpoint.pt", "metrics.json", "eval.json", "key.safetensors",
             "key.sealed", "export_3dgs.ply")
RUN_FOLDERS = ("model", "public", "renders")


class RunFolder:
    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    config = property(lambda self: self.path / "config.json")
    log = property(lambda self: self.path / "log.jsonl")
    checkpoint = property(lambda self: self.path / "checkpoint.pt")
    metrics = property(lambda self: self.path / "metrics.json")
    renders = property(lambda self: self.path / "renders")

    @property
    def model(self) -> Path:
        """The saved model: ``public/`` for a SecureGS container, else ``model/``."""
        public = self.path / "public"
        return public if public.is_dir() else self.path / "model"

    def clear(self) -> None:
        """Remove what an earlier run wrote here (the names in RUN_FILES / RUN_FOLDERS only)."""
        for name in RUN_FILES:
            (self.path / name).unlink(missing_ok=True)
        for name in RUN_FOLDERS:
            shutil.rmtree(self.path / name, ignore_errors=True)

    def write_json(self, path: Path, data: dict) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        text = json.dumps(data, indent=1, default=_json_default) + "\n"
        atomic_write(path, lambda f: f.write(text.encode()))

    def read_config(self) -> dict:
        if not self.config.is_file():
            raise FileNotFoundError(f"{self.config}: not a run folder (no config.json); train one with "
                                    "`securegs train` or `securegs hide`")
        try:
            return json.loads(self.config.read_text())
        except ValueError as e:
            raise ValueError(f"{self.config}: not valid JSON ({e})") from None

    def append_log(self, record: dict) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        with open(self.log, "a") as f:
            f.write(json.dumps(record, default=_json_default) + "\n")


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def png_name(camera_name: str, prefix: str = "") -> str:
    """A file name for a camera's render: real data names cameras by image path ("train/r_1.png"),
    which must not become subfolders or double extensions."""
    stem = camera_name.rsplit(".", 1)[0] if "." in camera_name.rsplit("/", 1)[-1] else camera_name
    return prefix + stem.replace("/", "_").replace("\\", "_") + ".png"


def save_png(path: Path, image) -> None:
    """Write an [H, W, 3] float image in [0, 1] (tensor or array) as an 8-bit PNG, atomically."""
    import imageio.v3 as iio

    array = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    data = iio.imwrite("<bytes>", (np.clip(array, 0, 1) * 255 + 0.5).astype(np.uint8), extension=".png")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: f.write(data))


def folder_size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file()) / 1e6
