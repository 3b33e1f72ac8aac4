"""Reading a NeRF-synthetic ("Blender") scene: transforms_{train,test}.json and RGBA images.

Each frame's ``transform_matrix`` is camera-to-world with OpenGL/Blender camera axes (x right,
y up, z backward); flipping its y and z columns gives OpenCV axes, and inverting it the viewmat.
The focal length comes from ``camera_angle_x`` (square pixels, principal point at the centre).
Images are composited over `background` with their alpha kept. The format has no point cloud, so
random points in a box stand in for one, as 3DGS does.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .cameras import Camera, SceneData, composite, read_image, resize_image
from .errors import DataError

# OpenGL camera axes (y up, z backward) to OpenCV (y down, z forward): negate y and z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _load_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise DataError(f"{path}: not valid JSON ({error})") from None


def _frame_image_path(root: Path, file_path: str) -> Path:
    """A frame's image file: file_path relative to the scene folder, '.png' added when it has no
    suffix (the original NeRF-synthetic files leave it out)."""
    path = root / file_path
    return path if path.suffix else path.with_suffix(".png")


def _read_split(root: Path, split: str, background, downscale: float) -> list[Camera]:
    """Cameras of transforms_<split>.json, with their images."""
    path = root / f"transforms_{split}.json"
    meta = _load_json(path)
    if "camera_angle_x" not in meta or "frames" not in meta:
        raise DataError(f"{path}: needs 'camera_angle_x' and 'frames'")
    cameras = []
    for index, frame in enumerate(meta["frames"]):
        try:
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
            image_path = _frame_image_path(root, frame["file_path"])
        except (KeyError, TypeError, ValueError) as error:
            raise DataError(
                f"{path}: frame {index} needs 'file_path' and a numeric 'transform_matrix' ({error})"
            ) from None
        if c2w.shape != (4, 4):
            raise DataError(f"{path}: frame {index} transform_matrix is {c2w.shape}, expected 4x4")
        rgb, alpha = read_image(image_path)
        size = (round(rgb.shape[1] / downscale), round(rgb.shape[0] / downscale))
        rgb, alpha = resize_image(rgb, size), resize_image(alpha, size)
        width, height = size
        focal = 0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"]))
        K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
        viewmat = np.linalg.inv(c2w @ _GL_TO_CV)
        if alpha is not None:
            rgb = composite(rgb, alpha, background)
        cameras.append(Camera(image_path.relative_to(root).as_posix(), viewmat, K, width, height, rgb, alpha))
    return cameras


def load_blender(
    path, *, background=(1.0, 1.0, 1.0), downscale: float = 1, n_points: int = 100_000, bound: float = 1.3,
    seed: int = 0,
) -> SceneData:
    """Read a NeRF-synthetic scene folder.

    Training views from transforms_train.json; test views from transforms_test.json, else
    transforms_val.json, else none. background: (3,) colour the RGBA images are composited over.
    downscale: divide the image size by this. Points: n_points uniform in the cube [-bound, bound]^3
    with uniform random colours (3DGS's initialisation for this format), from `seed`.
    Raises DataError for a missing folder, JSON file or image, or malformed JSON.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: Blender scene folder not found")
    if not (root / "transforms_train.json").is_file():
        raise DataError(f"{root}: transforms_train.json not found")
    train = _read_split(root, "train", background, downscale)
    test_split = next((s for s in ("test", "val") if (root / f"transforms_{s}.json").is_file()), None)
    test = _read_split(root, test_split, background, downscale) if test_split else []
    rng = np.random.default_rng(seed)
    points = rng.uniform(-bound, bound, (n_points, 3))
    return SceneData(root.name, train, test, points, rng.random((n_points, 3)), background=background)
