"""Run folders: what a training run writes and what ``render``/``eval``/``export`` read back.

    RUN/config.json      scene spec + training config (JSON; resuming checks it)
    RUN/log.jsonl        one JSON line per logged step
    RUN/checkpoint.pt    the latest checkpoint (tensors and numbers only, written atomically)
    RUN/model/           point_cloud.ply + MLP files (the Scaffold-GS release)
    RUN/metrics.json     held-out metrics of the final model
    RUN/renders/         PNG renders
"""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from .data import SceneData, load_scene
from .io.atomic import atomic_write


@dataclasses.dataclass
class SceneSpec:
    """How to (re)build a run's scene: a built-in name or a data folder, with loader options."""

    source: str = "synthetic"
    width: int = 128
    height: int = 96
    n_train: int = 32
    n_test: int = 8
    seed: int = 0
    hidden: str | None = None
    level: str = "object"
    downscale: int = 1

    @property
    def builtin(self) -> bool:
        return not Path(self.source).is_dir()

    def load(self) -> SceneData:
        if self.builtin:
            return load_scene(self.source, hidden=self.hidden, level=self.level, width=self.width,
                              height=self.height, n_train=self.n_train, n_test=self.n_test, seed=self.seed)
        return load_scene(self.source, downscale=self.downscale)


class RunFolder:
    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    config = property(lambda self: self.path / "config.json")
    log = property(lambda self: self.path / "log.jsonl")
    checkpoint = property(lambda self: self.path / "checkpoint.pt")
    model = property(lambda self: self.path / "model")
    metrics = property(lambda self: self.path / "metrics.json")
    renders = property(lambda self: self.path / "renders")

    def write_json(self, path: Path, data: dict) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        text = json.dumps(data, indent=1, default=_json_default) + "\n"
        atomic_write(path, lambda f: f.write(text.encode()))

    def read_config(self) -> dict:
        if not self.config.is_file():
            raise FileNotFoundError(f"{self.config}: not a run folder (no config.json); train one with `securegs train`")
        return json.loads(self.config.read_text())

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


def save_png(path: Path, image) -> None:
    """Write an [H, W, 3] float image in [0, 1] (tensor or array) as an 8-bit PNG, atomically."""
    import imageio.v3 as iio

    array = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    data = iio.imwrite("<bytes>", (np.clip(array, 0, 1) * 255 + 0.5).astype(np.uint8), extension=".png")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: f.write(data))


def folder_size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file()) / 1e6
